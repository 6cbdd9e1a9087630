"""Configurations of an evaluation: a seed and a light, the unit of every interval.

A built-in scene is regenerated per seed (its noise) and its receivers are drawn with that
seed; a :class:`~avsm_dr.Scene` object keeps its content and only its receivers are drawn
per seed.  The light is a name of :func:`light_variants` ('dir_a': the scene's own light,
'dir_b': it tilted by 25 degrees, 'spot': a spot light on its axis) or a light object.
"""
from __future__ import annotations

import dataclasses
from numbers import Integral

import numpy as np

from .. import builtin_scenes, receivers, validation as V
from ..capture import capture as _capture
from ..groundtruth.content import check_scene, content_sphere
from ..scene import DirectionalLight, Light, SpotLight

#: Light names a configuration takes (:func:`light_variants`).
LIGHTS = ("dir_a", "dir_b", "spot")
#: Host bytes per configuration while :func:`configurations` builds them (measured peak: 268),
#: checked before allocating.
BYTES_PER_CONFIGURATION = 300


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
    a = np.radians(tilt)                                     # Rodrigues rotation of d about the axis
    tilted = d * np.cos(a) + np.cross(axis, d) * np.sin(a) + axis * (axis @ d) * (1 - np.cos(a))
    c, R = content_sphere(check_scene(scene))
    dist = 2.5 * R
    fov = min(170.0, 2.2 * float(np.degrees(np.arcsin(R / dist))))
    return {"dir_a": light,
            "dir_b": DirectionalLight(direction=tilted, irradiance=light.irradiance),
            "spot": SpotLight(position=c - dist * d, direction=d, fov=fov)}


@dataclasses.dataclass(frozen=True)
class Configuration:
    """One configuration: ``seed`` (integer >= 0) and ``light`` (a name of :data:`LIGHTS`
    or a DirectionalLight / SpotLight / PointLight); :attr:`label` names it in tables."""
    seed: int = 0
    light: object = "dir_a"

    def __post_init__(self):
        object.__setattr__(self, "seed", V.integer(self.seed, "seed", 0))
        if isinstance(self.light, str):
            V.one_of(self.light, "light", LIGHTS)
        elif not isinstance(self.light, Light):
            raise ValueError(f"light: expected one of {LIGHTS} or a DirectionalLight, SpotLight or PointLight, "
                             f"got {self.light!r}")

    @property
    def light_label(self) -> str:
        """The light's name, or a short description of a light object."""
        return self.light if isinstance(self.light, str) else self.light.label()

    @property
    def label(self) -> str:
        """``s<seed>-<light>``, e.g. ``s0-dir_a`` (the labels of ``error_curves``)."""
        return f"s{self.seed}-{self.light_label}"

    def light_for(self, scene):
        """The light object of this configuration for ``scene``: 'dir_a' is the scene's own
        light (of any type); 'dir_b' and 'spot' need a directional one."""
        if not isinstance(self.light, str):
            return self.light
        return scene.light if self.light == "dir_a" else light_variants(scene)[self.light]

    def scene(self, scene):
        """``scene`` (a built-in scene's name: regenerated with :attr:`seed`) lit by :meth:`light_for`."""
        base = builtin_scenes.get(scene, seed=self.seed) if isinstance(scene, str) else scene
        return dataclasses.replace(base, light=self.light_for(base))

    def capture(self, scene, resolution: int, order: str = "depth", **options):
        """(:meth:`scene`, its :func:`avsm_dr.capture` at ``resolution`` in ``order`` with ``options``)."""
        scene = self.scene(scene)
        return scene, _capture(scene, resolution=resolution, order=order, **options)

    def in_volume_receivers(self, scene, n: int) -> np.ndarray:
        """:func:`avsm_dr.receivers.in_volume`: ``n`` receivers in ``scene`` drawn with :attr:`seed`."""
        return receivers.in_volume(scene, n, self.seed)


def configurations(seeds=1, lights=("dir_a",)) -> list[Configuration]:
    """Every seed x light, seeds outermost: ``seeds`` an integer n (seeds 0..n-1) or a
    sequence of seeds; ``lights`` a sequence of names of :data:`LIGHTS` and light objects
    (or one of them)."""
    lights = [lights] if isinstance(lights, (str, Light)) else list(lights)
    if isinstance(seeds, Integral) and not isinstance(seeds, bool):
        seeds = range(V.integer(seeds, "seeds", 1))
        V.check_memory("seeds", len(seeds), lambda n: float(n) * max(len(lights), 1) * BYTES_PER_CONFIGURATION,
                       lo=1, what="configurations")
    elif isinstance(seeds, (str, bytes)) or not hasattr(seeds, "__iter__"):
        raise ValueError(f"seeds: expected a count or a sequence of seeds, got {seeds!r}")
    seeds = list(seeds)
    if not seeds:
        raise ValueError("seeds: no seed given")
    if not lights:
        raise ValueError("lights: no light given")
    out = [Configuration(s, li) for s in seeds for li in lights]
    labels = [c.label for c in out]
    if len(set(labels)) != len(labels):
        raise ValueError(f"seeds: repeated configurations {sorted(x for x in labels if labels.count(x) > 1)}")
    return out
