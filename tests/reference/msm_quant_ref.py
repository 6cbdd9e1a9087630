"""The optimised 16-bit quantisation of 4 power moments (Peters and Klein 2015, "Moment
Shadow Mapping", I3D, sec. 5) in float64 NumPy, one texel at a time, by a different route
from avsm_dr/representations/moments.py (the MSM part): the x <-> u moment maps by expanding
((1 + x) / 2)^j and (2u - 1)^k with numpy.polynomial, the inverse transform by
numpy.linalg.solve, float16 codes from precision_ref (written out from the exponent).
Row-vector convention q = mu @ M + c, mu = (E u, .., E u^4), u in [0, 1], x = 2u - 1."""
from __future__ import annotations

import numpy as np
from numpy.polynomial import polynomial as Pn

from . import precision_ref as PR

M = np.array([[-2.07224649, 13.7948857237, 0.105877704, 9.7924062118],
              [32.23703778, -59.4683975703, -1.9077466311, -33.7652110555],
              [-68.571074599, 82.0359750338, 9.3496555107, 47.9456096605],
              [39.3703274134, -35.364903257, -6.6543490743, -23.9728048165]])
C = np.array([0.035955884801, 0.0, 0.0, 0.0])


def _expect(poly, moments):
    """E[p(v)] for the polynomial coefficients ``poly`` (ascending) and moments (1, E v, ..)."""
    return float(np.dot(poly, moments[:len(poly)]))


def u_moments(m):
    """E u^j, j = 1..4, from E x^k, k = 1..4 (u = (1 + x) / 2)."""
    full = np.concatenate([[1.0], m])
    return np.array([_expect(Pn.polypow([0.5, 0.5], j), full) for j in range(1, 5)])


def x_moments(mu):
    """E x^k, k = 1..4, from E u^j (x = 2u - 1)."""
    full = np.concatenate([[1.0], mu])
    return np.array([_expect(Pn.polypow([-1.0, 2.0], k), full) for k in range(1, 5)])


def forward(m):
    """q from one texel's x-moments m (4,)."""
    return u_moments(np.asarray(m, np.float64)) @ M + C


def inverse(q):
    """x-moments from q: solve mu @ M = q - C."""
    return x_moments(np.linalg.solve(M.T, np.asarray(q, np.float64) - C))


def stored(b, precision):
    """One texel's decoded moments (5,): q through ``precision`` codes, b_0 in float32."""
    b = np.asarray(b, np.float64)
    if b[0] <= 0:
        return np.zeros(5)
    b0 = float(np.float32(b[0]))
    return np.concatenate([[b0], b0 * inverse(PR.code(forward(b[1:] / b[0]), precision))])
