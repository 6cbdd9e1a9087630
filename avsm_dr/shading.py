"""Receivers and images shadowed by any transmittance representation.

Diffuse receiver lit by one light (no shadowing other than ``T``)::

    L_o(x) = rho / pi * E(x) * T(x) * max(0, n . l)

with ``E`` the unshadowed irradiance normal to the light (directional:
``irradiance``; point: ``I / r^2``; spot: ``I * falloff / r^2`` with Mitsuba's
``spot`` profile, full intensity inside ``beam_width = 3/4 * fov/2`` and linear in
angle down to 0 at the cutoff ``fov/2``), ``T`` the light's transmittance to ``x``
and ``l`` the unit direction to the light.

:func:`render_plane` draws the receiver plane of a scene from the same camera
and with the same conventions as :func:`avsm_dr.groundtruth.render_reference`
(two-sided diffuse square, black blockers, black background, box pixel filter,
rays from Mitsuba's own sensor), so the two images are comparable pixel by pixel::

    pixel = mean over s x s sub-pixel rays of  T_view(cam -> x) * L_o(x)   [+ L_ss]

``T_view`` is the (ground truth, float64 ray-marched) attenuation of the view ray
through the medium and particles; only the light's transmittance ``T`` comes from
the representation under test.  Optional single scattering (``albedo > 0``),
isotropic phase ``1 / (4 pi)``, midpoint rule with step ``h`` along the view ray::

    L_ss = sum_j h * T_view(t_j) * albedo * sigma_t(x_j) / (4 pi) * E(x_j) * T(x_j)

(the view ray's attenuation by particles is left out of ``L_ss``; hair is not
drawn).  This equals Mitsuba's ``volpath`` with ``max_depth = 2``.
"""
from __future__ import annotations

import math

import numpy as np

from . import validation as V
from .groundtruth.content import check_scene, particles_tau, to_light
from .groundtruth.images import camera_rays, check_camera, receiver_plane, receiver_plane_for
from .groundtruth.tracking import default_step, march, transmittance as gt_transmittance
from .scene import OpaquePlane, Scene, check_light

#: Points per call of a light-transmittance callable (host memory bound; the ground truth
#: marches at most ``groundtruth.MAX_SAMPLES`` = 2^28 samples per call, ~1000 per point).
CHUNK = 1 << 18


def irradiance(light, points) -> np.ndarray:
    """(K,) unshadowed irradiance E on a surface facing the light at ``points``
    (:meth:`~avsm_dr.scene.Light.irradiance_at`)."""
    return check_light(light).irradiance_at(V.points(points, allow_empty=True))


def shade_receivers(scene: Scene, transmittance, points=None, normals=None, albedo: float = 1.0) -> np.ndarray:
    """(K,) outgoing radiance ``albedo / pi * E * T * cos`` of diffuse receivers.

    transmittance: (K,) T at the points (any representation, or ground truth).
    points: (K, 3), default ``scene.receivers``.  normals: (K, 3) or (3,) one-sided
    normals (cos = max(0, n . l)); default: the receiver plane's normal, two-sided
    (cos = |n . l|), or cos = 1 (receivers facing the light) without a plane.
    """
    p = V.points(scene.receivers if points is None else points)
    T = V.array(transmittance, "transmittance").reshape(-1)
    if T.size != p.shape[0]:
        raise ValueError(f"transmittance: length {T.size} does not match {p.shape[0]} points")
    albedo = V.real(albedo, "albedo", 0.0)
    l = to_light(scene.light, p)
    if normals is not None:
        n = V.points(normals, "normals")
        if n.shape[0] not in (1, p.shape[0]):
            raise ValueError(f"normals: expected (3,) or ({p.shape[0]}, 3), got {n.shape}")
        n = np.broadcast_to(n, p.shape)
        m = np.max(np.abs(n), axis=1, keepdims=True)
        if np.any(m == 0):
            raise ValueError("normals: zero-length normal")
        n = n / m                                        # no overflow in the norm
        cos = np.maximum(np.sum(n / np.linalg.norm(n, axis=1, keepdims=True) * l, axis=1), 0.0)
    elif scene.receiver_plane is not None:
        _, n, _ = receiver_plane(scene)
        cos = np.abs(l @ n)
    else:
        cos = np.ones(p.shape[0])
    return albedo / math.pi * irradiance(scene.light, p) * T * cos


def _hit_blockers(o, d, blockers):
    """Nearest t > 0 of rays with any opaque blocker (inf = none)."""
    t = np.full(o.shape[0], np.inf)
    for b in blockers:
        t = np.minimum(t, b.surface_hit(o, d))
    return t


def _light_T(fn, x, mask):
    """(N,) T >= 0 of the light-transmittance callable ``fn`` at ``x[mask]`` (0 elsewhere),
    :data:`CHUNK` points per call."""
    T, idx = np.zeros(x.shape[0]), np.flatnonzero(mask)
    for a in range(0, idx.size, CHUNK):
        T[idx[a:a + CHUNK]] = np.clip(np.asarray(fn(x[idx[a:a + CHUNK]]), np.float64).reshape(-1), 0.0, None)
    return T


def render_plane(scene: Scene, light_transmittance, width: int = 128, height: int = 128,
                 camera=None, supersample: int = 2, reflectance: float = 1.0,
                 albedo: float = 0.0, step: float | None = None) -> np.ndarray:
    """(height, width) float64 image of the receiver plane lit through ``light_transmittance``.

    light_transmittance: callable (N, 3) world points -> (N,) T from the light (e.g. a
    representation via :func:`shade_plane`, or ground truth).  Called only where
    the light reaches (E * cos > 0).  supersample: s x s stratified rays per pixel.
    albedo > 0 adds single scattering in the medium (step: march step along view
    rays, default half the smallest voxel side).  See the module docstring.
    """
    content = check_scene(scene)
    cam = check_camera(scene, camera)
    c, n, half = receiver_plane_for(scene, cam)
    if not callable(light_transmittance):
        raise ValueError("light_transmittance: expected a callable points -> T")
    albedo = V.real(albedo, "albedo", 0.0, 1.0)
    reflectance = V.real(reflectance, "reflectance", 0.0)
    if step is not None:
        step = V.real(step, "step", 0.0, open_min=True)
    s = V.integer(supersample, "supersample", 1)
    o, d = camera_rays(scene, width, height, cam, s)
    t_plane = OpaquePlane(c, n, half).surface_hit(o, d)     # the receiver square, the same test
    t_block = _hit_blockers(o, d, content["blockers"])
    on_plane = np.isfinite(t_plane) & (t_plane < t_block)
    t_end = np.minimum(t_plane, t_block)
    radiance = np.zeros(o.shape[0])

    idx = np.nonzero(on_plane)[0]
    if idx.size:
        x = o[idx] + t_plane[idx, None] * d[idx]
        l = to_light(scene.light, x)
        n_cam = np.where(((-d[idx]) @ n)[:, None] >= 0, n, -n)
        shade = reflectance / math.pi * irradiance(scene.light, x) * np.maximum(np.sum(n_cam * l, 1), 0.0)
        T = _light_T(light_transmittance, x, shade > 0)
        radiance[idx] = shade * T * np.exp(-_view_tau(content, o[idx], d[idx], t_plane[idx]))

    if albedo > 0 and content["grid"] is not None:
        radiance += _single_scattering(scene, content, o, d, t_end, light_transmittance, albedo, step)
    return radiance.reshape(height, width, s * s).mean(axis=2)


def _view_tau(content, o, d, L):
    """Optical depth along view rays [0, L]: grid (float64 ray march) + particle chords."""
    tau = np.zeros(o.shape[0])
    if content["grid"] is not None:
        g, lo, hi = content["grid"]
        tau += march(g.astype(np.float64), lo, hi, o, d, L, default_step(g, lo, hi, 1 / 4))[0]
    if content["particles"] is not None:
        tau += particles_tau(content["particles"], o, d, L)
    return tau


def _single_scattering(scene, content, o, d, t_end, light_T, albedo, step):
    """L_ss of the module docstring along view rays [0, t_end] (the ground truth's ray march)."""
    g, lo, hi = content["grid"]
    if step is None:
        step = default_step(g, lo, hi, 1 / 2)

    def integrand(x, sig, h, tau_view):
        w = h * np.exp(-tau_view) * albedo * sig / (4 * math.pi) * irradiance(scene.light, x)
        return w * _light_T(light_T, x, w > 0)

    return march(g.astype(np.float64), lo, hi, o, d, t_end, step, integrand)[1]


def shade_plane(scene: Scene, rep, capture, width: int = 128, height: int = 128,
                camera=None, filter: str = "point", radius: float = 1.0, **kw) -> np.ndarray:
    """The :func:`render_plane` image with shadows from representation ``rep``.

    T at a world point = ``capture.transmittance(rep, points, filter, radius)`` (1 where
    the light's map does not reach, see :meth:`avsm_dr.capture.Capture.lookup`).
    Extra keywords go to :func:`render_plane` (supersample, reflectance, albedo, step).
    """
    def light_T(points):
        return np.asarray(capture.transmittance(rep, points, filter=filter, radius=radius), np.float64)
    return render_plane(scene, light_T, width, height, camera, **kw)


def groundtruth_plane(scene: Scene, width: int = 128, height: int = 128, camera=None,
                      step: float | None = None, **kw) -> np.ndarray:
    """:func:`render_plane` with the deterministic ground-truth transmittance (ray march)."""
    def light_T(points):
        return gt_transmittance(scene, points, method="raymarch", step=step)[0]
    return render_plane(scene, light_T, width, height, camera, **kw)

