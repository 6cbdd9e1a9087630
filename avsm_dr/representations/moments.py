"""Moment-based transmittance: four power moments of the absorbance with the Hamburger
4-moment bound (Peters and Klein 2015, "Moment Shadow Mapping", algorithm 2;
Muenstermann et al. 2018, "Moment-Based Order-Independent Transparency", sec. 3-4,
applied to optical depth as in the latter).

Depth is normalised to ``x = 2 u - 1`` in [-1, 1] (``u`` as in
:mod:`avsm_dr.representations.basis`, same ranges and clipping).  A texel stores

    b_0 = sum_i tau_i,    b_k = sum_i tau_i E_i[x^k]  (k = 1..4),

``E_i`` the mean over segment ``i`` (uniform density; a zero-length segment: ``x_i^k``),
computed without cancellation as ``E[x^k] = sum_{j=0..k} x1^(k-j) x0^j / (k + 1)``.
These are linear, so the projection is the basis kernel (one lane per segment,
scatter-add) with ``f_k(u) = x^k``.

Reconstruction at ``x_f`` (one lane per receiver):
1. normalise and bias toward an interior point of the moment space, the moments of the
   uniform distribution on [-1, 1]:  ``m = (1 - alpha) b / b_0 + alpha (0, 1/3, 0, 1/5)``;
2. solve ``B c = (1, x_f, x_f^2)`` with the Hankel matrix ``B = [m_{i+j}]`` (LDL^T);
3. the roots ``z_2 <= z_3`` of ``c_0 + c_1 z + c_2 z^2`` and ``x_f`` carry the canonical
   3-point distribution with these moments; its weights (Lagrange, moments 0..2) give
   the sharp bounds of the absorbance fraction in front of ``x_f``:
   ``L = sum_{z_i < x_f} w_i``, ``U = L + w_f`` (Chebyshev-Markov-Stieltjes);
4. ``D = b_0 clamp(L + beta w_f, 0, 1)`` with ``beta`` = ``overestimation`` (0: the lower
   bound, light; 1: the upper bound, dark; MBOIT uses 0.25), ``T = exp(-D)``.
``T = 1`` at and in front of near, ``T = exp(-b_0)`` at and behind far (exact there).

Parameters: ``bias`` alpha (default 1e-5 in float32, 1e-9 in float64: keeps ``B``
positive definite under rounding), ``overestimation`` beta in [0, 1], ``near``, ``far``,
``depth_range`` as for every basis.  ``monotone``: the bounds are non-decreasing in
exact arithmetic, but the float reconstruction is not guaranteed to be, so False.
``nbytes_per_texel`` = 5 itemsize (+ 2 itemsize per-texel range).
"""
from __future__ import annotations

import drjit as dr

from .registry import register
from .basis import Basis, BasisRepresentation, register_basis
from .schema import Param, Schema, depth_range_param, far_param, near_param

#: Moments of the uniform distribution on [-1, 1] (k = 1..4): the bias target.
UNIFORM_MOMENTS = (0.0, 1.0 / 3.0, 0.0, 1.0 / 5.0)
DEFAULT_BIAS = {"float32": 1e-5, "float64": 1e-9}


@register_basis("power_moments")
class PowerMomentBasis(Basis):
    """f_k(u) = (2u - 1)^k, k = 0..n (n power moments plus the total; not orthonormal:
    only the projection is used)."""

    def __init__(self, n: int = 4, arg: str = "moments"):
        super().__init__(n, arg)

    @property
    def n_coefficients(self) -> int:
        return self.n + 1

    def f(self, u):
        x = 2 * u - 1
        out = [1 + 0 * x]
        for _ in range(self.n):
            out.append(out[-1] * x)
        return out

    def F(self, u):
        x, p = 2 * u - 1, self.f(u)
        return [(p[k] * x - (-1) ** (k + 1)) * (0.5 / (k + 1)) for k in range(self.n + 1)]

    def average(self, u0, u1):
        p0, p1 = self.f(u0), self.f(u1)          # powers of x0 = 2 u0 - 1, x1 = 2 u1 - 1
        return [sum(p1[k - j] * p0[j] for j in range(k + 1)) * (1 / (k + 1))
                for k in range(self.n + 1)]


def hamburger4(b0, b1, b2, b3, b4, xf, alpha, beta):
    """Bound-based optical depth in front of ``xf`` from 4 power moments (module
    docstring, steps 1-4).  All arguments Dr.Jit arrays (or floats for alpha, beta).
    Returns (D, L, U): optical depth and the lower / upper absorbance-fraction bounds."""
    empty = b0 <= 0
    inv = 1 / dr.select(empty, 1, b0)
    m1 = (1 - alpha) * b1 * inv + alpha * UNIFORM_MOMENTS[0]
    m2 = (1 - alpha) * b2 * inv + alpha * UNIFORM_MOMENTS[1]
    m3 = (1 - alpha) * b3 * inv + alpha * UNIFORM_MOMENTS[2]
    m4 = (1 - alpha) * b4 * inv + alpha * UNIFORM_MOMENTS[3]
    # ---- LDL^T of B = [[1, m1, m2], [m1, m2, m3], [m2, m3, m4]], solve B c = (1, x, x^2)
    # The biased B >= alpha B_uniform (PSD order), so its pivots are at least alpha times
    # the uniform ones (1/3, 4/45): those floors hold in exact arithmetic and keep
    # rounding from making them vanish or turn negative.
    D1 = dr.maximum(m2 - m1 * m1, alpha / 3)
    L21 = (m3 - m1 * m2) / D1
    D2 = dr.maximum(m4 - m2 * m2 - L21 * L21 * D1, alpha * 4 / 45)
    y1 = xf - m1
    y2 = xf * xf - m2 - L21 * y1
    c2 = y2 / D2
    c1 = y1 / D1 - L21 * c2
    c0 = 1 - m1 * c1 - m2 * c2
    # ---- roots of c0 + c1 z + c2 z^2 (stable form; a vanishing c2 sends one root far)
    disc = dr.sqrt(dr.maximum(c1 * c1 - 4 * c0 * c2, 0))
    q = -0.5 * (c1 + dr.select(c1 >= 0, disc, -disc))
    q = dr.select(dr.abs(q) > 1e-30, q, 1e-30)
    big = 1e6
    ra = dr.clip(q / dr.select(dr.abs(c2) > 1e-30, c2, 1e-30), -big, big)
    rb = dr.clip(c0 / q, -big, big)
    z2, z3 = dr.minimum(ra, rb), dr.maximum(ra, rb)
    # ---- weights of the canonical representation {xf, z2, z3} (moments 0..2)
    def weight(p, r, s):
        den = (p - r) * (p - s)
        return (m2 - m1 * (r + s) + r * s) / dr.select(dr.abs(den) > 1e-30, den, 1e-30)
    wf = dr.clip(weight(xf, z2, z3), 0, 1)
    w2 = dr.clip(weight(z2, xf, z3), 0, 1)
    lower = dr.select(xf <= z2, 0, dr.select(xf <= z3, w2, 1 - wf))
    lower = dr.clip(lower, 0, 1)
    upper = dr.minimum(lower + wf, 1)
    frac = dr.clip(lower + beta * wf, 0, 1)
    D = dr.select(empty, 0, b0 * frac)
    return D, lower, upper


@register("moments")
class MomentShadowMap(BasisRepresentation):
    """Four power moments of the absorbance with the Hamburger bound (module docstring).
    ``bias`` (alpha), ``overestimation`` (beta, default 0.25), ``near``/``far``,
    ``depth_range`` 'global' | 'texel'."""

    schema = Schema(
        params=(
            Param("bias", "float", None, "alpha: weight of the uniform distribution's moments (default 1e-5 "
                  "in float32, 1e-9 in float64; keeps the Hankel matrix positive definite)",
                  min=0.0, max=1.0, open_min=True, nullable=True),
            Param("overestimation", "float", 0.25, "beta: 0 = lower bound (light), 1 = upper bound (dark)",
                  min=0.0, max=1.0),
            near_param(), far_param(), depth_range_param(),
        ),
        examples=({},),
        headline={},
        summary="4 power moments of the absorbance, Hamburger bound",
        paper="Peters & Klein 2015; Muenstermann et al. 2018",
    )

    def __init__(self, segments, **params):
        super().__init__(segments, **params)
        if self.params["bias"] is None:
            self.params["bias"] = DEFAULT_BIAS[segments.dtype]

    def _make_basis(self):
        return PowerMomentBasis(4)

    def bounds(self, texel, depth):
        """(lower, upper) bounds of the absorbance fraction in front of each receiver
        (Dr.Jit arrays; texel UInt32, depth Float)."""
        return self._reconstruct(texel, depth)[1:]

    def _reconstruct(self, texel, depth):
        return self._bounded(self._store, texel, self.normalized_depth(texel, depth))

    def _bounded(self, store, row, u):
        """(D, lower, upper) from moments read from a flat store ``store[row * 5 + k]``."""
        Float = self.Float
        K = self.basis.n_coefficients
        b = [dr.gather(Float, store, row * K + k) for k in range(K)]
        D, lo, up = hamburger4(*b, 2 * u - 1, self.params["bias"], self.params["overestimation"])
        D = dr.select(u <= 0, 0, dr.select(u >= 1, b[0], D))
        return D, lo, up

    def _reconstruct_from(self, store, row, u):
        return self._bounded(store, row, u)[0]
