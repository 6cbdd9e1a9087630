"""The registry itself: kind name -> Representation subclass, and the functions that read it.
Kind modules import :func:`register` from here; the package ``__init__`` imports every kind."""
from __future__ import annotations

from ..segments import Segments
from .base import Representation
from ..validation import did_you_mean
from .schema import BASE_PARAMETERS, Schema

REGISTRY: dict[str, type[Representation]] = {}


def register(kind: str):
    """Class decorator adding a :class:`Representation` subclass under ``kind``."""
    def deco(cls):
        if not (isinstance(cls, type) and issubclass(cls, Representation)):
            raise ValueError(f"kind: {kind!r} must register a Representation subclass, got {cls!r}")
        if not isinstance(cls.__dict__.get("schema", cls.schema), Schema):
            raise ValueError(f"kind: {kind!r} needs a Schema as its `schema` attribute")
        cls.kind = kind
        REGISTRY[kind] = cls
        return cls
    return deco


def _check_kind(kind) -> type[Representation]:
    if not isinstance(kind, str) or kind not in REGISTRY:
        raise ValueError(f"kind: unknown representation {kind!r}; known: {sorted(REGISTRY)}"
                         f"{did_you_mean(kind, REGISTRY)}")
    return REGISTRY[kind]


def build(kind: str, segments: Segments, **params) -> Representation:
    """Build representation ``kind`` from ``segments`` with ``params`` (see ``describe``);
    every kind also takes ``reverse='auto'|'trajectory'|'checkpoint'``, ``chunk`` and
    ``precision`` (None or one of ``describe(kind)['precisions']``)."""
    return _check_kind(kind)(segments, **params)


def kinds() -> list[str]:
    """Registered representation names, sorted."""
    return sorted(REGISTRY)


def describe(kind: str) -> dict:
    """What ``kind`` takes and how experiments size it: :meth:`.schema.Schema.describe`'s dict
    plus ``kind``, ``doc`` (the class docstring's first paragraph), ``precisions`` (accepted
    besides None) and the class attributes ``PRESET*``: ``preset``, ``preset_capture``,
    ``preset_variants``, ``preset_tuned`` (``preset_note`` only when that is False)."""
    cls = _check_kind(kind)
    out = cls.schema.describe()
    out.update(kind=kind, precisions=list(cls.precisions), doc=(cls.__doc__ or "").strip().split("\n\n")[0],
               preset=dict(cls.PRESET), preset_capture=dict(cls.PRESET_CAPTURE),
               preset_variants={k: dict(v) for k, v in cls.PRESET_VARIANTS.items()},
               preset_tuned=cls.PRESET_UNTUNED is None)
    if cls.PRESET_UNTUNED is not None:
        out["preset_note"] = cls.PRESET_UNTUNED
    return out


def configurations(kind: str, quick: bool = False) -> list[dict]:
    """Parameter sets of ``kind``'s sweep: ``headline`` with the size parameter set to each
    sweep value (the headline alone when the kind has no size parameter)."""
    d = describe(kind)
    base = dict(d["headline"])
    if d["size"] is None:
        return [base]
    return [dict(base, **{d["size"]: v}) for v in (d["quick_sweep"] if quick else d["sweep"])]


def allows(kind: str, params: dict) -> bool:
    """True when ``params`` are valid for ``kind`` (every parameter rule and the schema's
    cross-parameter ``constraint``, e.g. moments: 6 power moments but no 6 trigonometric)."""
    return _check_kind(kind).schema.allows(kind, {k: v for k, v in params.items() if k not in BASE_PARAMETERS})


def differentiable_configuration(kind: str) -> dict | None:
    """Parameters of ``kind``'s first differentiable configuration (its headline, then its
    schema's examples in order), or None when none is differentiable."""
    d = describe(kind)
    probe = Segments.from_arrays([0, 1], [0.2], [0.4], optical_depth=[0.5])
    for p in (d["headline"], *d["examples"]):
        if REGISTRY[kind](probe, **p).differentiable:
            return dict(p)
    return None
