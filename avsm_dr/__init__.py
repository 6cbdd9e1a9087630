"""avsm_dr: differentiable volumetric shadow representations on Dr.Jit.

Example::

    import avsm_dr as ad
    seg = ad.Segments.from_arrays(offsets, z0, z1, transmittance=t_exit)
    rep = ad.build("avsm", seg, nodes=8)
    T = rep.eval(texel, depth)
"""
from ._llvm import ensure_libllvm as _ensure_libllvm

_ensure_libllvm()  # must run before drjit is imported

from .backend import available_backends, get_backend, set_backend  # noqa: E402
from .representations import REGISTRY, allows, build, configurations, describe, kinds, register  # noqa: E402
from .representations.base import Representation  # noqa: E402
from .segments import OPAQUE_OPTICAL_DEPTH, Segments  # noqa: E402
from . import builtin_scenes as scenes, groundtruth, shading  # noqa: E402
from .capture import Capture, capture  # noqa: E402
from .scene import (DirectionalLight, Hair, OpaqueBox, OpaquePlane, OpaqueSphere, Particles, PointLight,  # noqa: E402
                    Scene, SpotLight)
from . import evaluation  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "Segments", "allows", "build", "describe", "configurations", "kinds", "register", "REGISTRY", "Representation",
    "set_backend", "get_backend", "available_backends", "OPAQUE_OPTICAL_DEPTH",
    "capture", "Capture", "scenes", "groundtruth", "shading",
    "Scene", "DirectionalLight", "SpotLight", "PointLight", "Particles", "Hair", "OpaqueSphere", "OpaqueBox",
    "OpaquePlane", "evaluation"]
