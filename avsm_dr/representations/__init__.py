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

# Each import registers its representation, in this order (a broken or misspelt module fails here).
from . import (exact, avsm, dsm, basis, fom, osm, moments, beer, greedy, optimal,  # noqa: E402,F401
               avsm_march, avsm_adaptive)

__all__ = ["REGISTRY", "Param", "allows", "Representation", "Schema", "build", "configurations", "describe",
           "differentiable_configuration", "kinds", "register"]
