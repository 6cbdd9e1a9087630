"""Density grids: trilinear sampling and light-ray marching into segments.

Grid convention (Mitsuba ``gridvolume``, see :mod:`avsm_dr.scene`): a (nz, ny, nx)
array of extinction ``sigma`` per world unit over ``bbox``; voxel values sit at cell
centres, ``sigma(p)`` is trilinear in between, clamped to the edge inside the box.

Marching (one Dr.Jit lane per texel ray, clipped to the occupied part of the box):
the ray walks the coarse block grid (``block^3`` voxels per block) with a 3-D DDA
[Amanatides & Woo 1987].  An empty block (max of every voxel that influences it
is 0) is crossed in one iteration; in an occupied block the ray takes steps of
length ``h = step`` (the last one up to the block's exit), and each step
``[t_a, t_b]`` becomes one segment whose optical depth is Simpson's rule ::

    tau = (t_b - t_a) / 6 * (sigma(t_a) + 4 sigma((t_a + t_b) / 2) + sigma(t_b))

(exact for the cubic that trilinear interpolation gives inside one lattice cell;
O(h^2) at the lattice planes where its derivative jumps).  Steps with tau = 0
emit nothing.  A ray stops once its accumulated optical depth exceeds
``-ln(epsilon)`` (transmittance below ``epsilon``).

Rays: made, clipped to the occupied box and compacted to the hitting lanes on the device
in float64 (:func:`hit_lanes`; the same formulas as the host's :func:`lane_rays`, no
per-ray host array).  Variable output per lane: one pass writes each lane's segments into
its own slots (a bound of its segments: steps plus block faces crossed), then
:func:`compact_slots` gathers the filled slots into CSR order; if the slots would exceed
:data:`MARCH_SLOT_BUDGET` or a lane fills them, the loop runs twice instead, first
counting segments per lane, then writing them at the prefix-sum offsets.  The two
samples of a step read their 8 voxels with one packet load each from the table of
corners per dual cell (:func:`~avsm_dr.capture.dual_cells.corner_table`).  When the
density is a Dr.Jit array with gradients enabled, the optical depths are then
recomputed per segment (one lane per segment, no loop) from differentiable
gathers, so gradients flow to the voxels; segment boundaries and counts are not
differentiated (they are piecewise constant in the density).

``method='exact'`` (:mod:`.dda`) integrates each crossing of the dual grid (cells between
voxel centres, where sigma is one cubic along the ray) exactly instead, with no step;
``method='march'`` (this module) stays the default (see :func:`check_method`).
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from .. import validation as V
from ..geometry import check_bbox, ray_box, ray_box_dr
from ..io import read_vol
from .assembly import TexelRuns
from .dual_cells import corner_table


# --------------------------------------------------------------------- host prep
def block_max(density: np.ndarray, block: int) -> np.ndarray:
    """(nbz, nby, nbx) upper bound of sigma over each block's region.

    Entry b is the max over voxels ``[b*block - 1, (b+1)*block]`` (clipped) along every
    axis - every voxel whose trilinear support reaches block b - so 0 means sigma = 0
    on the whole (closed) block.  Separable: z first (whole contiguous slabs, the cheap
    direction), then y and x on the 1/block-size result.
    """
    out = density
    for axis in (0, 1, 2):
        n = out.shape[axis]
        nb = -(-n // block)
        shape = list(out.shape)
        shape[axis] = nb
        res = np.empty(shape, out.dtype)
        for b in range(nb):
            src = [slice(None)] * 3
            src[axis] = slice(max(b * block - 1, 0), min((b + 1) * block + 1, n))
            dst = [slice(None)] * 3
            dst[axis] = b
            res[tuple(dst)] = out[tuple(src)].max(axis=axis)
        out = res
    return out


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
    ``capture(density=...)``) to skip the host preparation on repeated captures.
    """
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
        nz, ny, nx = self.shape
        return (self.bmax - self.bmin) / np.array([nx, ny, nz], np.float64)

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
            False marks every block occupied (no empty-space skipping).
        """
        if isinstance(density, GridVolume):
            return density
        if not isinstance(block, (int, np.integer)) or block < 1:
            raise ValueError(f"block: expected an integer >= 1, got {block!r}")
        if isinstance(density, (str, os.PathLike)):
            data, file_bbox = read_vol(density, with_bbox=True)
            if data.ndim != 3:
                raise ValueError(f"density: {density!r} has {data.shape[-1]} channels, expected 1")
            density = data
            if bbox is None:
                bbox = file_bbox
        if bbox is None:
            raise ValueError("bbox: a density grid needs its world box (min_xyz, max_xyz)")
        lo, hi = check_bbox(bbox)

        data = None
        if A.is_drjit(density):
            if not dr.is_tensor_v(density) or density.ndim != 3:
                raise ValueError("density: a Dr.Jit density must be a 3-D tensor (TensorXf) of shape (z, y, x)")
            V.grid_dtype(density, "density")
            flat = density.array
            if dtype is None:
                dtype = A.dtype_of(flat)
            data = A.to_float(flat, A.float_type(dtype))
        else:
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
            nb = [-(-s // block) for s in shape]
            occ = np.ones(nb, np.float32)
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

    # ------------------------------------------------------------- sampling
    def sample(self, points) -> np.ndarray:
        """sigma at world points (K, 3), float64 NumPy; 0 outside the box (Mitsuba's convention)."""
        p = np.asarray(points, np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points: expected shape (K, 3), got {p.shape}")
        if self.occupied is None or p.shape[0] == 0:
            return np.zeros(p.shape[0])
        Float = self.Float
        h = self.voxel
        wlo = self.bmin + self.window_lo * h
        whi = wlo + np.array(self.window_shape[::-1]) * h
        inside = np.all((p >= self.bmin) & (p <= self.bmax) & (p >= wlo) & (p <= whi), axis=1)
        x, y, z = (A.to_float(p[:, i], Float) for i in range(3))
        k = MarchKernel(self)
        val = k.trilinear(dr.detach(self.data), x, y, z, A.to_float(inside.astype(np.float64), Float) > 0)
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
        self.nx = dr.opaque(Int32, wx)
        self.ny = dr.opaque(Int32, wy)

    def trilinear(self, data, x, y, z, active=True):
        """sigma(x, y, z) by trilinear interpolation of cell-centred voxels, clamped to the
        edge of the window (equal to the whole grid's clamping: the window's own edge
        voxels are zero wherever it is smaller than the grid)."""
        Float, Int32, UInt32 = self.Float, self.Int32, self.UInt32
        idx, w = [], []
        for c, lo, s, nm in zip((x, y, z), self.lo, self.scale, self.nmax):
            u = (c - lo) * s - 0.5
            f = dr.floor(u)
            i0 = Int32(f)
            w.append(u - f)
            idx.append((dr.clip(i0, 0, nm), dr.clip(i0 + 1, 0, nm)))
        (x0, x1), (y0, y1), (z0, z1) = idx
        wx, wy, wz = w

        def g(i, j, k):
            return dr.gather(Float, data, UInt32((k * self.ny + j) * self.nx + i), active)

        c00 = dr.lerp(g(x0, y0, z0), g(x1, y0, z0), wx)
        c10 = dr.lerp(g(x0, y1, z0), g(x1, y1, z0), wx)
        c01 = dr.lerp(g(x0, y0, z1), g(x1, y0, z1), wx)
        c11 = dr.lerp(g(x0, y1, z1), g(x1, y1, z1), wx)
        return dr.lerp(dr.lerp(c00, c10, wy), dr.lerp(c01, c11, wy), wz)

    def trilinear_table(self, table, x, y, z, active=True):
        """:meth:`trilinear` with the 8 voxels read by one packet load from the dual cell's
        entry of :func:`~avsm_dr.capture.dual_cells.corner_table` (the table's edge padding repeats
        the edge voxels, which is the clamp): the same values, the same arithmetic."""
        Float, Int32, UInt32 = self.Float, self.Int32, self.UInt32
        cell, w = [], []
        for c, lo, s, nm in zip((x, y, z), self.lo, self.scale, self.nmax):
            u = (c - lo) * s - 0.5
            f = dr.floor(u)
            w.append(u - f)
            cell.append(dr.clip(Int32(f), -1, nm) + 1)
        cx, cy, cz = cell
        wx, wy, wz = w
        t = backend.types()
        ArrX = t.ArrayXf if Float is t.Float else t.ArrayXf64
        v = dr.gather(ArrX, table, UInt32((cz * (self.ny + 1) + cy) * (self.nx + 1) + cx), active,
                      shape=(8, dr.width(cx)))
        c00 = dr.lerp(v[0], v[1], wx)
        c10 = dr.lerp(v[2], v[3], wx)
        c01 = dr.lerp(v[4], v[5], wx)
        c11 = dr.lerp(v[6], v[7], wx)
        return dr.lerp(dr.lerp(c00, c10, wy), dr.lerp(c01, c11, wy), wz)


# --------------------------------------------------------------------- clipping
def lane_rays(grid: GridVolume, camera):
    """Texels whose ray meets the occupied part of ``grid`` (ascending) and their rays, clipped:
    (texels (L,) int64, origins (L, 3), unit directions (L, 3), t_in (L,), t_out (L,)), float64."""
    lo_occ, hi_occ = grid.occupied
    _, cand = camera.footprint(lo_occ[None], hi_occ[None])     # one box: distinct, ascending texels
    o, d = camera.rays(cand)
    t_in, t_out, hit = ray_box(o, d, lo_occ, hi_occ, t_min=0.0)
    return cand[hit], o[hit], d[hit], t_in[hit], t_out[hit]


def candidate_texels(camera, lo, hi):
    """Dr.Jit UInt32 texels (ascending) of ``camera.footprint`` for one box ``[lo, hi]``:
    enumerated on the device when the footprint is one rectangle, on the host otherwise."""
    UInt32 = backend.types().UInt32
    rects = [r for r in camera.footprint_rects(lo[None], hi[None]) if r[1][0] >= r[0][0] and r[3][0] >= r[2][0]]
    if len(rects) != 1:
        _, cand = camera.footprint(lo[None], hi[None])
        return A.to_uint32(cand)
    x0, x1, y0, y1, offset = (int(np.asarray(v).reshape(-1)[0]) for v in rects[0])
    w = x1 - x0 + 1
    i = dr.arange(UInt32, w * (y1 - y0 + 1))
    row = i // dr.opaque(UInt32, w)
    return (dr.opaque(UInt32, offset + y0 * camera.res + x0) + row * dr.opaque(UInt32, camera.res)
            + (i - row * dr.opaque(UInt32, w)))


def hit_lanes(grid: GridVolume, camera, per_lane=None):
    """The lanes of :func:`lane_rays` on the device: (texels UInt32 ascending, origins,
    directions (lists of three Float64), t_in, t_out (Float64), extra) of the rays that meet
    the occupied box.  One kernel makes, clips and tests every candidate ray (and evaluates
    ``per_lane(o, d, t_in, t_out)``, a UInt32 per ray, returned as ``extra`` for the hit
    lanes; None without it), ``dr.compress`` keeps the hits; the hit lanes' rays are then
    recomputed lazily (fused into the kernel that reads them) rather than stored.  No hit:
    empty texels, and every other entry None."""
    UInt32 = backend.types().UInt32
    lo, hi = grid.occupied
    cand = candidate_texels(camera, lo, hi)
    if dr.width(cand) == 0:
        return cand, None, None, None, None, None
    o, d = camera.rays_device(cand)
    F64 = type(o[0])
    box = [[dr.opaque(F64, float(x)) for x in corner] for corner in (lo, hi)]   # one kernel for any box
    t_in, t_out, hit = ray_box_dr(o, d, *box, t_min=0.0)
    extra = dr.select(hit, per_lane(o, d, t_in, t_out), 0) if per_lane is not None else None
    dr.eval(cand, hit, extra)
    sel = dr.compress(hit)
    if dr.width(sel) == 0:
        return UInt32(), None, None, None, None, None
    lanes = dr.gather(UInt32, cand, sel)
    extra = dr.gather(UInt32, extra, sel) if extra is not None else None
    dr.eval(lanes, extra)                                   # one kernel
    o, d = camera.rays_device(lanes)
    t_in, t_out, _ = ray_box_dr(o, d, *box, t_min=0.0)
    return lanes, o, d, t_in, t_out, extra


#: Bricks of the ``"submission"`` order (:func:`brick_keys`): voxels per side.
SUBMISSION_BRICK = 8


def brick_keys(grid: GridVolume, camera, texels, z0, z1, brick: int = SUBMISSION_BRICK):
    """Draw position of every grid segment in the ``"submission"`` order: the index
    ``(b_z n_y + b_y) n_x + b_x`` (x fastest, the grid's memory order) of the ``brick^3``-voxel
    brick of the whole grid that holds the segment's midpoint ``o + (z0 + z1) / 2 d`` (clamped
    into the grid), as a renderer draws a bricked volume brick by brick, each brick marching
    its stretch of the ray front to back.  texels: (S,) :class:`~.assembly.TexelRuns` or int64
    NumPy; z0, z1: Dr.Jit (S,).  Returns a Dr.Jit UInt32 (S,)."""
    t = backend.types()
    F64, UInt32 = t.Float64, t.UInt32
    tex = texels.device() if isinstance(texels, TexelRuns) else A.to_uint32(np.asarray(texels, np.int64))
    o, d = camera.rays_device(tex)
    zm = 0.5 * (F64(dr.detach(z0)) + F64(dr.detach(z1)))
    nb = -(-np.array(grid.shape[::-1], np.int64) // int(brick))          # bricks along (x, y, z)
    side = grid.voxel * int(brick)
    key = dr.zeros(UInt32, dr.width(tex))
    for a in (2, 1, 0):                                                   # z slowest, x fastest
        lo_a, side_a = dr.opaque(F64, float(grid.bmin[a])), dr.opaque(F64, float(side[a]))
        b = dr.clip(dr.floor((o[a] + d[a] * zm - lo_a) / side_a), 0, dr.opaque(F64, float(nb[a] - 1)))
        key = key * dr.opaque(UInt32, int(nb[a])) + UInt32(b)
    return key


#: Slot buffers hold 4 floats per slot (z0, z1, tau, unused): one packet store per segment in
#: the march, one packet load per segment in :func:`compact_slots` (3 gathers otherwise).
PACKET_SLOTS = True


def new_slots(Float, n: int) -> list:
    """Uninitialised slot buffers for ``n`` segments (z0, z1, tau), see :data:`PACKET_SLOTS`."""
    if PACKET_SLOTS:
        return [dr.empty(Float, 4 * n)]
    return [dr.empty(Float, n) for _ in range(3)]


def _arr4(Float):
    t = backend.types()
    return t.Array4f if Float is t.Float else t.Array4f64


def write_slots(bufs, values, idx, active) -> None:
    """Write (z0, z1, tau) ``values`` at slots ``idx`` of :func:`new_slots` buffers."""
    if len(bufs) == 1:
        dr.scatter(bufs[0], _arr4(type(values[0]))(*values, 0), idx, active)
    else:
        for b, v in zip(bufs, values):
            dr.scatter(b, v, idx, active)


def read_slots(bufs, idx, active=True) -> list:
    """(z0, z1, tau) at slots ``idx`` of :func:`new_slots` buffers."""
    Float = type(bufs[0])
    if len(bufs) == 1:
        v = dr.gather(_arr4(Float), bufs[0], idx, active)
        return [v[0], v[1], v[2]]
    return [dr.gather(Float, b, idx, active) for b in bufs]


def compact_slots(bufs, slot, counts, n_segments: int):
    """The first ``counts[i]`` slots from ``slot[i]`` of every lane i of the slot buffers
    ``bufs``, in lane order (CSR).  Output segment k of lane i reads slot
    ``k + slot[i] - off[i]`` (``off``: exclusive prefix sum of ``counts``); that shift is
    built without a per-segment lookup of the lane: a ``scatter_add`` at every lane's
    offset of the change of shift from the previous lane (``cap - count`` of that lane,
    ``cap`` = the slot gap), then an inclusive prefix sum (modulo 2^32), so the kernel over
    the segments only reads the values (one packet load with :data:`PACKET_SLOTS`)."""
    UInt32 = type(counts)
    Float = type(bufs[0])
    if n_segments == 0:
        return Float(), Float(), Float()
    n = dr.width(counts)
    off = dr.prefix_sum(counts)
    i = dr.arange(UInt32, n)
    prev = dr.maximum(i, 1) - 1
    step = dr.select(i > 0, slot - dr.gather(UInt32, slot, prev) - dr.gather(UInt32, counts, prev), 0)
    shift = dr.zeros(UInt32, n_segments)
    # Direct (atomic) mode: Auto may pick Expand on the LLVM backend, which bakes the target's
    # size into the kernel (a new compile for every capture)
    dr.scatter_add(shift, step, off, off < dr.opaque(UInt32, n_segments), mode=dr.ReduceMode.Direct)
    src = dr.arange(UInt32, n_segments) + dr.cumsum(shift)
    out = read_slots(bufs, src)
    dr.eval(out)
    dr.sync_thread()
    return out


# --------------------------------------------------------------------- marching
#: Most output slots of the march's one-pass layout (a bound of each lane's segments: 3.4x
#: the segments on the plume at 1024^2); above it, or when a lane fills its slots, two passes.
MARCH_SLOT_BUDGET = 1 << 25
#: Grid capture methods: 'exact' integrates each dual-cell crossing exactly (:mod:`.dda`),
#: 'march' takes Simpson steps of a given length (this module).
METHODS = ("exact", "march")


def check_method(method, step) -> str:
    """The grid capture method, 'march' when None; ValueError naming ``method`` (unknown)
    or ``step`` (given with 'exact', which has no step).

    'march' stays the default: the exact capture's segments span a whole dual cell (about
    one voxel instead of half), so a representation that interpolates inside a segment
    (uniform density assumed) errs more at receivers *inside* the smoke (plume, 64^2:
    max |dT| 0.10 vs 0.03), while at segment ends (receivers behind it) it is exact
    (1.6e-7 vs 2.0e-3)."""
    if method is None:
        return "march"
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    if method == "exact" and step is not None:
        raise ValueError("step: the 'exact' grid capture has no step (one segment per dual-cell "
                         "crossing); pass method='march' to march with a step")
    return method


def march(grid: GridVolume, camera, step: float | None, epsilon: float, keep_zero: bool = False,
          differentiable: bool | None = None, method: str = "march", runs: bool = False):
    """March every texel ray of ``camera`` through ``grid``.

    Returns (texel (S,) int64 NumPy in texel order, z0, z1, tau Dr.Jit Floats of ``grid.dtype``,
    stats dict).  Segments of one texel are in depth order.

    Parameters
    ----------
    method
        'march' only (Simpson steps of length ``step``); the 'exact' capture (one
        segment per dual-cell crossing) is :func:`.dda.traverse`, dispatched by ``capture``.
    keep_zero
        also emit steps with tau = 0 (gradients can then reach voxels that are
        still 0 inside occupied blocks; use ``GridVolume.prepare(..., skip_empty=False)``
        to reach every voxel).
    differentiable
        recompute tau from differentiable gathers (default: when the grid's
        data has gradients enabled).
    runs
        return the texels as :class:`~avsm_dr.capture.assembly.TexelRuns` (per ray: texel,
        count), not expanded to one per segment on the host.
    """
    if method != "march":
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    t = backend.types()
    Float, UInt32, Int32, Bool = grid.Float, t.UInt32, t.Int32, t.Bool
    empty = (np.zeros(0, np.int64), Float(), Float(), Float(), {"lanes": 0, "iterations": 0})
    if grid.occupied is None:
        return empty
    clock = time.perf_counter()
    nb = np.array(grid.occupancy.shape[::-1], np.int64)               # (nbx, nby, nbz)
    bs = grid.voxel * grid.block                                        # block size (x, y, z)

    def slots(o, d, t_in, t_out):
        """Bound on a lane's segments: its steps (ceil(length / step), plus one cut short per
        block face crossed) and its block faces crossed (+1 each for rounding), + 4."""
        F64 = type(t_in)
        n = dr.ceil((t_out - t_in) / dr.opaque(F64, float(step))) + 4
        for a in range(3):
            lo_a, bs_a = dr.opaque(F64, float(grid.bmin[a])), dr.opaque(F64, float(bs[a]))
            faces = dr.abs(dr.floor((o[a] + d[a] * t_out - lo_a) / bs_a) - dr.floor((o[a] + d[a] * t_in - lo_a) / bs_a))
            n += 2 * (faces + 1)
        return UInt32(dr.select(dr.isfinite(n), n, 0))

    lanes_d, o, d, t_in, t_out, cap = hit_lanes(grid, camera, slots)
    L = dr.width(lanes_d)
    if L == 0:
        return empty
    lanes = np.asarray(lanes_d.numpy(), np.int64)
    times = {"lanes_s": time.perf_counter() - clock}

    # ---- DDA initialisation over the block grid (float64 on the device)
    F64 = type(t_in)
    b, tmax, tdelta, sgn = [], [], [], []
    eps = 1e-6 * float(bs.min())
    for a in range(3):
        lo_a, bs_a = dr.opaque(F64, float(grid.bmin[a])), dr.opaque(F64, float(bs[a]))
        p = o[a] + d[a] * (t_in + dr.opaque(F64, eps))
        ba = Int32(dr.clip(dr.floor((p - lo_a) / bs_a), 0, dr.opaque(F64, float(nb[a] - 1))))
        nxt = lo_a + (F64(ba) + dr.select(d[a] > 0, 1.0, 0.0)) * bs_a
        b.append(ba)
        tmax.append(dr.select(d[a] != 0, (nxt - o[a]) / d[a], 1e30))
        tdelta.append(dr.select(d[a] != 0, bs_a / dr.abs(d[a]), 1e30))
        sgn.append(dr.select(d[a] < 0, Int32(-1), Int32(1)))
    # steps + one iteration per block face crossed (+ zero-length ones at edges and corners)
    max_iter = int(np.ceil(float(dr.max(t_out - t_in)[0]) / step)) + 3 * int(nb.sum()) + 16

    ox, oy, oz = (Float(v) for v in o)
    dx, dy, dz = (Float(v) for v in d)
    t_end = Float(t_out)
    tdx, tdy, tdz = (Float(v) for v in tdelta)
    sx, sy, sz = sgn
    occ = A.to_uint32((grid.occupancy > 0).ravel())
    nbx, nby, nbz = (dr.opaque(Int32, int(v)) for v in nb)
    kern = MarchKernel(grid)
    h = dr.opaque(Float, float(step))
    snap = dr.opaque(Float, 1e-3 * float(step))
    tau_max = dr.opaque(Float, float(-np.log(epsilon)))
    it_max = dr.opaque(UInt32, max_iter)

    table = corner_table(grid)                      # one load for a dual cell's 8 corners

    def sigma(tt, active):
        return kern.trilinear_table(table, ox + dx * tt, oy + dy * tt, oz + dz * tt, active)

    def run(write, stop: bool = False):
        """One pass of the march; ``write`` = (base, cap, buffers) or None; with
        ``stop`` a lane stops once it has written ``cap`` segments.  Returns (segments
        emitted, iterations, done) per lane."""
        t0 = Float(t_in)
        state = (t0, b[0], b[1], b[2],
                 Float(tmax[0]), Float(tmax[1]), Float(tmax[2]),
                 dr.zeros(Float, L),                  # tau: optical depth marched so far
                 sigma(t0, True),                     # s0: sigma at the current t
                 dr.zeros(UInt32, L),                 # n: segments emitted so far
                 dr.zeros(UInt32, L),                 # it: iterations (safety bound)
                 dr.zeros(Bool, L))                   # done

        def cond(t_, bx, by, bz, mx, my, mz, tau, s0, n, it, done):
            return ~done & (n < write[1]) if stop else ~done

        def body(t_, bx, by, bz, mx, my, mz, tau, s0, n, it, done):
            blk_exit = dr.minimum(dr.minimum(mx, my), dr.minimum(mz, t_end))
            bidx = UInt32((bz * nby + by) * nbx + bx)
            occupied = dr.gather(UInt32, occ, bidx) > 0
            t_step = t_ + h
            take = occupied & (t_step < blk_exit - snap)
            t1 = dr.select(take, t_step, blk_exit)
            sm = sigma(0.5 * (t_ + t1), occupied)
            s1 = sigma(t1, occupied)
            seg = dr.select(occupied, (t1 - t_) * (s0 + 4 * sm + s1) * (1.0 / 6.0), 0)
            emit = occupied if keep_zero else occupied & (seg > 0)
            if write is not None:
                base, cap, bufs = write
                write_slots(bufs, (t_, t1, seg), base + n, emit & (n < cap))
            n = n + dr.select(emit, 1, 0)
            tau = tau + seg
            s0 = dr.select(occupied, s1, 0)
            # DDA: leave the block through the face with the smallest exit time
            crossed = ~take
            ax = crossed & (mx <= my) & (mx <= mz)
            ay = crossed & ~ax & (my <= mz)
            az = crossed & ~ax & ~ay
            bx = bx + dr.select(ax, sx, 0)
            by = by + dr.select(ay, sy, 0)
            bz = bz + dr.select(az, sz, 0)
            mx = mx + dr.select(ax, tdx, 0)
            my = my + dr.select(ay, tdy, 0)
            mz = mz + dr.select(az, tdz, 0)
            it = it + 1
            outside = (bx < 0) | (by < 0) | (bz < 0) | (bx >= nbx) | (by >= nby) | (bz >= nbz)
            done = (t1 >= t_end) | (tau > tau_max) | outside | (it >= it_max)
            return t1, bx, by, bz, mx, my, mz, tau, s0, n, it, done

        out = dr.while_loop(state, cond, body, label="grid_march")
        return out[9], out[10], out[11]

    def check(counts, iters):
        S = int(counts.sum())
        stats = {"lanes": L, "iterations": int(iters.sum()), "segments": S, "max_iterations": int(iters.max()),
                 **times}
        if stats["max_iterations"] >= max_iter:
            raise RuntimeError(f"grid march: a ray hit the iteration bound {max_iter} (DDA did not advance)")
        return S, stats

    times["prep_s"], clock = time.perf_counter() - clock - times["lanes_s"], time.perf_counter()
    # ---- one pass into slots (a bound of every lane's segments), then the filled slots in CSR
    # order; a lane that fills its slots: a counting pass, then a pass writing at the offsets
    dr.eval(cap)
    n_slots = int(dr.sum(t.UInt64(cap))[0])
    res = None
    if n_slots <= MARCH_SLOT_BUDGET:
        slot = dr.prefix_sum(cap)
        bufs = new_slots(Float, n_slots)
        n_d, it_d, done = run((slot, cap, bufs), stop=True)
        dr.eval(n_d, it_d, done, bufs)
        if bool(dr.all(done)):
            counts, iters = (np.asarray(v.numpy(), np.int64) for v in (n_d, it_d))
            S, stats = check(counts, iters)
            stats["slots"] = n_slots
            times["march_s"], clock = time.perf_counter() - clock, time.perf_counter()
            res = compact_slots(bufs, slot, n_d, S)
            times["compact_s"] = time.perf_counter() - clock
    if res is None:
        counts_dr, iters, _ = run(None)
        dr.eval(counts_dr, iters)                           # one kernel for both outputs
        counts = np.asarray(counts_dr.numpy(), dtype=np.int64)
        S, stats = check(counts, np.asarray(iters.numpy(), dtype=np.int64))
        if S == 0:
            return empty[:4] + (stats,)
        base_h = np.concatenate([[0], np.cumsum(counts)[:-1]])
        res = dr.zeros(Float, S), dr.zeros(Float, S), dr.zeros(Float, S)
        written, _, _ = run((A.to_uint32(base_h), A.to_uint32(counts), res))
        if not np.array_equal(np.asarray(written.numpy(), np.int64), counts):
            raise RuntimeError("grid march: count and write passes disagree (non-deterministic kernel)")
        dr.eval(res)
        times["march_s"] = time.perf_counter() - clock
    stats.update(times)
    if S == 0:
        return empty[:4] + (stats,)
    z0, z1, tau = res

    # ---- differentiable optical depths: one lane per segment, no loop
    if differentiable is None:
        differentiable = dr.grad_enabled(grid.data)
    if differentiable:
        lane = A.to_uint32(np.repeat(np.arange(L, dtype=np.uint32), counts))
        gx, gy, gz = (dr.gather(Float, v, lane) for v in (ox, oy, oz))
        ex, ey, ez = (dr.gather(Float, v, lane) for v in (dx, dy, dz))

        def sig(tt):
            return kern.trilinear(grid.data, gx + ex * tt, gy + ey * tt, gz + ez * tt)
        tau = (z1 - z0) * (sig(z0) + 4 * sig(0.5 * (z0 + z1)) + sig(z1)) * (1.0 / 6.0)
    if runs:
        return TexelRuns(lanes, counts), z0, z1, tau, stats
    texel = np.repeat(lanes.astype(np.int64), counts)
    return texel, z0, z1, tau, stats
