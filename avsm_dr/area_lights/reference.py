"""Mitsuba 3 ground truth for area-light scenes: ``volpath`` with single scattering.

The same scene in Mitsuba: a ``homogeneous`` medium (albedo sigma_s / sigma_t, ``isotropic`` or
``hg`` phase) in a null-BSDF ``cube`` reaching slightly below the diffuse ``rectangle`` floor,
diffuse occluders and a one-sided ``rectangle`` ``area`` emitter.  ``volpath`` with
``max_depth = 2`` (Russian roulette off) is single scattering with next-event estimation; rays
are the pixel-centre rays of :meth:`PinholeCamera.rays` (no pixel filter), started in the medium.

The variant is set when a function is called (:func:`avsm_dr.groundtruth.mitsuba`), never at import.
"""
from __future__ import annotations

import math

import drjit as dr
import numpy as np

from .area_scene import AreaLightScene
from ..groundtruth.media import mitsuba as _mi
from ..scene import OpaqueBox, affine
from ..validation import integer as check_count


def _to_world(mi, cols, origin):
    return mi.ScalarTransform4f(affine(cols, origin).tolist())


def scene_dict(scene: AreaLightScene) -> dict:
    """The Mitsuba scene description (a dict for ``mi.load_dict``)."""
    mi = _mi()
    med = scene.medium
    lo, hi = scene.bounds
    mlo = lo - np.array([0.0, 0.01 * (hi[1] - lo[1]), 0.0])
    phase = {"type": "isotropic"} if med.g == 0 else {"type": "hg", "g": float(med.g)}
    albedo = med.sigma_s / med.sigma_t if med.sigma_t > 0 else 0.0
    d = {
        "type": "scene",
        "medium_box": dict(OpaqueBox(mlo, hi).to_mitsuba(mi, {"type": "null"}), interior={
            "type": "homogeneous", "albedo": float(albedo), "sigma_t": float(med.sigma_t), "phase": phase}),
        "floor": {
            "type": "rectangle",
            "to_world": _to_world(mi, [[(hi[0] - lo[0]) / 2, 0, 0], [0, 0, -(hi[2] - lo[2]) / 2], [0, 1, 0]],
                                [(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2]),
            "bsdf": {"type": "diffuse", "reflectance": float(scene.floor_albedo)},
        },
        "light": {
            "type": "rectangle",
            "to_world": _to_world(mi, [scene.light.edge_u / 2, scene.light.edge_v / 2, scene.light.normal],
                                scene.light.center),
            "emitter": {"type": "area", "radiance": float(scene.light.radiance)},
            "bsdf": {"type": "diffuse", "reflectance": 0.0},
        }}
    for i, o in enumerate(scene.occluders):
        d[f"occluder_{i}"] = o.to_mitsuba(mi, {"type": "diffuse", "reflectance": float(o.albedo)})
    return d


def render_mitsuba(scene: AreaLightScene, spp: int = 256, seed: int = 0, max_lanes: int = 2 ** 21,
                   max_depth: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth image (H, W) by Mitsuba ``volpath``, and its per-pixel standard error.

    spp: samples per pixel (>= 16), split into >= 16 independent passes; the standard error is
    the spread of the pass means / sqrt(passes) (t-distributed z-scores, 15 dof at 16 passes).
    max_depth: 2 = single scattering (3 adds double scattering)."""
    if not isinstance(scene, AreaLightScene):
        raise ValueError(f"scene: expected AreaLightScene, got {type(scene).__name__}")
    spp = check_count(spp, "spp", 16)
    check_count(max_depth, "max_depth", 1)
    mi = _mi()
    msc = mi.load_dict(scene_dict(scene))
    medium = [s for s in msc.shapes() if s.is_medium_transition()][0].interior_medium()
    integrator = mi.load_dict({"type": "volpath", "max_depth": int(max_depth), "rr_depth": 10 ** 6})
    cam = scene.camera
    n_pix = cam.width * cam.height
    passes = max(16, math.ceil(spp * n_pix / max_lanes))
    per_pass = [spp // passes + (1 if i < spp % passes else 0) for i in range(passes)]
    dirs = cam.rays().astype(np.float32)
    means = []
    sampler = mi.load_dict({"type": "independent"})
    for i, s in enumerate(per_pass):
        d = np.repeat(dirs, s, axis=0)
        ray = mi.RayDifferential3f(mi.Ray3f(mi.Point3f(*[float(v) for v in cam.origin]),
                                            mi.Vector3f(d[:, 0], d[:, 1], d[:, 2])))
        sampler.seed(seed * 7919 + i, n_pix * s)
        L, valid, _ = integrator.sample(msc, sampler, ray, medium, True)
        y = dr.select(valid, (L[0] + L[1] + L[2]) / 3, 0)
        means.append(np.asarray(dr.block_sum(y, s).numpy(), np.float64) / s)
    M = np.stack(means)
    w = np.array(per_pass, np.float64)[:, None]
    mean = (M * w).sum(0) / w.sum()
    # pass sizes differ by at most one sample: treat the pass means as i.i.d.
    stderr = M.std(0, ddof=1) / math.sqrt(passes)
    return mean.reshape(cam.height, cam.width), stderr.reshape(cam.height, cam.width)
