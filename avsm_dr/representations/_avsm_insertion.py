"""AVSM insertion variants (the ``insertion`` parameter of :class:`.avsm.AVSM`): what happens
when a texel's node list overflows (branch-free, like :mod:`.avsm`; measurements:
``docs/research/insertion_order.md``).  :data:`INSERTIONS`: ``stream`` (Salvi et al. 2010,
sec. 3.2: remove the node of least area metric, twice); ``refit`` (then refit its neighbours
to keep the area, ``fit="area"``); ``refit_l2`` (remove the node of least squared-L2 loss,
refit its neighbours by least squares, ``fit="l2"``); ``staged`` / ``staged_refit_l2``
(once full, insert 4 segments into ``N + 8`` nodes, then compress back to N); ``spare_refit_l2``
(``refit_l2`` on ``N + 8`` nodes while streaming, then down to N by least ``post`` metric);
``spare_exp`` (``spare_refit_l2`` with exponential ramps: :func:`.avsm.insert_segment`'s ``tau``).

Removal of interior node ``i`` with neighbours ``l = i - 1``, ``r = i + 1`` (and ``ll = i - 2``,
``rr = i + 2`` where they exist); ``c = (d_r - d_l)(t_r - t_i) - (d_r - d_i)(t_r - t_l)``:
``|c|`` is the paper's metric (twice the area lost), ``c^2 / (d_r - d_l)`` three times the
squared L2 error of the chord, ``-c / 2`` the signed area lost.  Refits change ``t_l`` only
when ``l`` is not the first node and ``t_r`` only when ``r`` is not the last (the last value
is the exact total transmittance):

* ``fit="area"``: both movable neighbours move by ``delta = -c / w`` with
  ``w = [l movable](d_r - d_ll) + [r movable](d_rr - d_l)``, keeping the polyline's area;
* ``fit="l2"``: ``(delta_l, delta_r)`` minimise the L2 distance over ``[d_ll, d_rr]`` to the
  polyline before the removal (``L0 = d_l - d_ll``, ``L1 = d_r - d_l``, ``L2 = d_rr - d_r``,
  ``p = (d_i - d_l) / L1``):
  ``2 (L0 + L1) delta_l + L1 delta_r = -c (2 - p)``, ``L1 delta_l + 2 (L1 + L2) delta_r = -c (1 + p)``;
  a fixed neighbour's row is replaced by ``delta = 0``.

The ``post`` metric, 3 x the squared L2 left after the unclipped least-squares refit (>= 0):
``c^2 / (d_r - d_l) + (c / 2)((2 - p) delta_l + (1 + p) delta_r)``.

Then both values are clipped to ``[lo, hi]`` (``hi = t_ll``, ``t_l`` when ``l`` is first;
``lo = t_rr``, ``t_r`` when ``r`` is last), and where they would cross both take their mean:
values stay in [0, 1] and non-increasing whenever they were before.
"""
from __future__ import annotations

import drjit as dr

from .. import backend

#: insertion name -> (refit: None / "area" / "l2", removal metric: "area" / "l2", segments per
#: batch, spare nodes kept while streaming (removed at the end by the "post" metric), segment
#: ramp: "linear" (the paper's) / "exp")
INSERTIONS = {
    "stream": (None, "area", 1, 0, "linear"),
    "refit": ("area", "area", 1, 0, "linear"),
    "refit_l2": ("l2", "l2", 1, 0, "linear"),
    "staged": (None, "area", 4, 0, "linear"),
    "staged_refit_l2": ("l2", "l2", 4, 0, "linear"),
    "spare_refit_l2": ("l2", "l2", 1, 8, "linear"),
    "spare_exp": ("l2", "l2", 1, 8, "exp"),
}


def remove_refit(d, t, fit, metric: str = "area", extra=(), last=None):
    """Remove the interior node of least ``metric`` (``"area"``: ``|c|``, the paper's; ``"l2"``:
    ``c^2 / (d_r - d_l)``; ``"post"``: after the refit; ties: the deepest) from ``d``, ``t`` and
    the ``extra`` lists carried along, and refit its neighbours (``fit``: None, ``"area"`` or
    ``"l2"``; module docstring).  ``last``: per lane, the index of the list's last node (UInt32,
    >= 2; the nodes behind it are ignored; default ``len(d) - 1``).  Returns the shortened
    ``(d, t, *extra)``."""
    n = len(d)
    UInt32 = backend.types().UInt32
    best = idx = None
    keep = {}
    for i in range(1, n - 1):
        c = (d[i + 1] - d[i - 1]) * (t[i + 1] - t[i]) - (d[i + 1] - d[i]) * (t[i + 1] - t[i - 1])
        if metric == "area":
            m = dr.abs(c)
        else:
            w = d[i + 1] - d[i - 1]
            m = c * c / dr.select(w > 0, w, 1)
        # the neighbourhood of node i (ll / rr: the node itself where it does not exist)
        nb = dict(c=c, dll=d[max(i - 2, 0)], dl=d[i - 1], di=d[i], dr=d[i + 1], drr=d[min(i + 2, n - 1)],
                  tll=t[max(i - 2, 0)], tl=t[i - 1], tr=t[i + 1], trr=t[min(i + 2, n - 1)])
        if metric == "post":
            dlt_l, dlt_r, p = l2_deltas(nb, i >= 2, i <= n - 3 if last is None else i + 2 <= last)
            m = dr.maximum(m + 0.5 * c * ((2 - p) * dlt_l + (1 + p) * dlt_r), 0)
        if i == 1:
            best, idx, keep = m, dr.full(UInt32, 1, dr.width(m)), nb
            continue
        take = m <= best if last is None else (m <= best) & (i < last)
        best = dr.select(take, m, best)
        idx = dr.select(take, UInt32(i), idx)
        if fit is not None:
            keep = {k: dr.select(take, v, keep[k]) for k, v in nb.items()}
    out = [[dr.select(idx <= j, x[j + 1], x[j]) for j in range(n - 1)] for x in (d, t, *extra)]
    if fit is not None:
        tl, tr = refit_values(keep, idx >= 2, idx <= n - 3 if last is None else idx + 2 <= last, fit)
        for j in range(1, n - 2):        # l = idx - 1 >= 1 and r = idx <= n - 3 in the new list
            out[1][j] = dr.select(idx == j + 1, tl, dr.select(idx == j, tr, out[1][j]))
    return tuple(out)


def refit_values(nb, move_l, move_r, fit):
    """New (t_l, t_r) after removing the node whose neighbourhood is ``nb`` (the dict of
    :func:`remove_refit`); ``move_l`` / ``move_r``: the neighbour is not the first / last node."""
    c, dll, dl, dr_, drr = nb["c"], nb["dll"], nb["dl"], nb["dr"], nb["drr"]
    tll, tl, tr, trr = nb["tll"], nb["tl"], nb["tr"], nb["trr"]
    zero = dr.zeros(type(c), dr.width(c))
    if fit == "area":
        w = dr.select(move_l, dr_ - dll, zero) + dr.select(move_r, drr - dl, zero)
        delta = -c / dr.select(w > 0, w, 1)
        delta = dr.select(w > 0, delta, zero)
        dlt_l = dr.select(move_l, delta, zero)
        dlt_r = dr.select(move_r, delta, zero)
    else:
        dlt_l, dlt_r, _ = l2_deltas(nb, move_l, move_r)
    hi = dr.select(move_l, tll, tl)
    lo = dr.select(move_r, trr, tr)
    ul = dr.minimum(dr.maximum(tl + dlt_l, lo), hi)
    ur = dr.minimum(dr.maximum(tr + dlt_r, lo), hi)
    mean = (ul + ur) * 0.5
    cross = ur > ul
    ul = dr.select(move_l, dr.select(cross, mean, ul), tl)
    ur = dr.select(move_r, dr.select(cross, mean, ur), tr)
    return ul, ur


def l2_deltas(nb, move_l, move_r):
    """Unclipped least-squares ``(delta_l, delta_r, p)`` of ``fit="l2"`` (module docstring)."""
    c, dll, dl, di, dr_, drr = nb["c"], nb["dll"], nb["dl"], nb["di"], nb["dr"], nb["drr"]
    zero = dr.zeros(type(c), dr.width(c))
    l0, l1, l2 = dl - dll, dr_ - dl, drr - dr_
    p = (di - dl) / dr.select(l1 > 0, l1, 1)
    a11 = dr.select(move_l, 2 * (l0 + l1), 1)
    a22 = dr.select(move_r, 2 * (l1 + l2), 1)
    a12 = dr.select(move_l & move_r, l1, zero)
    b1 = dr.select(move_l, -c * (2 - p), zero)
    b2 = dr.select(move_r, -c * (1 + p), zero)
    det = a11 * a22 - a12 * a12
    ok, inv = det > 0, 1 / dr.select(det > 0, det, 1)
    return dr.select(ok, (b1 * a22 - a12 * b2) * inv, zero), dr.select(ok, (a11 * b2 - a12 * b1) * inv, zero), p
