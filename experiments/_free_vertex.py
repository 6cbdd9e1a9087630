"""The free-vertex optimum: N nodes anywhere in depth with any values in [0, 1], the best
fit of one texel's exact curve under the metric of :func:`avsm_dr.evaluation.depth_l2`.

``optimal`` searches node *subsets of the exact curve's points* (then refits the values);
AVSM's nodes leave the curve, so the gap to the true optimum needs nodes free in depth as
well.  For one texel with the counted midpoints ``z_j`` of
:func:`avsm_dr.evaluation.depth_grid` and the exact values ``T_j`` there, the node list
``(d_1 <= .. <= d_N, v_1..v_N)`` is looked up as AVSM's (``T = 1`` in front of ``d_1``,
linear between nodes, ``v_N`` behind ``d_N``), so its values at the midpoints are
``f = H(d) v + c(d)`` (hat functions; ``c_j = 1`` in front of ``d_1``) and ::

    L2(d) = sqrt( min_{v in [0, 1]^N} mean_j (H(d) v + c(d) - T)_j^2 )

(variable projection: for fixed depths the values are a bounded linear least-squares
problem, :func:`fit_values`).  The depths are refined by Powell's method inside the texel's
range, from ``optimal``'s nodes and from N uniform nodes; the lower result is kept.  A
local optimum: an upper bound of the true free-vertex optimum that is never above the
best subset it starts from (its start is scored first).  Float64, host NumPy / SciPy,
O(texels x function evaluations x n_depths N): meant for a sample of texels.
"""
from __future__ import annotations

import numpy as np

#: Function evaluations per start and node (Powell's ``maxfev`` = this x N).
MAXFEV_PER_NODE = 150


def lookup_matrix(z, d):
    """(H, c): the lookup of nodes at sorted depths ``d`` (N,) at depths ``z`` (M,) is
    ``H @ v + c`` for node values ``v`` (module docstring)."""
    z = np.asarray(z, np.float64)
    d = np.asarray(d, np.float64)
    m, n = z.size, d.size
    H = np.zeros((m, n))
    c = np.zeros(m)
    k = np.searchsorted(d, z, side="right") - 1           # last node at or before z
    c[k < 0] = 1.0
    last = k == n - 1
    H[last, n - 1] = 1.0
    mid = (k >= 0) & (k < n - 1)
    km = k[mid]
    w = (z[mid] - d[km]) / np.maximum(d[km + 1] - d[km], 1e-300)
    rows = np.flatnonzero(mid)
    H[rows, km] = 1.0 - w
    H[rows, km + 1] = w
    return H, c


def fit_values(z, T, d):
    """(values (N,), mean squared error) of the best node values in [0, 1] for node depths
    ``d`` against the curve ``T`` at ``z`` (bounded least squares)."""
    H, c = lookup_matrix(z, d)
    r = np.asarray(T, np.float64) - c
    v, *_ = np.linalg.lstsq(H, r, rcond=None)
    if np.any((v < 0) | (v > 1)):
        from scipy.optimize import lsq_linear
        v = lsq_linear(H, r, bounds=(0.0, 1.0)).x
    e = H @ v - r
    return v, float(np.mean(e * e))


def refine(z, T, d0, lo=None, hi=None):
    """(depths, values, L2) of the free-vertex fit of one texel: Powell on the node depths
    in ``[lo, hi]`` (default: the range of ``z``) from ``d0`` and from uniform depths."""
    from scipy.optimize import minimize
    z = np.asarray(z, np.float64)
    lo = float(z.min()) if lo is None else lo
    hi = float(z.max()) if hi is None else hi
    n = len(d0)
    cost = lambda d: fit_values(z, T, np.sort(d))[1]       # noqa: E731
    starts = [np.clip(np.sort(np.asarray(d0, np.float64)), lo, hi), np.linspace(lo, hi, n)]
    best_d, best = starts[0], cost(starts[0])
    for s in starts:
        if hi > lo:
            r = minimize(cost, s, method="Powell", bounds=[(lo, hi)] * n,
                         options=dict(maxfev=MAXFEV_PER_NODE * n, xtol=1e-6 * (hi - lo), ftol=1e-12))
            if r.fun < best:
                best_d, best = np.sort(r.x), float(r.fun)
    v, mse = fit_values(z, T, best_d)
    return best_d, v, float(np.sqrt(mse))


def free_vertex_l2(segments, exact_curve, start, texels, n_depths):
    """Per-texel free-vertex L2 on ``texels`` (indices into the rows of
    :func:`avsm_dr.evaluation.depth_grid`): ``exact_curve`` the exact curve's
    :func:`~avsm_dr.evaluation.curve_values` on that grid, ``start`` a node list (``optimal``)
    whose ``nodes_numpy()`` gives the starting depths."""
    from avsm_dr.evaluation import depth_grid
    tex, z, counted = depth_grid(segments, n_depths)
    D, _ = start.nodes_numpy()
    out = np.empty(len(texels))
    for i, row in enumerate(texels):
        keep = counted[row]
        half = 0.5 * (z[row, 1] - z[row, 0]) if z.shape[1] > 1 else 0.0
        out[i] = refine(z[row][keep], exact_curve[row][keep], D[tex[row]],
                        lo=z[row, 0] - half, hi=z[row, -1] + half)[2]
    return out
