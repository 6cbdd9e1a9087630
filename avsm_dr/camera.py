"""The package's one pinhole camera: ground-truth images, shading, area lights and the
Mitsuba integrator's sensor.

:class:`PinholeCamera` at ``origin`` looks at ``target`` with ``up`` giving the image's
upward direction; ``fov`` is the horizontal field of view in degrees (Mitsuba's
``fov_axis='x'``).  Frame: ``f = normalize(target - origin)``, ``r = normalize(f x up)``,
``u = r x f``; pixel (row j, column i) of a ``width x height`` image (row 0 at the top)
has the pixel-centre ray direction ``normalize(f + x tan(fov/2) r + y tan(fov/2) (H/W) u)``
with ``x = 2 (i + 1/2) / W - 1``, ``y = 1 - 2 (j + 1/2) / H``: the convention of
Mitsuba's ``perspective`` sensor with ``look_at(origin, target, up)`` (:meth:`sensor_dict`;
its rays agree with :meth:`rays` up to float32 rounding).

A camera dict ``{origin, target, up, fov}`` (the ground-truth functions' ``camera=``
argument, still accepted) is this class's keyword arguments (:meth:`PinholeCamera.of`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from . import validation as V

#: Largest image side (pixels).
MAX_SIDE = 1 << 14


@dataclass
class PinholeCamera:
    """Pinhole camera (see the module docstring for the frame and pixel convention).

    Parameters
    ----------
    origin, target : (3,) array_like
        Eye and look-at point; they must differ.
    up : (3,) array_like
        Upward direction, non-zero and not parallel to ``target - origin``.
    fov : float
        Horizontal field of view in degrees, in (0, 180).
    width, height : int
        Image size in pixels, in [1, ``MAX_SIDE``]."""
    origin: np.ndarray
    target: np.ndarray
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    fov: float = 60.0
    width: int = 32
    height: int = 32

    def __post_init__(self):
        self.origin, self.target, self.up = (V.vec3(getattr(self, n), n) for n in ("origin", "target", "up"))
        self.fov = V.real(self.fov, "fov", 0.0, 180.0, open_min=True, open_max=True)
        self.width = V.integer(self.width, "width", 1, MAX_SIDE)
        self.height = V.integer(self.height, "height", 1, MAX_SIDE)
        fwd = self.target - self.origin
        if np.linalg.norm(fwd) == 0:
            raise ValueError("target: must differ from origin")
        if np.linalg.norm(self.up) == 0:
            raise ValueError("up: must be non-zero")
        if np.linalg.norm(np.cross(fwd, self.up)) <= 1e-9 * np.linalg.norm(fwd) * np.linalg.norm(self.up):
            raise ValueError("up: must not be parallel to the viewing direction")

    @classmethod
    def of(cls, camera, fov: float = 40.0, width: int = 32, height: int = 32) -> "PinholeCamera":
        """``camera`` (a :class:`PinholeCamera`, or a dict ``{origin, target, up[, fov]}``) as a
        camera of ``width x height`` pixels; ``fov`` fills a dict without one.  ValueError
        names ``camera`` or ``camera.<field>``."""
        if isinstance(camera, cls):
            kw = dict(origin=camera.origin, target=camera.target, up=camera.up, fov=camera.fov)
        elif isinstance(camera, dict):
            kw = {"fov": fov, **camera}
            for key in ("origin", "target", "up"):
                if key not in kw:
                    raise ValueError(f"camera: missing {key!r} (expected origin, target, up, fov)")
            kw = {key: kw[key] for key in ("origin", "target", "up", "fov")}
        else:
            raise ValueError(f"camera: expected a dict (origin, target, up, fov) or a PinholeCamera, "
                             f"got {type(camera).__name__}")
        try:
            return cls(**kw, width=width, height=height)
        except ValueError as e:
            if str(e).startswith(("width", "height")):
                raise
            raise ValueError(f"camera.{e}") from None

    def frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(forward f, right r, up u) unit vectors, float64."""
        fwd = self.target - self.origin
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, self.up)
        right /= np.linalg.norm(right)
        return fwd, right, np.cross(right, fwd)

    def rays(self) -> np.ndarray:
        """(H*W, 3) float64 unit directions through the pixel centres, row-major from the top."""
        fwd, right, up = self.frame()
        tx = math.tan(math.radians(self.fov) / 2)
        ty = tx * self.height / self.width
        i = (np.arange(self.width) + 0.5) / self.width * 2 - 1
        j = 1 - (np.arange(self.height) + 0.5) / self.height * 2
        X, Y = np.meshgrid(i * tx, j * ty)
        d = fwd[None] + X.reshape(-1, 1) * right[None] + Y.reshape(-1, 1) * up[None]
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def sensor_dict(self, mi, spp: int = 1) -> dict:
        """Mitsuba ``perspective`` sensor of this camera (``mi``: the mitsuba module with a
        variant set): ``look_at(origin, target, up)``, ``fov_axis='x'``, an ``hdrfilm`` of
        ``width x height`` with a box filter, an ``independent`` sampler of ``spp`` samples."""
        return {
            "type": "perspective",
            "fov": self.fov,
            "fov_axis": "x",
            "to_world": mi.ScalarTransform4f().look_at(origin=self.origin.tolist(), target=self.target.tolist(),
                                                       up=self.up.tolist()),
            "film": {"type": "hdrfilm", "width": int(self.width), "height": int(self.height),
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": V.integer(spp, "spp", 1)}}
