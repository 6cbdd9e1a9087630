"""Virtual point lights (VPLs) on the quad light, and the light-space grid they share.

Area light as K point lights (Wyman and Dai 2013, "Imperfect Voxelized Shadow
Volumes", sec. 1, after Heckbert and Herf 1997)::

    L_in(x) = sum_k  L_e (A / K) max(0, n . w_k) / r_k^2,   w_k = (x - p_k) / r_k,

with p_k stratified on the quad: cell centres of a sqrt(K) x sqrt(K) grid when K is a
square (optionally jittered inside each cell), Hammersley points otherwise.

Every VPL k gets R x R x R voxels in its own light space (Wyman and Dai 2013, sec. 2): texel
(i, j) is the direction ``e_u s + e_v t + n``, ``(s, t)`` in ``[s_min, s_max] x [t_min, t_max]``
(one frustum around all occluders, shared by all VPLs); depth bins 0 .. R-2 split the occluders'
distance range ``[r_near, r_far]`` linearly, bin R-1 holds everything beyond.  A point outside
the frustum or nearer than ``r_near`` has no occluder before the VPL: it is visible.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..validation import integer as check_count
from .area_scene import AreaLightScene, QuadLight


def _radical_inverse2(i: np.ndarray) -> np.ndarray:
    out = np.zeros(i.shape, np.float64)
    f = 0.5
    i = i.copy()
    while np.any(i):
        out += f * (i & 1)
        i >>= 1
        f *= 0.5
    return out


def sample_vpls(light: QuadLight, K: int, jitter: bool = False, seed: int = 0) -> np.ndarray:
    """(K, 3) VPL positions p_k on the quad (float64), stratified as the module docstring says;
    each carries intensity ``L_e (A / K) max(0, n . w)`` (W/sr per unit radiance)."""
    K = check_count(K, "vpls", 1)
    m = int(round(math.sqrt(K)))
    if m * m == K:
        i, j = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
        off = np.random.default_rng(seed).random((K, 2)) if jitter else np.full((K, 2), 0.5)
        uv = (np.stack([i.ravel(), j.ravel()], 1) + off) / m
    else:
        k = np.arange(K)
        uv = np.stack([(k + 0.5) / K, _radical_inverse2(k)], 1)
        if jitter:
            uv = (uv + np.random.default_rng(seed).random(2)) % 1.0  # Cranley-Patterson rotation
    uv = uv - 0.5
    return light.center[None] + uv[:, :1] * light.edge_u[None] + uv[:, 1:] * light.edge_v[None]


@dataclass(frozen=True)
class LightGrid:
    """Per-VPL light-space grid shared by all VPLs (see the module docstring).

    R: texels per side and depth bins; s_min..t_max: the frustum in slope units
    (x / z, y / z in the light frame); r_near, r_far: occluder distance range;
    ``dr_bin = (r_far - r_near) / (R - 1)``; words = ceil(R / 32) UInt32 per texel ray."""
    R: int
    s_min: float
    s_max: float
    t_min: float
    t_max: float
    r_near: float
    r_far: float
    empty: bool = False
    z_near: float = 0.0     # smallest light-frame depth n . (x - p) of any occluder

    @property
    def words(self) -> int:
        return (self.R + 31) // 32

    @property
    def dr_bin(self) -> float:
        return (self.r_far - self.r_near) / (self.R - 1)


def fit_grid(scene: AreaLightScene, vpls: np.ndarray, R: int) -> LightGrid:
    """The frustum and depth range of every VPL's grid around all occluders: an occluder with
    light-frame extents x in [x_lo, x_hi], z in [z_lo, z_hi] (z_lo > 0) has slopes x / z in
    [min(x_lo / z_lo, x_lo / z_hi), max(x_hi / z_lo, x_hi / z_hi)]; the union over occluders
    and VPLs, padded by half a texel, is the shared frustum."""
    R = check_count(R, "resolution", 2)
    frame = scene.light.frame()
    if not scene.occluders:
        return LightGrid(R, -1.0, 1.0, -1.0, 1.0, 0.0, 1.0, empty=True)
    ext = np.array([o.light_frame_extent(vpls, frame) for o in scene.occluders])    # (occluder, 8, K)
    x0, x1, y0, y1, z0, z1, r_lo, r_hi = (ext[:, i] for i in range(8))
    s_min, s_max = float(np.min(np.minimum(x0 / z0, x0 / z1))), float(np.max(np.maximum(x1 / z0, x1 / z1)))
    t_min, t_max = float(np.min(np.minimum(y0 / z0, y0 / z1))), float(np.max(np.maximum(y1 / z0, y1 / z1)))
    ps = 0.5 * (s_max - s_min) / R + 1e-6
    pt = 0.5 * (t_max - t_min) / R + 1e-6
    r_near, r_far = float(np.min(r_lo)), float(np.max(r_hi))
    pad = 1e-4 * (r_far - r_near) + 1e-7
    return LightGrid(R, s_min - ps, s_max + ps, t_min - pt, t_max + pt,
                     max(r_near - pad, 0.0), r_far + pad, z_near=float(np.min(z0)))
