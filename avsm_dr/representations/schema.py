"""Parameter schemas: each representation declares its parameters once, and validation,
``ad.describe(kind)``, the experiments' sweeps and the docs' tables read them.

One rule for every parameter: ``int`` an integral number (Python or NumPy, never ``bool``);
``float`` a real, finite number (integers allowed, never ``bool`` or ``str``), ``min``/``max``
inclusive unless ``open_min``/``open_max``; ``bool`` ``True``/``False`` only; ``choice`` one of
``choices``; ``object`` passed through (validated by the representation).  ``nullable=True``
admits ``None`` (derived from the segments, e.g. near/far).  Errors are
``ValueError("<name>: expected ..., got ...")``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from .. import validation as V

KINDS = ("int", "float", "bool", "choice", "object")

#: Parameters every kind takes besides its schema's (read by ``Representation`` itself).
BASE_PARAMETERS = ("precision", "reverse", "chunk")


@dataclass(frozen=True)
class Param:
    """One build parameter: name, type (see :data:`KINDS`), default, valid range, doc."""

    name: str
    type: str
    default: Any = None
    doc: str = ""
    min: float | None = None
    max: float | None = None
    open_min: bool = False
    open_max: bool = False
    choices: tuple = ()
    nullable: bool = False

    def __post_init__(self):
        if self.type not in KINDS:
            raise ValueError(f"type: expected one of {KINDS}, got {self.type!r}")
        if self.type == "int" and (self.open_min or self.open_max):
            raise ValueError(f"open_min: int parameter {self.name!r} takes closed bounds")

    def validate(self, value):
        """The value converted to its Python type, or ValueError naming the parameter."""
        if (value is None and self.nullable) or self.type == "object":
            return value
        if self.type == "bool":
            if isinstance(value, (bool, np.bool_)):
                return bool(value)
            raise ValueError(f"{self.name}: expected True or False, got {value!r}")
        if self.type == "choice":
            return V.one_of(value, self.name, self.choices)
        if self.type == "int":
            return V.integer(value, self.name, self.min, self.max)
        return V.real(value, self.name, self.min, self.max, open_min=self.open_min, open_max=self.open_max)

    def describe(self) -> dict:
        """Plain-data description (for ``ad.describe`` and the docs)."""
        out = {"default": self.default, "type": self.type, "min": self.min, "max": self.max, "doc": self.doc}
        if self.choices:
            out["choices"] = list(self.choices)
        if self.nullable:
            out["nullable"] = True
        return out


@dataclass(frozen=True)
class Schema:
    """A kind's parameters: ``size`` the one that trades memory for accuracy (or None),
    ``sweep`` / ``quick_sweep`` its values in the experiments (full / ``--quick``),
    ``examples`` parameter sets the contract tests run, ``headline`` the configuration
    benchmarks use, ``summary`` / ``paper`` the docs' kinds table; ``offline``: an offline
    reference (host code, cost superlinear in the segments per texel) that benchmarks run only
    where it fits; ``constraint``: a rule across parameters, ``params -> message | None`` (the
    message starts with the offending parameter's name), checked after the per-parameter ones.
    """

    params: tuple = ()
    size: str | None = None
    sweep: tuple = ()
    quick_sweep: tuple = ()
    examples: tuple = ()
    headline: dict = field(default_factory=dict)
    summary: str = ""
    paper: str = ""
    offline: bool = False
    constraint: Callable[[dict], str | None] | None = None

    def __post_init__(self):
        names = [p.name for p in self.params]
        if len(set(names)) != len(names):
            raise ValueError(f"params: duplicate names in {names}")
        if self.size is not None and self.size not in names:
            raise ValueError(f"size: {self.size!r} is not a parameter ({names})")

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(name)

    def names(self) -> list[str]:
        return [p.name for p in self.params]

    def public_names(self) -> list[str]:
        """The parameters a message lists: the schema's public ones (private ``_`` switches
        are accepted, not listed), then :data:`BASE_PARAMETERS`."""
        return [n for n in self.names() if not n.startswith("_")] + list(BASE_PARAMETERS)

    def unknown_message(self, kind: str, name: str) -> str:
        """``"<name>: unknown parameter of <kind>; known: [...]"`` (public names), with a
        "did you mean" for a misspelling."""
        known = self.public_names()
        return f"{name}: unknown parameter of {kind!r}; known: {known}{V.did_you_mean(name, known)}"

    def validate(self, kind: str, given: dict) -> dict:
        """Defaults filled in and every value checked; unknown names raise ValueError."""
        unknown = sorted(set(given) - set(self.names()))
        if unknown:
            raise ValueError(self.unknown_message(kind, unknown[0]))
        out = {p.name: p.validate(given.get(p.name, p.default)) for p in self.params}
        if self.constraint is not None and (msg := self.constraint(out)):
            raise ValueError(msg)
        return out

    def allows(self, kind: str, given: dict) -> bool:
        """True when ``given`` passes :meth:`validate` (every rule, the constraint too)."""
        try:
            self.validate(kind, given)
        except ValueError:
            return False
        return True

    def describe(self) -> dict:
        """Plain-data description, private ``_`` parameters left out."""
        return {"params": {p.name: p.describe() for p in self.params if not p.name.startswith("_")},
                "size": self.size,
                "sweep": list(self.sweep), "quick_sweep": list(self.quick_sweep or self.sweep),
                "examples": [dict(e) for e in self.examples], "headline": dict(self.headline),
                "summary": self.summary, "paper": self.paper, "offline": self.offline}


#: Parameters several kinds share (one definition, one message): the depth range.
NEAR = Param("near", "float", None, "start of the depth range (default: the segments' global bounds)", nullable=True)
FAR = Param("far", "float", None, "end of the depth range (default: the segments' global bounds)", nullable=True)
DEPTH_RANGE = Param("depth_range", "choice", "global", "'global': one [near, far] for all texels; 'texel': tight "
                    "per-texel bounds, stored (2 floats per texel)", choices=("global", "texel"))
