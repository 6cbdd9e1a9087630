"""Registry of transmittance representations: one module each, one import line here.

``build(kind, segments, **params)`` constructs any of them; ``describe(kind)`` says what
parameters it takes (defaults, types, ranges), which one is its size parameter and the
values experiments sweep.  Tests, experiments, benchmarks and the docs read the registry,
so a new kind joins all of them by being registered.
"""
from __future__ import annotations

from .base import Representation
from .registry import REGISTRY, allows, build, configurations, describe, differentiable_configuration, kinds, register
from .schema import Param, Schema

# Each import registers its representation (a broken or misspelt module fails here).
from . import exact  # noqa: E402,F401
from . import avsm  # noqa: E402,F401
from . import dsm  # noqa: E402,F401
from . import basis  # noqa: E402,F401
from . import fom  # noqa: E402,F401
from . import osm  # noqa: E402,F401
from . import moments  # noqa: E402,F401
from . import beer  # noqa: E402,F401
from . import greedy  # noqa: E402,F401
from . import optimal  # noqa: E402,F401
from . import avsm_march  # noqa: E402,F401
from . import avsm_adaptive  # noqa: E402,F401

__all__ = ["REGISTRY", "Param", "allows", "Representation", "Schema", "build", "configurations", "describe",
           "differentiable_configuration", "kinds", "register"]
