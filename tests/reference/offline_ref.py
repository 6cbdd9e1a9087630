"""Offline node selection on one texel's exact curve in plain float64 Python/NumPy:
curve points by direct summation, Visvalingam-Whyatt with AVSM's metric, brute force
over breakpoint subsets, L2 costs by Gauss-Legendre quadrature on every smooth piece,
L-infinity by dense sampling, least-squares refit by a dense weighted solve.
Also accurate measures for sharp exponentials (an opaque segment's piece decays by up to
e^-1e4): :func:`l2_error_graded` (composite Gauss-Legendre of the pointwise squared
difference on a mesh graded towards each piece's left end) and :func:`linf_error_golden`
(golden section on each smooth piece, where node curve - exact has one extremum).
Independent of avsm_dr (checks greedy.py and optimal.py)."""
from __future__ import annotations

import itertools

import numpy as np

GL_X, GL_W = np.polynomial.legendre.leggauss(24)


def optical_depth(z0, z1, tau, d, left=False):
    """tau(d) (right-continuous), or its left limit tau(d^-) with ``left``."""
    total = 0.0
    for a, b, t in zip(z0, z1, tau):
        if b > a:
            total += t * min(max((d - a) / (b - a), 0.0), 1.0)
        elif (d > a) if left else (d >= a):
            total += t
    return total


def points(z0, z1, tau):
    """[(depth, T, left)] of the exact curve: every unique segment end, the value just
    before a step first where a zero-length segment with tau > 0 sits."""
    out = []
    for d in sorted(set(np.r_[z0, z1].tolist())):
        tl = optical_depth(z0, z1, tau, d, left=True)
        tr = optical_depth(z0, z1, tau, d)
        if tr > tl:
            out.append((d, np.exp(-tl), True))
        out.append((d, np.exp(-tr), False))
    return out


def chord(d0, t0, d1, t1, x, interp):
    """Value at x in [d0, d1] of the lookup's interpolation between two nodes."""
    if d1 <= d0:
        return t1
    w = (x - d0) / (d1 - d0)
    if interp == "exp" and t0 > 0 and t1 > 0:
        return t0 * (t1 / t0) ** w
    return t0 + w * (t1 - t0)


def node_curve(nodes, x, interp):
    """Right-continuous node curve: 1 in front, last value behind."""
    if x < nodes[0][0]:
        return 1.0
    for k in range(len(nodes) - 1, -1, -1):
        if nodes[k][0] <= x:
            if k + 1 < len(nodes):
                return chord(*nodes[k][:2], *nodes[k + 1][:2], x, interp)
            return nodes[k][1]


def _pieces(z0, z1, tau, nodes):
    """Depth intervals on which both the exact curve and the node curve are smooth."""
    cuts = sorted(set(np.r_[z0, z1, [n[0] for n in nodes]].tolist()))
    return [(a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]


def l2_error(z0, z1, tau, nodes, interp):
    """int (node curve - exact)^2 over [first, last point] (Gauss-Legendre per piece)."""
    total = 0.0
    for a, b in _pieces(z0, z1, tau, nodes):
        xs = 0.5 * (a + b) + 0.5 * (b - a) * GL_X
        f = [node_curve(nodes, x, interp) - np.exp(-optical_depth(z0, z1, tau, x)) for x in xs]
        total += 0.5 * (b - a) * float(np.dot(GL_W, np.square(f)))
    return total


def _exact_many(z0, z1, tau, xs):
    """T at many depths (vectorised :func:`optical_depth`)."""
    z0, z1, tau = (np.asarray(a, np.float64)[None, :] for a in (z0, z1, tau))
    x = np.asarray(xs, np.float64)[:, None]
    length = z1 - z0
    frac = np.where(length > 0, np.clip((x - z0) / np.where(length > 0, length, 1.0), 0, 1), x >= z0)
    return np.exp(-(tau * frac).sum(axis=1))


def _nodes_many(nodes, xs, interp):
    """:func:`node_curve` at many depths."""
    d = np.array([n[0] for n in nodes])
    t = np.array([n[1] for n in nodes])
    k = np.searchsorted(d, xs, side="right") - 1              # last node with d <= x
    a = np.clip(k, 0, len(d) - 1)
    b = np.minimum(a + 1, len(d) - 1)
    dd = d[b] - d[a]
    w = np.clip(np.where(dd > 0, (xs - d[a]) / np.where(dd > 0, dd, 1.0), 0.0), 0.0, 1.0)
    lin = t[a] + w * (t[b] - t[a])
    if interp == "exp":
        ok = (t[a] > 0) & (t[b] > 0)
        lin = np.where(ok, np.where(ok, t[a], 1.0) * (np.where(ok, t[b], 1.0) / np.where(ok, t[a], 1.0)) ** w, lin)
    return np.where(k >= 0, np.where(b > a, lin, t[a]), 1.0)


def linf_error(z0, z1, tau, nodes, interp, samples=4001):
    """max |node curve - exact| over both sides of every point and node depth and
    ``samples`` depths inside every smooth piece."""
    worst = _one_sided(z0, z1, tau, nodes, interp)
    for a, b in _pieces(z0, z1, tau, nodes):
        x = np.linspace(a, b, samples)[1:-1]
        worst = max(worst, float(np.max(np.abs(_nodes_many(nodes, x, interp) - _exact_many(z0, z1, tau, x)))))
    return worst


def _graded_mesh(uniform=8, halvings=64):
    """Sub-interval ends on [0, 1]: ``uniform`` equal ones, the first halved ``halvings``
    times.  Every curve here decays from the left end of a smooth piece (T and an
    exponential chord as ``e^{-lambda t}``, lambda up to the piece's optical depth; a linear
    chord is a polynomial), so on ``[t, 2 t]`` ``lambda t <= 30`` where the integrand is
    not below ``e^-60`` of its peak: 16-point Gauss-Legendre is then exact to rounding."""
    return np.unique(np.r_[np.linspace(0.0, 1.0, uniform + 1), 0.5 ** np.arange(1, halvings + 1) / uniform])


_GL16_X, _GL16_W = np.polynomial.legendre.leggauss(16)


def _piece_samples(z0, z1, tau, nodes):
    """Per smooth piece: quadrature depths and weights on the graded mesh."""
    t = _graded_mesh()
    xs, ws = [], []
    for a, b in _pieces(z0, z1, tau, nodes):
        lo, hi = a + (b - a) * t[:-1], a + (b - a) * t[1:]
        mid, half = (lo + hi) / 2, (hi - lo) / 2
        xs.append((mid[:, None] + half[:, None] * _GL16_X[None, :]).ravel())
        ws.append((half[:, None] * _GL16_W[None, :]).ravel())
    return xs, ws


def l2_error_graded(z0, z1, tau, nodes, interp):
    """int (node curve - exact)^2 over every smooth piece, from the pointwise difference
    (no cancellation between int T^2, int T chord, int chord^2) on the graded mesh."""
    xs, ws = _piece_samples(z0, z1, tau, nodes)
    if not xs:
        return 0.0
    x, w = np.concatenate(xs), np.concatenate(ws)
    diff = _nodes_many(nodes, x, interp) - _exact_many(z0, z1, tau, x)
    return float(np.dot(w, diff * diff))


def linf_error_golden(z0, z1, tau, nodes, interp, iterations=80):
    """max |node curve - exact|: both sides of every point and node depth, and per smooth
    piece the largest of ``max D`` and ``max -D`` (``D`` = node curve - exact) by golden
    section.  On a piece ``D`` is an exponential minus a line or another exponential, so
    ``D' = 0`` at most once: ``D`` is monotone on both sides of its one extremum and golden
    section finds the maximum of ``D`` (and of ``-D``) over the piece (an end where the
    extremum is the other kind), to 0.618^80 ~ 2e-17 of the piece."""
    worst = _one_sided(z0, z1, tau, nodes, interp)
    pieces = np.array(_pieces(z0, z1, tau, nodes)).reshape(-1, 2)
    if pieces.size == 0:
        return worst
    g = (np.sqrt(5.0) - 1) / 2
    sign = np.repeat([1.0, -1.0], pieces.shape[0])        # max D and max -D, side by side
    lo, hi = np.tile(pieces[:, 0], 2), np.tile(pieces[:, 1], 2)

    def f(x):
        return sign * (_nodes_many(nodes, x, interp) - _exact_many(z0, z1, tau, x))

    x1, x2 = hi - g * (hi - lo), lo + g * (hi - lo)
    f1, f2 = f(x1), f(x2)
    for _ in range(iterations):
        right = f1 < f2                                   # the maximum is in [x1, hi]
        lo, hi = np.where(right, x1, lo), np.where(right, hi, x2)
        x1, x2 = np.where(right, x2, hi - g * (hi - lo)), np.where(right, lo + g * (hi - lo), x1)
        new = f(np.where(right, x2, x1))
        f1, f2 = np.where(right, f2, new), np.where(right, new, f1)
    return max(worst, float(np.max(np.maximum(f1, f2))))


def _one_sided(z0, z1, tau, nodes, interp):
    """max |node curve - exact| over both one-sided limits at every point and node depth
    (either curve may step there: the exact one at a zero-length segment, the node curve
    at a double node and from 1 to its first value)."""
    worst = 0.0
    for d in sorted(set(np.r_[z0, z1, [n[0] for n in nodes]].tolist())):
        worst = max(worst, abs(node_curve(nodes, d, interp) - np.exp(-optical_depth(z0, z1, tau, d))),
                    abs(_left_node_value(nodes, d, interp) - np.exp(-optical_depth(z0, z1, tau, d, left=True))))
    return worst


def _left_node_value(nodes, d, interp):
    """Node curve just before depth d (left limit)."""
    prev = [n for n in nodes if n[0] < d]
    if not prev:
        return 1.0
    k = len(prev) - 1
    if k + 1 < len(nodes):
        return chord(*nodes[k][:2], *nodes[k + 1][:2], d, interp)
    return nodes[k][1]


def brute_force(z0, z1, tau, N, norm, interp, measure=None, tiny=0.0):
    """(best cost, best nodes) over every subset of at most N points containing the last
    one (the curve is 1 in front of the first node), nodes carrying the exact values
    (positive ones at least ``tiny``: the stored values of exponentially interpolated
    nodes).  ``measure(z0, z1, tau, nodes, interp)``: the cost (default :func:`l2_error` /
    :func:`linf_error` by ``norm``)."""
    pts = points(z0, z1, tau)
    K = len(pts)
    best = (np.inf, None)
    for m in range(0, min(N, K)):
        for sub in itertools.combinations(range(K - 1), m):
            idx = [*sub, K - 1]
            nodes = [(pts[i][0], max(pts[i][1], tiny) if pts[i][1] > 0 else 0.0) for i in idx]
            c = (measure or (l2_error if norm == "l2" else linf_error))(z0, z1, tau, nodes, interp)
            if c < best[0]:
                best = (c, nodes)
    return best


def refit(z0, z1, tau, depths):
    """Least-squares node values (linear interpolation) at ``depths`` with the first and
    last value pinned to the exact curve (dense weighted solve on Gauss-Legendre nodes)."""
    xs, ws = [], []
    for a, b in _pieces(z0, z1, tau, [(d, 0.0) for d in depths]):
        xs.append(0.5 * (a + b) + 0.5 * (b - a) * GL_X)
        ws.append(0.5 * (b - a) * GL_W)
    x, w = np.concatenate(xs), np.concatenate(ws)
    target = np.exp(-np.array([optical_depth(z0, z1, tau, xi) for xi in x]))
    n = len(depths)
    basis = np.zeros((x.size, n))
    for m in range(n):
        e = np.zeros(n)
        e[m] = 1.0
        basis[:, m] = [node_curve(list(zip(depths, e)), xi, "linear") if xi >= depths[0] else 0.0 for xi in x]
    v0 = np.exp(-optical_depth(z0, z1, tau, depths[0], left=True))
    vn = np.exp(-optical_depth(z0, z1, tau, depths[-1]))
    rhs = target - v0 * basis[:, 0] - vn * basis[:, -1]
    sw = np.sqrt(w)
    inner, *_ = np.linalg.lstsq(basis[:, 1:-1] * sw[:, None], rhs * sw, rcond=None)
    return np.r_[v0, inner, vn]


def visvalingam(z0, z1, tau, N):
    """Remove the interior point of smallest AVSM area metric (ties: the deepest) until N
    points remain; returns [(depth, T)]."""
    nodes = [p[:2] for p in points(z0, z1, tau)]
    while len(nodes) > N:
        best, idx = np.inf, None
        for i in range(1, len(nodes) - 1):
            (d0, t0), (d1, t1), (d2, t2) = nodes[i - 1], nodes[i], nodes[i + 1]
            m = abs((d2 - d0) * (t2 - t1) - (d2 - d1) * (t2 - t0))
            if m <= best:
                best, idx = m, i
        nodes.pop(idx)
    return nodes
