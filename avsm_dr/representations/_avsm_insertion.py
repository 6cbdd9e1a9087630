"""AVSM insertion variants (the ``insertion`` parameter of :class:`.avsm.AVSM`): what happens
when a texel's node list overflows (branch-free, like :mod:`.avsm`; measurements:
``docs/research/insertion_order.md``).  :data:`INSERTIONS`: ``stream`` (Salvi et al. 2010,
sec. 3.2: remove the node of least area metric, twice); ``refit`` (then refit its neighbours
to keep the area, ``fit="area"``); ``refit_l2`` (remove the node of least squared-L2 loss,
refit its neighbours by least squares, ``fit="l2"``); ``staged`` / ``staged_refit_l2``
(once full, insert 4 segments into ``N + 8`` nodes, then compress back to N); ``spare_refit_l2``
(``refit_l2`` on ``N + 8`` nodes while streaming, then down to N by least ``post`` metric);
``spare_exp`` (``spare_refit_l2`` with exponential ramps: :func:`.avsm.insert_segment`'s ``tau``);
``spare_exp_fit`` (``spare_exp``, then the least-squares values of :func:`fit_values` where
streaming kept the exact curve).

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

The final fit (``spare_exp_fit``): on a texel where no removal while streaming moved the
``N + 8`` working list's curve by more than :data:`KEEP_TOL` (the removed node that close to
its neighbours' chord: coincident nodes, as contiguous segments give, or flat stretches),
the nodes hold the exact curve's values and its exponential interpolation (uniform density
between nodes) is the exact curve, up to that tolerance.  After the compression to N, the N
values (depths fixed) are the least-squares fit of the linear lookup to that curve over the
node range: the first and the last node fixed, ``sum_j M_kj x_j = b_k`` with the tridiagonal
``M_kk = (h_{k-1} + h_k) / 3``, ``M_k,k+1 = h_k / 6`` (``h_k`` the width of piece k) and
``b_k = int T phi_k`` (``phi_k`` node k's hat function), solved by the Thomas algorithm,
clipped to ``[t_last, 1]`` and made non-increasing by the mean of the running minimum from
the front and the running maximum from the back.  ``b`` comes from the moments ``S0 = int T``,
``S1 = int T (z - d_k)`` of each piece (:func:`piece_moments`), merged when a node is removed
(:func:`remove_refit`'s ``moments``).  Other texels keep ``spare_exp``'s values.
"""
from __future__ import annotations

import math

import drjit as dr

from .. import _arrays as A
from .. import backend

#: insertion name -> (refit: None / "area" / "l2", removal metric: "area" / "l2", segments per
#: batch, spare nodes kept while streaming (removed at the end by the "post" metric), segment
#: ramp: "linear" (the paper's) / "exp", final value fit: False / True (:func:`fit_values`)
INSERTIONS = {
    "stream": (None, "area", 1, 0, "linear", False),
    "refit": ("area", "area", 1, 0, "linear", False),
    "refit_l2": ("l2", "l2", 1, 0, "linear", False),
    "staged": (None, "area", 4, 0, "linear", False),
    "staged_refit_l2": ("l2", "l2", 4, 0, "linear", False),
    "spare_refit_l2": ("l2", "l2", 1, 8, "linear", False),
    "spare_exp": ("l2", "l2", 1, 8, "exp", False),
    "spare_exp_fit": ("l2", "l2", 1, 8, "exp", True)}
#: A removal keeps the curve (final fit) when the removed node lies within this of its
#: neighbours' chord (measured: 1e-4 never worse than no fit; 1e-3 worse on some scenes at N = 16).
KEEP_TOL = 1e-4
#: Below this exponent the moments use their Taylor series (:func:`piece_moments`).
SERIES_BELOW = 0.25


def remove_refit(d, t, fit, metric: str = "area", extra=(), last=None, moments=None, with_gap=False):
    """Remove the interior node of least ``metric`` (``"area"``: ``|c|``, the paper's; ``"l2"``:
    ``c^2 / (d_r - d_l)``; ``"post"``: after the refit; ties: the deepest) from ``d``, ``t`` and
    the ``extra`` lists carried along, and refit its neighbours (``fit``: None, ``"area"`` or
    ``"l2"``; module docstring).  ``last``: per lane, the index of the list's last node (UInt32,
    >= 2; the nodes behind it are ignored; default ``len(d) - 1``).  ``moments``: lists
    ``(S0, S1)`` of each piece's moments (:func:`piece_moments`), the removed node's piece
    merged into its left neighbour's.  Returns the shortened ``(d, t, *extra)`` (then the
    moments' two lists; then, ``with_gap``, the removed node's distance to its neighbours'
    chord per lane: ``|c| / (d_r - d_l)``, 0 where ``d_r = d_l``)."""
    n = len(d)
    UInt32 = backend.types().UInt32
    cands = []          # (metric, first index, [index, gap, *neighbourhood]) per interior node
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
        w = d[i + 1] - d[i - 1]
        g = [dr.abs(c) / dr.select(w > 0, w, 1)] if with_gap else []
        cands.append((m, i, [dr.full(UInt32, i, dr.width(m)), *g, *(nb.values() if fit is not None else ())]))
    # least metric, ties to the deepest, by a tree (``last``: a subtree whose first node is not a candidate has none)
    def merge(lt, rt):
        (ml, il, pl), (mr, ir, pr) = lt, rt
        take = mr <= ml if last is None else (mr <= ml) & (UInt32(ir) < last)
        return dr.select(take, mr, ml), il, [dr.select(take, b, a) for a, b in zip(pl, pr)]
    idx, *rest = A.pairwise(cands, merge)[2]
    gap = rest.pop(0) if with_gap else None
    keep = dict(zip(nb, rest))                  # the neighbourhood keys (every node's nb has the same)
    out = [[dr.select(idx <= j, x[j + 1], x[j]) for j in range(n - 1)] for x in (d, t, *extra)]
    if fit is not None:
        tl, tr = refit_values(keep, idx >= 2, idx <= n - 3 if last is None else idx + 2 <= last, fit)
        for j in range(1, n - 2):        # l = idx - 1 >= 1 and r = idx <= n - 3 in the new list
            out[1][j] = dr.select(idx == j + 1, tl, dr.select(idx == j, tr, out[1][j]))
    if moments is not None:              # piece idx - 1 absorbs piece idx (S1 about its start)
        s0, s1 = moments
        out += [[dr.select(idx == j + 1, s0[j] + s0[j + 1], dr.select(idx <= j, s0[j + 1], s0[j]))
                 for j in range(n - 1)],
                [dr.select(idx == j + 1, s1[j] + s1[j + 1] + (d[j + 1] - d[j]) * s0[j + 1],
                           dr.select(idx <= j, s1[j + 1], s1[j])) for j in range(n - 1)]]
    return (*out, gap) if with_gap else tuple(out)


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


def piece_moments(d, t, count):
    """Moments of the exponential interpolation ``T = t_j (t_{j+1} / t_j)^u`` (linear where a
    value is 0) over each piece ``j`` of the node list, ``u = (z - d_j) / L``, ``L = d_{j+1} - d_j``:
    ``S0 = int T dz = L t_j phi1(a)``, ``S1 = int T (z - d_j) dz = L^2 t_j phi2(a)``, ``a =
    ln(t_j / t_{j+1})``, ``phi1(a) = (1 - e^-a) / a``, ``phi2(a) = (1 - (1 + a) e^-a) / a^2``
    (Taylor series to ``a^10`` below :data:`SERIES_BELOW`); 0 for the pieces from node
    ``count - 1`` on (``count``: UInt32 per lane, the real nodes).  Returns ``(S0, S1)``,
    lists of ``len(d)`` arrays."""
    n = len(d)
    s0, s1 = [], []
    zero = dr.zeros(type(d[0]), dr.width(d[0]))
    for j in range(n - 1):
        v0, v1, length = t[j], t[j + 1], dr.maximum(d[j + 1] - d[j], 0)
        ok = (v0 > 0) & (v1 > 0)
        a = dr.maximum(dr.log(dr.select(ok, v0, 1)) - dr.log(dr.select(ok, v1, 1)), 0)
        p1, p2 = _phi(a)
        m0 = dr.select(ok, v0 * p1, (v0 + v1) * 0.5) * length
        m1 = dr.select(ok, v0 * p2, (v0 + 2 * v1) * (1 / 6)) * length * length
        real = count > j + 1
        s0.append(dr.select(real, m0, zero))
        s1.append(dr.select(real, m1, zero))
    return s0 + [zero], s1 + [zero]


def _phi(a):
    """``(phi1(a), phi2(a))`` for ``a >= 0`` (:func:`piece_moments`): the closed forms, or their
    Taylor series ``sum_k (-a)^k / (k + 1)!`` and ``sum_k (-a)^k / (k! (k + 2))`` (Horner, to
    ``a^10``) below :data:`SERIES_BELOW`, where the closed forms cancel."""
    small = a < SERIES_BELOW
    x = dr.select(small, 1, a)
    ex = dr.exp(-x)
    s1 = s2 = 0
    for k in reversed(range(11)):
        s1 = s1 * a + (-1) ** k / math.factorial(k + 1)
        s2 = s2 * a + (-1) ** k / (math.factorial(k) * (k + 2))
    return dr.select(small, s1, (1 - ex) / x), dr.select(small, s2, (1 - (1 + x) * ex) / (x * x))


def fit_values(d, t, s0, s1, last, active):
    """Least-squares node values (module docstring, "final fit") of the list ``(d, t)`` against
    the curve whose piece moments are ``(s0, s1)``: node 0 and node ``last`` (UInt32 per lane)
    fixed, the nodes behind ``last`` kept; only where ``active``.  Returns the values."""
    n = len(d)
    Float = type(d[0])
    one = dr.full(Float, 1.0, dr.width(d[0]))
    h = [d[k + 1] - d[k] for k in range(n - 1)]
    hs = [dr.select(x > 0, x, 1) for x in h]
    right = [dr.select(h[k] > 0, s1[k] / hs[k], 0) for k in range(n - 1)]   # int T phi_{k+1} on piece k
    lo = t[0]
    for k in range(1, n):                 # the last real node's value (lower clip)
        lo = dr.select(last == k, t[k], lo)
    # Thomas forward sweep: row k free when 0 < k < last and the row is not empty
    cp, dp = [], []
    for k in range(n):
        a = h[k - 1] * (1 / 6) if k else None
        c = h[k] * (1 / 6) if k < n - 1 else None
        diag = ((h[k - 1] if k else 0) + (h[k] if k < n - 1 else 0)) * (1 / 3)
        rhs = (right[k - 1] if k else 0) + (s0[k] - right[k] if k < n - 1 else 0)
        free = (last > k) & (diag > 0) if k else dr.zeros(type(active), dr.width(d[0]))
        if a is not None:
            den = diag - a * cp[k - 1]
            rhs = rhs - a * dp[k - 1]
        else:
            den = diag
        den = dr.select(free, den, 1)
        cp.append(dr.select(free, c / den, 0) if c is not None else 0)
        dp.append(dr.select(free, rhs / den, t[k]))
    x = [None] * n
    x[n - 1] = dp[n - 1]
    for k in range(n - 2, -1, -1):
        x[k] = dp[k] - cp[k] * x[k + 1]
    x = [dr.minimum(dr.maximum(v, lo), one) for v in x]
    fwd, bwd = list(x), list(x)
    for k in range(1, n):
        fwd[k] = dr.minimum(fwd[k - 1], x[k])
    for k in range(n - 2, -1, -1):
        bwd[k] = dr.maximum(bwd[k + 1], x[k])
    return [dr.select(active & (last > k) & (k > 0), (fwd[k] + bwd[k]) * 0.5, t[k]) for k in range(n)]
