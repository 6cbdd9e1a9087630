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
rays from Mitsuba's own sensor), so the two images are comparable pixel by pixel:

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

from . import groundtruth as gt
from .scene import DirectionalLight, OpaqueBox, OpaquePlane, OpaqueSphere, Scene, SpotLight

#: Points per chunk when querying a representation (host memory bound).
CHUNK = 1 << 20


# ================================================================== lighting
def spot_falloff(light: SpotLight, points) -> np.ndarray:
    """(K,) Mitsuba ``spot`` profile in [0, 1] at ``points`` (K, 3)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    v = p - light.position
    r = np.linalg.norm(v, axis=1)
    cos = np.where(r > 0, (v @ light.direction) / np.where(r > 0, r, 1.0), 1.0)
    cutoff = math.radians(light.fov / 2)
    beam = math.radians(gt.spot_beam_width(light))
    ang = np.arccos(np.clip(cos, -1.0, 1.0))
    prof = np.where(cos >= math.cos(beam), 1.0, (cutoff - ang) / (cutoff - beam))
    return np.where(cos > math.cos(cutoff), prof, 0.0)


def irradiance(light, points) -> np.ndarray:
    """(K,) unshadowed irradiance E on a surface facing the light at ``points``."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if isinstance(light, DirectionalLight):
        return np.full(p.shape[0], float(light.irradiance))
    r2 = np.sum((p - light.position) ** 2, axis=1)
    e = float(light.intensity) / np.maximum(r2, 1e-300)
    if isinstance(light, SpotLight):
        e = e * spot_falloff(light, p)
    return e


def shade_receivers(scene: Scene, transmittance, points=None, normals=None,
                    albedo: float = 1.0) -> np.ndarray:
    """(K,) outgoing radiance ``albedo / pi * E * T * cos`` of diffuse receivers.

    transmittance: (K,) T at the points (any representation, or ground truth).
    points: (K, 3), default ``scene.receivers``.  normals: (K, 3) or (3,) one-sided
    normals (cos = max(0, n . l)); default: the receiver plane's normal, two-sided
    (cos = |n . l|), or cos = 1 (receivers facing the light) without a plane.
    """
    p = gt.check_points(scene.receivers if points is None else points)
    T = np.asarray(transmittance, np.float64).reshape(-1)
    if T.size != p.shape[0]:
        raise ValueError(f"transmittance: length {T.size} does not match {p.shape[0]} points")
    if not np.all(np.isfinite(T)):
        raise ValueError("transmittance: contains NaN or inf")
    if not (np.isfinite(albedo) and albedo >= 0):
        raise ValueError(f"albedo: must be a finite number >= 0, got {albedo!r}")
    l = gt._to_light(scene.light, p)
    if normals is not None:
        n = np.asarray(normals, np.float64)
        n = np.broadcast_to(n.reshape(-1, 3) if n.size != 3 else n.reshape(1, 3), p.shape)
        if not np.all(np.isfinite(n)):
            raise ValueError("normals: contains NaN or inf")
        nn = np.linalg.norm(n, axis=1, keepdims=True)
        if np.any(nn == 0):
            raise ValueError("normals: zero-length normal")
        cos = np.maximum(np.sum(n / nn * l, axis=1), 0.0)
    elif scene.receiver_plane is not None:
        _, n, _ = gt._receiver_plane(scene)
        cos = np.abs(l @ n)
    else:
        cos = np.ones(p.shape[0])
    return albedo / math.pi * irradiance(scene.light, p) * T * cos


# ================================================================ ray casting
def _hit_plane(o, d, c, n, half):
    """t (N,) of rays with the square (c, n, half) oriented by plane_basis; inf = miss."""
    u, v, n = gt.plane_basis(n)
    den = d @ n
    ok = np.abs(den) > 1e-300
    t = np.where(ok, ((c - o) @ n) / np.where(ok, den, 1.0), np.inf)
    q = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d - c
    ok &= (t > 0) & (np.abs(q @ u) <= half) & (np.abs(q @ v) <= half)
    return np.where(ok, t, np.inf)


def _hit_blockers(o, d, blockers):
    """Nearest t > 0 of rays with any opaque blocker (inf = none)."""
    t = np.full(o.shape[0], np.inf)
    for b in blockers:
        if isinstance(b, OpaqueSphere):
            t0, t1, hit = gt.ray_sphere(o, d, np.asarray(b.center, np.float64), float(b.radius))
            th = np.where(t0 > 0, t0, t1)
            t = np.where(hit & (th > 0), np.minimum(t, th), t)
        elif isinstance(b, OpaqueBox):
            t0, t1 = gt.ray_box(o, d, np.asarray(b.min, np.float64), np.asarray(b.max, np.float64))
            th = np.where(t0 > 0, t0, t1)
            t = np.where((t0 <= t1) & (th > 0), np.minimum(t, th), t)
        elif isinstance(b, OpaquePlane):
            t = np.minimum(t, _hit_plane(o, d, np.asarray(b.point, np.float64), b.normal, float(b.extent)))
    return t


def _chunked(fn, x):
    out = np.empty(x.shape[0])
    for a in range(0, x.shape[0], CHUNK):
        out[a:a + CHUNK] = np.asarray(fn(x[a:a + CHUNK]), np.float64).reshape(-1)
    return out


# ==================================================================== images
def render_plane(scene: Scene, light_transmittance, width: int = 128, height: int = 128,
                 camera: dict | None = None, supersample: int = 2, reflectance: float = 1.0,
                 albedo: float = 0.0, step: float | None = None) -> np.ndarray:
    """(height, width) float64 image of the receiver plane lit through ``light_transmittance``.

    light_transmittance: callable (N, 3) world points -> (N,) T from the light (e.g. a
    representation via :func:`shade_plane`, or ground truth).  Called only where
    the light reaches (E * cos > 0).  supersample: s x s stratified rays per pixel.
    albedo > 0 adds single scattering in the medium (step: march step along view
    rays, default half the smallest voxel side).  See the module docstring.
    """
    content = gt._check_scene(scene)
    cam = gt.check_camera(scene, camera)
    c, n, half = gt.receiver_plane_for(scene, cam)
    if not callable(light_transmittance):
        raise ValueError("light_transmittance: expected a callable points -> T")
    if not (0 <= albedo <= 1):
        raise ValueError(f"albedo: must lie in [0, 1], got {albedo!r}")
    s = int(supersample)
    o, d = gt.camera_rays(scene, width, height, cam, s)
    N = o.shape[0]
    t_plane = _hit_plane(o, d, c, n, half)
    t_block = _hit_blockers(o, d, content["blockers"])
    on_plane = np.isfinite(t_plane) & (t_plane < t_block)
    t_end = np.minimum(t_plane, t_block)
    radiance = np.zeros(N)

    idx = np.nonzero(on_plane)[0]
    if idx.size:
        x = o[idx] + t_plane[idx, None] * d[idx]
        l = gt._to_light(scene.light, x)
        n_cam = np.where(((-d[idx]) @ n)[:, None] >= 0, n, -n)
        shade = reflectance / math.pi * irradiance(scene.light, x) * np.maximum(np.sum(n_cam * l, 1), 0.0)
        lit = shade > 0
        T = np.zeros(idx.size)
        if lit.any():
            T[lit] = np.clip(_chunked(light_transmittance, x[lit]), 0.0, None)
        radiance[idx] = shade * T * np.exp(-_view_tau(content, o[idx], d[idx], t_plane[idx]))

    if albedo > 0 and content["grid"] is not None:
        radiance += _single_scattering(scene, content, o, d, t_end, light_transmittance, albedo, step)
    return radiance.reshape(height, width, s * s).mean(axis=2) if s > 1 else \
        radiance.reshape(height, width)


def _view_tau(content, o, d, L):
    """Optical depth along view rays [0, L]: grid (float64 ray march) + particle chords."""
    tau = np.zeros(o.shape[0])
    if content["grid"] is not None:
        g, lo, hi = content["grid"]
        step = float(np.min((hi - lo) / np.array(g.shape[::-1]))) / 4
        tau += gt._raymarch(g.astype(np.float64), lo, hi, o, d, L, step)
    if content["particles"] is not None:
        tau += gt._particles_tau(content["particles"], o, d, L)
    return tau


def _single_scattering(scene, content, o, d, t_end, light_T, albedo, step):
    g, lo, hi = content["grid"]
    g = g.astype(np.float64)
    if step is None:
        step = float(np.min((hi - lo) / np.array(g.shape[::-1]))) / 2
    t0, t1 = gt.ray_box(o, d, lo, hi)
    t0 = np.maximum(t0, 0.0)
    t1 = np.minimum(t1, t_end)
    length = np.where(t1 > t0, t1 - t0, 0.0)
    cnt = np.ceil(length / step).astype(np.int64)
    h = np.where(cnt > 0, length / np.maximum(cnt, 1), 0.0)
    out = np.zeros(o.shape[0])
    rays = np.nonzero(cnt)[0]
    start = 0
    while start < rays.size:
        csum = np.cumsum(cnt[rays[start:]])
        stop = start + max(1, int(np.searchsorted(csum, CHUNK, side="right")))
        r = rays[start:stop]
        k = cnt[r]
        rid = np.repeat(np.arange(r.size), k)
        first = np.cumsum(k) - k
        j = np.arange(k.sum()) - np.repeat(first, k)
        hh = h[r][rid]
        t = t0[r][rid] + (j + 0.5) * hh
        x = o[r][rid] + t[:, None] * d[r][rid]
        sig = gt._sample(g, lo, hi, x)
        # view transmittance to the sample: all earlier pieces plus half of its own
        od = sig * hh
        cum = np.cumsum(od)
        before = cum - od - np.repeat(cum[first] - od[first], k)
        tv = np.exp(-(before + 0.5 * od))
        e = irradiance(scene.light, x)
        w = hh * tv * albedo * sig / (4 * math.pi) * e
        m = w > 0
        T = np.zeros(x.shape[0])
        if m.any():
            T[m] = np.clip(np.asarray(light_T(x[m]), np.float64).reshape(-1), 0.0, None)
        out[r] = np.bincount(rid, weights=w * T, minlength=r.size)
        start = stop
    return out


def shade_plane(scene: Scene, rep, capture, width: int = 128, height: int = 128,
                camera: dict | None = None, filter: str = "point", radius: float = 1.0,
                **kw) -> np.ndarray:
    """The :func:`render_plane` image with shadows from representation ``rep``.

    T at a world point = ``rep.eval(*capture.lookup(points))`` (``filter='point'``), or
    ``rep.eval(coords, depth, filter=..., width=capture.width, height=capture.height)``
    with ``coords, depth = capture.lookup(points, continuous=True)`` for other filters.
    Extra keywords go to :func:`render_plane` (supersample, reflectance, albedo, step).
    """
    def light_T(points):
        if filter == "point":
            texel, depth = capture.lookup(points)
            return np.asarray(rep.eval(texel, depth), np.float64)
        coords, depth = capture.lookup(points, continuous=True)
        return np.asarray(rep.eval(coords, depth, filter=filter, width=capture.width,
                                   height=capture.height, radius=radius), np.float64)
    return render_plane(scene, light_T, width, height, camera, **kw)


def groundtruth_plane(scene: Scene, width: int = 128, height: int = 128, camera: dict | None = None,
                      step: float | None = None, **kw) -> np.ndarray:
    """:func:`render_plane` with the deterministic ground-truth transmittance (ray march)."""
    def light_T(points):
        return gt.transmittance(scene, points, method="raymarch", step=step)[0]
    return render_plane(scene, light_T, width, height, camera, **kw)


# ================================================================ comparison
def compare_images(a, b) -> dict:
    """Error of image ``b`` against reference ``a`` (same shape).

    Returns dict(rmse, max_abs, mean_abs, rel_rmse = rmse / mean |a|, diff4x = 4 |a - b|).
    """
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"b: shape {b.shape} does not match a's {a.shape}")
    if a.size == 0:
        raise ValueError("a: empty image")
    for name, x in (("a", a), ("b", b)):
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{name}: contains NaN or inf")
    diff = a - b
    rmse = float(np.sqrt(np.mean(diff ** 2)))
    scale = float(np.mean(np.abs(a)))
    return {"rmse": rmse, "max_abs": float(np.abs(diff).max()), "mean_abs": float(np.mean(np.abs(diff))),
            "rel_rmse": rmse / scale if scale > 0 else float("inf"), "diff4x": 4 * np.abs(diff)}


def plot_comparison(reference, ours, path=None, titles=("Mitsuba reference", "ours", "4x |difference|"),
                    vmax: float | None = None, dpi: int = 100):
    """Reference / ours / 4x |difference| side by side (same grey scale); saved as PNG at ``path``.

    Returns the matplotlib Figure (no pyplot state is touched).
    """
    from matplotlib.figure import Figure
    cmp = compare_images(reference, ours)
    ref = np.asarray(reference, np.float64)
    if vmax is None:
        vmax = float(np.percentile(ref, 99.5)) or 1.0
    fig = Figure(figsize=(12, 4.2), dpi=dpi)
    axes = fig.subplots(1, 3)
    for ax, img, title in zip(axes, (ref, np.asarray(ours, np.float64), cmp["diff4x"]), titles):
        im = ax.imshow(img, cmap="gray", vmin=0.0, vmax=vmax, interpolation="nearest")
        ax.set_title(title)
        ax.set_axis_off()
    fig.colorbar(im, ax=axes, fraction=0.02)
    fig.suptitle(f"RMSE {cmp['rmse']:.4g}   max |diff| {cmp['max_abs']:.4g}   "
                 f"relative RMSE {cmp['rel_rmse']:.3%}")
    if path is not None:
        fig.savefig(path)
    return fig
