"""Scene description: volumetric content, a light and receiver points.

Conventions shared by capture, ground truth and shading:

* World space is right-handed, units arbitrary (the scenes use about 1 unit).
* A density grid is a (nz, ny, nx) float32 array of extinction coefficients per
  world unit over the box ``bbox = (min_xyz, max_xyz)``.  Voxel (k, j, i) is the
  value at the cell centre ``min + ((i, j, k) + 0.5) * (max - min) / (nx, ny, nz)``;
  in between it is trilinear, clamped to the edge inside the box and 0 outside
  the box - the interpretation of Mitsuba 3's ``gridvolume`` with
  ``filter_type='trilinear'`` and ``to_world`` mapping the unit cube to the box.
* Light-space depth is distance from the light along its ray (point/spot lights),
  or distance from the light's reference plane along ``direction`` (directional).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import drjit as dr
import numpy as np

from . import validation as V
from .geometry import check_bbox, orthonormal_basis, ray_box, ray_sphere


class Light:
    """A light: a subclass (a dataclass) carries what capture, ground truth, shading and Mitsuba
    need, so a new light is one class.  Points: float64 (K, 3).

    * ``directions_to(p)``: (K, 3) unit directions towards the light (read-only);
    * ``paths(p, center, radius)``: origins, unit directions and lengths of the light's paths to
      ``p`` (ground truth; directional: from the light side of the content's bounding sphere);
    * ``irradiance_at(p)``: (K,) unshadowed irradiance on a surface facing the light (shading);
    * ``shadow_camera(cameras, res, bmin, bmax)``: the shadow-map camera from the module
      :mod:`avsm_dr.capture.camera` (passed in: a layer above), fitted to content boxes (N, 3);
    * ``to_mitsuba(mi)``: the emitter dict, and back: the classmethod ``from_mitsuba(emitter,
      params)`` of the Mitsuba class named ``mitsuba_class`` (:meth:`of_mitsuba` dispatches);
    * ``label()``: a short text.  A light at a point (spot, point) has a ``position``.
    """
    #: Mitsuba emitter class (``emitter.class_name()``) that :meth:`from_mitsuba` converts.
    mitsuba_class = ""
    _by_mitsuba_class: dict = {}

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if cls.mitsuba_class:
            Light._by_mitsuba_class[cls.mitsuba_class] = cls

    @staticmethod
    def of_mitsuba(emitter, params) -> "Light":
        """The light of a Mitsuba ``emitter`` (``params = mi.traverse(emitter)``): the
        ``from_mitsuba`` of the class registered for its Mitsuba class; ValueError otherwise."""
        kind = Light._by_mitsuba_class.get(emitter.class_name())
        if kind is None:
            raise ValueError(f"emitter: expected a Mitsuba {' / '.join(Light._by_mitsuba_class)}, "
                             f"got {emitter.class_name()}")
        return kind.from_mitsuba(emitter, params)


def _fmt(v) -> str:
    return "(" + ", ".join(f"{x:.3g}" for x in np.asarray(v, np.float64)) + ")"


def _rgb(value) -> dict:
    return {"type": "rgb", "value": [float(value)] * 3}


@dataclass
class DirectionalLight(Light):
    """Parallel light travelling along ``direction``; irradiance ``irradiance`` (W/m^2)."""
    direction: np.ndarray
    irradiance: float = 1.0
    mitsuba_class = "DirectionalEmitter"

    def __post_init__(self):
        self.direction = V.unit_vector(self.direction, "direction")
        self.irradiance = V.real(self.irradiance, "irradiance", 0.0)

    def directions_to(self, p):
        return np.broadcast_to(-self.direction, p.shape)

    def paths(self, p, center, radius):            # L back to the sphere's light-side tangent plane
        w = self.direction
        L = np.maximum((p - center) @ w + radius, 0.0) * (1 + 1e-9) + 1e-9 * (1 + radius)
        d = np.broadcast_to(w, p.shape).copy()
        return p - L[:, None] * d, d, L

    def irradiance_at(self, p):
        return np.full(p.shape[0], float(self.irradiance))

    def shadow_camera(self, cameras, res, bmin, bmax):
        return cameras.OrthoCamera.fit(self.direction, bmin, bmax, res)

    def to_mitsuba(self, mi):
        return {"type": "directional", "direction": self.direction.tolist(), "irradiance": _rgb(self.irradiance)}

    @classmethod
    def from_mitsuba(cls, emitter, params):
        return cls(np.asarray(emitter.world_transform().matrix, np.float64).reshape(4, 4)[:3, 2])

    def label(self):
        return f"directional{_fmt(self.direction)}"


class _LightAt(Light):
    """A light at ``position`` (spot, point): paths start there; inverse-square irradiance."""
    def __post_init__(self):
        self.position = V.vec3(self.position, "position")
        self.intensity = V.real(self.intensity, "intensity", 0.0)
    def directions_to(self, p):
        v = self.position - p
        return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)

    def paths(self, p, center, radius):            # a spot's cone does not limit T (shading applies it)
        o = np.broadcast_to(self.position, p.shape).astype(np.float64)
        v = p - o
        L = np.linalg.norm(v, axis=1)
        d = np.where(L[:, None] > 0, v / np.where(L > 0, L, 1.0)[:, None], np.array([0.0, 0.0, 1.0]))
        return o, d, L

    def irradiance_at(self, p):
        r2 = np.sum((p - self.position) ** 2, axis=1)
        return float(self.intensity) / np.maximum(r2, 1e-300)


@dataclass
class SpotLight(_LightAt):
    """Spot light at ``position`` pointing along ``direction`` with full cone angle ``fov`` degrees."""
    position: np.ndarray
    direction: np.ndarray
    fov: float = 60.0
    intensity: float = 1.0
    mitsuba_class = "SpotLight"

    def __post_init__(self):
        super().__post_init__()
        self.direction = V.unit_vector(self.direction, "direction")
        self.fov = V.real(self.fov, "fov", 0.0, 180.0, open_min=True, open_max=True)

    @property
    def beam_width(self) -> float:
        """Full-intensity half angle (degrees): 3/4 of the cutoff fov / 2 (Mitsuba's default)."""
        return 0.75 * self.fov / 2

    def falloff(self, p) -> np.ndarray:
        """(K,) Mitsuba ``spot`` profile in [0, 1] at ``p``."""
        v = p - self.position
        r = np.linalg.norm(v, axis=1)
        cos = np.where(r > 0, (v @ self.direction) / np.where(r > 0, r, 1.0), 1.0)
        cutoff = math.radians(self.fov / 2)
        beam = math.radians(self.beam_width)
        ang = np.arccos(np.clip(cos, -1.0, 1.0))
        prof = np.where(cos >= math.cos(beam), 1.0, (cutoff - ang) / (cutoff - beam))
        return np.where(cos > math.cos(cutoff), prof, 0.0)

    def irradiance_at(self, p):
        return super().irradiance_at(p) * self.falloff(p)

    def shadow_camera(self, cameras, res, bmin, bmax):
        return cameras.PerspectiveCamera(self.position, self.direction, self.fov, res)

    def to_mitsuba(self, mi):
        pos = self.position
        up = orthonormal_basis(self.direction)[1]
        return {"type": "spot", "cutoff_angle": self.fov / 2, "beam_width": self.beam_width,
                "intensity": _rgb(self.intensity),
                "to_world": mi.ScalarTransform4f().look_at(origin=pos.tolist(), target=(pos + self.direction).tolist(),
                                                           up=up.tolist())}

    @classmethod
    def from_mitsuba(cls, emitter, params):
        m = np.asarray(params["to_world"].matrix, np.float64).reshape(4, 4)
        return cls(m[:3, 3], m[:3, 2], fov=2.0 * float(np.asarray(params["cutoff_angle"]).reshape(-1)[0]))

    def label(self):
        return f"spot{_fmt(self.position)}->{_fmt(self.direction)}"


@dataclass
class PointLight(_LightAt):
    """Isotropic point light at ``position`` (captured as a cube of six shadow maps)."""
    position: np.ndarray
    intensity: float = 1.0
    mitsuba_class = "PointLight"

    def shadow_camera(self, cameras, res, bmin, bmax):
        return cameras.CubeCamera(self.position, res)

    def to_mitsuba(self, mi):
        return {"type": "point", "position": self.position.tolist(), "intensity": _rgb(self.intensity)}

    @classmethod
    def from_mitsuba(cls, emitter, params):
        return cls(np.asarray(params["position"], np.float64).reshape(3))

    def label(self):
        return f"point{_fmt(self.position)}"


def check_light(light, name: str = "light") -> Light:
    """``light`` if it is a :class:`Light`; ValueError naming ``name`` otherwise."""
    if not isinstance(light, Light):
        kinds = " / ".join(t.__name__ for t in Light._by_mitsuba_class.values())
        raise ValueError(f"{name}: expected a Light ({kinds}), got {type(light).__name__}")
    return light


@dataclass
class Particles:
    """Spheres of uniform extinction: centres (P, 3), radii (P,), density (P,) per unit."""
    centers: np.ndarray
    radii: np.ndarray
    density: np.ndarray

    def validate(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Host float64 copies (centers (P, 3), radii (P,), density (P,)) after checks;
        ValueError names ``particles.<field>``.  At least one particle (an empty cloud is
        ``Scene.particles = None``), radii > 0, density >= 0."""
        c = V.array(self.centers, "particles.centers")
        r, s = (V.array(getattr(self, n), f"particles.{n}").reshape(-1) for n in ("radii", "density"))
        if c.ndim != 2 or c.shape[1] != 3:
            raise ValueError(f"particles.centers: expected shape (P, 3), got {c.shape}")
        P = c.shape[0]
        if P == 0:
            raise ValueError("particles.centers: no particles (P = 0); leave Scene.particles = None "
                             "for a scene without particles")
        for name, a in (("particles.radii", r), ("particles.density", s)):
            if a.size != P:
                raise ValueError(f"{name}: expected {P} values (one per particle), got {a.size}")
        if np.any(r <= 0):
            raise ValueError("particles.radii: radii must be > 0")
        if np.any(s < 0):
            raise ValueError("particles.density: negative density")
        return c, r, s

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World AABB (lo, hi) of the checked spheres: ``min / max of centers -+ radii``."""
        c, r, _ = self.validate()
        return (c - r[:, None]).min(0), (c + r[:, None]).max(0)


@dataclass
class Hair:
    """Strands as polylines (S, V, 3) of radius ``radius``; each crossing of a light ray
    within the radius absorbs with ``opacity`` (per strand crossing, in [0, 1])."""
    strands: np.ndarray
    radius: float
    opacity: float = 0.3

    def validate(self) -> tuple[np.ndarray, float, float]:
        """(strands (S, V, 3) float64, radius > 0, opacity in [0, 1]) after checks, S >= 1,
        V >= 2; ValueError names ``hair.<field>``."""
        s = V.array(self.strands, "hair.strands")
        if s.ndim != 3 or s.shape[2] != 3 or s.shape[1] < 2 or s.shape[0] < 1:
            raise ValueError(f"hair.strands: expected shape (S, V, 3) with S >= 1, V >= 2, got {s.shape}")
        r = V.real(self.radius, "hair.radius", 0.0, open_min=True)
        op = V.real(self.opacity, "hair.opacity", 0.0, 1.0)
        return s, r, op

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World AABB (lo, hi) of the checked strands: their vertices' box grown by ``radius``."""
        s, r, _ = self.validate()
        pts = s.reshape(-1, 3)
        return pts.min(0) - r, pts.max(0) + r


class Blocker:
    """An opaque blocker: a subclass (a dataclass) carries everything capture, ground truth,
    shading and Mitsuba need, so a new shape is one class.  ``validate(name)`` returns a checked
    copy (ValueError names ``<name>.<field>``); the others take float64 rays ``o``, ``d`` (K, 3),
    ``|d| = 1``.

    * ``bounds()``: world AABB (lo, hi);  ``contains(p)``: p inside the solid (default: never);
    * ``first_hit(o, d)``: ``(t, hit, cos)`` of the first surface at ``t >= 0``, ``cos = |d . n|``
      (capture: :mod:`avsm_dr.capture.opaque_map`);
    * ``blocks(o, d, far)``: (K,) the blocker meets the open path ``(0, far)`` (ground truth);
    * ``surface_hit(o, d)``: (K,) nearest surface crossing at ``t > 0``, inf = none (view rays);
    * ``to_mitsuba(mi, bsdf)``: the Mitsuba shape dict with ``bsdf``.

    A solid defines ``_chord(o, d)``, its ``(t0, t1, hit)``, and inherits ``blocks`` (the chord
    meets ``(0, far)``) and ``surface_hit`` (``t0`` if > 0, else ``t1``).
    """
    def contains(self, p) -> bool:
        return False

    def blocks(self, o, d, far):
        t0, t1, hit = self._chord(o, d)
        return hit & (np.maximum(t0, 0.0) < np.minimum(t1, far))

    def surface_hit(self, o, d):
        t0, t1, hit = self._chord(o, d)
        th = np.where(t0 > 0, t0, t1)
        return np.where(hit & (th > 0), th, np.inf)


@dataclass
class OpaqueSphere(Blocker):
    """Solid sphere; first hit: the first root of ``|o + t d - c| = r``."""
    center: np.ndarray
    radius: float

    def validate(self, name: str = "blocker") -> "OpaqueSphere":
        """A checked float64 copy (radius > 0); ValueError names ``<name>.<field>``."""
        return OpaqueSphere(V.vec3(self.center, f"{name}.center"),
                            V.real(self.radius, f"{name}.radius", 0.0, open_min=True))

    def bounds(self):
        return self.center - self.radius, self.center + self.radius

    def contains(self, p) -> bool:
        return bool(np.linalg.norm(p - self.center) < self.radius)

    def first_hit(self, o, d):
        c = np.broadcast_to(self.center, o.shape)
        t0, _, hit = ray_sphere(o, d, c, np.full(o.shape[0], self.radius), t_min=0.0)
        n = (o + t0[:, None] * d - c) / self.radius
        return t0, hit, np.abs(np.einsum("ij,ij->i", n, d))

    def _chord(self, o, d):
        return ray_sphere(o, d, np.asarray(self.center, np.float64), float(self.radius))

    def to_mitsuba(self, mi, bsdf):
        return {"type": "sphere", "center": np.asarray(self.center, float).tolist(),
                "radius": float(self.radius), "bsdf": bsdf}


@dataclass
class OpaqueBox(Blocker):
    """Solid axis-aligned box [min, max]; first hit: the slab entry."""
    min: np.ndarray
    max: np.ndarray

    def validate(self, name: str = "blocker") -> "OpaqueBox":
        """A checked float64 copy (max > min on every axis); ValueError names ``<name>.<field>``."""
        lo, hi = V.vec3(self.min, f"{name}.min"), V.vec3(self.max, f"{name}.max")
        if np.any(hi <= lo):
            raise ValueError(f"{name}.max: zero-size box (max must exceed min on every axis)")
        return OpaqueBox(lo, hi)

    def bounds(self):
        return self.min, self.max

    def contains(self, p) -> bool:
        return bool(np.all((p > self.min) & (p < self.max)))

    def first_hit(self, o, d):
        t0, _, hit = ray_box(o, d, self.min, self.max, t_min=0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (self.min - o) / d
            tb = (self.max - o) / d
        entry = np.where(np.isnan(ta), -np.inf, np.minimum(ta, tb))
        axis = np.argmax(entry, axis=1)                  # the face the ray enters through
        return t0, hit, np.abs(d[np.arange(d.shape[0]), axis])

    def _chord(self, o, d):
        t0, t1, _ = ray_box(o, d, np.asarray(self.min, np.float64), np.asarray(self.max, np.float64))
        return t0, t1, t0 <= t1

    def to_mitsuba(self, mi, bsdf):     # from the matrix, not translate @ scale: the inverse rounds otherwise
        lo, hi = np.asarray(self.min, float), np.asarray(self.max, float)
        m = affine(np.diag((hi - lo) / 2), (hi + lo) / 2)
        return {"type": "cube", "to_world": mi.ScalarTransform4f(m.tolist()), "bsdf": bsdf}


@dataclass
class OpaquePlane(Blocker):
    """Finite square of half-size ``extent`` centred at ``point`` with normal ``normal``:
    ``|(p - point) . u| <= extent``, ``|(p - point) . v| <= extent`` with (u, v, normal) =
    :func:`~avsm_dr.geometry.orthonormal_basis` (normal); blocks from both sides."""
    point: np.ndarray
    normal: np.ndarray
    extent: float = 1.0

    def validate(self, name: str = "blocker") -> "OpaquePlane":
        """A checked float64 copy (unit normal, extent > 0); ValueError names ``<name>.<field>``."""
        return OpaquePlane(V.vec3(self.point, f"{name}.point"), V.unit_vector(self.normal, f"{name}.normal"),
                           V.real(self.extent, f"{name}.extent", 0.0, open_min=True))

    def bounds(self):
        u, v, _ = orthonormal_basis(self.normal)
        half = self.extent * (np.abs(u) + np.abs(v))
        return self.point - half, self.point + half

    def _crossing(self, o, d, tiny: float):
        """(t, on the square, d . n) of the rays' crossing of the plane; none (t = -1) where
        ``|d . n| <= tiny``."""
        u, v, n = orthonormal_basis(self.normal)
        c = np.asarray(self.point, np.float64)
        dn = d @ n
        ok = np.abs(dn) > tiny
        t = np.where(ok, ((c - o) @ n) / np.where(ok, dn, 1.0), -1.0)
        q = o + t[:, None] * d - c
        return t, ok & (np.abs(q @ u) <= self.extent) & (np.abs(q @ v) <= self.extent), dn

    def first_hit(self, o, d):
        t, hit, dn = self._crossing(o, d, 1e-12)
        return t, hit & (t >= 0), np.abs(dn)

    def blocks(self, o, d, far):
        t, hit, _ = self._crossing(o, d, 0.0)
        return hit & (t > 0) & (t < far)

    def surface_hit(self, o, d):
        t, hit, _ = self._crossing(o, d, 1e-300)
        return np.where(hit & (t > 0), t, np.inf)

    def to_mitsuba(self, mi, bsdf):
        return {"type": "rectangle", "bsdf": {"type": "twosided", "bsdf": bsdf},
                "to_world": mi.ScalarTransform4f(square_to_world(self.point, self.normal, self.extent))}


def affine(cols, origin) -> np.ndarray:
    """4 x 4 matrix whose columns are ``cols`` (the images of the x, y, z axes) and ``origin``."""
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = np.transpose(cols), origin
    return m


def square_to_world(c, n, half) -> np.ndarray:
    """4 x 4 matrix taking Mitsuba's rectangle [-1, 1]^2 (z = 0) onto the square centred at
    ``c`` with normal ``n`` and half size ``half``, axes of :func:`~avsm_dr.geometry.orthonormal_basis`."""
    u, v, n = orthonormal_basis(n)
    return affine([u * half, v * half, n], np.asarray(c, float))


def validate_blockers(blockers) -> list:
    """Checked copies of a list of blockers (each its type's ``validate``); ValueError names
    ``blockers[i].field``."""
    if not isinstance(blockers, (list, tuple)):
        raise ValueError(f"blockers: expected a list, got {type(blockers).__name__}")
    out = []
    for i, b in enumerate(blockers):
        if not isinstance(b, Blocker):
            kinds = ", ".join(t.__name__ for t in Blocker.__subclasses__())
            raise ValueError(f"blockers[{i}]: expected a Blocker ({kinds}), got {type(b).__name__}")
        out.append(b.validate(f"blockers[{i}]"))
    return out


@dataclass
class Scene:
    """Everything a shadow needs: content, light, receivers.

    Attributes
    ----------
    name
        the scene's name (figures, tables).
    light
        DirectionalLight, SpotLight or PointLight.
    density
        (nz, ny, nx) float32 extinction per world unit, or None for non-grid content
        (floating point: integer and boolean grids are refused, :func:`avsm_dr.validation.grid_dtype`).
    bbox
        (min_xyz, max_xyz) of the grid, or None.
    receivers
        (K, 3) world points where shadows are evaluated.
    particles
        :class:`Particles`, or None.
    hair
        :class:`Hair`, or None.
    blockers
        a list of opaque blockers.
    receiver_plane
        (point, normal, half_size) of the plane used for images, or None.
    meta
        free-form provenance (source file, scale, ...).
    """
    name: str
    light: Light
    receivers: np.ndarray
    density: Optional[np.ndarray] = None
    bbox: Optional[tuple] = None
    particles: Optional[Particles] = None
    hair: Optional[Hair] = None
    blockers: list = field(default_factory=list)
    receiver_plane: Optional[tuple] = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self):      # the dtype only: validation.density_grid runs where the grid is read
        if isinstance(self.density, (np.ndarray, list, tuple)) or dr.is_array_v(self.density):
            V.grid_dtype(self.density, "density")

    @classmethod
    def from_grid(cls, grid_or_path, bbox=None, density_scale: float = 1.0, light=None, name=None,
                  receivers=None) -> "Scene":
        """A scene holding one density grid: your own volume.

        No receiver plane (so no 'surface' receiver set).  ``meta`` records the source, the
        shape, the density scale and where the box came from.

        Parameters
        ----------
        grid_or_path
            (nz, ny, nx) floating-point array (NumPy or Dr.Jit) of extinction per world unit
            before ``density_scale``, or a ``.npy`` or Mitsuba ``.vol`` file (one channel).
        bbox
            (min_xyz, max_xyz) world box of the whole grid.  Default: the ``.vol`` header's
            box, else voxels of side 1 centred at the origin, ``-+ (nx, ny, nz) / 2`` (the
            grid's own aspect ratio, never stretched).  An explicit box is used as given.
        density_scale
            factor > 0: extinction = density_scale x value (nothing else rescales it).
        light
            a :class:`Light`; default from above, ``DirectionalLight((0, -1, 0))``.
        name
            the scene's name (default: the file's stem, or 'grid').
        receivers
            (K, 3) world points, a count K, or None (1024): K points drawn uniformly
            in the voxels with density > 0 (anywhere in the box for an all-zero grid), seed 0.
        """
        import os
        from numbers import Integral
        source, box_from, file_box = "array", "argument", None
        if isinstance(grid_or_path, (str, os.PathLike)):
            source = os.fspath(grid_or_path)
            grid, file_box = _read_grid(source)
            name = os.path.splitext(os.path.basename(source))[0] if name is None else name
        else:
            grid = grid_or_path
        grid = V.density_grid(grid, "grid_or_path", np.float64)
        scale = V.real(density_scale, "density_scale", 0.0, open_min=True)
        dens = V.density_grid(grid * scale, "density_scale", np.float32)
        nz, ny, nx = dens.shape
        if bbox is None and file_box is not None:
            bbox, box_from = file_box, "vol header"
        if bbox is None:
            half = 0.5 * np.array([nx, ny, nz], np.float64)
            lo, hi, box_from = -half, half, "unit voxels"
        else:
            lo, hi = check_bbox(bbox)
        light = DirectionalLight(direction=(0.0, -1.0, 0.0)) if light is None else check_light(light)
        name = "grid" if name is None else name
        if not (isinstance(name, str) and name):
            raise ValueError(f"name: expected a non-empty string, got {name!r}")
        if receivers is None or (isinstance(receivers, Integral) and not isinstance(receivers, bool)):
            k = V.integer(1024 if receivers is None else receivers, "receivers", 1)
            V.check_memory("receivers", k, lambda m: float(m) * RECEIVER_BYTES, lo=1, what="points")
            pts = voxel_coords(dens if np.any(dens > 0) else np.ones(dens.shape), k, np.random.default_rng(0))
            pts = lo + pts * (hi - lo) / np.array([nx, ny, nz])
        else:
            pts = V.points(receivers, "receivers")
        return cls(name, light, pts, density=dens, bbox=(lo, hi),
                   meta={"source": source, "shape": (nz, ny, nx), "density_scale": scale, "bbox_from": box_from})


def voxel_coords(density, k: int, rng) -> np.ndarray:
    """(k, 3) points (x, y, z) in voxel units, one uniform in each of k voxels drawn among those
    with density > 0 (with replacement when fewer); (0, 3) when there is none or k = 0."""
    nz, ny, nx = density.shape
    idx = np.flatnonzero(density.ravel() > 0)
    if idx.size == 0 or k == 0:
        return np.zeros((0, 3))
    pick = rng.choice(idx, size=k, replace=idx.size < k)
    kz, rem = np.divmod(pick, ny * nx)
    ky, kx = np.divmod(rem, nx)
    return np.stack([kx, ky, kz], 1) + rng.random((k, 3))


#: Host bytes per receiver point that :meth:`Scene.from_grid` draws (indices, jitter, points), checked first.
RECEIVER_BYTES = 128


def _read_grid(path: str):
    """(grid, box or None) of a ``.npy`` or ``.vol`` file; ValueError naming ``grid_or_path``.
    A ``.npy`` is memory-mapped, then copied: a header announcing more data than the file holds is
    refused before any allocation; object arrays are refused (never unpickled)."""
    ext = path.lower().rsplit(".", 1)[-1] if "." in path else ""
    if ext not in ("npy", "vol"):
        raise ValueError(f"grid_or_path: expected a .npy or .vol file, got {path!r}")
    try:
        if ext == "npy":
            return np.array(np.load(path, mmap_mode="r", allow_pickle=False)), None
        from .io import read_vol
        grid, box = read_vol(path, with_bbox=True)
        if grid.ndim != 3:
            raise ValueError(f"{path!r} has {grid.shape[-1]} channels, expected 1")
        return grid, box
    except OSError as exc:
        raise ValueError(f"grid_or_path: cannot read {path!r} ({exc})") from None
    except ValueError as exc:
        msg = str(exc)
        if ext == "npy":
            why = ("truncated, or its header announces more data than it holds"
                   if "greater than file size" in msg else msg)
            msg = f"{path!r} is not a readable .npy grid ({why})"
        raise ValueError(f"grid_or_path: {msg[6:] if msg.startswith('path: ') else msg}") from None
    except Exception as exc:                   # a malformed .npy header (SyntaxError, TokenError)
        if ext != "npy":
            raise
        raise ValueError(f"grid_or_path: {path!r} is not a readable .npy file ({type(exc).__name__}: {exc})") from None
