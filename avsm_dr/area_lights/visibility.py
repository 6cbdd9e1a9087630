"""Per-VPL voxel visibility: voxelize, scan into shadow volumes, look up (Wyman and Dai 2013,
"Imperfect Voxelized Shadow Volumes", HPG, sec. 2).

Storage: VPL ``k``'s grid (:class:`~.vpl.LightGrid`) is a bit volume; texel ray ``k R^2 + j R +
i`` owns ``W = ceil(R / 32)`` UInt32 words, bit ``b & 31`` of its word ``b >> 5`` is depth bin
``b``; all VPLs of a batch share one buffer (the paper's "single render target").

1. *Voxelize* (occupancy ``O``): the bin of each occluder surface seen along a texel ray, by the
   exact texel-centre ray (``voxelize_rays``, naive VSVs) or by splatting random occluder surface
   points, a different set per VPL (``voxelize_points``; imperfect shadow maps, Ritschel et al. 2008).
2. *Scan* along light rays (bit-parallel within a word): ``S_b = O_0 | ... | O_{b-1}``, an
   exclusive prefix-OR: bin ``b`` is in shadow iff an occluder lies in an earlier bin.
3. *Boundary mask* ``E = OR_3x3(S) & ~AND_3x3(S)`` (3 x 3 texels, same bin): where ``E`` is 0
   the bilinear visibility equals the nearest-texel one.

Lookup of a point x for VPL p: light frame ``(X, Y, Z) = ((x-p).e_u, (x-p).e_v, (x-p).n)``,
texel coordinates ``f_s = (X/Z - s_min) / (s_max - s_min) R`` (same for t), bin
``b = min(floor((|x - p| - r_near) / dr_bin), R - 1)``; points outside the frustum
or nearer than ``r_near`` are visible.  Visibility ``V = 1 - S_b``.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from .. import backend
from .geometry import Kit
from .area_scene import AreaLightScene
from .vpl import LightGrid

FULL = 0xFFFFFFFF


@dataclass
class GridCoords:
    """Continuous light-space coordinates of points in one VPL's grid."""
    inside: object   # Bool: in front of the light, inside the frustum, beyond r_near
    fs: object       # Float texel coordinate along e_u (texel i covers [i, i+1))
    ft: object       # Float texel coordinate along e_v
    b: object        # UInt32 depth bin, clamped to R - 1


def project(grid: LightGrid, k: Kit, frame, x, p) -> GridCoords:
    """Grid coordinates of points x for VPLs at p (both Vec3, broadcastable)."""
    eu, ev, n = frame
    v = x - p
    Z = dr.dot(v, n)
    Zs = dr.select(Z > 0, Z, 1)
    R = grid.R
    fs = (dr.dot(v, eu) / Zs - grid.s_min) * (R / (grid.s_max - grid.s_min))
    ft = (dr.dot(v, ev) / Zs - grid.t_min) * (R / (grid.t_max - grid.t_min))
    fb = (dr.norm(v) - grid.r_near) * (1.0 / grid.dr_bin)
    inside = (Z > 0) & (fs >= 0) & (fs < R) & (ft >= 0) & (ft < R) & (fb >= 0)
    b = k.UInt32(dr.minimum(dr.maximum(fb, 0), R - 1))
    return GridCoords(inside, fs, ft, b)


def _word_index(grid: LightGrid, vpl, i, j, b):
    return ((vpl * grid.R + j) * grid.R + i) * grid.words + (b >> 5)


def _set_bin(grid: LightGrid, k: Kit, words, vpl, i, j, r, active) -> None:
    """OR the bit of distance r into texel (i, j) of VPL ``vpl`` (occupancy, bins 0..R-2)."""
    fb = (r - grid.r_near) * (1.0 / grid.dr_bin)
    b = k.UInt32(dr.clip(fb, 0, grid.R - 2))
    bit = k.UInt32(1) << (b & 31)
    dr.scatter_reduce(dr.ReduceOp.Or, words, bit, _word_index(grid, vpl, i, j, b), active)


def voxelize_rays(scene: AreaLightScene, grid: LightGrid, k: Kit, frame, P, n_vpl: int):
    """Occupancy by exact ray casting: one ray per texel centre from each VPL,
    marking the entry bin of every occluder it meets.  P: Vec3 positions (width n_vpl).
    Returns UInt32 words (n_vpl R^2 W)."""
    words = dr.zeros(k.UInt32, n_vpl * grid.R ** 2 * grid.words)      # zeroed occupancy bits
    if grid.empty:
        return words
    eu, ev, n = frame
    R = grid.R
    lane = dr.arange(k.UInt32, n_vpl * R * R)
    vpl = lane // (R * R)
    tex = lane - vpl * (R * R)
    j = tex // R
    i = tex - j * R
    s = grid.s_min + (k.Float(i) + 0.5) * ((grid.s_max - grid.s_min) / R)
    t = grid.t_min + (k.Float(j) + 0.5) * ((grid.t_max - grid.t_min) / R)
    d = dr.normalize(eu * s + ev * t + n)
    p = dr.gather(k.Vec3, P, vpl) if n_vpl > 1 else P
    for occ in scene.occluders:
        t0, _, h = occ.hit_dr(k, p, d)
        _set_bin(grid, k, words, vpl, i, j, t0, h & (t0 > 0))
    return words


def surface_points(scene: AreaLightScene, k: Kit, n: int, seed: int):
    """n random points, uniform by area over all occluder surfaces (Vec3)."""
    state = (0x853C49E6748FEA9B ^ (int(seed) * 0x9E3779B97F4A7C15)) % 2**64
    rng = k.PCG32(n, initstate=backend.types().UInt64(state))
    u0, u1, u2, u3 = (k.Float(rng.next_float32()) for _ in range(4))
    areas = np.array([o.area for o in scene.occluders])
    cdf = np.cumsum(areas) / areas.sum()
    x = dr.zeros(k.Vec3, n)
    lo_c = 0.0
    for occ, hi_c in zip(scene.occluders, cdf):
        sel = (u0 >= lo_c) & (u0 < hi_c) if hi_c < 1 else (u0 >= lo_c)
        x = dr.select(sel, occ.sample_dr(k, u1, u2, u3), x)
        lo_c = hi_c
    return x


def splat_radius(scene: AreaLightScene, points_per_vpl: int, coverage: float = 1.5) -> float:
    """World radius of each splatted point: ``sqrt(c A / (pi M))``, so that M discs cover
    ``c`` times the occluders' total area ``A`` (a fraction ``1 - exp(-c)`` of it when
    the points are uniform; front and back surfaces fill each other's holes)."""
    area = sum(o.area for o in scene.occluders)
    return float(np.sqrt(coverage * area / (np.pi * points_per_vpl)))


def voxelize_points(scene: AreaLightScene, grid: LightGrid, k: Kit, frame, P, n_vpl: int,
                    points_per_vpl: int, seed: int = 0, coverage: float = 1.5):
    """Imperfect occupancy (imperfect shadow maps, Ritschel et al. 2008): each VPL splats
    its own ``points_per_vpl`` = M random occluder surface points, a different set per VPL.
    A point of world radius ``rho`` (:func:`splat_radius`) at light depth Z covers the
    texels whose centre lies inside its projected ellipse (radii ``rho / (Z ds)``,
    ``rho / (Z dt)`` texels); it marks them at its own distance bin.  No hole filling.
    Lanes are (VPL, point); returns UInt32 words (n_vpl R^2 W)."""
    words = dr.zeros(k.UInt32, n_vpl * grid.R ** 2 * grid.words)      # zeroed occupancy bits
    if grid.empty:
        return words
    M, R = points_per_vpl, grid.R
    rho = splat_radius(scene, M, coverage)
    eu, ev, n = frame
    lane = dr.arange(k.UInt32, n_vpl * M)
    vpl = lane // M
    x = surface_points(scene, k, n_vpl * M, seed)
    p = dr.gather(k.Vec3, P, vpl) if n_vpl > 1 else P
    c = project(grid, k, frame, x, p)
    Z = dr.maximum(dr.dot(x - p, n), 1e-12)
    ds, dt = (grid.s_max - grid.s_min) / R, (grid.t_max - grid.t_min) / R
    inv_rs = Z * (ds / rho)                     # 1 / (footprint radius in texels), along s
    inv_rt = Z * (dt / rho)
    r = dr.norm(x - p)
    # largest footprint over the grid (nearest occluder distance) bounds the neighbourhood
    m = int(min(3, np.ceil(rho / (max(grid.z_near, 1e-9) * min(ds, dt)) + 0.5)))
    i0, j0 = k.Int32(dr.floor(c.fs)), k.Int32(dr.floor(c.ft))
    for oy in range(-m, m + 1):
        for ox in range(-m, m + 1):
            i, j = i0 + ox, j0 + oy
            ex = (k.Float(i) + 0.5 - c.fs) * inv_rs
            ey = (k.Float(j) + 0.5 - c.ft) * inv_rt
            hit = c.inside & (i >= 0) & (i < R) & (j >= 0) & (j < R) & (ex * ex + ey * ey <= 1)
            _set_bin(grid, k, words, vpl, k.UInt32(dr.maximum(i, 0)), k.UInt32(dr.maximum(j, 0)), r, hit)
    return words


def scan(words, grid: LightGrid, k: Kit):
    """Exclusive prefix-OR of the occupancy along every texel ray (shadow volumes S): within a word,
    a log-step OR scan sets bit b iff a bit <= b is set, shifted by one bin."""
    inner = words
    for s in (1, 2, 4, 8, 16):
        inner = inner | (inner << s)
    inner = inner << 1
    if grid.words == 1:
        return inner
    carry = dr.block_prefix_reduce(dr.ReduceOp.Or, words, grid.words, exclusive=True)
    return dr.select(carry != 0, k.UInt32(FULL), inner)


def boundary_mask(S, grid: LightGrid, k: Kit):
    """E = OR_3x3(S) & ~AND_3x3(S) per word (texels outside the map count as lit, 0);
    separable: a horizontal pass then a vertical one."""
    W, R = grid.words, grid.R
    n = dr.width(S)
    lane = dr.arange(k.UInt32, n)
    ray = lane // W
    tex = ray % (R * R)
    j = tex // R
    i = tex - j * R

    def pass_(a, o, step, c):
        lo_a, lo_o = (dr.gather(k.UInt32, x, lane - step, c > 0) for x in (a, o))
        hi_a, hi_o = (dr.gather(k.UInt32, x, lane + step, c < R - 1) for x in (a, o))
        return a & lo_a & hi_a, o | lo_o | hi_o

    a1, o1 = pass_(S, S, W, i)
    dr.eval(a1, o1)
    a2, o2 = pass_(a1, o1, W * R, j)
    return o2 & ~a2


def interleave(S, E, k: Kit):
    """One buffer with S and E of each word side by side (``SE[2 w] = S[w]``, ``SE[2 w + 1] =
    E[w]``): the boundary flag read at every Riemann step shares the visibility word's cache line."""
    n = dr.width(S)
    SE = dr.zeros(k.UInt32, 2 * n)
    idx = dr.arange(k.UInt32, n) * 2
    dr.scatter(SE, S, idx)
    dr.scatter(SE, E, idx + 1)
    return SE


def bit_at(k: Kit, S, idx, b, active, stride: int = 1):
    """Bin b's bit (0 or 1, UInt32) of word idx (stored at ``stride * idx``); 0 where inactive."""
    w = dr.gather(k.UInt32, S, idx * stride if stride != 1 else idx, active)
    return (w >> (b & 31)) & 1


def _nearest_word(grid: LightGrid, k: Kit, vpl, c: GridCoords):
    i, j = (k.UInt32(dr.clip(f, 0, grid.R - 1)) for f in (c.fs, c.ft))
    return _word_index(grid, vpl, i, j, c.b)


def lookup_point(grid: LightGrid, k: Kit, S, vpl, c: GridCoords, stride: int = 1):
    """Visibility from the nearest texel: 1 - S_b (1 outside the grid)."""
    return 1 - k.Float(bit_at(k, S, _nearest_word(grid, k, vpl, c), c.b, c.inside, stride))


def lookup_bilinear(grid: LightGrid, k: Kit, S, vpl, c: GridCoords, stride: int = 1):
    """Bilinear visibility over the 2 x 2 texels around (f_s, f_t) at bin b; taps
    outside the map are lit."""
    R = grid.R
    fx, fy = c.fs - 0.5, c.ft - 0.5
    x0, y0 = dr.floor(fx), dr.floor(fy)
    wx, wy = fx - x0, fy - y0
    ix, iy = k.Int32(x0), k.Int32(y0)
    V = dr.zeros(k.Float, dr.width(c.fs))
    for dx, dy, w in ((0, 0, (1 - wx) * (1 - wy)), (1, 0, wx * (1 - wy)), (0, 1, (1 - wx) * wy), (1, 1, wx * wy)):
        tx, ty = ix + dx, iy + dy
        ok = c.inside & (tx >= 0) & (tx < R) & (ty >= 0) & (ty < R)
        idx = _word_index(grid, vpl, k.UInt32(dr.maximum(tx, 0)), k.UInt32(dr.maximum(ty, 0)), c.b)
        V += w * (1 - k.Float(bit_at(k, S, idx, c.b, ok, stride)))
    return V


def lookup_point_edge(grid: LightGrid, k: Kit, SE, vpl, c: GridCoords):
    """Nearest-texel visibility and the boundary flag E at the same voxel, from the
    interleaved buffer of :func:`interleave`.  Where E is 0 the bilinear visibility equals
    the nearest one (Wyman and Dai 2013: "interpolate at shadow boundaries";
    :func:`~.gather.boundary_correction` adds the difference where E is 1)."""
    idx = _nearest_word(grid, k, vpl, c) * 2
    s = bit_at(k, SE, idx, c.b, c.inside)
    e = bit_at(k, SE, idx + 1, c.b, c.inside) != 0
    return 1 - k.Float(s), e
