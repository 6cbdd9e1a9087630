"""Declared cost models of the kinds error_curves may find slow: a deterministic work
estimate of one build from the segments it is built on, never a clock (the selection of
rows must not depend on the machine's load)."""
from __future__ import annotations

from avsm_dr import describe
from avsm_dr.representations import _curve


def optimal_work(segments, params: dict) -> float:
    """Work of an ``optimal`` build with schema ``params``, in units of about 7 ns of one
    core (fitted to the idle error_curves run on the built-in scenes):
    ``sum_texels 150 K + N Kp^2 + (3 [linf] + 2 [exp]) Kp^3``, K the texel's exact-curve
    points, Kp the largest K of its bucket (the padded blocks the dynamic programme and its
    pair costs work on: N K^2 and, for 'linf' or 'exp', K^3)."""
    p = {k: v["default"] for k, v in describe("optimal")["params"].items()} | dict(params)
    off = _curve.points(segments)["off"]
    cubic = 3 * (p["norm"] == "linf") + 2 * (p["interpolation"] == "exp")
    work = 150.0 * off[-1]
    for tex, kmax in _curve.buckets(off, power=2, max_elems=1 << 21):
        work += tex.size * (p["nodes"] * kmax ** 2 + cubic * kmax ** 3)
    return float(work)


#: Kind -> ``(segments, params) -> work units``; kinds without one are linear in the
#: segments and never slow.
BUILD_WORK = {"optimal": optimal_work}
