"""AVSM with a blended removal metric, hard and through a smooth surrogate (the
``learned_warp`` experiment's second part).

The paper removes the interior node of smallest area change (Salvi, Vidimce, Lauritzen and
Lefohn 2010, "Adaptive Volumetric Shadow Maps", sec. 3.2.1), ``A_i`` = :func:`area_metric`.
Here the metric is a blend

    m_i = (1 - beta) A_i + beta G_i,   G_i = (d_{i+1} - d_{i-1}) (t_{i-1} - t_{i+1}),

``G_i`` the depth gap the node's two intervals span times the transmittance drop across it
(the bounding box of the triangle whose area is ``A_i``, so ``A_i <= G_i``, same units);
``beta = sigmoid(phi)`` in (0, 1), ``beta -> 0`` is the paper.

* **hard** (:func:`avsm_nodes` with ``temperature=None``): the avsm kind's algorithm, one
  lane per non-empty texel, segments in the given order, reusing the kind's own insertion
  (:func:`~avsm_dr.representations.avsm.insert_segment`) and sampling; removal is the argmin
  of ``m`` (ties: the deepest node).  With ``beta = 0`` it gives the avsm kind's nodes (the
  tests check it), so a learned ``beta`` is evaluated by the real algorithm without a new
  parameter on the kind.
* **surrogate** (``temperature=tau``): the argmin is replaced by a softmin over the interior
  nodes, ``p_i = softmax(-m_i / (tau mean_j m_j))``, and the shortened list is the
  expectation of the hard ones, slot ``j`` = ``x_j P(i > j) + x_{j+1} P(i <= j)``; smooth in
  ``phi``, so reverse mode gives d loss / d phi.  The temperature is annealed during training.

The loop over a texel's segments is unrolled in Python (one step per segment slot, lanes
past their count keep their state), so reverse mode needs no loop machinery.
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from avsm_dr import _arrays as A
from avsm_dr import backend
from avsm_dr.representations.avsm import curve_at, insert_segment, interpolate


def area_metric(d, t, i):
    """Area change when removing interior node i (Salvi et al. 2010, sec. 3.2.1)."""
    return dr.abs((d[i + 1] - d[i - 1]) * (t[i + 1] - t[i])
                  - (d[i + 1] - d[i]) * (t[i + 1] - t[i - 1]))


def _remove(d, t, beta, temperature):
    """One removal from the node lists (n -> n - 1 entries), hard or soft."""
    n = len(d)
    m = [(1 - beta) * area_metric(d, t, i) + beta * (d[i + 1] - d[i - 1]) * dr.abs(t[i - 1] - t[i + 1])
         for i in range(1, n - 1)]
    if temperature is None:
        UInt32 = backend.types().UInt32
        best, idx = m[0], dr.full(UInt32, 1, dr.width(m[0]))
        for i in range(2, n - 1):
            take = m[i - 1] <= best
            best = dr.select(take, m[i - 1], best)
            idx = dr.select(take, UInt32(i), idx)
        return tuple([dr.select(idx <= j, x[j + 1], x[j]) for j in range(n - 1)] for x in (d, t))
    scale = sum(m) / len(m)
    scale = temperature * dr.select(scale > 0, scale, 1)
    lo = m[0]
    for v in m[1:]:
        lo = dr.minimum(lo, v)
    w = [dr.exp(-(v - lo) / scale) for v in m]               # softmin weights of nodes 1..n-2
    total = sum(w)
    cum, below = [], 0                                       # P(i <= j), j = 0..n-2
    for j in range(n - 1):
        if 1 <= j <= n - 2:
            below = below + w[j - 1]
        cum.append(below / total)
    return tuple([x[j] + cum[j] * (x[j + 1] - x[j]) for j in range(n - 1)] for x in (d, t))


def avsm_nodes(seg, N: int, beta, temperature=None):
    """(lanes (NumPy texel index of each lane), depths, values): N node lists, one lane
    per non-empty texel of ``seg``, built with the blended metric (module docstring).
    ``beta``: Dr.Jit Float of width 1 (AD kept) or a float."""
    t_ = backend.types()
    Float, UInt32 = seg.Float, t_.UInt32
    lanes = np.flatnonzero(seg.counts > 0)
    L = lanes.size
    far = seg.bounds()[1]
    start = A.to_uint32(seg.offsets[lanes])
    count = A.to_uint32(seg.counts[lanes])
    d = [dr.full(Float, far, L) for _ in range(N)]
    t = [dr.full(Float, 1.0, L) for _ in range(N)]
    used = dr.zeros(UInt32, L)
    for j in range(int(seg.counts.max()) if L else 0):
        jj = dr.opaque(UInt32, j)          # opaque: every step reuses one compiled kernel
        active = jj < count
        i = start + dr.minimum(jj, count - 1)
        a = dr.gather(Float, seg.z0, i)
        b = dr.gather(Float, seg.z1, i)
        ts = dr.exp(-dr.gather(Float, seg.optical_depth, i))
        ta, zero = curve_at(d, t, a)
        nd, nt = insert_segment(d, t, used, a, b, ts, ta=ta)
        full = used + 2 > N
        rd, rt = _remove(*_remove(nd, nt, beta, temperature), beta, temperature)
        skip = ~active | zero                                   # the kind's rule: nothing behind T = 0
        d = [dr.select(skip, d[k], dr.select(full, rd[k], nd[k])) for k in range(N)]
        t = [dr.select(skip, t[k], dr.select(full, rt[k], nt[k])) for k in range(N)]
        used = dr.select(skip | full, used, used + 2)
        dr.eval(d, t, used)
    return lanes, d, t


def lookup(seg, lanes, d, t, texel, depth):
    """T at receivers (texel, depth) from the lane node lists (linear interpolation);
    receivers must lie in non-empty texels."""
    Float = seg.Float
    lane_of = np.full(seg.n_texels, -1, np.int64)
    lane_of[lanes] = np.arange(lanes.size)
    li = lane_of[np.asarray(texel)]
    if np.any(li < 0):
        raise ValueError("texel: receivers in empty texels have no AVSM lane")
    idx = A.to_uint32(li)
    N = len(d)
    dd = [dr.gather(Float, d[k], idx) for k in range(N)]
    tt = [dr.gather(Float, t[k], idx) for k in range(N)]
    return interpolate(dd, tt, A.to_float(depth, Float), "linear")


class NodeLists:
    """The hard blended-metric AVSM-``N`` of ``seg`` (:func:`avsm_nodes` at ``beta``) as
    something to look up: ``eval(texel, depth)`` -> (K,) T, 1 in empty texels (nothing in
    front of any depth), so bilinear taps may touch them."""

    def __init__(self, seg, N: int, beta: float):
        self.seg = seg
        self.lanes, self.d, self.t = avsm_nodes(seg, N, _opaque(beta))

    def eval(self, texel, depth):
        texel = np.asarray(texel, np.int64)
        depth = np.asarray(depth, np.float64)
        out = np.ones(texel.size)
        has = self.seg.counts[texel] > 0
        if np.any(has):
            out[has] = np.asarray(lookup(self.seg, self.lanes, self.d, self.t, texel[has], depth[has]), np.float64)
        return out


def _opaque(x):
    """A width-1 opaque Float (a new value does not recompile the kernels), or None."""
    return None if x is None else dr.opaque(backend.types().Float, float(x))


def rmse(data, N: int, beta: float, temperature=None, key: str = "eval") -> float:
    """RMSE of the blended-metric AVSM (hard, or the surrogate at ``temperature``) at the
    receivers ``key`` of a :class:`~experiments.learned_warp.SceneData`."""
    t, z, exact = data.sets[key]
    lanes, d, v = avsm_nodes(data.seg, N, _opaque(beta), _opaque(temperature))
    e = np.asarray(lookup(data.seg, lanes, d, v, t, z), np.float64) - np.asarray(exact, np.float64)
    return float(np.sqrt(np.mean(e * e)))


def sigmoid(x: float) -> float:
    """1 / (1 + exp(-x))."""
    return 1.0 / (1.0 + np.exp(-x))


def train_metric(scenes, N: int, P: dict, progress=None):
    """Learn ``phi`` (``beta = sigmoid(phi)``) on the surrogate: Adam on the mean training
    MSE, temperature annealed geometrically from ``P['metric_tau']`` (first, last); the
    gradient by central differences in ``phi`` (step ``P['metric_fd']``): reverse mode
    through the unrolled loop built one kernel too large to compile in minutes (measured).
    Returns (phi, rows of iteration, phi, beta, temperature, surrogate MSE)."""
    phi, m, v = P["metric_phi0"], 0.0, 0.0
    b1, b2, lr, h = 0.9, 0.999, P["metric_lr"], P["metric_fd"]
    it = P["metric_iterations"]
    t0, t1 = P["metric_tau"]
    rows = []

    def loss(x, tau):
        return float(np.mean([rmse(d, N, sigmoid(x), tau, "train") ** 2 for d in scenes]))

    for k in range(it):
        tau = t0 * (t1 / t0) ** (k / max(it - 1, 1))
        g = (loss(phi + h, tau) - loss(phi - h, tau)) / (2 * h)
        rows.append({"iteration": k, "phi": phi, "beta": sigmoid(phi), "temperature": tau,
                     "surrogate_mse": loss(phi, tau)})
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g * g
        phi -= lr * (m / (1 - b1 ** (k + 1))) / (np.sqrt(v / (1 - b2 ** (k + 1))) + 1e-12)
        if progress is not None:
            progress.update(1)
    return phi, rows


__all__ = ["avsm_nodes", "lookup", "rmse", "sigmoid", "train_metric"]
