"""Declared cost models of the kinds a study may find slow: a deterministic work estimate of
one build from the segments it is built on, never a clock (which rows a study builds must not
depend on the machine's load).  One unit is about 7 ns of one core throughout:
:data:`BUILD_WORK` gates error_curves' variants, :data:`FRAME_WORK` frame's builds."""
from __future__ import annotations

import numpy as np

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


def linear_work(per_segment: float, per_texel: float):
    """The model ``(segments, params) -> per_segment S + per_texel T`` of a build linear in the
    segments ``S`` and the non-empty texels ``T`` (read from the offsets alone)."""
    def work(segments, params: dict) -> float:
        return per_segment * segments.n_segments + per_texel * float(np.count_nonzero(segments.counts))
    return work


#: Kind -> ``(segments, params) -> work units``; kinds without one are linear in the
#: segments and never slow.
BUILD_WORK = {"optimal": optimal_work}

#: The frame's models (at its headline parameters, all it builds): the online kinds whose build
#: costs about 0.35 us of one core per segment and 2-6 us per texel (host curve points: ``dsm``,
#: ``avsm_march``) or 11 us per texel (``avsm_adaptive``'s allocation), fitted by least squares to
#: process CPU time of builds on the size-48 built-in grids at 256^2 and 512^2 (13 captures,
#: 0.16-8.3 M segments; measured / model within 0.5-2.3x on a loaded 2-core machine).  AVSM-8,
#: FOM and Beer took at most 0.05 us per segment there; kinds without a model are never skipped.
FRAME_WORK = {"dsm": linear_work(50.0, 800.0), "avsm_march": linear_work(50.0, 250.0),
              "avsm_adaptive": linear_work(6.5, 1600.0)}
