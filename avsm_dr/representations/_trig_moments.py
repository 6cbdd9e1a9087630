"""Trigonometric moments of the absorbance (n = 2, 3, 4 complex moments) and their bound,
branch-free Dr.Jit (Muenstermann, Krumpen, Klein, Peters 2018, "Moment-Based
Order-Independent Transparency", sec. 4: trigonometric moments, Toeplitz matrix, canonical
representations on the unit circle).

Phase: the warped depth x in [-1, 1] maps to ``phi = (pi / 2) x`` in [-pi/2, pi/2] (the cut
is at ``phi = pi``).  A texel stores ``b_0 = sum tau`` and ``Re b_k, Im b_k`` of
``b_k = sum_i tau_i E_i[e^{i k phi}]``, k = 1..n.  Segment means, ``phi = (pi/2)(mid + h tau)``,
``w = k (pi/2) h``: linear warp ``e^{ik (pi/2) mid} sinc(w)``; log warp (density ~
``e^{kappa tau}``, :mod:`.moments`) ``e^{ik (pi/2) mid} G``,
``G = kappa sinh(kappa + i w) / ((kappa + i w) sinh kappa)``, without cancellation
``Re G = (kappa^2 cos w + q w^2 sinc w) / (kappa^2 + w^2)``,
``Im G = kappa w ((q - 1) sinc w + (sinc w - cos w)) / (kappa^2 + w^2)``, ``q = kappa
coth kappa`` (``q - 1`` and ``sinc w - cos w`` by Taylor series below :data:`SERIES_BELOW`).

Bound.  The Cayley transform ``x = tan(phi / 2)`` maps Laurent polynomials of degree n in
``e^{i phi}`` onto polynomials of degree 2n over ``(1 + x^2)^n``: ``mu`` has trigonometric
moments ``t_0..t_n`` exactly when ``nu = mu / (1 + x^2)^n`` has the power moments
``M_j = E_mu[sin^j(phi/2) cos^(2n-j)(phi/2)]`` (linear in ``t``, :func:`cayley_matrix`), with
canonical representations point by point.  So the Toeplitz problem through ``phi_f`` is the
Hankel problem of :mod:`._moment_bounds` for ``m = M / M_0`` through ``x_f = tan(phi_f / 2)``;
a support point ``psi = atan(x)`` weighs ``w = M_0 / (s^T B_m^-1 s)``,
``s_j = sin^j(psi) cos^(n-j)(psi)``; ``L = sum_{x_i < x_f} w_i``, ``U = L + w_f``.

Bias toward the uniform distribution on the circle (``t_k = 0``): ``t = (1 - alpha) b / b_0``;
the Hankel pivots of ``nu`` are floored at ``alpha`` times the uniform distribution's over
``M_0``.
"""
from __future__ import annotations

import math

import drjit as dr
import numpy as np

from ._moment_bounds import BIG, NEGLIGIBLE, bounded_depth, kernel_polynomial, real_roots
from .basis_functions import sinc as _sinc

#: Below this argument ``q - 1`` and ``sinc w - cos w`` use their series.
SERIES_BELOW = 0.1


def cayley_matrix(n: int) -> np.ndarray:
    """(2n + 1, 2n + 1) float64 A with M_j = sum_c A[j, c] r_c, r = (1, Re t_1, Im t_1, ..,
    Re t_n, Im t_n) and M_j = E[sin^j(phi/2) cos^(2n-j)(phi/2)] (exact: a trigonometric
    polynomial of degree n in phi, read off by a discrete Fourier transform at 4n + 4
    points)."""
    N = 4 * n + 4
    phi = 2 * np.pi * np.arange(N) / N
    A = np.zeros((2 * n + 1, 2 * n + 1))
    for j in range(2 * n + 1):
        f = np.sin(phi / 2) ** j * np.cos(phi / 2) ** (2 * n - j)
        A[j, 0] = f.mean()
        for k in range(1, n + 1):
            A[j, 2 * k - 1] = 2 * np.mean(f * np.cos(k * phi))
            A[j, 2 * k] = 2 * np.mean(f * np.sin(k * phi))
    A[np.abs(A) < 1e-15] = 0.0
    return A


def tilted_phase_mean(kappa, w):
    """(Re G, Im G) of G = E[e^{i w tau}] under the density ~ e^{kappa tau} on [-1, 1]
    (kappa, w >= 0; module docstring)."""
    k2, w2 = kappa * kappa, w * w
    ks = dr.select(kappa > SERIES_BELOW, kappa, 1)
    q_minus_1 = dr.select(kappa > SERIES_BELOW, ks / dr.tanh(ks) - 1,
                          k2 * (1 / 3 - k2 * (1 / 45 - k2 * (2 / 945 - k2 * (1 / 4725 - k2 * (2 / 93555))))))
    ws = dr.select(w > SERIES_BELOW, w, 1)
    sc = _sinc(w)
    sinc_minus_cos = dr.select(w > SERIES_BELOW, dr.sin(ws) / ws - dr.cos(ws),
                               w2 * (1 / 3 - w2 * (1 / 30 - w2 * (1 / 840 - w2 * (1 / 45360)))))
    den = k2 + w2
    tiny = den <= 0
    inv = 1 / dr.select(tiny, 1, den)
    re = dr.select(tiny, 1, (k2 * dr.cos(w) + (1 + q_minus_1) * w2 * sc) * inv)
    im = dr.select(tiny, 0, kappa * w * (q_minus_1 * sc + sinc_minus_cos) * inv)
    return re, im


def trig_means(x0, x1, n: int, lam=None):
    """[1, E cos(k phi), E sin(k phi), ..] (2n + 1 arrays) over [x0, x1] in warped x for
    optical depth uniform in z: linear warp (lam None) or log warp (density ~ e^{lam x})."""
    mid, h = 0.5 * (x0 + x1), 0.5 * (x1 - x0)
    out = [1 + 0 * mid]
    for k in range(1, n + 1):
        s, c = dr.sincos((k * math.pi / 2) * mid)
        w = (k * math.pi / 2) * h
        if lam is None:
            g_re, g_im = _sinc(w), 0 * w
        else:
            g_re, g_im = tilted_phase_mean(lam * h, w)
        out += [c * g_re - s * g_im, s * g_re + c * g_im]
    return out


def _christoffel(Lm, D, psi, n):
    """1 / (s^T B^-1 s), s_j = sin^j(psi) cos^(n-j)(psi), with B = L D L^T (D_0 = 1)."""
    sn, cs = dr.sin(psi), dr.cos(psi)
    s = [cs ** n if n else 1] + [sn ** j * cs ** (n - j) for j in range(1, n + 1)]
    y = [s[0]]
    q = s[0] * s[0]
    for i in range(1, n + 1):
        acc = s[i] - Lm[i, 0] * y[0]
        for k in range(1, i):
            acc = acc - Lm[i, k] * y[k]
        y.append(acc)
        q = q + acc * acc / D[i]
    return 1 / dr.maximum(q, 1e-30)


def trig_bound(b, xw, alpha, beta, A, pivots):
    """Optical depth in front of warped depth ``xw`` and the bounds (module docstring).

    b: 2n + 1 Dr.Jit arrays [b_0, Re b_1, Im b_1, ..]; xw: Float in [-1, 1]; alpha, beta:
    floats; A: :func:`cayley_matrix`; pivots: :func:`._moment_bounds.hankel_pivots` of its first
    column (the uniform distribution's M, unnormalised).  Returns (D, L, U)."""
    n = (len(b) - 1) // 2
    b0 = b[0]
    empty = b0 <= NEGLIGIBLE        # flushed higher moments: _moment_bounds.NEGLIGIBLE
    inv = (1 - alpha) / dr.select(empty, 1, b0)
    r = [1] + [bk * inv for bk in b[1:]]                       # biased t (uniform target: 0)
    M = [sum((float(A[j, c]) * r[c] for c in range(1, 2 * n + 1) if A[j, c] != 0.0), float(A[j, 0]) + 0 * b0)
         for j in range(2 * n + 1)]                           # M = A r (module docstring)
    M0 = dr.maximum(M[0], 1e-30)
    m = [None] + [Mj / M0 for Mj in M[1:]]
    psi_f = (math.pi / 4) * xw
    xf = dr.tan(psi_f)
    Lm, D, c = kernel_polynomial(m, xf, [None] + [alpha * p / M0 for p in pivots[1:]])
    # weights of mu: M_0 / (s^T B_m^-1 s)
    wf = dr.clip(_christoffel(Lm, D, psi_f, n) * M0, 0, 1)
    lower = sum(dr.select(z < xf, dr.clip(_christoffel(Lm, D, dr.atan(dr.clip(z, -BIG, BIG)), n) * M0, 0, 1), 0)
                for z in real_roots(c))
    return bounded_depth(b0, empty, lower, wf, beta)
