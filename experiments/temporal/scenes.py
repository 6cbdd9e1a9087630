"""The animations of the ``temporal`` experiment: what moves, frame by frame.

Each animation is a function ``frame(t) -> Frame`` over ``t = 0..F-1`` with the receivers
fixed: the same world points in every frame, except under a moving camera, where receiver
``i`` is the same pixel (and the same fraction along its view ray through the box).

* ``smoke``   the stable-fluids plume (:func:`avsm_dr.fluid.simulate_plume_sequence`), one
              frame per solver step; light fixed; the map fitted to the grid's box, so only
              the content moves.
* ``light``   the last smoke frame, still; the light turns about the vertical axis by
              ``light_step`` degrees per frame (:func:`turned`: a directional light's
              direction; a spot light orbits the vertical line through its aim point, aiming
              at it): the map (refitted to the box for each direction) swims over the content.
* ``camera``  the last smoke frame and the light still; the receivers are the points at 1/3
              and 2/3 of each pixel's view ray through the box for a camera orbiting the
              plume by ``camera_step`` degrees per frame (Stam-style volume shading
              samples the light's T at such points).
* ``hair``    the built-in hair-and-smoke scene with its strands swaying: vertex ``v`` of a
              strand (``s = v / (V - 1)`` along it) moves by ``A s^2 (sin(w t + p), 0,
              cos(w t + p) / 2)`` (``p`` a random phase per strand); smoke and light still.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from avsm_dr.scene import DirectionalLight, Hair, Scene, SpotLight

#: The plume's box (that of :func:`avsm_dr.builtin_scenes.simulated_plume`) and receiver wall.
PLUME_BOX = (np.array([-0.5, 0.0, -0.5]), np.array([0.5, 1.5, 0.5]))
PLUME_WALL = (np.array([0.8, 0.75, 0.0]), np.array([-1.0, 0.0, 0.0]), 0.75)
#: Box the hair scene's map is fitted to (the scene's box grown so swaying strands stay inside).
HAIR_FIT = (np.full(3, -0.7), np.full(3, 0.7))


@dataclasses.dataclass
class Frame:
    """One frame: the scene, the ``bounds`` its map is fitted to, the (K, 3) receivers and
    the (G*G, 3) points of the animated image (:func:`slice_points`; None: no image)."""
    scene: Scene
    bounds: tuple
    receivers: np.ndarray
    image: np.ndarray | None


def slice_points(box, n: int) -> np.ndarray:
    """(n * n, 3) points of the box's mid-depth slice z = const, row-major from the bottom
    (rows along y, columns along x, at cell centres): the light's T inside the content, where
    the representations differ (behind it, on the wall, they nearly agree)."""
    lo, hi = (np.asarray(b, np.float64) for b in box)
    s = (np.arange(n) + 0.5) / n
    y, x = np.meshgrid(lo[1] + s * (hi[1] - lo[1]), lo[0] + s * (hi[0] - lo[0]), indexing="ij")
    return np.stack([x.ravel(), y.ravel(), np.full(n * n, 0.5 * (lo[2] + hi[2]))], axis=1)


def rotate_y(v, degrees: float) -> np.ndarray:
    """``v`` turned about the vertical (y) axis by ``degrees``."""
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    v = np.asarray(v, np.float64)
    return np.array([c * v[0] + s * v[2], v[1], -s * v[0] + c * v[2]])


def plume_scene(density, light, n_receivers: int, seed: int) -> Scene:
    """The plume box with ``density`` (the scene of frame 0); receivers: half at random
    points of voxels with density > 0 (``density`` should be the union over frames), half
    on the wall behind it."""
    from avsm_dr.builtin_scenes import half_volume_half_surface
    bmin, bmax = PLUME_BOX
    rng = np.random.default_rng(seed + 1)
    c, _, half = PLUME_WALL
    rec = half_volume_half_surface(density, bmin, bmax, n_receivers, rng, c, (0, 1, 0), (0, 0, 1), half)
    return Scene("temporal_plume", light, rec, density=density, bbox=(bmin, bmax), receiver_plane=PLUME_WALL)


def smoke(base: Scene, frames: np.ndarray, image_n: int):
    """``frame(t)`` of the ``smoke`` animation (``frames``: (F, nz, ny, nx) densities)."""
    img = slice_points(base.bbox, image_n) if image_n else None

    def frame(t):
        return Frame(dataclasses.replace(base, density=frames[t]), base.bbox, base.receivers, img)
    return frame


def turned(light, degrees: float, centre):
    """``light`` turned about the vertical axis by ``degrees``: a DirectionalLight's direction;
    a SpotLight orbits the vertical line through its aim point ``a = p + ((c - p) . d) d`` (the
    point of its axis nearest ``centre`` c: the content's centre, at which
    :func:`avsm_dr.evaluation.light_variants` aims it), its direction turned alike, so it keeps
    aiming at ``a`` and its distance to it."""
    if isinstance(light, SpotLight):
        p, d = light.position, light.direction
        a = p + np.dot(np.asarray(centre, np.float64) - p, d) * d
        return dataclasses.replace(light, position=a + rotate_y(p - a, degrees), direction=rotate_y(d, degrees))
    return DirectionalLight(direction=rotate_y(light.direction, degrees), irradiance=light.irradiance)


def light(base: Scene, density, step: float, image_n: int):
    """``frame(t)`` of the ``light`` animation: the light :func:`turned` by ``t * step``
    degrees about the box's centre."""
    img = slice_points(base.bbox, image_n) if image_n else None
    centre = 0.5 * (np.asarray(base.bbox[0], np.float64) + np.asarray(base.bbox[1], np.float64))

    def frame(t):
        li = turned(base.light, t * step, centre)
        return Frame(dataclasses.replace(base, density=density, light=li), base.bbox, base.receivers, img)
    return frame


def camera_points(box, angle: float, pixels: int, distance: float = 3.0, fov: float = 14.0) -> np.ndarray:
    """(pixels^2 * 2, 3): for each pixel of a pinhole camera at ``distance`` from the box's
    centre, orbiting about the vertical axis by ``angle`` degrees (0: on the +z side, looking
    along -z), the points at 1/3 and 2/3 of its view ray's chord through the box (pixel-major).
    The default ``fov`` keeps every ray inside the plume box's silhouette."""
    from avsm_dr.geometry import ray_box
    lo, hi = (np.asarray(b, np.float64) for b in box)
    c = 0.5 * (lo + hi)
    eye = c + rotate_y([0.0, 0.0, distance], angle)
    w = (c - eye) / np.linalg.norm(c - eye)
    u = np.cross(w, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(u, w)
    s = (np.arange(pixels) + 0.5) / pixels * 2 - 1
    a, b = np.meshgrid(s, s, indexing="ij")
    tan = np.tan(np.radians(fov) / 2)
    d = w + tan * (b.reshape(-1, 1) * u + a.reshape(-1, 1) * v)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(eye, d.shape)
    t0, t1, _ = ray_box(o, d, lo, hi)
    if np.any(t1 <= t0):
        raise ValueError(f"fov: {fov} degrees lets view rays miss the box")
    f = np.array([1 / 3, 2 / 3])
    t = t0[:, None] + f[None, :] * (t1 - t0)[:, None]
    return (o[:, None, :] + t[..., None] * d[:, None, :]).reshape(-1, 3)


def camera(base: Scene, density, step: float, pixels: int):
    """``frame(t)`` of the ``camera`` animation: the camera turned by ``t * step`` degrees."""
    scene = dataclasses.replace(base, density=density)

    def frame(t):
        return Frame(scene, base.bbox, camera_points(base.bbox, t * step, pixels), None)
    return frame


def hair(base: Scene, amplitude: float, period: float, image_n: int, seed: int):
    """``frame(t)`` of the ``hair`` animation (module docstring; ``period`` in frames)."""
    strands = np.asarray(base.hair.strands, np.float64)
    S, Vn, _ = strands.shape
    phase = 2 * np.pi * np.random.default_rng(seed + 7).random(S)
    s2 = (np.arange(Vn) / (Vn - 1)) ** 2
    img = slice_points(base.bbox, image_n) if image_n else None

    def frame(t):
        a = 2 * np.pi * t / period + phase
        off = np.stack([np.sin(a), np.zeros(S), 0.5 * np.cos(a)], axis=1)      # (S, 3)
        moved = strands + amplitude * s2[None, :, None] * off[:, None, :]
        h = Hair(strands=moved.astype(np.float32), radius=base.hair.radius, opacity=base.hair.opacity)
        return Frame(dataclasses.replace(base, hair=h), HAIR_FIT, base.receivers, img)
    return frame
