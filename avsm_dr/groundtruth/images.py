"""Reference images with Mitsuba 3: the receiver plane, the volume and the blockers.

:func:`render_reference` renders with ``volpath``; :mod:`avsm_dr.shading` draws the same
plane from the same camera (:func:`camera_rays`, Mitsuba's own sensor) with shadows
from any representation, so the two images compare pixel by pixel.  A camera is an
:class:`avsm_dr.camera.PinholeCamera` or a dict of its fields (:meth:`PinholeCamera.of`);
:func:`default_camera` picks one.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from .. import validation as V
from ..camera import MAX_SIDE, PinholeCamera
from ..geometry import check_bbox, orthonormal_basis, ray_box
from ..scene import OpaqueBox, Scene, square_to_world
from .content import check_scene, to_light
from .media import check_grid, medium_dict, mitsuba
from .tracking import default_step, march

#: Most samples (pixels x spp) of one Mitsuba render: every sample is a lane of one
#: wavefront (hundreds of bytes each); average renders with several seeds for more.
MAX_RENDER_SAMPLES = 1 << 26
#: Most camera rays (pixels x supersample^2) of :func:`camera_rays`.
MAX_RAYS = 1 << 24


def default_camera(scene: Scene, fov: float = 40.0, distance: float | None = None, direction=None) -> PinholeCamera:
    """A camera looking at the receiver plane's centre from the light's side of the plane.

    The view direction v (from the plane centre to the camera) is ``direction`` if given;
    otherwise the candidate, among v0 = normalize(2 n + l) (n: the plane normal turned
    towards the light, l: unit direction to the light) and 32 directions tilted 25..60
    degrees from n, whose view of the plane is least hidden by the smoke: the smallest
    mean opacity 1 - exp(-tau) along 25 view rays to the plane (ray-marched), plus
    0.05 per radian away from v0 (prefer frontal views).  The distance frames the square
    with a 15 % margin (``distance`` overrides); a camera inside the volume's box is
    moved out along v with the fov narrowed to keep the framing.
    Returns a :class:`~avsm_dr.camera.PinholeCamera` of 32 x 32 pixels (fov in degrees along x;
    :meth:`~avsm_dr.camera.PinholeCamera.of` resizes it)."""
    fov = V.real(fov, "fov", 0.0, 180.0, open_min=True, open_max=True)
    if distance is not None:
        distance = V.real(distance, "distance", 0.0, open_min=True)
    if direction is not None:
        direction = V.unit_vector(direction, "direction")
    c, n, half = receiver_plane(scene)
    l = to_light(scene.light, c[None])[0]
    if n @ l < 0:
        n = -n
    u, w, _ = orthonormal_basis(n)
    grid = check_grid(scene.density, scene.bbox) if scene.density is not None and scene.bbox is not None else None

    def place(v):
        dist = distance
        f = fov
        if dist is None:
            dist = 1.15 * half / math.tan(math.radians(f) / 2) + half * abs(v @ n - 1)
            if grid is not None:
                t0, t1, _ = ray_box(c[None], v[None], grid[1], grid[2])
                if t0[0] <= t1[0] and t0[0] <= dist <= t1[0]:
                    dist = float(t1[0]) + 0.1 * half
                    f = min(f, 2 * math.degrees(math.atan(1.15 * half / dist)))
        return c + dist * v, f

    v0 = 2 * n + l
    v = v0 = v0 / np.linalg.norm(v0)
    if direction is not None:
        v = direction
    elif grid is not None:                 # the candidate whose view of the plane is least hidden
        g, lo, hi = grid
        a, b = np.meshgrid(np.linspace(-0.8, 0.8, 5), np.linspace(-0.8, 0.8, 5))
        targets = c + half * (a.reshape(-1, 1) * u + b.reshape(-1, 1) * w)
        step = default_step(g, lo, hi, 1 / 2)
        best = None
        for cand in [v0] + [math.cos(a) * n + math.sin(a) * (math.cos(p) * u + math.sin(p) * w)
                            for a in np.radians([25.0, 40.0, 50.0, 60.0])
                            for p in np.radians(np.arange(0.0, 360.0, 45.0))]:
            origin, f = place(cand)
            dv = targets - origin
            L = np.linalg.norm(dv, axis=1)
            tau, _ = march(g.astype(np.float64), lo, hi, np.broadcast_to(origin, dv.shape), dv / L[:, None], L, step)
            score = float(np.mean(1 - np.exp(-tau))) + 0.05 * math.acos(np.clip(cand @ v0, -1, 1))
            if best is None or score < best[0] - 1e-12:
                best = (score, cand)
        v = best[1]
    origin, f = place(v)
    up = w if abs(w @ v) < 0.9 else u
    return PinholeCamera(origin, c, up, float(f))


def receiver_plane(scene) -> tuple[np.ndarray, np.ndarray, float]:
    """(centre, unit normal, half size) of ``scene.receiver_plane``; ValueError names it."""
    if scene.receiver_plane is None:
        raise ValueError("scene: has no receiver_plane = (point, normal, half_size)")
    try:
        c, n, half = scene.receiver_plane
    except (TypeError, ValueError):
        raise ValueError(f"scene.receiver_plane: expected (point, normal, half_size), "
                         f"got {scene.receiver_plane!r}") from None
    c = V.vec3(c, "scene.receiver_plane.point")
    n = V.unit_vector(n, "scene.receiver_plane.normal")
    half = V.real(half, "scene.receiver_plane.half_size", 0.0, open_min=True)
    return c, n, half


#: Offset of the receiver plane towards the camera (times max(1, half size)) in both
#: renderers, so that a plane lying on a blocker's face (a table top) is seen, not the face.
PLANE_OFFSET = 1e-5


def receiver_plane_for(scene: Scene, camera) -> tuple[np.ndarray, np.ndarray, float]:
    """(centre, normal facing the camera, half size) of the receiver plane as both renderers
    draw it: moved ``PLANE_OFFSET * max(1, half)`` towards the camera (a
    :class:`~avsm_dr.camera.PinholeCamera` or a camera dict)."""
    c, n, half = receiver_plane(scene)
    if (PinholeCamera.of(camera).origin - c) @ n < 0:
        n = -n
    return c + PLANE_OFFSET * max(1.0, half) * n, n, half


def check_camera(scene, camera, width: int = 32, height: int = 32) -> PinholeCamera:
    """The :class:`~avsm_dr.camera.PinholeCamera` of ``camera`` (a PinholeCamera or a dict
    (origin, target, up[, fov]), fov 40 when a dict has none; the default view when None) with
    ``width x height`` pixels, checked.  ValueError names ``camera`` or ``camera.<field>``."""
    cam = PinholeCamera.of(default_camera(scene) if camera is None else camera, width=width, height=height)
    if scene.density is not None and scene.bbox is not None:
        lo, hi = check_bbox(scene.bbox)
        if np.all(cam.origin >= lo) and np.all(cam.origin <= hi):
            raise ValueError("camera: origin lies inside the volume's box (unsupported)")
    return cam


def camera_rays(scene: Scene, width: int, height: int, camera=None, supersample: int = 1):
    """Origins and unit directions (H*W*s*s, 3) of the camera rays (Mitsuba's own sensor),
    ``s x s`` stratified positions per pixel, ordered (row, column, sub-row, sub-column)."""
    width, height = check_size(width, height)
    s = V.integer(supersample, "supersample", 1)
    if width * height * s * s > MAX_RAYS:
        raise ValueError(f"supersample: {width} x {height} pixels x {s}^2 rays exceed {MAX_RAYS} (2^24)")
    mi = mitsuba()
    sensor = mi.load_dict(check_camera(scene, camera, width, height).sensor_dict(mi, 1))
    y, x, sy, sx = np.meshgrid(np.arange(height), np.arange(width), np.arange(s), np.arange(s), indexing="ij")
    u = ((x + (sx + 0.5) / s) / width).ravel()
    v = ((y + (sy + 0.5) / s) / height).ravel()
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(mi.Float(u.astype(np.float32)), mi.Float(v.astype(np.float32))),
                               mi.Point2f(0.5, 0.5))
    o, d = (np.stack([np.asarray(v[i].numpy(), np.float64) for i in range(3)], axis=1) for v in (ray.o, ray.d))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o, d


def check_size(width, height) -> tuple[int, int]:
    """(width, height) as ints in [1, MAX_SIDE]; ValueError names the argument."""
    return V.integer(width, "width", 1, MAX_SIDE), V.integer(height, "height", 1, MAX_SIDE)


def render_reference(scene: Scene, width: int = 128, height: int = 128, spp: int = 64,
                     camera=None, albedo: float = 0.0, reflectance: float = 1.0,
                     max_depth: int = 2, seed: int = 0) -> np.ndarray:
    """Mitsuba ``volpath`` image (height, width) float64 of the volume and the receiver plane.

    The receiver plane is a two-sided diffuse square (``reflectance``, axes of
    :func:`~avsm_dr.geometry.orthonormal_basis`); the volume the medium of ``scene.density``
    (single-scattering ``albedo``, 0 = absorbing) in a null-BSDF cube on ``scene.bbox``; blockers
    are black (they cast shadows, reflect nothing); the light is ``scene.light.to_mitsuba``; the
    camera :func:`default_camera` unless given.  Box pixel filter; ``max_depth = 2`` is direct
    lighting.  Returns the red channel (everything is grey).  Particles and hair: ValueError.
    """
    content = check_scene(scene)
    width, height = check_size(width, height)
    spp = V.integer(spp, "spp", 1)
    if width * height * spp > MAX_RENDER_SAMPLES:
        raise ValueError(f"spp: {width} x {height} pixels x {spp} spp exceed {MAX_RENDER_SAMPLES} "
                         f"(2^26) samples in one render; average renders with several seeds")
    if content["particles"] is not None or content["hair"] is not None:
        raise ValueError("scene: render_reference renders density grids and opaque blockers only "
                         "(particles / hair have no Mitsuba counterpart here)")
    albedo = V.real(albedo, "albedo", 0.0, 1.0)
    reflectance = V.real(reflectance, "reflectance", 0.0)
    max_depth = V.integer(max_depth, "max_depth", 1)
    seed = V.integer(seed, "seed", 0)
    cam = check_camera(scene, camera, width, height)
    mi = mitsuba()
    c, n, half = receiver_plane_for(scene, cam)
    black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
    d: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": int(max_depth)},
        "sensor": cam.sensor_dict(mi, spp),
        "light": scene.light.to_mitsuba(mi),
        "plane": {"type": "rectangle", "to_world": mi.ScalarTransform4f(square_to_world(c, n, half)),
                  "bsdf": {"type": "twosided", "bsdf": {
                      "type": "diffuse", "reflectance": {"type": "rgb", "value": [float(reflectance)] * 3}}}}}
    if content["grid"] is not None:
        grid, lo, hi = content["grid"]
        d["volume"] = dict(OpaqueBox(lo, hi).to_mitsuba(mi, {"type": "null"}),
                           interior=medium_dict(mi, grid, lo, hi, albedo))
    for i, b in enumerate(content["blockers"]):
        d[f"blocker{i}"] = b.to_mitsuba(mi, black)
    img = mi.render(mi.load_dict(d), spp=int(spp), seed=int(seed))
    return np.asarray(img, np.float64)[..., 0]
