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

from dataclasses import dataclass, field
from typing import Optional, Union

import numpy as np

from . import validation as V


@dataclass
class DirectionalLight:
    """Parallel light travelling along ``direction``; irradiance ``irradiance`` (W/m^2)."""
    direction: np.ndarray
    irradiance: float = 1.0

    def __post_init__(self):
        self.direction = V.unit_vector(self.direction, "direction")
        self.irradiance = V.real(self.irradiance, "irradiance", 0.0)


@dataclass
class SpotLight:
    """Spot light at ``position`` pointing along ``direction`` with full cone angle ``fov`` degrees."""
    position: np.ndarray
    direction: np.ndarray
    fov: float = 60.0
    intensity: float = 1.0

    def __post_init__(self):
        self.position = V.vec3(self.position, "position")
        self.direction = V.unit_vector(self.direction, "direction")
        self.fov = V.real(self.fov, "fov", 0.0, 180.0, open_min=True, open_max=True)
        self.intensity = V.real(self.intensity, "intensity", 0.0)


@dataclass
class PointLight:
    """Isotropic point light at ``position`` (captured as a cube of six shadow maps)."""
    position: np.ndarray
    intensity: float = 1.0

    def __post_init__(self):
        self.position = V.vec3(self.position, "position")
        self.intensity = V.real(self.intensity, "intensity", 0.0)


Light = Union[DirectionalLight, SpotLight, PointLight]


@dataclass
class Particles:
    """Spheres of uniform extinction: centres (P, 3), radii (P,), density (P,) per unit."""
    centers: np.ndarray
    radii: np.ndarray
    density: np.ndarray


@dataclass
class Hair:
    """Strands as polylines (S, V, 3) of radius ``radius``; each crossing of a light ray
    within the radius absorbs with ``opacity`` (per strand crossing, in [0, 1])."""
    strands: np.ndarray
    radius: float
    opacity: float = 0.3


@dataclass
class OpaqueSphere:
    center: np.ndarray
    radius: float


@dataclass
class OpaqueBox:
    min: np.ndarray
    max: np.ndarray


@dataclass
class OpaquePlane:
    """Finite square of half-size ``extent`` centred at ``point`` with normal ``normal``."""
    point: np.ndarray
    normal: np.ndarray
    extent: float = 1.0


@dataclass
class Scene:
    """Everything a shadow needs: content, light, receivers.

    density: (nz, ny, nx) float32 extinction per world unit, or None for non-grid content.
    bbox: (min_xyz, max_xyz) of the grid, or None.
    receivers: (K, 3) world points where shadows are evaluated.
    receiver_plane: (point, normal, half_size) of the plane used for images, or None.
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
