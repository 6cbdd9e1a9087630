"""Four power moments of the absorbance and the Hamburger bound, in float64 NumPy by a
different route from the kernel: moments by Gauss-Legendre quadrature (exact for
polynomials), the canonical representation by ``numpy.linalg.solve`` on the Hankel
matrix, ``numpy.roots`` and a Vandermonde solve for the weights.
Conventions as in avsm_dr/representations/moments.py (x = 2u - 1, bias toward the
uniform distribution's moments (0, 1/3, 0, 1/5))."""
from __future__ import annotations

import numpy as np

from . import linear_ref as R

UNIFORM = np.array([1.0, 0.0, 1.0 / 3.0, 0.0, 1.0 / 5.0])


def power_functions():
    return [(lambda u, k=k: (2 * u - 1.0) ** k) for k in range(5)]


def moments(case, **rng):
    """(T, 5) b_k = sum_i tau_i E_i[x^k]."""
    return R.basis_coefficients(case, power_functions(), **rng)


def bounds(b, x, alpha):
    """(lower, upper) absorbance fraction in front of x from one texel's moments b."""
    if b[0] <= 0:
        return 0.0, 0.0
    m = (1 - alpha) * b / b[0] + alpha * UNIFORM
    B = np.array([[m[i + j] for j in range(3)] for i in range(3)])
    c = np.linalg.solve(B, [1.0, x, x * x])
    z = np.roots([c[2], c[1], c[0]]).real
    points = np.array([x, *z])
    w = np.linalg.solve(np.vander(points, 3, increasing=True).T, m[:3])
    lower = float(w[1:][z < x].sum())
    return lower, lower + float(w[0])


def optical_depth(b, u, alpha, beta):
    """D = b_0 clamp(L + beta w_f, 0, 1); 0 at u <= 0 and b_0 at u >= 1."""
    out = np.zeros(len(u))
    for j, uj in enumerate(u):
        if uj <= 0 or b[0] <= 0:
            continue
        if uj >= 1:
            out[j] = b[0]
            continue
        lo, up = bounds(b, 2 * uj - 1, alpha)
        out[j] = b[0] * min(max(lo + beta * (up - lo), 0.0), 1.0)
    return out
