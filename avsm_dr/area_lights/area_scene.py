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
* Occluders (one :class:`Occluder` subclass per shape: spheres, axis-aligned boxes) are
  opaque and diffuse and lie strictly in front of the light plane (``(x - c) . n > 0``).
* Radiance is grey (one channel); lengths in world units, ``sigma`` per unit.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import drjit as dr
import numpy as np

from .. import validation as V
from ..camera import PinholeCamera
from ..geometry import box_corners, check_bbox, ray_box_dr, ray_sphere_dr
from ..scene import OpaqueBox, OpaqueSphere


@dataclass
class Medium:
    """Homogeneous single-scattering medium.

    sigma_s: scattering coefficient per unit (>= 0); sigma_t: extinction per unit
    (>= sigma_s); g: Henyey-Greenstein asymmetry in (-1, 1), 0 = isotropic.
    Phase function ``p(cos) = (1 - g^2) / (4 pi (1 + g^2 - 2 g cos)^(3/2))`` with
    ``cos`` the cosine between the light's and the scattered light's directions of travel."""
    sigma_s: float
    sigma_t: float
    g: float = 0.0

    def __post_init__(self):
        self.sigma_s, self.sigma_t = (V.real(getattr(self, n), n, 0.0) for n in ("sigma_s", "sigma_t"))
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
        self.center, self.edge_u, self.edge_v = (V.vec3(getattr(self, n), n) for n in ("center", "edge_u", "edge_v"))
        self.radiance = V.real(self.radiance, "radiance", 0.0)
        if self.area <= 1e-12 * max(1.0, np.linalg.norm(self.edge_u) * np.linalg.norm(self.edge_v)):
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


def safe_dir(d):
    """Replace exact zero components by a tiny value so 1 / d stays finite-signed (the
    slab test of every ray then takes the same, non-parallel branch)."""
    return type(d)(*[dr.select(c == 0, 1e-20, c) for c in (d.x, d.y, d.z)])


class Occluder:
    """An opaque diffuse occluder: a subclass (a dataclass) is one shape, a package blocker
    (:class:`avsm_dr.scene.Blocker`: ``bounds()``, ``to_mitsuba(mi, bsdf)``) with an ``albedo``
    and an ``area``; ``k`` is the :class:`~avsm_dr.area_lights.geometry.Kit`, rays have unit ``d``:
    ``hit_dr(k, o, d)``: ``(t0, t1, hit)`` of the chord;  ``normal_dr(k, x)``: the outward normal;
    ``sample_dr(k, u1, u2, u3)``: surface points uniform by area;  ``light_frame_extent(vpls,
    frame)``: per VPL (x_lo, x_hi, y_lo, y_hi, z_lo, z_hi, r_lo, r_hi) in the light frame
    (e_u, e_v, n) centred at the VPL (exact for spheres per axis)."""
    def __post_init__(self):        # the blocker's checks (ValueError names ``sphere.radius``, ...)
        checked = self.validate(type(self).__name__.lower())
        for f in dataclasses.fields(checked):
            setattr(self, f.name, getattr(checked, f.name))
        self.albedo = V.real(self.albedo, "albedo", 0.0, 1.0)


@dataclass
class Sphere(OpaqueSphere, Occluder):
    """Opaque diffuse sphere."""
    albedo: float = 0.5

    @property
    def area(self) -> float:
        return 4.0 * math.pi * self.radius ** 2

    def hit_dr(self, k, o, d):
        return ray_sphere_dr(o, d, k.vec(self.center), float(self.radius))

    def normal_dr(self, k, x):
        return (x - k.vec(self.center)) / float(self.radius)

    def sample_dr(self, k, u1, u2, u3):
        z = 1 - 2 * u1
        sxy = dr.safe_sqrt(1 - z * z)
        phi = 2 * np.pi * u2
        return k.vec(self.center) + float(self.radius) * k.Vec3(sxy * dr.cos(phi), sxy * dr.sin(phi), z)

    def light_frame_extent(self, vpls, frame):
        eu, ev, n = frame
        d = self.center[None] - vpls
        cx, cy, cz = d @ eu, d @ ev, d @ n
        dist = np.linalg.norm(d, axis=1)
        r = self.radius
        return cx - r, cx + r, cy - r, cy + r, cz - r, cz + r, np.maximum(dist - r, 0), dist + r


@dataclass
class Box(OpaqueBox, Occluder):
    """Opaque diffuse axis-aligned box ``[min, max]``."""
    albedo: float = 0.5

    @property
    def area(self) -> float:
        e = self.max - self.min
        return float(2 * (e[0] * e[1] + e[1] * e[2] + e[0] * e[2]))

    def hit_dr(self, k, o, d):
        return ray_box_dr(o, safe_dir(d), k.vec(self.min), k.vec(self.max))

    def normal_dr(self, k, x):         # the outward normal of the face nearest to x
        lo, hi = k.vec(self.min), k.vec(self.max)
        q = (x - (lo + hi) * 0.5) / ((hi - lo) * 0.5)
        ax, ay, az = dr.abs(q.x), dr.abs(q.y), dr.abs(q.z)
        isx = (ax >= ay) & (ax >= az)
        isy = ~isx & (ay >= az)
        return k.Vec3(dr.select(isx, dr.sign(q.x), 0), dr.select(isy, dr.sign(q.y), 0),
                      dr.select(~isx & ~isy, dr.sign(q.z), 0))

    def sample_dr(self, k, u1, u2, u3):
        e = self.max - self.min
        fa = np.array([e[1] * e[2], e[0] * e[2], e[0] * e[1]])
        fc = np.cumsum(fa) / fa.sum()                # which axis is fixed: x, y or z
        side = u3 * 2
        hi_side = side >= 1
        side = dr.select(hi_side, side - 1, side)    # reuse u3 for the axis choice
        ax_x = side < fc[0]
        ax_y = ~ax_x & (side < fc[1])
        fixed = dr.select(hi_side, 1.0, 0.0)
        # coordinates in [0, 1]^3: the fixed axis at 0 or 1, the other two from (u1, u2)
        cx = dr.select(ax_x, fixed, u1)
        cy = dr.select(ax_x, u1, dr.select(ax_y, fixed, u2))
        cz = dr.select(ax_x | ax_y, u2, fixed)
        return k.vec(self.min) + k.Vec3(cx * e[0], cy * e[1], cz * e[2])

    def light_frame_extent(self, vpls, frame):
        eu, ev, n = frame
        a, b = self.bounds()
        d = box_corners(a, b) - vpls[:, None, :]                        # (K, 8, 3)
        x, y, z = d @ eu, d @ ev, d @ n
        r_lo = np.linalg.norm(np.maximum(np.maximum(a[None] - vpls, 0), vpls - b[None]), axis=1)   # to the box
        return x.min(1), x.max(1), y.min(1), y.max(1), z.min(1), z.max(1), r_lo, np.linalg.norm(d, axis=2).max(axis=1)


def _as_occluder(o):
    """Accept our occluders, and the package blockers they extend (OpaqueSphere, OpaqueBox:
    the default albedo)."""
    if isinstance(o, Occluder):
        return o
    for kind in Occluder.__subclasses__():
        if type(o) in kind.__bases__:
            return kind(*dataclasses.astuple(o))
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
        for name, kind in (("medium", Medium), ("light", QuadLight), ("camera", PinholeCamera)):
            if not isinstance(getattr(self, name), kind):
                raise ValueError(f"{name}: expected {kind.__name__}, got {type(getattr(self, name)).__name__}")
        self.bounds = lo, hi = check_bbox(self.bounds, "bounds")
        self.floor_albedo = V.real(self.floor_albedo, "floor_albedo", 0.0, 1.0)
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
            a, b = o.bounds()
            if not (inside(a, False) and inside(b, False)):
                raise ValueError(f"occluders: occluder {i} extends outside bounds")
            if o.light_frame_extent(c[None], (n, n, n))[4][0] <= 0:       # z_lo: lowest above the plane
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
               Box([0.45, 0.0, -0.9], [0.8, 0.75, -0.55], albedo=0.5), Sphere([-0.35, 0.3, 0.35], 0.22, albedo=0.7)]
    cam = PinholeCamera(origin=[0.0, 1.05, 1.42], target=[0.0, 0.85, -0.6], fov=72.0, width=width, height=height)
    return AreaLightScene(Medium(sigma_s, sigma_t, g), light, cam, (lo, hi), occ, floor_albedo=0.5,
                          name="default" if occluders else "default_unoccluded")
