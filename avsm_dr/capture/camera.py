"""Light cameras: one light ray per shadow-map texel, and world point -> (texel, depth).

Every camera shoots the ray of texel ``k`` from ``origin[k]`` along the unit
direction ``dir[k]``; the light-space depth of the point ``origin + t * dir`` is
``t`` itself, so segments ``[z0, z1]`` are ray parameters and a receiver's depth
comes from the same camera (:meth:`LightCamera.project`):

* :class:`OrthoCamera` (directional light): the map is a square window of
  half-size ``half`` on the plane through ``center`` orthogonal to ``d``, fitted
  to the content; depth ``= (p - center) . d`` (distance from that plane).
* :class:`PerspectiveCamera` (spot light, and each face of a cube): square map
  over the cone of full angle ``fov``; depth ``= |p - position|``.
* :class:`CubeCamera` (point light): six 90-degree faces (+x, -x, +y, -y, +z, -z)
  stacked vertically, ``width = res``, ``height = 6 res``; texel index
  ``face * res * res + y * res + x``.

Texel ``(i, j)`` covers the continuous coordinates ``[i, i+1) x [j, j+1)``
(the convention of :mod:`avsm_dr.filtering`); its ray passes through its centre.
A point whose coordinates fall outside ``[0, width) x [0, height)`` (behind a spot
light, outside its square frustum, beside a directional map's window) is not seen by
the map (:meth:`LightCamera.covers`); :meth:`avsm_dr.capture.Capture.lookup` treats it
as lit.
"""
from __future__ import annotations

import math
import sys

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from ..geometry import box_corners, orthonormal_basis


def _rect_from_coords(x, y, res):
    """Inclusive texel rectangle covering continuous coordinates (x, y) (..., n); empty -> x0 > x1."""
    x0, x1, y0, y1 = (np.floor(f(c, axis=-1)).astype(np.int64) for c in (x, y) for f in (np.min, np.max))
    empty = (x1 < 0) | (y1 < 0) | (x0 > res - 1) | (y0 > res - 1)
    x0, x1, y0, y1 = (np.clip(v, 0, res - 1) for v in (x0, x1, y0, y1))
    return x0, np.where(empty, x0 - 1, x1), y0, y1


#: (box, texel) pairs enumerated at once by :meth:`LightCamera.footprint_chunks` (host memory:
#: the rays of one chunk take 2 x 3 float64 per pair, 200 MB).
MAX_PAIRS = 1 << 22
#: Most (item, texel) pairs one capture of particles or hair enumerates (each becomes at most
#: one segment, ~40 bytes on the host while sorting).
MAX_CANDIDATES = 1 << 27


def _rect_areas(x0, x1, y0, y1) -> np.ndarray:
    """Texels in each inclusive rectangle (0 when empty)."""
    return np.maximum(x1 - x0 + 1, 0) * np.maximum(y1 - y0 + 1, 0)


def expand_rects(x0, x1, y0, y1, res: int, texel_offset: int = 0):
    """All (item, texel) pairs of inclusive rectangles; texel = offset + y * res + x."""
    wx = np.maximum(x1 - x0 + 1, 0)
    counts = _rect_areas(x0, x1, y0, y1)
    item = np.repeat(np.arange(counts.size, dtype=np.int64), counts)
    starts = np.cumsum(counts) - counts
    ly, lx = np.divmod(np.arange(int(counts.sum()), dtype=np.int64) - starts[item], wx[item])
    return item, texel_offset + (y0[item] + ly) * res + (x0[item] + lx)


class LightCamera:
    """Common interface of the light cameras.  ``width``, ``height``, ``n_texels``, ``res``
    (texels per side of a face), ``texel_offset`` (of a cube's face); see the module docstring."""

    width: int
    height: int
    res: int
    texel_offset = 0

    @property
    def n_texels(self) -> int:
        return self.width * self.height

    def rays_device(self, texels) -> tuple[list, list]:
        """Texel rays on the device: texels a Dr.Jit UInt32 array -> (origin, unit direction),
        each a list of three Dr.Jit Float64 arrays (the camera's constants enter as opaque
        scalars, so one compiled kernel serves every camera of a class)."""
        raise NotImplementedError

    def rays(self, texels=None) -> tuple[np.ndarray, np.ndarray]:
        """(origins (K, 3), unit directions (K, 3)) float64 of the given texels (default: all),
        :meth:`rays_device` read back."""
        t = self.texel_offset + np.arange(self.n_texels) if texels is None else np.asarray(texels, np.int64)
        if t.size == 0:
            return np.zeros((0, 3)), np.zeros((0, 3))
        o, d = self.rays_device(A.to_uint32(t))
        dr.eval(o, d)
        return tuple(np.stack([np.asarray(v.numpy(), np.float64) for v in x], axis=1) for x in (o, d))

    def project(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Continuous map coordinates (K, 2) (x, y in texel units) and depths (K,) float64."""
        raise NotImplementedError

    def texel_index(self, coords) -> np.ndarray:
        """Texel containing each continuous coordinate, clamped to the map (cube: to the face)."""
        ix = np.clip(np.floor(coords[:, 0]), 0, self.res - 1).astype(np.int64)
        face = np.clip(np.floor(coords[:, 1] / self.res), 0, self.height // self.res - 1).astype(np.int64)
        iy = np.clip(np.floor(coords[:, 1] - face * self.res), 0, self.res - 1).astype(np.int64)
        return self.texel_offset + face * self.res * self.res + iy * self.res + ix

    def covers(self, coords) -> np.ndarray:
        """(K,) bool: the continuous coordinates (K, 2) lie on the map, ``[0, width) x [0, height)``."""
        c = np.asarray(coords, np.float64)
        return (c[:, 0] >= 0) & (c[:, 0] < self.width) & (c[:, 1] >= 0) & (c[:, 1] < self.height)

    def footprint_rects(self, bmin, bmax) -> list:
        """Inclusive texel rectangles of N boxes, one tuple ``(x0, x1, y0, y1, texel_offset)``
        of (N,) int64 arrays per map face, holding every texel whose ray may meet the box
        (conservative; empty rectangles have ``x0 > x1``)."""
        raise NotImplementedError

    def footprint_chunks(self, bmin, bmax):
        """Yield the candidate (item, texel) int64 pairs of the boxes (every texel whose ray may
        meet box ``item``, :meth:`footprint_rects`) in chunks of at most :data:`MAX_PAIRS` pairs
        (or one box's footprint when that alone is larger)."""
        for x0, x1, y0, y1, offset in self.footprint_rects(bmin, bmax):
            csum = np.cumsum(_rect_areas(x0, x1, y0, y1))
            start = 0
            while start < csum.size:
                base = int(csum[start - 1]) if start else 0
                stop = max(start + 1, int(np.searchsorted(csum, base + MAX_PAIRS, side="right")))
                sl = slice(start, stop)
                item, texel = expand_rects(x0[sl], x1[sl], y0[sl], y1[sl], self.res, offset)
                if texel.size:
                    yield item + start, texel
                start = stop

    def footprint_hits(self, bmin, bmax, hit, n_values: int, chunk: int = 1, name: str | None = None) -> list:
        """``[item, texel, *values]``: int64, int64 and ``n_values`` float64 NumPy arrays over the
        candidate pairs of :meth:`footprint_chunks`, ``chunk`` boxes at a time (bounding the host
        memory of their rectangles), whose rays (:meth:`rays`) ``hit(item, origins, directions)
        -> (*values, mask)`` keeps (a ray-shape intersection of :mod:`avsm_dr.geometry`); with
        ``name``, ValueError naming it when the footprints hold more than
        :data:`MAX_CANDIDATES` pairs (counted without enumerating them)."""
        total = name and sum(int(_rect_areas(*r[:4]).sum()) for s in range(0, bmin.shape[0], chunk)
                             for r in self.footprint_rects(bmin[s:s + chunk], bmax[s:s + chunk]))
        if name and total > MAX_CANDIDATES:
            raise ValueError(f"{name}: the footprints cover {total:.3g} (item, texel) pairs, more than the "
                             f"{MAX_CANDIDATES:.3g} one capture handles; use fewer or smaller items, or a "
                             f"lower resolution")
        out = [(np.zeros(0, np.int64),) * 2 + (np.zeros(0),) * n_values]
        for start in range(0, bmin.shape[0], chunk):
            for item, texel in self.footprint_chunks(bmin[start:start + chunk], bmax[start:start + chunk]):
                *values, m = hit(item + start, *self.rays(texel))
                out.append(((item + start)[m], texel[m], *(v[m] for v in values)))
        return [np.concatenate(a) for a in zip(*out)]

    def texel_width(self, texels, t) -> np.ndarray:
        """World width of a texel's footprint across its ray at depth ``t`` (K,)."""
        raise NotImplementedError


class OrthoCamera(LightCamera):
    """Orthographic map for a directional light travelling along ``direction``.

    center: (3,) point on the reference plane (depth 0) at the map centre.
    half: half-size of the square window in world units; res: texels per side."""

    def __init__(self, direction, center, half: float, res: int):
        self.u, self.v, self.d = orthonormal_basis(direction)
        self.center = np.asarray(center, dtype=np.float64)
        self.half = float(half)
        self.res = self.width = self.height = int(res)
        self.texel_size = 2.0 * self.half / self.res

    @classmethod
    def fit(cls, direction, bmin, bmax, res: int):
        """Fit the window to the union of boxes (N, 3) ``bmin``/``bmax``, keeping one empty
        texel on each side (so edge-clamped lookups outside the content read an empty texel),
        with the reference plane in front of all of it."""
        u, v, d = orthonormal_basis(direction)
        corners = box_corners(bmin, bmax).reshape(-1, 3)
        pu, pv, pd = corners @ u, corners @ v, corners @ d
        size = max(np.ptp(pu), np.ptp(pv), np.ptp(pd), 1e-6)
        ext = max(np.ptp(pu), np.ptp(pv), 1e-6 * size)
        half = 0.5 * ext * res / (res - 2.0)
        cu, cv = 0.5 * (pu.min() + pu.max()), 0.5 * (pv.min() + pv.max())
        cd = pd.min() - 0.05 * size
        return cls(d, cu * u + cv * v + cd * d, half, res)

    def rays_device(self, texels):
        F64 = backend.types().Float64
        res = dr.opaque(type(texels), self.res)
        ts, half = (dr.opaque(F64, v) for v in (self.texel_size, self.half))
        x, y = ((F64(c) + 0.5) * ts - half for c in (texels % res, texels // res))
        c, u, v, d = (_opaque_vec(a) for a in (self.center, self.u, self.v, self.d))
        o = [c[a] + x * u[a] + y * v[a] for a in range(3)]
        return o, [dr.full(F64, 0.0, dr.width(texels)) + d[a] for a in range(3)]

    def _coords(self, p):
        """Map coordinates (x, y) and depth of points ``p`` (..., 3)."""
        q = p - self.center
        return (q @ self.u + self.half) / self.texel_size, (q @ self.v + self.half) / self.texel_size, q @ self.d

    def project(self, points):
        x, y, depth = self._coords(np.asarray(points, np.float64))
        return np.stack([x, y], axis=1), depth

    def texel_width(self, texels, t):
        return np.full(np.shape(t), self.texel_size)

    def footprint_rects(self, bmin, bmax):
        x, y, _ = self._coords(box_corners(bmin, bmax))               # (N, 8) each
        return [(*_rect_from_coords(x, y, self.res), 0)]


class PerspectiveCamera(LightCamera):
    """Perspective square map at ``position`` looking along ``direction``, full angle ``fov``
    degrees (spot light, or one cube face with fov = 90)."""

    def __init__(self, position, direction, fov: float, res: int, texel_offset: int = 0):
        self.position = np.asarray(position, dtype=np.float64)
        self.u, self.v, self.w = orthonormal_basis(direction)
        self.fov = float(fov)
        self.tan_half = math.tan(math.radians(self.fov) / 2)
        self.res = self.width = self.height = int(res)
        self.texel_offset = int(texel_offset)

    def rays_device(self, texels):
        t = texels - dr.opaque(type(texels), self.texel_offset)
        return _perspective_rays(t, self.res, self.tan_half, *(_opaque_vec(a) for a in (self.u, self.v, self.w)),
                                 _opaque_vec(self.position))

    def _coords(self, q):
        zc = q @ self.w
        safe = np.where(zc > 0, zc, 1.0)
        x, y = (((q @ a) / (safe * self.tan_half) + 1) * 0.5 * self.res for a in (self.u, self.v))
        return x, y, zc

    def project(self, points):
        """Points behind the light (or on its plane) get coordinates far outside the map."""
        q = np.asarray(points, np.float64) - self.position
        x, y, zc = self._coords(q)
        return np.where((zc > 0)[:, None], np.stack([x, y], axis=1), -1e9), np.linalg.norm(q, axis=1)

    def texel_width(self, texels, t):
        """t * (2 tan(fov/2) / res) / cos^2(alpha), alpha the ray's angle off the axis (an
        upper bound of the footprint's extent across the ray)."""
        _, d = self.rays(texels)
        cos = d @ self.w
        return np.asarray(t) * (2 * self.tan_half / self.res) / (cos * cos)

    def footprint_rects(self, bmin, bmax):
        x, y, zc = self._coords(box_corners(bmin, bmax) - self.position)
        tiny = 1e-9
        front = np.all(zc > tiny, axis=1)
        behind = np.all(zc <= tiny, axis=1)
        x0, x1, y0, y1 = _rect_from_coords(x, y, self.res)
        straddle = ~front & ~behind          # box crosses the light's plane: whole face
        x1 = np.where(straddle, self.res - 1, np.where(behind, x0 - 1, x1))   # behind the light: empty
        y1 = np.where(straddle, self.res - 1, y1)
        x0, y0 = (np.where(straddle, 0, v) for v in (x0, y0))
        return [(x0, x1, y0, y1, self.texel_offset)]


#: Cube faces: (forward axis, sign); face f owns texels [f res^2, (f+1) res^2).
CUBE_FACES = ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0), (2, 1.0), (2, -1.0))


class CubeCamera(LightCamera):
    """Six 90-degree perspective faces around a point light, stacked vertically."""

    def __init__(self, position, res: int):
        self.position = np.asarray(position, dtype=np.float64)
        self.res = int(res)
        self.width, self.height = self.res, 6 * self.res
        self.faces = [PerspectiveCamera(position, np.where(np.arange(3) == axis, sign, 0.0), 90.0, res,
                                        texel_offset=f * res * res) for f, (axis, sign) in enumerate(CUBE_FACES)]

    def rays_device(self, texels):
        """Each lane reads its face's basis from (6, 3) tables: one kernel for all faces."""
        F64 = backend.types().Float64
        UInt32 = type(texels)
        n2 = dr.opaque(UInt32, self.res * self.res)
        face = texels // n2
        basis = [[dr.gather(F64, F64(np.ascontiguousarray([getattr(c, name)[a] for c in self.faces])), UInt32(face))
                  for a in range(3)] for name in ("u", "v", "w")]
        return _perspective_rays(texels - face * n2, self.res, self.faces[0].tan_half, *basis,
                                 _opaque_vec(self.position))

    def project(self, points):
        """Face: the dominant axis of ``p - position`` and its sign; y includes the face offset
        ``face * res``; within a face the coordinates are clamped to [0.5, res - 0.5] so bilinear
        taps never read a neighbouring face (wider filters near face edges still do)."""
        q = np.asarray(points, np.float64) - self.position
        axis = np.argmax(np.abs(q), axis=1)
        face = 2 * axis + (q[np.arange(q.shape[0]), axis] < 0)
        xy = np.empty((q.shape[0], 2))
        for f, cam in enumerate(self.faces):
            m = face == f
            x, y, _ = cam._coords(q[m])
            xy[m, 0] = np.clip(x, 0.5, self.res - 0.5)
            xy[m, 1] = np.clip(y, 0.5, self.res - 0.5) + f * self.res
        return xy, np.linalg.norm(q, axis=1)

    def texel_width(self, texels, t):
        """As :meth:`PerspectiveCamera.texel_width`, with each texel's face axis."""
        texels = np.asarray(texels, np.int64)
        _, d = self.rays(texels)
        cos = np.einsum("ij,ij->i", d, np.array([c.w for c in self.faces])[texels // (self.res * self.res)])
        return (np.broadcast_to(np.asarray(t, np.float64), texels.shape)
                * (2 * self.faces[0].tan_half / self.res) / (cos * cos))

    def footprint_rects(self, bmin, bmax):
        return [r for cam in self.faces for r in cam.footprint_rects(bmin, bmax)]


def _opaque_vec(a) -> list:
    """A float64 3-vector as three opaque Dr.Jit Float64 scalars."""
    return [dr.opaque(backend.types().Float64, float(x)) for x in np.asarray(a, np.float64).reshape(3)]


def _perspective_rays(t, res: int, tan_half: float, u, v, w, position):
    """Device rays of face-local texels ``t`` of a square perspective map (basis u, v, w:
    lists of Float64): the formulas of :meth:`PerspectiveCamera.rays`."""
    F64 = backend.types().Float64
    r = dr.opaque(type(t), int(res))
    rf, th = dr.opaque(F64, float(res)), dr.opaque(F64, float(tan_half))
    sx, sy = (((F64(c) + 0.5) / rf * 2 - 1) * th for c in (t % r, t // r))
    d = [w[a] + sx * u[a] + sy * v[a] for a in range(3)]
    norm = dr.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    zero = dr.zeros(F64, dr.width(t))
    return [zero + position[a] for a in range(3)], [d[a] / norm for a in range(3)]


def make_camera(light, res: int, bmin=None, bmax=None) -> LightCamera:
    """The camera of ``light`` (``Light.shadow_camera``): ortho fitted to boxes (N, 3)
    ``bmin``/``bmax`` (directional), perspective (spot), a cube (point)."""
    from ..scene import check_light
    return check_light(light).shadow_camera(sys.modules[__name__], res, bmin, bmax)
