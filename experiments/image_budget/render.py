"""Images of the ``image_budget`` study: the temporal study's plume frames as Mitsuba scenes,
renders with ``avsm_single_scatter`` (recording the bytes per texel of the map it built), the
``volpath`` reference in two independent halves, and the fixed tonemap + FLIP.

Scene (one per frame): the plume's density grid (:data:`experiments.temporal.scenes.PLUME_BOX`)
as a ``heterogeneous`` medium (albedo :data:`ALBEDO`) in a null-BSDF cube, the receiver wall of
the temporal study (:data:`experiments.temporal.scenes.PLUME_WALL`, diffuse, reflectance
:data:`WALL_REFLECTANCE`) behind it, the frame's light, a pinhole camera (:data:`CAMERA`) that
sees the smoke's self-shadowing and its shadow on the wall; box pixel filter.  The light: a
directional light of irradiance :data:`IRRADIANCE`, or a spot light (the configurations'
``spot``) of intensity ``IRRADIANCE * d^2``, the same irradiance at the plume box's centre at
distance ``d`` (Mitsuba's ``spot``: cutoff half the light's ``fov``).

Tonemap (fixed per animation, so frames and kinds compare): ``sRGB(min(I / S, 1))`` with the
display white ``S`` = the 99.5th percentile of frame 0's reference (per configuration); FLIP
(``flip_evaluator``, LDR mode, its default 67 pixels per degree) of the encoded images, the
red channel replicated (grey light and media).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..temporal import scenes as S

#: Single-scattering albedo of the smoke.
ALBEDO = 0.9
#: Diffuse reflectance of the wall behind the smoke (dim, so the smoke and the shadow both show).
WALL_REFLECTANCE = 0.25
#: Irradiance of the directional light (the tonemap's white follows the reference, so only
#: the ratio of smoke to wall matters).
IRRADIANCE = 3.0
#: Pinhole camera: in front of the plume, to the light's side, looking at the plume and the wall.
CAMERA = dict(origin=[-1.6, 1.2, 2.8], target=[0.3, 0.75, 0.0], up=[0.0, 1.0, 0.0], fov=36.0)
#: Percentile of frame 0's reference that maps to display white.
WHITE_PERCENTILE = 99.5


def mitsuba():
    """Mitsuba with the package's variant and the ``avsm_single_scatter`` plugin registered."""
    from avsm_dr import groundtruth as gt
    mi = gt.mitsuba()
    import avsm_dr.mitsuba  # noqa: F401  (registers the integrator for the variant)
    return mi


def emitter(mi, light) -> dict:
    """``load_dict`` description of the frame's light (module docstring): a DirectionalLight
    or a SpotLight."""
    from avsm_dr.scene import DirectionalLight, SpotLight
    if isinstance(light, DirectionalLight):
        return {"type": "directional", "direction": [float(v) for v in light.direction], "irradiance": IRRADIANCE}
    if isinstance(light, SpotLight):
        c = 0.5 * (np.asarray(S.PLUME_BOX[0], np.float64) + np.asarray(S.PLUME_BOX[1], np.float64))
        d2 = float(np.sum((c - light.position) ** 2))
        return dataclasses.replace(light, intensity=IRRADIANCE * d2).to_mitsuba(mi)
    raise ValueError(f"light: expected a DirectionalLight or SpotLight, got {type(light).__name__}")


def scene_dict(mi, density, light, image: int) -> dict:
    """``load_dict`` description of one frame (module docstring), ``image`` x ``image`` pixels."""
    from avsm_dr.groundtruth import media
    lo, hi = (np.asarray(b, np.float64) for b in S.PLUME_BOX)
    c, _normal, half = S.PLUME_WALL          # the wall faces -x (towards the plume)
    T = mi.ScalarTransform4f
    cube = media.grid_to_world(mi, lo, hi) @ T().translate([0.5, 0.5, 0.5]) @ T().scale(0.5)   # [-1, 1]^3 -> box
    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": CAMERA["fov"],
                   "to_world": T().look_at(origin=CAMERA["origin"], target=CAMERA["target"], up=CAMERA["up"]),
                   "film": {"type": "hdrfilm", "width": int(image), "height": int(image),
                            "rfilter": {"type": "box"}}},
        "light": emitter(mi, light),
        "smoke": {"type": "cube", "bsdf": {"type": "null"}, "to_world": cube,
                  "interior": media.medium_dict(mi, np.asarray(density, np.float32), lo, hi, ALBEDO)},
        "wall": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": WALL_REFLECTANCE},
                 "to_world": T().translate([float(v) for v in c]).rotate([0, 1, 0], -90).scale([half, half, 1])},
    }


def load_scene(mi, frame, image: int):
    """The Mitsuba scene of a temporal :class:`~experiments.temporal.scenes.Frame`."""
    return mi.load_dict(scene_dict(mi, frame.scene.density, frame.scene.light, image))


def recording_class(mi):
    """``avsm_single_scatter``'s class for the current variant, extended to record the bytes
    per texel of the representation each render builds (``bytes_per_texel``: dense,
    ``nbytes_per_texel``; ``sparse_bytes``: ``nbytes_sparse_per_texel``) and the map itself
    (``last_map``: (segments, representation) of the last render, for its curve metrics; the
    caller clears it)."""
    from avsm_dr import mitsuba as am
    base = am.integrator_class()

    class Recording(base):
        bytes_per_texel = float("nan")
        sparse_bytes = float("nan")
        last_map = None

        def prepare_shadow(self, scene):
            shadow = super().prepare_shadow(scene)
            self.bytes_per_texel = float(shadow[1].nbytes_per_texel)
            self.sparse_bytes = float(shadow[1].nbytes_sparse_per_texel)
            self.last_map = (shadow[0].segments, shadow[1])
            return shadow
    return Recording


def curve_metrics(mi, segments, rep, reference) -> dict:
    """The curve metrics of one render's map against ``reference``, the exact
    curve's :func:`avsm_dr.evaluation.curve_values` on the same segments (None: ``rep`` is the
    exact curve, all zero): ``depth_l2`` (:func:`avsm_dr.evaluation.depth_l2`), and over the
    same depth grid (opaque interiors left out) ``curve_signed_mean``, the mean of
    ``T_rep - T_exact`` (> 0: light leaking), and ``curve_leak_share``, the share above 0.02
    (:func:`avsm_dr.metrics.error_stats`).  Evaluated on the Mitsuba variant's backend; the
    curve is evaluated once (``depth_l2``'s formula on its values: the RMS over texels of
    ``sqrt(mean over the kept depths of (T_rep - T_exact)^2)``)."""
    from avsm_dr import backend
    from avsm_dr.evaluation import curve_values, depth_grid
    from avsm_dr.evaluation.curves import rms
    from avsm_dr.metrics import error_stats
    if reference is None:
        return dict(depth_l2=0.0, curve_signed_mean=0.0, curve_leak_share=0.0)
    with backend.use_backend("cuda" if mi.variant().startswith("cuda") else "llvm"):
        est = curve_values(rep, segments)
    keep, ref = depth_grid(segments)[2], np.asarray(reference, np.float64)
    l2 = rms(np.sqrt(np.sum(np.square(est - ref) * keep, axis=1) / np.maximum(keep.sum(axis=1), 1)))
    s = error_stats(est[keep], ref[keep])
    return dict(depth_l2=float(l2), curve_signed_mean=float(s["mean_error"]),
                curve_leak_share=float(s["leak_fraction"]))


def exact_curve(mi, segments, rep) -> np.ndarray:
    """:func:`avsm_dr.evaluation.curve_values` of the exact map ``rep`` on ``segments`` (the
    ``reference`` of :func:`curve_metrics`), on the Mitsuba variant's backend."""
    from avsm_dr import backend
    from avsm_dr.evaluation import curve_values
    with backend.use_backend("cuda" if mi.variant().startswith("cuda") else "llvm"):
        return curve_values(rep, segments)


def integrator(mi, cls, kind: str, params: dict, resolution: int, march_steps: int):
    """An ``avsm_single_scatter`` integrator (of ``cls``) for ``kind`` with ``params``."""
    from avsm_dr import mitsuba as am
    props = mi.Properties(am.NAME)
    props["representation"] = kind
    props["resolution"] = int(resolution)
    props["march_steps"] = int(march_steps)
    for k, v in params.items():
        props[k] = v
    return cls(props)


def render(mi, scene, integ, spp: int, seed: int) -> np.ndarray:
    """(H, W) float64 red channel of ``mi.render``."""
    return np.asarray(mi.render(scene, integrator=integ, spp=int(spp), seed=int(seed)), np.float64)[..., 0]


def reference_halves(mi, scene, spp: int, seeds) -> tuple[np.ndarray, np.ndarray]:
    """Two independent ``volpath`` (max_depth 2: single scattering) renders of ``spp`` each."""
    vp = mi.load_dict({"type": "volpath", "max_depth": 2})
    return render(mi, scene, vp, spp, seeds[0]), render(mi, scene, vp, spp, seeds[1])


def white(reference) -> float:
    """Display white ``S`` of an animation: the :data:`WHITE_PERCENTILE` percentile of its
    frame-0 reference (> 0)."""
    s = float(np.percentile(np.asarray(reference, np.float64), WHITE_PERCENTILE))
    if not s > 0:
        raise ValueError("reference: the image is black; no display white")
    return s


def _srgb(x):
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055)


def tonemap(img, s: float) -> np.ndarray:
    """(H, W, 3) float32 ``sRGB(min(max(img, 0) / s, 1))``: FLIP's LDR input."""
    x = _srgb(np.clip(np.asarray(img, np.float64) / s, 0.0, 1.0))
    return np.ascontiguousarray(np.repeat(x[..., None], 3, axis=2), np.float32)


def flip(a, b, s: float) -> float:
    """Mean FLIP (LDR) between images ``a`` (reference role) and ``b`` under :func:`tonemap` with white ``s``."""
    import flip_evaluator
    if np.array_equal(a, b):
        return 0.0
    return float(flip_evaluator.evaluate(tonemap(a, s), tonemap(b, s), "LDR", applyMagma=False)[1])
