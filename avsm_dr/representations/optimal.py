"""Offline optimum: the best N-node curve whose nodes are a subset of the exact curve's
points ("best breakpoint subset"), by dynamic programming.

The candidates are the texel's exact-curve points (:mod:`._curve`; the last one is always
kept).  Starting at point j costs the error of ``T = 1`` on ``[z_0, z_j)`` (:func:`start_costs`);
between chosen points ``i < j`` the curve is the lookup's chord (``'linear'``: AVSM's eq. 2;
``'exp'``: ``T_i (T_j / T_i)^w``, linear where a value is 0), with cost ``C(i, j)``
(:func:`pair_costs`): ``norm='l2'`` ``int (T - chord)^2 dz``, ``norm='linf'`` ``max |T - chord|``
over the continuous curve.  DP over "at most n nodes": ``D_1(j) = S(j)``,
``D_n(j) = min(D_{n-1}(j), min_{i<j} D_{n-1}(i) (+|max) C(i, j))``, O(N K^2) per texel; the
answer ``D_N(K-1)``, backtracked.  With ``norm='l2'`` and linear interpolation the chosen
nodes' values are then refitted by least squares (:func:`refit_l2`) where that lowers the
texel's L2 error: the best subset refitted, not the joint optimum over subsets and values.

Host NumPy in float64 (depths normalised to [0, 1] per texel), vectorised over texels of
similar point count.  Builds above :data:`MAX_WORK` work units or with a texel above
:data:`MAX_POINTS` points raise :class:`~avsm_dr.validation.WorkLimitError` (a ValueError)
before computing.  ``objective``: each texel's
cost of the stored curve, RMS over ``[first, last point]`` (l2) or the max error (linf).
"""
from __future__ import annotations

import numpy as np

from ..validation import WorkLimitError
from . import _curve
from ._curve import exp_stored_values
from .avsm import INTERPOLATION, NODES, NodeList
from .registry import register
from .schema import Param, Schema

NORMS = ("l2", "linf")
#: Most points a texel may have (a (K, K) float64 cost block per texel: 32 MiB at 2048).
MAX_POINTS = 2048
#: Most work units per build: sum over texels of N K^2 (+ 3 K^3 for O(K) pair costs).
MAX_WORK = 2e9


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


def piece_exponents(x, tau):
    """(B, K) optical depth across the piece after each point, ``tau_{k+1} - tau_k`` (0 for a
    zero-width piece: a step, padding, after the last point).  The pieces' ``s_k h_k``
    without forming the slope in normalised units, which can overflow (thin opaque
    segments in a wide texel)."""
    h = np.diff(x, axis=1)
    a = np.where(h > 0, np.maximum(np.diff(tau, axis=1), 0.0), 0.0)
    return np.concatenate([a, np.zeros((x.shape[0], 1))], 1)


def prefix_integrals(x, v, a):
    """Prefix sums over a (B, K) block of points: ``P0 = int T``, ``P1 = int x T``,
    ``P2 = int T^2`` from the first point to each point (the piece after point k is
    ``v_k exp(-a_k (x - x_k) / h_k)`` up to ``x_{k+1}``, ``a`` from :func:`piece_exponents`)."""
    h = np.diff(x, axis=1)
    vk, ak, xk = v[:, :-1], a[:, :-1], x[:, :-1]
    i0 = vk * h * phi1(ak)
    i1 = xk * i0 + vk * h * h * phi2(ak)
    i2 = vk * vk * h * phi1(2 * ak)
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


def pair_costs(x, tau, a, count, norm: str, interp: str, store=np.float64):
    """(B, K, K) costs of the chord from point i to point j (i < j < count; inf else), from
    the points' normalised depths ``x``, optical depths ``tau`` and piece exponents ``a``;
    ``store``: the dtype the node values are stored in.  l2: closed forms per interval from
    :func:`prefix_integrals`; linf: the points and the one interior extremum per piece.
    The chord is the lookup's (:func:`.avsm.interpolate`) on the stored values, formed from
    ``tau``, logs of normal numbers and ratios in [0, 1]: every valid cost is finite
    (RuntimeError otherwise)."""
    B, K = x.shape
    v = np.exp(-tau)
    ii = np.arange(K)[None, :, None]
    jj = np.arange(K)[None, None, :]
    valid = (ii < jj) & (jj < count[:, None, None])
    if norm == "l2" and interp == "linear":
        P0, P1, P2 = prefix_integrals(x, v, a)
        C = linear_chord_l2(P0[:, None, :] - P0[:, :, None], P1[:, None, :] - P1[:, :, None],
                            P2[:, None, :] - P2[:, :, None], x[:, :, None], x[:, None, :],
                            v[:, :, None], v[:, None, :])
        C = np.where(valid, C, np.inf)
        _check_finite(C, valid)
        return C
    C = np.full((B, K, K), np.inf)
    P = prefix_integrals(x, v, a) if norm == "l2" else None
    h = np.diff(x, axis=1, append=x[:, -1:])          # piece after point k (0 after the last)
    # the chord's end values as stored; exp: exponential between two positive ones
    vn = exp_stored_values(v, store) if interp == "exp" else v
    expo = vn > 0 if interp == "exp" else np.zeros((B, K), bool)
    lv = np.log(np.where(expo, vn, 1.0))               # >= ln(tiny): finite
    for i in range(K - 1):
        # rows: j in (i, K); columns: k in [i, K) (points / pieces between i and j)
        xj, vj, lj, ej = (m[:, i + 1:, None] for m in (x, vn, lv, expo))
        xi, vi, li, ei = (m[:, i, None, None] for m in (x, vn, lv, expo))
        xk, vk, tk, ak, hk = (m[:, None, i:] for m in (x, v, tau, a, h))
        kidx = np.arange(i, K)[None, None, :]
        jidx = np.arange(i + 1, K)[None, :, None]
        d = xj - xi
        dd = np.where(d > 0, d, 1.0)
        f = np.clip((xk - xi) / dd, 0.0, 1.0)          # where point k sits in the chord
        g = np.clip(hk / dd, 0.0, 1.0)                 # piece k's share of the chord
        use_exp = ei & ej
        drop = np.where(use_exp, li - lj, 0.0)         # log decrease over the chord (exp)
        lc = li - drop * f                             # log chord at point k (exp)
        R = drop * g                                   # its decrease over piece k (exp)
        rise = vj - vi                                 # change over the chord (linear)
        cl = vi + rise * f                             # linear chord at point k
        S = rise * g
        ck = np.where(use_exp, np.exp(lc), cl)
        inside = kidx < jidx                           # pieces k in [i, j)
        if norm == "l2":
            q = P[2][:, i + 1:] - P[2][:, i, None]
            c = linear_chord_l2(P[0][:, i + 1:] - P[0][:, i, None], P[1][:, i + 1:] - P[1][:, i, None],
                                q, x[:, i, None], x[:, i + 1:], vn[:, i, None], vn[:, i + 1:])
            if interp == "exp":
                # int T chord per piece, both exponentials: h_k e^{-tau_k + lc_k} phi1(a_k + R_k)
                te = np.where(inside, np.exp(lc - tk) * hk * phi1(ak + R), 0.0).sum(axis=2)
                ee = d[:, :, 0] * np.exp(2 * li[:, :, 0]) * phi1(2 * drop[:, :, 0])   # int chord^2
                c = np.where(use_exp[:, :, 0], np.maximum(q - 2 * te + ee, 0.0), c)
            c = np.where(d[:, :, 0] > 0, c, 0.0)
        else:
            at_pts = np.where(kidx <= jidx, np.abs(vk - ck), 0.0).max(axis=2)
            # the one critical point of T - chord on piece k, at t* of its width:
            # exp chord: a e^{-tau - a t} = R e^{lc - R t}; linear: a e^{-tau - a t} = -S
            la = np.log(np.where(ak > 0, ak, 1.0))
            ok_e = use_exp & (ak > 0) & (R > 0) & (ak != R)
            ok_l = ~use_exp & (ak > 0) & (S < 0)
            num = np.where(use_exp, la - tk - np.log(np.where(R > 0, R, 1.0)) - lc,
                           la - tk - np.log(np.where(S < 0, -S, 1.0)))
            den = np.where(ok_e, ak - R, np.where(ok_l, ak, 1.0))
            with np.errstate(over="ignore"):           # t* far outside (0, 1): dropped below
                t = num / den
            ok = inside & np.where(use_exp, ok_e, ok_l) & (t > 0) & (t < 1)
            t = np.where(ok, t, 0.0)
            chord_t = np.where(use_exp, np.exp(lc - R * t), cl + S * t)
            dev = np.where(ok, np.abs(np.exp(-tk - ak * t) - chord_t), 0.0).max(axis=2)
            c = np.where(d[:, :, 0] > 0, np.maximum(at_pts, dev), 0.0)   # two points at one depth: a step
        C[:, i, i + 1:] = np.where(valid[:, i, i + 1:], c, np.inf)
    _check_finite(C, valid)
    return C


def _check_finite(C, valid):
    """Every valid pair cost is finite (the DP would otherwise skip or pick it silently)."""
    bad = valid & ~np.isfinite(C)
    if bad.any():
        b, i, j = (int(u[0]) for u in np.nonzero(bad))
        raise RuntimeError(f"optimal: non-finite pair cost {C[b, i, j]} (row {b}, points {i} -> {j}); "
                           "a bug in avsm_dr.representations.optimal.pair_costs")


def start_costs(x, tau, a, count, norm: str):
    """(B, K) cost of starting the node list at point j: the lookup gives 1 in front of the
    first node, so ``[x_0, x_j)`` costs ``int (1 - T)^2`` (l2) or ``1 - T(x_j^-)`` (linf,
    T non-increasing); 0 at j = 0 and at the right point of a leading step (its left
    point, T = 1, is then no node's business); inf for padding."""
    B, K = x.shape
    if norm == "l2":
        P0, _, P2 = prefix_integrals(x, np.exp(-tau), a)
        S = np.maximum(x - x[:, :1] - 2 * P0 + P2, 0.0)
    else:
        step = np.zeros((B, K), bool)
        step[:, 1:] = x[:, 1:] == x[:, :-1]           # point j is the right side of a step
        left = np.where(step, np.roll(tau, 1, axis=1), tau)
        S = -np.expm1(-left)
    S[:, 0] = 0.0
    valid = np.arange(K)[None, :] < count[:, None]
    S = np.where(valid, S, np.inf)
    _check_finite(S, valid)
    return S


def best_subset(C, S, count, N: int, norm: str):
    """(B, K) bool mask of the chosen points (at most N, the last included) and the (B,)
    optimal cost: the module docstring's DP on ``C`` and ``S``; ties keep fewer nodes."""
    B, K = C.shape[:2]
    rows = np.arange(B)
    dp = S.copy()
    parents = []
    for _ in range(1, N):
        cand = (np.maximum(dp[:, :, None], C) if norm == "linf" else dp[:, :, None] + C)
        best = cand.min(axis=1)
        better = best < dp
        parents.append(np.where(better, np.argmin(cand, axis=1), -1))
        dp = np.where(better, best, dp)
    last = count - 1
    cost = dp[rows, last]
    chosen = np.zeros((B, K), bool)
    chosen[rows, last] = True
    j = last.copy()
    for par in reversed(parents):
        p = par[rows, j]
        move = p >= 0
        chosen[rows[move], p[move]] = True
        j = np.where(move, p, j)
    return chosen, cost


def chosen_order(chosen):
    """(order, real) of a (B, K) mask of chosen points: their indices first, in depth order,
    (B, M) with M the most chosen in a row, and which entries are chosen points."""
    n = chosen.sum(axis=1)
    M = int(n.max())
    return np.argsort(~chosen, axis=1, kind="stable")[:, :M], np.arange(M)[None, :] < n[:, None]


def refit_l2(x, v, a, chosen, count):
    """Least-squares values of the chosen nodes (linear interpolation, first and last value
    pinned), clipped to [0, 1], where they lower the L2 error; returns (values (B, M), L2
    error (B,)) over the chosen nodes in order (M = max chosen per row, padded)."""
    B, K = x.shape
    P = prefix_integrals(x, v, a)
    order, real = chosen_order(chosen)
    n, M = chosen.sum(axis=1), order.shape[1]
    idx = np.where(real, order, order[np.arange(B), n - 1][:, None])   # pad: repeat the last node
    X = np.take_along_axis(x, idx, 1)
    V0 = np.take_along_axis(v, idx, 1)
    if M == 1:                                                         # one node each: no interval
        return V0, np.zeros(B), idx, real
    rows = np.arange(B)[:, None]
    P0, P1 = P[0], P[1]
    h = np.diff(X, axis=1)                                             # (B, M-1)
    a0 = P0[rows, idx[:, 1:]] - P0[rows, idx[:, :-1]]
    a1 = P1[rows, idx[:, 1:]] - P1[rows, idx[:, :-1]]
    hs = np.where(h > 0, h, 1.0)
    rise = np.where(h > 0, (a1 - X[:, :-1] * a0) / hs, 0.0)    # int T (x - X_m) / h_m on interval m
    fall = np.where(h > 0, (X[:, 1:] * a0 - a1) / hs, 0.0)     # int T (X_{m+1} - x) / h_m
    # normal equations for interior nodes 1..n-2: sub a, diag b, super c, rhs d (other rows: identity)
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
    """Work of a build: sum over texels of N K^2 (DP), + 3 K^3 where pair costs are O(K)."""
    k = count.astype(np.float64)
    cubic = not (norm == "l2" and interp == "linear")
    return float(np.sum(N * k * k + (3 * k ** 3 if cubic else 0.0)))


@register("optimal")
class OptimalSubset(NodeList):
    """Best N-node breakpoint subset of the exact curve (DP, offline; module docstring), a
    :class:`~.avsm.NodeList`; ``node_counts`` (T,), ``objective`` (T,) float64 (0 for empty
    texels).  ValueError (naming ``segments``) above :data:`MAX_POINTS` points per texel or
    :data:`MAX_WORK` work units.
    """

    schema = Schema(
        params=(
            NODES,
            Param("norm", "choice", "l2", "objective per texel, uniform in depth: 'l2' (squared error "
                  "integral) or 'linf' (max error over the continuous curve)", choices=NORMS),
            INTERPOLATION,
            # Private ablation switch (the avsm_gap experiment): the subset's exact values
            Param("_refit", "bool", True, "private: refit the values for 'l2' + 'linear' (False: keep "
                  "the best subset's exact values)"),
        ),
        size="nodes", sweep=(2, 4, 8, 16), quick_sweep=(2, 4, 8),
        examples=({"nodes": 4}, {"nodes": 4, "norm": "linf"}, {"nodes": 4, "interpolation": "exp"},
                  {"nodes": 3, "norm": "linf", "interpolation": "exp"}),
        headline={"nodes": 8},
        summary="offline best N-node subset of the exact curve's breakpoints (DP; L2 values refitted)",
        paper="-", offline=True)

    def _resolve(self):
        super()._resolve()
        P = self.params
        self.norm, self.interp = P["norm"], P["interpolation"]
        # the least-squares refit ('l2', linear) can overshoot a step and is a host solve (no gradients)
        self._refit = self.norm == "l2" and self.interp == "linear" and P["_refit"]
        self.monotone = self.differentiable = not self._refit
        counts = np.diff(_curve.points(self.segments)["off"])
        if counts.size and counts.max() > MAX_POINTS:
            t = int(np.argmax(counts))
            raise WorkLimitError(f"segments: texel {t} has {int(counts[t])} exact-curve points (segment ends, two "
                             f"at a step), above the {MAX_POINTS} per texel that 'optimal' accepts "
                             f"(avsm_dr.representations.optimal.MAX_POINTS: a K x K float64 cost block per "
                             f"texel); {int(np.sum(counts > MAX_POINTS))} texels exceed it; 'greedy' has no "
                             "such limit", int(counts.max()), MAX_POINTS)
        work = work_units(counts, self.N, self.norm, self.interp)
        if work > MAX_WORK:
            raise WorkLimitError(self._work_message(counts, work), work, MAX_WORK)

    def _work_message(self, counts, work: float) -> str:
        """Why a build is refused above :data:`MAX_WORK`, and what fits."""
        k2 = float(np.sum(counts.astype(np.float64) ** 2))
        cubic = work - self.N * k2
        fits = []
        n_fit = int(min(self.N - 1, (MAX_WORK - cubic) // k2)) if k2 > 0 else 0
        if n_fit >= 2:
            fits.append(f"nodes={n_fit}")
        fits.append(f"about {max(MAX_WORK / work, 0.0):.1%} of the texels (a tile) at nodes={self.N}")
        if cubic > 0 and work_units(counts, self.N, "l2", "linear") <= MAX_WORK:
            fits.append("norm='l2' with interpolation='linear' (no K^3 term)")
        return (f"segments: 'optimal' (nodes={self.N}, norm={self.norm!r}, interpolation={self.interp!r}) "
                f"needs {work:.3g} work units (sum over texels of N K^2{' + 3 K^3' if cubic > 0 else ''}, "
                f"K = exact-curve points per texel, largest {int(counts.max())}), above MAX_WORK = "
                f"{MAX_WORK:.3g} (avsm_dr.representations.optimal.MAX_WORK); fits: "
                f"{'; '.join(fits)}; or use 'greedy' (O(K log K), no limit)")

    def _build(self):
        seg, pts = self.segments, _curve.points(self.segments)
        T, N = seg.n_texels, self.N
        off = pts["off"]
        self.objective = np.zeros(T)
        sel_tex, sel_pt, slot, vals = [], [], [], []
        for tex, kmax in _curve.buckets(off, power=2, max_elems=1 << 21):
            count, (z, v, tau) = _curve.padded(off, tex, kmax, pts["z"], pts["v"], pts["tau"])
            lo = z[:, 0]
            span = z[np.arange(tex.size), count - 1] - lo
            span = np.where(span > 0, span, 1.0)
            x = (z - lo[:, None]) / span[:, None]              # depths normalised to [0, 1]
            a = piece_exponents(x, tau)
            if kmax == 1:
                chosen = np.ones((tex.size, 1), bool)
                cost = np.zeros(tex.size)
            else:
                C = pair_costs(x, tau, a, count, self.norm, self.interp, store=seg.dtype)
                S = start_costs(x, tau, a, count, self.norm)
                chosen, cost = best_subset(C, S, count, N, self.norm)
            if self._refit and kmax > 1:
                V, cost, idx, real = refit_l2(x, v, a, chosen, count)
                cost = cost + S[np.arange(tex.size), idx[:, 0]]     # the refit keeps the first node
            else:
                idx, real = chosen_order(chosen)
                V = np.take_along_axis(v, idx, 1)
            self.objective[tex] = np.sqrt(cost) if self.norm == "l2" else cost
            r, m = np.nonzero(real)
            sel_tex.append(tex[r])
            sel_pt.append(off[tex[r]] + idx[r, m])
            slot.append(m)
            vals.append(V[r, m])
        sel_tex, sel_pt, slot, vals = (np.concatenate(a) if a else np.zeros(0, np.int64)
                                       for a in (sel_tex, sel_pt, slot, vals))
        self.node_counts = np.bincount(sel_tex, minlength=T)
        src = _curve.fill_slots(sel_tex, sel_pt, slot, N, T)
        value = _curve.fill_slots(sel_tex, vals.astype(np.float64), slot, N, T, fill=1.0) if self._refit else None
        self.depths, self.values = _curve.store_nodes(seg, src, pts, values=value, exp=self.interp == "exp")
