"""Registry of transmittance representations: one module each, one line here.

``build(kind, segments, **params)`` constructs any of them.
"""
from __future__ import annotations

from typing import Callable

from ..segments import Segments
from .base import Representation

REGISTRY: dict[str, Callable[..., Representation]] = {}


def register(kind: str):
    """Class decorator adding a representation under ``kind``."""
    def deco(cls):
        cls.kind = kind
        REGISTRY[kind] = cls
        return cls
    return deco


def build(kind: str, segments: Segments, **params) -> Representation:
    """Build representation ``kind`` ('exact', 'avsm', 'dsm', 'osm', 'fom', ...)."""
    if kind not in REGISTRY:
        raise ValueError(f"kind: unknown representation {kind!r}; known: {sorted(REGISTRY)}")
    return REGISTRY[kind](segments, **params)


def kinds() -> list[str]:
    """Registered representation names, sorted."""
    return sorted(REGISTRY)


# Each import registers its representation.
from . import exact  # noqa: E402,F401


for _optional in ("avsm", "fom", "osm", "basis", "dsm", "moments"):
    try:
        __import__(f"{__name__}.{_optional}")
    except ModuleNotFoundError as _exc:  # module not written yet
        if _exc.name != f"{__name__}.{_optional}":
            raise
