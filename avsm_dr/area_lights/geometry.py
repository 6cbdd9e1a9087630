"""Vectorised ray geometry (Dr.Jit, one lane per ray, the types of :class:`Kit`): camera hits,
shadow-ray occlusion; scene constants enter kernels as literals."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from ..geometry import ray_box_dr
from .area_scene import AreaLightScene, safe_dir

#: Surface kinds returned by :func:`camera_hits`.
EXIT, DIFFUSE, LIGHT_FRONT, LIGHT_BACK = 0, 1, 2, 3


@dataclass(frozen=True)
class Kit:
    """Dr.Jit types for one precision: Float, Vec3, UInt32, Int32, Bool, PCG32."""
    Float: type
    Vec3: type
    UInt32: type
    Int32: type
    Bool: type
    PCG32: type

    def vec(self, v) -> object:
        """A width-1 Vec3 from 3 numbers, opaque: Dr.Jit 1.5 resizes a literal Array3f with a zero
        component in place when it meets a wider array."""
        v = np.asarray(v, np.float64)
        return self.Vec3(*(dr.opaque(self.Float, float(c)) for c in v))

    def vec_array(self, a: np.ndarray) -> object:
        """Vec3 of width N from an (N, 3) array."""
        a = np.asarray(a, np.float64)
        return self.Vec3(*(A.to_float(np.ascontiguousarray(a[:, c]), self.Float) for c in range(3)))


def kit(dtype: str = "float32") -> Kit:
    """The Dr.Jit types (Float, Vec3, UInt32, ...) of the current backend for ``dtype``."""
    t = backend.types()
    Float = A.float_type(dtype)
    Vec3 = t.Array3f if dtype == "float32" else t.Array3f64
    return Kit(Float, Vec3, t.UInt32, t.Int32, t.Bool, t.PCG32)


def occluded(scene: AreaLightScene, k: Kit, x, p, eps: float):
    """True where the open segment x -> p (shortened by eps at both ends) meets an occluder."""
    v = p - x
    r = dr.norm(v)
    d = v / dr.select(r > 0, r, 1)
    blocked = dr.zeros(k.Bool, dr.width(r))
    for occ in scene.occluders:
        t0, t1, h = occ.hit_dr(k, x, d)
        blocked |= h & (t1 > eps) & (t0 < r - eps)
    return blocked


@dataclass
class CameraHits:
    """Per pixel: origin o (width 1), unit direction d, end distance t_end (first surface
    or medium-box exit), surface kind, normal n and albedo at the end point."""
    o: object
    d: object
    t_end: object
    kind: object
    n: object
    albedo: object


def camera_hits(scene: AreaLightScene, k: Kit) -> CameraHits:
    """Closest hit of each pixel-centre camera ray with floor, occluders, light and box."""
    o = k.vec(scene.camera.origin)
    d = k.vec_array(scene.camera.rays())
    n_pix = dr.width(d)
    lo, hi = scene.bounds

    # -- medium box exit (the camera is inside) ------------------------------------
    _, t_best, _ = ray_box_dr(o, safe_dir(d), k.vec(lo), k.vec(hi))
    kind = dr.full(k.UInt32, EXIT, n_pix)
    nrm = k.Vec3(0, 1, 0) + dr.zeros(k.Vec3, n_pix)
    alb = dr.zeros(k.Float, n_pix)

    # -- floor: the bottom face y = lo_y; it wins near-ties with the box exit (the two
    #    distances round differently, which left unlit speckles on the floor) ---------
    dy = dr.select(d.y < 0, d.y, -1)
    t_floor = (float(lo[1]) - o.y) / dy
    m = (d.y < 0) & (t_floor <= t_best + 1e-5 * scene.extent)
    t_best = dr.select(m, t_floor, t_best)
    kind = dr.select(m, DIFFUSE, kind)
    alb = dr.select(m, float(scene.floor_albedo), alb)

    # -- occluders ------------------------------------------------------------------
    for occ in scene.occluders:
        t0, _, h = occ.hit_dr(k, o, d)
        m = h & (t0 > 0) & (t0 < t_best)
        t_best = dr.select(m, t0, t_best)
        kind = dr.select(m, DIFFUSE, kind)
        alb = dr.select(m, float(occ.albedo), alb)
        nrm = dr.select(m, occ.normal_dr(k, o + t0 * d), nrm)

    # -- the light quad: front side emits, back side is black ---------------------------
    L = scene.light
    ln = k.vec(L.normal)
    denom = dr.dot(d, ln)
    sd = dr.select(denom != 0, denom, 1)
    t_l = dr.dot(k.vec(L.center) - o, ln) / sd
    dual = np.linalg.pinv(np.stack([L.edge_u, L.edge_v], 1))     # (2, 3): a, b from x - c
    rel = o + t_l * d - k.vec(L.center)
    a = dr.dot(rel, k.vec(dual[0]))
    b = dr.dot(rel, k.vec(dual[1]))
    m = (denom != 0) & (t_l > 0) & (t_l < t_best) & (dr.abs(a) <= 0.5) & (dr.abs(b) <= 0.5)
    t_best = dr.select(m, t_l, t_best)
    kind = dr.select(m, dr.select(denom < 0, LIGHT_FRONT, LIGHT_BACK), kind)
    return CameraHits(o, d, t_best, kind, nrm, alb)
