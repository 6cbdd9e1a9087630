"""Fourier opacity maps (Jansen and Bavoil 2010, "Fourier Opacity Mapping", I3D, eqs. 1-6).

With ``n`` harmonics a texel stores ``2n + 1`` coefficients, in the paper's
packing order ``[a'_0, a'_1, b'_1, ..., a'_n, b'_n]`` (Jansen and Bavoil 2010, fig. 2):

    a'_k = 2 int_0^1 sigma(u) cos(2 pi k u) du                                   (1)
    b'_k = 2 int_0^1 sigma(u) sin(2 pi k u) du                                   (2)
    D(u) = a'_0 u / 2 + sum_k [a'_k sin(2 pi k u) + b'_k (1 - cos(2 pi k u))] / (2 pi k)  (3)
    T(u) = clamp(exp(-D(u)), 0, 1)                                               (sec. 7.3)

Segments are integrated analytically, not as points (eqs. 5, 6 are the
zero-length limit): a segment ``[u0, u1]`` with optical depth ``tau`` adds

    a'_k += 2 tau cos(2 pi k m) sinc(pi k du),   b'_k += 2 tau sin(2 pi k m) sinc(pi k du)

with ``m = (u0 + u1) / 2``, ``du = u1 - u0`` (the segment mean of ``2 cos(2 pi k u)``
written without cancellation).  Every angle is reduced before it is multiplied by pi
(:func:`~avsm_dr.representations.basis.sincos_pi`), so ``T(near) = 1`` and
``T(far) = exp(-a'_0 / 2) = exp(-sum tau)`` hold to float rounding of the sum.

Reconstruction rings (``monotone = False``) and is clamped to [0, 1].  Depth range,
clipping and kernel layout: see :mod:`avsm_dr.representations.basis`.
"""
from __future__ import annotations

import math

import drjit as dr

from .registry import register
from .basis import Basis, BasisRepresentation, register_basis, sinc, sincos_pi
from .schema import Param, Schema, depth_range_param, far_param, near_param


@register_basis("fourier")
class FourierBasis(Basis):
    """The paper's Fourier basis with ``n`` harmonics (2n + 1 coefficients, eqs. 1-3):
    f = [2, 2 cos(2 pi k u), 2 sin(2 pi k u)],  g = [u/2, sin(2 pi k u)/(2 pi k),
    (1 - cos(2 pi k u))/(2 pi k)] (biorthogonal pair: int f_j g_k' = delta_jk)."""

    def __init__(self, n: int, arg: str = "harmonics"):
        super().__init__(n, arg)

    @property
    def n_coefficients(self) -> int:
        return 2 * self.n + 1

    def _half_angles(self, u):
        """(sin(pi k u), cos(pi k u)) for k = 1..n."""
        return [sincos_pi(k * u) for k in range(1, self.n + 1)]

    def f(self, u):
        out = [2 + 0 * u]
        for k in range(1, self.n + 1):
            s, c = sincos_pi(2 * k * u)
            out += [2 * c, 2 * s]
        return out

    def F(self, u):
        out = [2 * u]
        for k, (s, c) in enumerate(self._half_angles(u), start=1):
            out += [(2 / (math.pi * k)) * s * c, (2 / (math.pi * k)) * s * s]
        return out

    def g(self, u):
        # sin(2x) = 2 sin(x) cos(x),  1 - cos(2x) = 2 sin(x)^2  (x = pi k u, no cancellation)
        out = [0.5 * u]
        for k, (s, c) in enumerate(self._half_angles(u), start=1):
            out += [(1 / (math.pi * k)) * s * c, (1 / (math.pi * k)) * s * s]
        return out

    def average(self, u0, u1):
        m, du = 0.5 * (u0 + u1), u1 - u0
        out = [2 + 0 * m]
        for k in range(1, self.n + 1):
            s, c = sincos_pi(2 * k * m)
            w = 2 * sinc(math.pi * k * du)
            out += [w * c, w * s]
        return out

    # ---- indexed forms (coefficient j of [a'_0, a'_1, b'_1, ...]: harmonic (j + 1) // 2)
    indexed = True

    @staticmethod
    def _harmonic(j, u):
        """(k as a float array, True for a b'_k coefficient) of coefficient index j."""
        return type(u)((j + 1) >> 1), (j > 0) & ((j & 1) == 0)

    def f_at(self, j, u):
        k, is_b = self._harmonic(j, u)
        s, c = sincos_pi(2 * k * u)
        return dr.select(j == 0, 2.0, 2 * dr.select(is_b, s, c))

    def F_at(self, j, u):
        k, is_b = self._harmonic(j, u)
        s, c = sincos_pi(k * u)
        return dr.select(j == 0, 2 * u, (2 / math.pi) / dr.maximum(k, 1) * s * dr.select(is_b, s, c))

    def g_at(self, j, u):
        k, is_b = self._harmonic(j, u)
        s, c = sincos_pi(k * u)
        return dr.select(j == 0, 0.5 * u, (1 / math.pi) / dr.maximum(k, 1) * s * dr.select(is_b, s, c))

    def average_at(self, j, u0, u1):
        k, is_b = self._harmonic(j, u0)
        s, c = sincos_pi(2 * k * (0.5 * (u0 + u1)))
        w = 2 * sinc(math.pi * k * (u1 - u0))
        return dr.select(j == 0, 2.0, w * dr.select(is_b, s, c))


@register("fom")
class FourierOpacityMap(BasisRepresentation):
    """Fourier opacity map: ``harmonics`` n >= 1 (default 3, the paper's 7 coefficients),
    ``near``/``far`` (default: global bounds of the segments), ``depth_range``
    'global' | 'texel'.  ``nbytes_per_texel`` = (2n + 1) itemsize (+ 2 itemsize per-texel
    range).  Coefficients: ``a[k]`` = a'_k (k = 0..n), ``b[k]`` = b'_k (k = 1..n, b[0] = None)."""

    schema = Schema(
        params=(
            Param("harmonics", "int", 3, "n harmonics: 2n + 1 coefficients per texel (the paper's 7: n = 3)",
                  min=1),
            near_param(), far_param(), depth_range_param(),
        ),
        size="harmonics", sweep=(1, 2, 3, 4, 6, 8, 12, 16), quick_sweep=(1, 4, 8, 16),
        examples=({"harmonics": 4}, {"harmonics": 3, "depth_range": "texel"}),
        headline={"harmonics": 4},
        summary="2n+1 Fourier coefficients of the absorption",
        paper="Jansen & Bavoil 2010",
    )

    def _make_basis(self):
        return FourierBasis(self.params["harmonics"])

    @property
    def a(self) -> list:
        return [self.coefficients[0]] + self.coefficients[1::2]

    @property
    def b(self) -> list:
        return [None] + self.coefficients[2::2]
