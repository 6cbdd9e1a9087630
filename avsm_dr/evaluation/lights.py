"""The light configurations of an evaluation: the scene's own directional light, a tilted
copy and a spot light on the same axis (:func:`light_variants`)."""
from __future__ import annotations

import numpy as np

from ..scene import DirectionalLight, SpotLight


def _rotate(v, axis, degrees):
    """Rodrigues rotation of v about the unit axis."""
    a = np.radians(degrees)
    return v * np.cos(a) + np.cross(axis, v) * np.sin(a) + axis * (axis @ v) * (1 - np.cos(a))


def light_variants(scene, tilt: float = 25.0) -> dict:
    """{'dir_a': the scene's directional light, 'dir_b': it tilted by ``tilt`` degrees
    about the horizontal axis orthogonal to it, 'spot': a spot light on the same axis at
    2.5 content radii from the content's centre, its cone covering the content sphere}.

    Built for the scenes' default directional lights (ValueError otherwise)."""
    light = scene.light
    if not isinstance(light, DirectionalLight):
        raise ValueError(f"scene: light_variants needs a DirectionalLight, got {type(light).__name__}")
    d = np.asarray(light.direction, np.float64)
    up = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    axis = np.cross(d, up)
    axis /= np.linalg.norm(axis)
    from ..groundtruth.content import check_scene, content_sphere
    c, R = content_sphere(check_scene(scene))
    dist = 2.5 * R
    fov = min(170.0, 2.2 * float(np.degrees(np.arcsin(R / dist))))
    return {"dir_a": light,
            "dir_b": DirectionalLight(direction=_rotate(d, axis, tilt), irradiance=light.irradiance),
            "spot": SpotLight(position=c - dist * d, direction=d, fov=fov)}
