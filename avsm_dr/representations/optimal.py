"""Offline optimum: the best N-node curve whose nodes are a subset of the exact curve's
points ("best breakpoint subset"), by dynamic programming.

The candidate nodes are the texel's exact-curve points (:mod:`._curve`: segment ends
with the exact curve's values, two points at a step); the first and the last point are
always kept.  Between chosen points ``i < j`` the curve is the chord of the lookup's
interpolation (``interpolation='linear'``: AVSM's eq. 2; ``'exp'``: ``T_i (T_j /
T_i)^w``, linear where a value is 0), and its cost ``C(i, j)`` on ``[z_i, z_j]``:

* ``norm='l2'``: ``int (T - chord)^2 dz``.  Linear chords: O(1) per pair from prefix
  sums of ``int T``, ``int z T`` and ``int T^2`` (each interval between points is one
  exponential, integrated in closed form).  Exponential chords: ``int T^2`` from the
  prefix sums, ``int chord^2`` in closed form and ``int T chord`` as a sum of closed-form
  integrals over the intervals between ``i`` and ``j`` (O(K) per pair).
* ``norm='linf'``: ``max |T - chord|`` over the continuous curve: at every point between
  ``i`` and ``j`` and at the one interior extremum per interval (``T - chord`` is a
  difference of an exponential and a line or an exponential: one critical point, in
  closed form).  O(K) per pair.

DP over "at most m intervals": ``D_m(j) = min(D_{m-1}(j), min_{i<j} D_{m-1}(i) (+|max)
C(i, j))``, m = 1..N-1, O(N K^2) per texel; the answer is ``D_{N-1}(K-1)``, backtracked.
This is exact for nodes carrying the exact curve's values.  With ``norm='l2'`` and
linear interpolation the chosen nodes' values are then refitted by least squares (the
normal equations of the hat functions: tridiagonal, solved by the Thomas algorithm) with
the first and last value pinned (T = 1 in front, the total optical depth behind), kept
only where that lowers the texel's L2 error (values are clipped to [0, 1]); the result
is the best subset for interpolating nodes, refitted - not the joint optimum over
subsets and values, and not the optimum over free node depths (AVSM's off-curve nodes
can beat it on some texels).  Other settings keep the exact values.

An offline reference: host NumPy in float64 (depths normalised to [0, 1] per texel),
vectorised over texels of similar point count.  Work grows as ``N K^2`` per texel
(``K^3 / 3`` more pair evaluations for the O(K) costs); builds above :data:`MAX_WORK` or with a texel
above :data:`MAX_POINTS` points raise ValueError before computing.  ``objective``
holds each texel's cost of the stored curve: RMS over ``[first, last point]`` (l2) or
the max error (linf).
"""
from __future__ import annotations

import numpy as np

from . import _curve
from .avsm import INTERPOLATIONS, NodeList
from .registry import register
from .schema import Param, Schema

NORMS = ("l2", "linf")
#: Most points a texel may have (a (K, K) float64 cost block and a few temporaries of that
#: size per texel: 32 MiB each at 2048).
MAX_POINTS = 2048
#: Most work units per build: sum over texels of N K^2 (+ 3 K^3 for O(K) pair costs).
#: Measured ~1e7 units/s for both terms (three_columns at 128^2, 2 busy CPU cores): ~3 minutes.
MAX_WORK = 2e9


# ----------------------------------------------------------------------------
# Closed-form integrals of one exponential piece T(y) = v exp(-s y), y in [0, h]
# ----------------------------------------------------------------------------
def phi1(z):
    """(1 - e^-z) / z, 1 at z = 0 (``int_0^1 e^{-z t} dt``)."""
    z = np.asarray(z, np.float64)
    safe = np.where(z == 0, 1.0, z)
    return np.where(np.abs(z) < 1e-12, 1.0 - z / 2, -np.expm1(-safe) / safe)


def phi2(z):
    """(1 - (1 + z) e^-z) / z^2 (``int_0^1 t e^{-z t} dt``), series below 1e-2."""
    z = np.asarray(z, np.float64)
    small = np.abs(z) < 1e-2
    safe = np.where(small, 1.0, z)
    direct = (-np.expm1(-safe) - safe * np.exp(-safe)) / (safe * safe)
    series = 0.5 - z / 3 + z * z / 8 - z ** 3 / 30 + z ** 4 / 144
    return np.where(small, series, direct)


def prefix_integrals(x, v, s):
    """Prefix sums over a (B, K) block of points: ``P0 = int T``, ``P1 = int x T``,
    ``P2 = int T^2`` from the first point to each point (the piece after point k is
    ``v_k exp(-s_k (x - x_k))`` up to ``x_{k+1}``)."""
    h = np.diff(x, axis=1)
    vk, sk, xk = v[:, :-1], s[:, :-1], x[:, :-1]
    i0 = vk * h * phi1(sk * h)
    i1 = xk * i0 + vk * h * h * phi2(sk * h)
    i2 = vk * vk * h * phi1(2 * sk * h)
    z = np.zeros((x.shape[0], 1))
    return (np.concatenate([z, np.cumsum(i0, 1)], 1), np.concatenate([z, np.cumsum(i1, 1)], 1),
            np.concatenate([z, np.cumsum(i2, 1)], 1))


def linear_chord_l2(a0, a1, q, xa, xb, va, vb):
    """``int (T - L)^2`` over ``[xa, xb]`` for the line L from (xa, va) to (xb, vb), from
    ``a0 = int T``, ``a1 = int x T``, ``q = int T^2`` over that interval.  Broadcasts."""
    d = xb - xa
    b = (vb - va) / np.where(d > 0, d, 1.0)
    tl = va * a0 + b * (a1 - xa * a0)
    ll = d * (va * va + va * vb + vb * vb) / 3
    return np.where(d > 0, np.maximum(q - 2 * tl + ll, 0.0), 0.0)


# ----------------------------------------------------------------------------
# Pair costs C(i, j) for a (B, K) block
# ----------------------------------------------------------------------------
def pair_costs(x, v, s, count, norm: str, interp: str):
    """(B, K, K) costs of the chord from point i to point j (i < j < count; inf else)."""
    B, K = x.shape
    ii = np.arange(K)[None, :, None]
    jj = np.arange(K)[None, None, :]
    valid = (ii < jj) & (jj < count[:, None, None])
    if norm == "l2" and interp == "linear":
        P0, P1, P2 = prefix_integrals(x, v, s)
        c = linear_chord_l2(P0[:, None, :] - P0[:, :, None], P1[:, None, :] - P1[:, :, None],
                            P2[:, None, :] - P2[:, :, None], x[:, :, None], x[:, None, :],
                            v[:, :, None], v[:, None, :])
        return np.where(valid, c, np.inf)
    C = np.full((B, K, K), np.inf)
    P = prefix_integrals(x, v, s) if norm == "l2" else None
    h = np.diff(x, axis=1, append=x[:, -1:])          # piece after point k (0 after the last)
    for i in range(K - 1):
        # rows: j in (i, K); columns: k in [i, K) (points / pieces between i and j)
        xj, vj = x[:, i + 1:, None], v[:, i + 1:, None]
        xi, vi = x[:, i, None, None], v[:, i, None, None]
        xk, vk, sk, hk = x[:, None, i:], v[:, None, i:], s[:, None, i:], h[:, None, i:]
        kidx = np.arange(i, K)[None, None, :]
        jidx = np.arange(i + 1, K)[None, :, None]
        d = xj - xi
        dd = np.where(d > 0, d, 1.0)
        use_exp = (interp == "exp") & (vi > 0) & (vj > 0)
        rate = np.where(use_exp, np.log(np.where(use_exp, vi, 1.0) / np.where(use_exp, vj, 1.0)) / dd, 0.0)
        slope = (vj - vi) / dd                              # linear chord's slope
        # chord value at point k and at the start of piece k
        ck = np.where(use_exp, vi * np.exp(-rate * (xk - xi)), vi + slope * (xk - xi))
        if norm == "l2":
            inside = (kidx < jidx)                          # pieces k in [i, j)
            # int T chord over piece k: exponential chord in closed form; linear via prefix sums
            te = np.where(inside, vk * ck * hk * phi1((sk + rate) * hk), 0.0).sum(axis=2)
            q = (P[2][:, i + 1:] - P[2][:, i, None])
            ee = vi[:, :, 0] ** 2 * d[:, :, 0] * phi1(2 * rate[:, :, 0] * d[:, :, 0])
            c_exp = np.maximum(q - 2 * te + ee, 0.0)
            c_lin = linear_chord_l2(P[0][:, i + 1:] - P[0][:, i, None], P[1][:, i + 1:] - P[1][:, i, None],
                                    q, x[:, i, None], x[:, i + 1:], v[:, i, None], v[:, i + 1:])
            c = np.where(use_exp[:, :, 0], c_exp, c_lin)
            c = np.where(d[:, :, 0] > 0, c, 0.0)
        else:
            at_pts = np.where(kidx <= jidx, np.abs(vk - ck), 0.0).max(axis=2)
            # interior extremum of T - chord on piece k (k < j), y* in (0, h_k)
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                # linear chord: -s v e^{-s y} = slope -> y* = ln(-s v / slope) / s
                arg_l = np.where((sk > 0) & (slope < 0), -sk * vk / np.where(slope < 0, slope, -1.0), 0.0)
                y_l = np.where(arg_l > 1, np.log(np.where(arg_l > 1, arg_l, 1.0)) / np.where(sk > 0, sk, 1.0), -1.0)
                # exponential chord: s v e^{-s y} = r c e^{-r y} -> y* = ln(s v / (r c)) / (s - r)
                den = sk - rate
                arg_e = np.where((sk > 0) & (rate > 0) & (ck > 0) & (vk > 0) & (den != 0),
                                 sk * vk / np.where(rate * ck > 0, rate * ck, 1.0), 1.0)
                y_e = np.log(np.where(arg_e > 0, arg_e, 1.0)) / np.where(den != 0, den, 1.0)
                y = np.where(use_exp, y_e, y_l)
                ok = (kidx < jidx) & (y > 0) & (y < hk) & np.isfinite(y)
                yy = np.where(ok, y, 0.0)
                chord_y = np.where(use_exp, ck * np.exp(-rate * yy), ck + slope * yy)
                dev = np.where(ok, np.abs(vk * np.exp(-sk * yy) - chord_y), 0.0).max(axis=2)
            c = np.where(d[:, :, 0] > 0, np.maximum(at_pts, dev), 0.0)   # two points at one depth: a step
        m = valid[:, i, i + 1:]
        C[:, i, i + 1:] = np.where(m, c, np.inf)
    return C


# ----------------------------------------------------------------------------
# DP and refit
# ----------------------------------------------------------------------------
def best_subset(C, count, N: int, norm: str):
    """(B, K) bool mask of the chosen points (at most N, first and last included) and
    the (B,) optimal cost, from the (B, K, K) pair costs ``C``."""
    B, K = C.shape[:2]
    rows = np.arange(B)
    dp = C[:, 0, :].copy()
    dp[:, 0] = 0.0
    parents = []
    for _ in range(2, N):
        cand = (np.maximum(dp[:, :, None], C) if norm == "linf" else dp[:, :, None] + C)
        arg = np.argmin(cand, axis=1)
        best = cand.min(axis=1)
        better = best < dp
        parents.append(np.where(better, arg, -1))
        dp = np.where(better, best, dp)
    last = count - 1
    cost = dp[rows, last]
    chosen = np.zeros((B, K), bool)
    chosen[rows, 0] = True
    chosen[rows, last] = True
    j = last.copy()
    for par in reversed(parents):
        p = par[rows, j]
        move = p >= 0
        chosen[rows[move], p[move]] = True
        j = np.where(move, p, j)
    return chosen, cost


def refit_l2(x, v, s, chosen, count):
    """Least-squares values of the chosen nodes (linear interpolation, first and last value
    pinned), clipped to [0, 1], where they lower the L2 error; returns (values (B, M), L2
    error (B,)) over the chosen nodes in order (M = max chosen per row, padded)."""
    B, K = x.shape
    P = prefix_integrals(x, v, s)
    n = chosen.sum(axis=1)
    M = int(n.max())
    order = np.argsort(~chosen, axis=1, kind="stable")[:, :M]         # chosen indices first, in order
    col = np.arange(M)[None, :]
    real = col < n[:, None]
    idx = np.where(real, order, order[np.arange(B), n - 1][:, None])   # pad: repeat the last node
    X = np.take_along_axis(x, idx, 1)
    V0 = np.take_along_axis(v, idx, 1)
    rows = np.arange(B)[:, None]
    P0, P1 = P[0], P[1]
    h = np.diff(X, axis=1)                                             # (B, M-1)
    a0 = P0[rows, idx[:, 1:]] - P0[rows, idx[:, :-1]]
    a1 = P1[rows, idx[:, 1:]] - P1[rows, idx[:, :-1]]
    hs = np.where(h > 0, h, 1.0)
    rise = np.where(h > 0, (a1 - X[:, :-1] * a0) / hs, 0.0)    # int T (x - X_m) / h_m on interval m
    fall = np.where(h > 0, (X[:, 1:] * a0 - a1) / hs, 0.0)     # int T (X_{m+1} - x) / h_m
    # normal equations for interior nodes 1..n-2: sub a, diag b, super c, rhs d
    a = np.zeros((B, M))
    b = np.ones((B, M))
    c = np.zeros((B, M))
    d = V0.copy()
    for m in range(1, M - 1):
        inner = m < n - 1
        hl, hr = h[:, m - 1], h[:, m]
        diag = (hl + hr) / 3
        ok = inner & (diag > 0)
        b[:, m] = np.where(ok, diag, 1.0)
        a[:, m] = np.where(ok, hl / 6, 0.0)
        c[:, m] = np.where(ok, hr / 6, 0.0)
        d[:, m] = np.where(ok, rise[:, m - 1] + fall[:, m], V0[:, m])
    # pinned ends: move the first and last values to the right-hand side
    d[:, 1] -= np.where(n > 2, a[:, 1] * V0[:, 0], 0.0)
    a[:, 1] = np.where(n > 2, 0.0, a[:, 1])
    last = n - 2
    has = last >= 1
    lr = np.where(has, last, 1)
    cl = c[np.arange(B), lr]
    d[np.arange(B), lr] -= np.where(has, cl * V0[np.arange(B), n - 1], 0.0)
    c[np.arange(B), lr] = np.where(has, 0.0, cl)
    # rows outside 1..n-2 are identity (their values stay V0)
    for m in range(M):
        outside = (m == 0) | (m >= n - 1)
        a[:, m] = np.where(outside, 0.0, a[:, m])
        c[:, m] = np.where(outside, 0.0, c[:, m])
        b[:, m] = np.where(outside, 1.0, b[:, m])
        d[:, m] = np.where(outside, V0[:, m], d[:, m])
    # Thomas algorithm (diagonally dominant: (h_l + h_r) / 3 > h_l / 6 + h_r / 6)
    cp = np.zeros((B, M))
    dp = np.zeros((B, M))
    cp[:, 0] = c[:, 0] / b[:, 0]
    dp[:, 0] = d[:, 0] / b[:, 0]
    for m in range(1, M):
        den = b[:, m] - a[:, m] * cp[:, m - 1]
        cp[:, m] = c[:, m] / den
        dp[:, m] = (d[:, m] - a[:, m] * dp[:, m - 1]) / den
    V = np.zeros((B, M))
    V[:, M - 1] = dp[:, M - 1]
    for m in range(M - 2, -1, -1):
        V[:, m] = dp[:, m] - cp[:, m] * V[:, m + 1]
    V = np.clip(V, 0.0, 1.0)

    q = P[2][rows, idx[:, 1:]] - P[2][rows, idx[:, :-1]]

    def l2(vals):
        e = linear_chord_l2(a0, a1, q, X[:, :-1], X[:, 1:], vals[:, :-1], vals[:, 1:])
        return np.where(real[:, 1:], e, 0.0).sum(axis=1)

    e_fit, e_int = l2(V), l2(V0)
    use = e_fit < e_int
    return np.where(use[:, None], V, V0), np.where(use, e_fit, e_int), idx, real


def work_units(count: np.ndarray, N: int, norm: str, interp: str) -> float:
    """Work of a build: sum over texels of N K^2 (DP), + 3 K^3 where pair costs are O(K)
    (weights from timings: the K^3 / 3 pair loop costs ~9x a DP step per element)."""
    k = count.astype(np.float64)
    cubic = not (norm == "l2" and interp == "linear")
    return float(np.sum(N * k * k + (3 * k ** 3 if cubic else 0.0)))


@register("optimal")
class OptimalSubset(NodeList):
    """Best N-node breakpoint subset of the exact curve (DP, offline; see the module
    docstring).

    Parameters: nodes N in [2, 64]; norm 'l2' | 'linf'; interpolation 'linear' | 'exp'.
    ``nbytes_per_texel`` = 2 N itemsize (as AVSM).  Attributes: ``depths``/``values``
    (N Dr.Jit arrays of length T), ``node_counts`` (T,), ``objective`` (T,) float64: the
    stored curve's RMS error over ``[first, last point]`` (l2; for 'l2'+'linear' after the
    refit) or its max error (linf), 0 for empty texels.
    Raises ValueError (naming ``segments``) above :data:`MAX_POINTS` points per texel or
    :data:`MAX_WORK` work units.
    """

    schema = Schema(
        params=(
            Param("nodes", "int", 8, "N nodes (depth, transmittance) per texel", min=2, max=64),
            Param("norm", "choice", "l2", "objective per texel, uniform in depth: 'l2' (squared error "
                  "integral) or 'linf' (max error over the continuous curve)", choices=NORMS),
            Param("interpolation", "choice", "linear", "between nodes: 'linear' or 'exp' (as AVSM)",
                  choices=INTERPOLATIONS),
            # Private ablation switch (the avsm_gap experiment): the subset's exact values
            Param("_refit", "bool", True, "private: refit the values for 'l2' + 'linear' (False: keep "
                  "the best subset's exact values)"),
        ),
        size="nodes", sweep=(2, 4, 8, 16), quick_sweep=(2, 4, 8),
        examples=({"nodes": 4}, {"nodes": 4, "norm": "linf"}, {"nodes": 4, "interpolation": "exp"},
                  {"nodes": 3, "norm": "linf", "interpolation": "exp"}),
        headline={"nodes": 8},
        summary="offline best N-node subset of the exact curve's breakpoints (DP; L2 values refitted)",
        paper="-", offline=True,
    )

    def __init__(self, segments, **params):
        super().__init__(segments, **params)
        P = self.params
        self.N, self.norm, self.interp = P["nodes"], P["norm"], P["interpolation"]
        pts = _curve.cached(segments, "curve_points", lambda: _curve.curve_points(segments))
        off = pts["off"]
        counts = np.diff(off)
        if counts.size and counts.max() > MAX_POINTS:
            t = int(np.argmax(counts))
            raise ValueError(f"segments: texel {t} has {int(counts[t])} exact-curve points, above the "
                             f"{MAX_POINTS} that 'optimal' accepts (avsm_dr.representations.optimal.MAX_POINTS)")
        work = work_units(counts, self.N, self.norm, self.interp)
        if work > MAX_WORK:
            raise ValueError(f"segments: 'optimal' (nodes={self.N}, norm={self.norm!r}, interpolation="
                             f"{self.interp!r}) needs {work:.3g} work units (sum over texels of N K^2"
                             f"{'' if self.norm == 'l2' and self.interp == 'linear' else ' + 3 K^3'}), above "
                             f"MAX_WORK = {MAX_WORK:.3g}; use fewer texels, a coarser capture or 'greedy'")
        self._build(pts)

    @property
    def monotone(self) -> bool:
        """False for 'l2' with linear interpolation: least-squares values can overshoot
        (the L2 projection onto hat functions of a step rises above it); the exact values
        kept otherwise are monotone."""
        return not self._refit

    @property
    def differentiable(self) -> bool:
        """Not for 'l2' with linear interpolation (values from a host least-squares
        solve); otherwise the exact curve's gradients at the fixed node depths."""
        return not self._refit

    @property
    def _refit(self) -> bool:
        P = self.params
        return P["norm"] == "l2" and P["interpolation"] == "linear" and P["_refit"]

    def _build(self, pts):
        seg = self.segments
        T, N = seg.n_texels, self.N
        off = pts["off"]
        self.objective = np.zeros(T)
        sel_tex, sel_pt, slot, vals = [], [], [], []
        for tex, kmax in _curve.buckets(off, power=2, max_elems=1 << 21):
            count, (z, v, s) = _curve.padded(off, tex, kmax, pts["z"], pts["v"], pts["slope"])
            lo = z[:, 0]
            span = z[np.arange(tex.size), count - 1] - lo
            span = np.where(span > 0, span, 1.0)
            x = (z - lo[:, None]) / span[:, None]              # depths normalised to [0, 1]
            sn = s * span[:, None]
            if kmax == 1:
                chosen = np.ones((tex.size, 1), bool)
                cost = np.zeros(tex.size)
            else:
                C = pair_costs(x, v, sn, count, self.norm, self.interp)
                chosen, cost = best_subset(C, count, N, self.norm)
            if self._refit and kmax > 1:
                V, cost, idx, real = refit_l2(x, v, sn, chosen, count)
            else:
                n = chosen.sum(axis=1)
                M = int(n.max())
                order = np.argsort(~chosen, axis=1, kind="stable")[:, :M]
                real = np.arange(M)[None, :] < n[:, None]
                idx = order
                V = np.take_along_axis(v, idx, 1)
            self.objective[tex] = np.sqrt(cost) if self.norm == "l2" else cost
            r, m = np.nonzero(real)
            sel_tex.append(tex[r])
            sel_pt.append(off[tex[r]] + idx[r, m])
            slot.append(m)
            vals.append(V[r, m])
        def cat(a, dt):
            return np.concatenate(a) if a else np.zeros(0, dt)
        sel_tex, sel_pt, slot = cat(sel_tex, np.int64), cat(sel_pt, np.int64), cat(slot, np.int64)
        self.node_counts = np.bincount(sel_tex, minlength=T)
        src = _curve.fill_slots(sel_tex, sel_pt, slot, N, T)
        if self._refit:
            value = np.ones((N, T))
            value[slot, sel_tex] = cat(vals, np.float64)
            nz = np.flatnonzero(self.node_counts)
            lastv = value[self.node_counts[nz] - 1, nz]
            for k in range(N):
                fill = self.node_counts[nz] <= k
                value[k, nz[fill]] = lastv[fill]
            self.depths, self.values = _curve.store_nodes(seg, src, pts, values=value)
        else:
            self.depths, self.values = _curve.store_nodes(seg, src, pts)
