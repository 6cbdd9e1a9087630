"""The few human lines a run ends with: numbers and intervals formatted for reading, and the
generic fallback for a study that declares no ``headline`` (:class:`experiments._study.Study`).

Every study's ``headline(summary) -> list[str]`` reads its own ``summary`` (as recorded in
``meta.json``: JSON types only, so a reused run prints the same lines) and says what was
measured with its headline numbers, ``estimate [low, high]`` where the study has an interval.
"""
from __future__ import annotations

import math
from typing import Iterable

#: Keys of a point estimate in an interval dict ``{<key>, low, high}`` (the first present is used).
ESTIMATE_KEYS = ("estimate", "ratio", "rmse_ratio", "rmse", "value", "mean")


def num(value, digits: int = 3) -> str:
    """A number for reading: ``digits`` significant digits, thousands and millions spelled
    out (``2.6 M``), booleans as yes/no, ``None`` and NaN as ``n/a``."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if not isinstance(value, (int, float)):
        return str(value)
    if isinstance(value, int) and abs(value) < 10 ** 6:
        return str(value)
    if abs(value) >= 1e6:
        return f"{value / 1e6:.{digits}g} M"
    if abs(value) >= 1e4:
        return f"{value:,.0f}"
    return f"{value:.{digits}g}"


def is_interval(d) -> bool:
    """True for ``{estimate|ratio|rmse|value|mean, low, high, ...}``."""
    return isinstance(d, dict) and "low" in d and "high" in d and any(k in d for k in ESTIMATE_KEYS)


def interval(d, digits: int = 3) -> str:
    """``estimate [low, high]`` of an interval dict (:func:`is_interval`), a plain number as :func:`num`."""
    if not is_interval(d):
        return num(d, digits)
    est = next(d[k] for k in ESTIMATE_KEYS if k in d)
    return f"{num(est, digits)} [{num(d['low'], digits)}, {num(d['high'], digits)}]"


def label(key) -> str:
    """A summary key for reading: underscores as spaces (``run_seconds`` -> ``run seconds``)."""
    return str(key).replace("_", " ")


def listing(items: Iterable, limit: int = 6) -> str:
    """``a, b, c`` (at most ``limit``, then ``and N more``)."""
    items = [str(i) for i in items]
    more = len(items) - limit
    return ", ".join(items[:limit]) + (f" and {more} more" if more > 0 else "")


def wrap(prefix: str, items: Iterable[str], width: int = 100) -> list[str]:
    """``prefix`` and ``items`` (joined by ``, ``) packed into lines of about ``width``
    characters, continuation lines indented by two spaces."""
    lines, line = [], prefix
    for item in items:
        if line != prefix and len(line) + len(item) + 2 > width:
            lines.append(line + ",")
            line = "  " + item
        else:
            line += ("" if line in (prefix, "  ") else ", ") + item
    return lines + [line] if line != prefix else lines


def generic(summary, width: int = 110) -> list[str]:
    """Lines for a summary with no declared headline: one per leaf, its path of keys as words
    (``scene / N=8 / avsm over optimal: 2.9 [2.6, 3.1]``); a dict of plain numbers on one line;
    never a dict's repr."""
    if not isinstance(summary, dict):
        return [_clip(_value(summary), width)] if summary not in (None, "", []) else []
    lines = []

    def walk(d, path):
        leaves = {k: v for k, v in d.items() if not isinstance(v, dict) or is_interval(v)}
        nested = {k: v for k, v in d.items() if k not in leaves}
        if path and leaves and all(isinstance(v, (int, float)) for v in leaves.values()):
            lines.append(f"{' / '.join(path)}: " + ", ".join(f"{label(k)} {num(v)}" for k, v in leaves.items()))
        else:
            lines.extend(f"{' / '.join([*path, label(k)])}: {_value(v)}" for k, v in leaves.items())
        for k, v in nested.items():
            walk(v, [*path, label(k)])
    walk(summary, [])
    return [_clip(ln, width) for ln in lines]


def _value(v) -> str:
    if is_interval(v):
        return interval(v)
    if isinstance(v, dict):
        return ", ".join(f"{label(k)} {_value(x)}" for k, x in v.items())
    if isinstance(v, (list, tuple)):
        return listing(_value(x) for x in v)
    return num(v)


def _clip(text: str, width: int) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= width else text[:width - 4] + " ..."
