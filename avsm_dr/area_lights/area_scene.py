"""Scene description for area-light volumetric shadows (Wyman and Dai, "Imperfect Voxelized
Shadow Volumes", HPG 2013).

Conventions (shared by every method and by the Mitsuba reference):

* World space is right-handed with **y up**.  The homogeneous medium fills the
  axis-aligned box ``bounds = (min_xyz, max_xyz)``; the camera and the light lie
  inside it.  The box's bottom face ``y = min_y`` is a diffuse floor (albedo
  ``floor_albedo``); its other faces are invisible medium boundaries (camera rays
  end there, nothing lies outside).
* The quad light is ``c + a * edge_u + b * edge_v`` with ``a, b`` in ``[-1/2, 1/2]``;
  it emits the constant radiance ``L_e`` from the side of
  ``n = normalize(edge_u x edge_v)`` only (Mitsuba's one-sided ``area`` emitter);
  its back side is black.
* Occluders are opaque diffuse spheres and axis-aligned boxes that lie strictly in
  front of the light plane (``(x - c) . n > 0`` for every point of the occluder).
* Radiance is grey (one channel); lengths in world units, ``sigma`` per unit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .. import validation as V
from ..camera import MAX_SIDE, PinholeCamera  # noqa: F401  (the package's one camera, re-exported)
from ..scene import OpaqueBox, OpaqueSphere

def _albedo(v, name: str = "albedo") -> float:
    return V.real(v, name, 0.0, 1.0)


@dataclass
class Medium:
    """Homogeneous single-scattering medium.

    sigma_s: scattering coefficient per unit (>= 0); sigma_t: extinction per unit
    (>= sigma_s); g: Henyey-Greenstein asymmetry in (-1, 1), 0 = isotropic.
    Phase function ``p(cos) = (1 - g^2) / (4 pi (1 + g^2 - 2 g cos)^(3/2))`` with
    ``cos`` the cosine between the light's and the scattered light's directions of travel.
    """
    sigma_s: float
    sigma_t: float
    g: float = 0.0

    def __post_init__(self):
        self.sigma_s = V.real(self.sigma_s, "sigma_s", 0.0)
        self.sigma_t = V.real(self.sigma_t, "sigma_t", 0.0)
        if self.sigma_s > self.sigma_t:
            raise ValueError(f"sigma_s: must be <= sigma_t ({self.sigma_t}), got {self.sigma_s}")
        self.g = V.real(self.g, "g", -1.0, 1.0, open_min=True, open_max=True)


@dataclass
class QuadLight:
    """One-sided quad emitter ``center + a edge_u + b edge_v`` (a, b in [-1/2, 1/2]),
    constant radiance ``radiance`` (L_e) towards ``normal = normalize(edge_u x edge_v)``."""
    center: np.ndarray
    edge_u: np.ndarray
    edge_v: np.ndarray
    radiance: float = 1.0

    def __post_init__(self):
        self.center = V.vec3(self.center, "center")
        self.edge_u = V.vec3(self.edge_u, "edge_u")
        self.edge_v = V.vec3(self.edge_v, "edge_v")
        self.radiance = V.real(self.radiance, "radiance", 0.0)
        cr = np.cross(self.edge_u, self.edge_v)
        if np.linalg.norm(cr) <= 1e-12 * max(1.0, np.linalg.norm(self.edge_u) * np.linalg.norm(self.edge_v)):
            raise ValueError("edge_u: edge_u and edge_v must be non-zero and not parallel")

    @property
    def normal(self) -> np.ndarray:
        cr = np.cross(self.edge_u, self.edge_v)
        return cr / np.linalg.norm(cr)

    @property
    def area(self) -> float:
        return float(np.linalg.norm(np.cross(self.edge_u, self.edge_v)))

    def frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Orthonormal light frame (e_u, e_v, n): e_u along edge_u, n the emitting side."""
        n = self.normal
        eu = self.edge_u - np.dot(self.edge_u, n) * n
        eu /= np.linalg.norm(eu)
        return eu, np.cross(n, eu), n

    def corners(self) -> np.ndarray:
        """(4, 3) corners."""
        return np.array([self.center + a * self.edge_u + b * self.edge_v
                         for a in (-0.5, 0.5) for b in (-0.5, 0.5)])


@dataclass
class Sphere:
    """Opaque diffuse sphere."""
    center: np.ndarray
    radius: float
    albedo: float = 0.5

    def __post_init__(self):
        self.center = V.vec3(self.center, "center")
        self.radius = V.real(self.radius, "radius", 0.0, open_min=True)
        self.albedo = _albedo(self.albedo)

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        return self.center - self.radius, self.center + self.radius

    @property
    def area(self) -> float:
        return 4.0 * math.pi * self.radius ** 2


@dataclass
class Box:
    """Opaque diffuse axis-aligned box ``[min, max]``."""
    min: np.ndarray
    max: np.ndarray
    albedo: float = 0.5

    def __post_init__(self):
        self.min = V.vec3(self.min, "min")
        self.max = V.vec3(self.max, "max")
        if np.any(self.max <= self.min):
            raise ValueError(f"max: must exceed min on every axis, got min={self.min}, max={self.max}")
        self.albedo = _albedo(self.albedo)

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        return self.min.copy(), self.max.copy()

    @property
    def area(self) -> float:
        e = self.max - self.min
        return float(2 * (e[0] * e[1] + e[1] * e[2] + e[0] * e[2]))


def _as_occluder(o):
    """Accept our Sphere/Box and the package's avsm_dr.scene.OpaqueSphere/OpaqueBox."""
    if isinstance(o, (Sphere, Box)):
        return o
    if isinstance(o, OpaqueSphere):
        return Sphere(o.center, o.radius)
    if isinstance(o, OpaqueBox):
        return Box(o.min, o.max)
    raise ValueError(f"occluders: expected Sphere or Box entries, got {type(o).__name__}")


@dataclass
class AreaLightScene:
    """Occluders in a homogeneous medium box lit by a quad light, seen by a camera."""
    medium: Medium
    light: QuadLight
    camera: PinholeCamera
    bounds: tuple
    occluders: list = field(default_factory=list)
    floor_albedo: float = 0.5
    name: str = "area_light_scene"

    def __post_init__(self):
        if not isinstance(self.medium, Medium):
            raise ValueError(f"medium: expected Medium, got {type(self.medium).__name__}")
        if not isinstance(self.light, QuadLight):
            raise ValueError(f"light: expected QuadLight, got {type(self.light).__name__}")
        if not isinstance(self.camera, PinholeCamera):
            raise ValueError(f"camera: expected PinholeCamera, got {type(self.camera).__name__}")
        try:
            lo, hi = self.bounds
        except (TypeError, ValueError):
            raise ValueError(f"bounds: expected (min_xyz, max_xyz), got {self.bounds!r}") from None
        lo, hi = V.vec3(lo, "bounds"), V.vec3(hi, "bounds")
        if np.any(hi <= lo):
            raise ValueError(f"bounds: max must exceed min on every axis, got {lo}, {hi}")
        self.bounds = (lo, hi)
        self.floor_albedo = _albedo(self.floor_albedo, "floor_albedo")
        self.occluders = [_as_occluder(o) for o in list(self.occluders)]

        def inside(p, strict=True):
            return bool(np.all(p > lo) and np.all(p < hi)) if strict else \
                bool(np.all(p >= lo) and np.all(p <= hi))
        if not inside(self.camera.origin):
            raise ValueError("camera: origin must lie strictly inside bounds")
        if not all(inside(c) for c in self.light.corners()):
            raise ValueError("light: the quad must lie strictly inside bounds")
        c, n = self.light.center, self.light.normal
        for i, o in enumerate(self.occluders):
            a, b = o.aabb()
            if not (inside(a, False) and inside(b, False)):
                raise ValueError(f"occluders: occluder {i} extends outside bounds")
            corners = np.array([[x, y, z] for x in (a[0], b[0]) for y in (a[1], b[1]) for z in (a[2], b[2])])
            if isinstance(o, Sphere):
                lowest = float(np.dot(o.center - c, n)) - o.radius
            else:
                lowest = float(np.min((corners - c) @ n))
            if lowest <= 0:
                raise ValueError(f"occluders: occluder {i} must lie strictly in front of the light plane")

    @property
    def extent(self) -> float:
        """Diagonal of the medium box (a length scale for biases)."""
        lo, hi = self.bounds
        return float(np.linalg.norm(hi - lo))


def default_scene(width: int = 32, height: int = 32, occluders: bool = True, sigma_s: float = 0.5,
                  sigma_t: float = 0.6, g: float = 0.0, radiance: float = 4.0,
                  light_size: float = 0.8) -> AreaLightScene:
    """The experiment's scene: a 3 x 2.4 x 3 medium box, a 0.8 x 0.8 ceiling light
    facing down, a sphere, a slab and a pillar casting shafts onto the floor."""
    lo, hi = np.array([-1.5, 0.0, -1.5]), np.array([1.5, 2.4, 1.5])
    light = QuadLight(center=[0.0, 2.3, -0.1], edge_u=[light_size, 0, 0], edge_v=[0, 0, light_size],
                      radiance=radiance)
    occ = []
    if occluders:
        occ = [Sphere([0.35, 1.45, -0.05], 0.28, albedo=0.6),
               Box([-0.8, 1.05, -0.55], [-0.1, 1.2, 0.15], albedo=0.5),
               Box([0.45, 0.0, -0.9], [0.8, 0.75, -0.55], albedo=0.5),
               Sphere([-0.35, 0.3, 0.35], 0.22, albedo=0.7)]
    cam = PinholeCamera(origin=[0.0, 1.05, 1.42], target=[0.0, 0.85, -0.6], fov=72.0, width=width, height=height)
    return AreaLightScene(Medium(sigma_s, sigma_t, g), light, cam, (lo, hi), occ, floor_albedo=0.5,
                          name="default" if occluders else "default_unoccluded")
