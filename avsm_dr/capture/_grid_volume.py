"""Density grids: validation, preparation (occupancy blocks, voxel window) and trilinear sampling.

Grid convention (Mitsuba ``gridvolume``, see :mod:`avsm_dr.scene`): a (nz, ny, nx)
array of extinction ``sigma`` per world unit over ``bbox``; voxel values sit at cell
centres, ``sigma(p)`` is trilinear in between, clamped to the edge inside the box.
The marching that reads these grids is :mod:`.grid` (and :mod:`.dda`).

The *dual grid* (cells between voxel centres, inside which trilinear density is a cubic
along a ray): its edge-padded window, per-block occupancy for block skipping
(:func:`dual_grid`), and the table of every dual cell's 8 corner voxels
(:func:`corner_table`, one packet load per crossing), cached on the grid.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from .. import validation as V
from ..geometry import check_bbox
from ..io import read_vol


def window_max(a: np.ndarray, block: int, lo: int, n_blocks) -> np.ndarray:
    """Max of ``a`` over the windows ``[b block + lo, (b + 1) block]`` (inclusive, clipped),
    ``b < n_blocks(n)``, along every axis; separable, z first (whole contiguous slabs)."""
    for axis in (0, 1, 2):
        n = a.shape[axis]
        a = np.stack([a[(slice(None),) * axis + (slice(max(b * block + lo, 0), min((b + 1) * block + 1, n)),)]
                      .max(axis=axis) for b in range(n_blocks(n))], axis=axis)
    return a


def block_max(density: np.ndarray, block: int) -> np.ndarray:
    """(nbz, nby, nbx) upper bound of sigma over each block's region: the max over voxels
    ``[b*block - 1, (b+1)*block]`` (clipped) along every axis, every voxel whose trilinear
    support reaches block b, so 0 means sigma = 0 on the whole (closed) block."""
    return window_max(density, block, -1, lambda n: -(-n // block))


@dataclass(eq=False)
class GridVolume:
    """A validated density grid ready for marching.

    Build with :meth:`prepare`.  ``shape`` = (nz, ny, nx) and ``bmin``/``bmax`` describe
    the whole grid; ``occupancy`` is its (nbz, nby, nbx) block max and ``occupied`` =
    (lo, hi) the world bounds of the non-zero density's support (None if all zero).
    ``data`` is the flat Dr.Jit Float the kernels read (index ``(k * wy + j) * wx + i``)
    over the voxel window ``window_lo`` (x, y, z) .. ``+ window_shape`` (z, y, x): the
    whole grid for Dr.Jit input (AD graph kept), otherwise only the occupied voxels
    plus one voxel of zeros, so padding a grid with empty space costs no device memory
    or upload time.  A prepared grid may be stored in ``Scene.density`` (or passed as
    ``capture(density=...)``) to skip the host preparation on repeated captures."""
    data: Any
    shape: tuple
    bmin: np.ndarray
    bmax: np.ndarray
    block: int
    occupancy: np.ndarray
    occupied: Any
    dtype: str
    window_lo: np.ndarray
    window_shape: tuple

    @property
    def voxel(self) -> np.ndarray:
        """(3,) voxel size (x, y, z) in world units."""
        return (self.bmax - self.bmin) / np.array(self.shape[::-1], np.float64)

    @property
    def Float(self):
        return type(self.data)

    @classmethod
    def prepare(cls, density, bbox=None, block: int = 8, dtype: str | None = None,
                skip_empty: bool = True) -> "GridVolume":
        """Validate and prepare ``density``.

        Parameters
        ----------
        density
            (z, y, x) NumPy array, a 3-D Dr.Jit tensor (``TensorXf``/``TensorXf64``;
            gradients kept), a path to a Mitsuba ``.vol`` file, or a GridVolume (returned).
        bbox
            (min_xyz, max_xyz); for ``.vol`` files default the header's box.
        block
            voxels per side of an empty-space-skipping block (>= 1).
        dtype
            'float32' | 'float64'; default float32, or float64 for TensorXf64 input.
        skip_empty
            False marks every block occupied (no empty-space skipping)."""
        if isinstance(density, GridVolume):
            return density
        V.integer(block, "block", 1)
        if isinstance(density, (str, os.PathLike)):
            path = density
            density, file_bbox = read_vol(path, with_bbox=True)
            if density.ndim != 3:
                raise ValueError(f"density: {path!r} has {density.shape[-1]} channels, expected 1")
            bbox = file_bbox if bbox is None else bbox
        if bbox is None:
            raise ValueError("bbox: a density grid needs its world box (min_xyz, max_xyz)")
        lo, hi = check_bbox(bbox)

        data = None
        if A.is_drjit(density):
            if not dr.is_tensor_v(density) or density.ndim != 3:
                raise ValueError("density: a Dr.Jit density must be a 3-D tensor (TensorXf) of shape (z, y, x)")
            V.grid_dtype(density, "density")
            dtype = dtype or A.dtype_of(density.array)
            data = A.to_float(density.array, A.float_type(dtype))
        dtype = dtype or "float32"
        # one rule for every grid entry point: float input, 3-D, non-empty, finite, >= 0
        host = V.density_grid(density, "density", np.float64 if dtype == "float64" else np.float32)
        shape = host.shape

        n = np.array(shape[::-1], np.int64)                        # (nx, ny, nz)
        if skip_empty:
            occ = block_max(host, block)
            occupied = None
            w0, w1 = np.zeros(3, np.int64), np.zeros(3, np.int64)   # voxel window [w0, w1] (x, y, z)
            if occ.max() > 0:
                # exact voxel bounds, searched only inside the occupied blocks
                nzb = [np.flatnonzero(occ.max(axis=ax) > 0) for ax in ((0, 1), (0, 2), (1, 2))]
                b0 = np.array([a[0] for a in nzb]) * block
                b1 = np.minimum((np.array([a[-1] for a in nzb]) + 1) * block, n)
                sub = host[b0[2]:b1[2], b0[1]:b1[1], b0[0]:b1[0]]
                prof = [sub.max(axis=(0, 1)), sub.max(axis=(0, 2)), sub.max(axis=(1, 2))]
                imin = b0 + np.array([np.argmax(p > 0) for p in prof])
                imax = b0 + np.array([p.size - 1 - np.argmax(p[::-1] > 0) for p in prof])
                h = (hi - lo) / n
                occupied = (lo + np.maximum(imin - 0.5, 0) * h, lo + np.minimum(imax + 1.5, n) * h)
                w0, w1 = np.maximum(imin - 1, 0), np.minimum(imax + 1, n - 1)
        else:
            occ = np.ones([-(-s // block) for s in shape], np.float32)
            occupied = (lo.copy(), hi.copy())
            w0, w1 = np.zeros(3, np.int64), n - 1
        Float = A.float_type(dtype)
        if data is None:
            win = host[w0[2]:w1[2] + 1, w0[1]:w1[1] + 1, w0[0]:w1[0] + 1]
            data = A.to_float(win, Float)
            wshape = win.shape
        else:
            w0, wshape = np.zeros(3, np.int64), tuple(shape)
        return cls(data, tuple(shape), lo, hi, int(block), occ, occupied, dtype, w0, tuple(wshape))

    def sample(self, points) -> np.ndarray:
        """sigma at world points (K, 3), float64 NumPy; 0 outside the box (Mitsuba's convention)."""
        p = V.points(points, "points", allow_empty=True)
        if self.occupied is None or p.shape[0] == 0:
            return np.zeros(p.shape[0])
        h = self.voxel
        wlo = self.bmin + self.window_lo * h
        whi = wlo + np.array(self.window_shape[::-1]) * h
        inside = np.all((p >= self.bmin) & (p <= self.bmax) & (p >= wlo) & (p <= whi), axis=1)
        x, y, z = (A.to_float(p[:, i], self.Float) for i in range(3))
        val = MarchKernel(self).trilinear(dr.detach(self.data), x, y, z, backend.types().Bool(inside))
        return np.where(inside, np.asarray(val.numpy(), np.float64), 0.0)


class MarchKernel:
    """Grid constants as opaque Dr.Jit scalars (one compiled kernel for all grids)."""

    def __init__(self, grid: GridVolume):
        t = backend.types()
        self.Float, self.UInt32, self.Int32 = grid.Float, t.UInt32, t.Int32
        Float, Int32 = self.Float, self.Int32
        wz, wy, wx = grid.window_shape
        h = grid.voxel
        wlo = grid.bmin + grid.window_lo * h
        self.lo = [dr.opaque(Float, float(v)) for v in wlo]
        self.scale = [dr.opaque(Float, float(v)) for v in 1.0 / h]
        self.nmax = [dr.opaque(Int32, int(v) - 1) for v in (wx, wy, wz)]
        self.nx, self.ny = dr.opaque(Int32, wx), dr.opaque(Int32, wy)

    def _cells(self, x, y, z):
        """Per axis the Int32 ``floor(u)`` and the weight ``u - floor(u)`` of the window
        coordinate ``u = (c - lo) / h - 1/2`` (voxel centres at integers)."""
        idx, w = [], []
        for c, lo, s in zip((x, y, z), self.lo, self.scale):
            u = (c - lo) * s - 0.5
            f = dr.floor(u)
            idx.append(self.Int32(f))
            w.append(u - f)
        return idx, w

    def trilinear(self, data, x, y, z, active=True):
        """sigma(x, y, z) by trilinear interpolation of cell-centred voxels, clamped to the
        edge of the window (equal to the whole grid's clamping: the window's own edge
        voxels are zero wherever it is smaller than the grid)."""
        (ix, iy, iz), (wx, wy, wz) = self._cells(x, y, z)
        (x0, x1), (y0, y1), (z0, z1) = ((dr.clip(i, 0, nm), dr.clip(i + 1, 0, nm))
                                        for i, nm in zip((ix, iy, iz), self.nmax))

        def g(i, j, k):
            return dr.gather(self.Float, data, self.UInt32((k * self.ny + j) * self.nx + i), active)

        # gathers interleaved with the blends: the AD graph's order, hence the gradient sums
        c00, c10, c01, c11 = (dr.lerp(g(x0, y, z), g(x1, y, z), wx) for z in (z0, z1) for y in (y0, y1))
        return dr.lerp(dr.lerp(c00, c10, wy), dr.lerp(c01, c11, wy), wz)

    def trilinear_corners(self, corners, x, y, z, active=True):
        """:meth:`trilinear` with the 8 voxels read by a :class:`DualCorners` ``corners`` (the
        padded window repeats the edge voxels, which is the clamp): the same values, the same
        arithmetic."""
        idx, w = self._cells(x, y, z)
        return _lerp8(corners(*(dr.clip(i, -1, nm) for i, nm in zip(idx, self.nmax)), active), *w)


def _lerp8(v, wx, wy, wz):
    """Trilinear blend of corners ``v[4 k + 2 j + i]`` (i along x, j along y, k along z)."""
    c00, c10, c01, c11 = (dr.lerp(v[2 * m], v[2 * m + 1], wx) for m in range(4))
    return dr.lerp(dr.lerp(c00, c10, wy), dr.lerp(c01, c11, wy), wz)


def segment_tau(grid: GridVolume, o, d, counts, z0, z1):
    """Simpson optical depth of each segment ``[z0, z1]`` of lane ray ``o + t d`` (``o``, ``d``:
    three Dr.Jit ``grid.Float`` arrays per lane; ``counts`` segments per lane, in lane order)
    from differentiable gathers of ``grid.data``, so gradients flow to the voxels::

        tau = (z1 - z0) / 6 * (sigma(z0) + 4 sigma((z0 + z1) / 2) + sigma(z1))"""
    Float, kern = grid.Float, MarchKernel(grid)
    lane = A.to_uint32(np.repeat(np.arange(counts.size, dtype=np.uint32), counts))
    gx, gy, gz = (dr.gather(Float, v, lane) for v in o)
    ex, ey, ez = (dr.gather(Float, v, lane) for v in d)

    def sig(tt):
        return kern.trilinear(grid.data, gx + ex * tt, gy + ey * tt, gz + ez * tt)
    return (z1 - z0) * (sig(z0) + 4 * sig(0.5 * (z0 + z1)) + sig(z1)) * (1.0 / 6.0)


#: Most dual cells of the table of 8 corners per cell (:func:`corner_table`, 256 MB in float32);
#: larger windows read the 8 corners with 8 gathers from the padded window.
CORNER_TABLE_CELLS = 1 << 23


def dual_block_max(padded: np.ndarray, block: int) -> np.ndarray:
    """(nbz, nby, nbx) max of the edge-padded window ``padded`` over each dual block.

    ``padded`` is the (wz + 2, wy + 2, wx + 2) window with one layer of repeated edge
    voxels on every side; dual cell ``c`` (window voxel units, -1 <= c <= w - 1) has
    corners ``padded[c + 1]`` and ``padded[c + 2]`` along each axis; block ``B`` holds
    the cells with ``(c + 1) // block == B``, i.e. padded voxels ``[B block, (B + 1) block]``
    (inclusive).  0 means sigma = 0 on the whole closed block."""
    return window_max(padded, block, 0, lambda n: (n - 2) // block + 1)


def dual_grid(grid):
    """(padded data (Dr.Jit Float, detached), dual block occupancy (host uint32, flat),
    occupancy shape (nbz, nby, nbx)) of ``grid``, computed once and cached on it."""
    cache = grid.__dict__.setdefault("_dual_cache", {})
    if "pad" not in cache:
        host = np.asarray(dr.detach(grid.data).numpy()).reshape(grid.window_shape)
        pad = np.pad(host, 1, mode="edge")
        occ = dual_block_max(pad, grid.block) > 0
        cache["pad"] = A.to_float(pad, grid.Float)
        cache["occ"] = A.to_uint32(occ.ravel().astype(np.uint32))
        cache["occ_shape"] = occ.shape
    return cache["pad"], cache["occ"], cache["occ_shape"]


def corner_table(grid):
    """The 8 corner voxels of every dual cell, contiguous: cell ``((cz + 1) (wy + 1) + cy + 1)
    (wx + 1) + cx + 1``, corner ``4 k + 2 j + i``, so a crossing reads them with one packet
    load instead of 8 gathers (bit-identical values).  Gathered on the device from the padded
    window of :func:`dual_grid` and cached on the grid; None when it would exceed
    :data:`CORNER_TABLE_CELLS` cells (8 x the window's memory)."""
    cache = grid.__dict__.setdefault("_dual_cache", {})
    if "table" not in cache:
        pad, _, _ = dual_grid(grid)
        wz, wy, wx = grid.window_shape
        n = (wx + 1) * (wy + 1) * (wz + 1)
        table = None
        if n <= CORNER_TABLE_CELLS:
            UInt32 = backend.types().UInt32
            i = dr.arange(UInt32, 8 * n)
            cell, c = i // 8, i % 8
            cz = cell // dr.opaque(UInt32, (wx + 1) * (wy + 1))
            rest = cell - cz * dr.opaque(UInt32, (wx + 1) * (wy + 1))
            cy = rest // dr.opaque(UInt32, wx + 1)
            cx = rest - cy * dr.opaque(UInt32, wx + 1)
            src = (((cz + (c >> 2)) * dr.opaque(UInt32, wy + 2) + cy + ((c >> 1) & 1)) * dr.opaque(UInt32, wx + 2)
                   + cx + (c & 1))
            table = dr.gather(grid.Float, pad, src)
            dr.eval(table)
        cache["table"] = table
    return cache["table"]


class DualCorners:
    """``corners(cx, cy, cz, active)``: the 8 corner voxels ``v[4 k + 2 j + i]`` (i along x) of
    dual cells ``(cx, cy, cz)`` (window voxel units, -1 .. w - 1), one packet load from
    :func:`corner_table`, or 8 gathers from the padded window of :func:`dual_grid` where there
    is no table (the same values)."""

    def __init__(self, grid):
        t = backend.types()
        self.table = corner_table(grid)
        self.pad = dual_grid(grid)[0]
        self.Float, self.UInt32 = grid.Float, t.UInt32
        self.ArrX = t.ArrayXf if grid.Float is t.Float else t.ArrayXf64
        wz, wy, wx = grid.window_shape
        self.cx, self.cy, self.px, self.py = (dr.opaque(t.Int32, int(v)) for v in (wx + 1, wy + 1, wx + 2, wy + 2))

    def __call__(self, cx, cy, cz, active=True) -> list:
        if self.table is not None:
            v = dr.gather(self.ArrX, self.table, self.UInt32(((cz + 1) * self.cy + (cy + 1)) * self.cx + (cx + 1)),
                          active, shape=(8, dr.width(cx)))
            return [v[c] for c in range(8)]
        base = self.UInt32(((cz + 1) * self.py + (cy + 1)) * self.px + (cx + 1))
        sy, sz = self.UInt32(self.px), self.UInt32(self.px * self.py)
        return [dr.gather(self.Float, self.pad, base + (c >> 2) * sz + ((c >> 1) & 1) * sy + (c & 1), active)
                for c in range(8)]
