"""Fourier opacity maps (Jansen and Bavoil 2010, "Fourier Opacity Mapping", I3D, eqs. 1-6).

With ``n`` harmonics a texel stores ``2n + 1`` coefficients, in the paper's
packing order ``[a'_0, a'_1, b'_1, ..., a'_n, b'_n]`` (Jansen and Bavoil 2010, fig. 2)::

    a'_k = 2 int_0^1 sigma(u) cos(2 pi k u) du                                   (1)
    b'_k = 2 int_0^1 sigma(u) sin(2 pi k u) du                                   (2)
    D(u) = a'_0 u / 2 + sum_k [a'_k sin(2 pi k u) + b'_k (1 - cos(2 pi k u))] / (2 pi k)  (3)
    T(u) = clamp(exp(-D(u)), 0, 1)                                               (sec. 7.3)

A segment ``[u0, u1]`` with optical depth ``tau`` adds (eqs. 5, 6 are its zero-length limit)
``a'_k += 2 tau cos(2 pi k m) sinc(pi k du)``, ``b'_k += 2 tau sin(2 pi k m) sinc(pi k du)``,
``m = (u0 + u1) / 2``, ``du = u1 - u0`` (no cancellation).  Angles are reduced before the
multiply by pi (:func:`~.basis_functions.sincos_pi`): ``T(near) = 1`` and
``T(far) = exp(-a'_0 / 2) = exp(-sum tau)`` to rounding of the sum.  Reconstruction rings
(``monotone = False``) and is clamped to [0, 1]; depth range and layout as :mod:`.basis`.
"""
from __future__ import annotations

import math

import drjit as dr

from .. import backend
from .registry import register
from ._loops import texel_lanes
from .basis import MAX_COEFFICIENTS, BasisRepresentation
from .basis_functions import Basis, clip_segment, register_basis, sinc, sincos_pi
from .schema import DEPTH_RANGE, FAR, NEAR, Param, Schema


@register_basis("fourier")
class FourierBasis(Basis):
    """The paper's Fourier basis with ``n`` harmonics (2n + 1 coefficients, eqs. 1-3):
    f = [2, 2 cos(2 pi k u), 2 sin(2 pi k u)],  g = [u/2, sin(2 pi k u)/(2 pi k),
    (1 - cos(2 pi k u))/(2 pi k)] (biorthogonal pair: int f_j g_k' = delta_jk)."""

    arg = "harmonics"

    @property
    def n_coefficients(self) -> int:
        return 2 * self.n + 1

    def f(self, u):
        return [2 + 0 * u] + [2 * x for k in range(1, self.n + 1) for x in sincos_pi(2 * k * u)[::-1]]

    def g(self, u):
        # sin(2x) = 2 sin(x) cos(x),  1 - cos(2x) = 2 sin(x)^2  (x = pi k u, no cancellation)
        out = [0.5 * u]
        for k in range(1, self.n + 1):
            s, c = sincos_pi(k * u)
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

    def g_at(self, j, u):
        k, is_b = self._harmonic(j, u)
        s, c = sincos_pi(k * u)
        return dr.select(j == 0, 0.5 * u, (1 / math.pi) / dr.maximum(k, 1) * s * dr.select(is_b, s, c))

    def average_at(self, j, u0, u1):
        k, is_b = self._harmonic(j, u0)
        s, c = sincos_pi(2 * k * (0.5 * (u0 + u1)))
        w = 2 * sinc(math.pi * k * (u1 - u0))
        return dr.select(j == 0, 2.0, w * dr.select(is_b, s, c))


#: Harmonics per unrolled block of the lookup (:meth:`FourierOpacityMap._reconstruct_from`):
#: beyond it one kernel reused for every block and every n (opaque indices).
LOOKUP_UNROLL_HARMONICS = 32

#: Most harmonics built by the one-lane-per-texel recurrence (its body is unrolled over k).
RECURRENCE_HARMONICS = 16


@register("fom")
class FourierOpacityMap(BasisRepresentation):
    """Fourier opacity map: n ``harmonics``, ``coefficients`` in the paper's packing order."""

    schema = Schema(
        params=(
            Param("harmonics", "int", 3, "n harmonics: 2n + 1 coefficients per texel (the paper's 7: n = 3)",
                  min=1, max=(MAX_COEFFICIENTS - 1) // 2),
            NEAR, FAR, DEPTH_RANGE,
        ),
        size="harmonics", sweep=(1, 2, 3, 4, 6, 8, 12, 16), quick_sweep=(1, 4, 8, 16),
        examples=({"harmonics": 4}, {"harmonics": 3, "depth_range": "texel"}),
        headline={"harmonics": 4},
        summary="2n+1 Fourier coefficients of the absorption",
        paper="Jansen & Bavoil 2010")

    def _make_basis(self):
        return FourierBasis(self.params["harmonics"])

    def _build_bytes(self, K: int) -> float:
        """The recurrence path (:meth:`_project_texels`): K sums per texel lane and the store;
        otherwise the base class' estimate."""
        seg = self.segments
        if seg.Float is backend.types().Float32 and not seg.requires_grad and (K - 1) // 2 <= RECURRENCE_HARMONICS:
            return 3.0 * seg.itemsize * seg.n_texels * K
        return super()._build_bytes(K)

    def _project_texels(self):
        """Float32 segments: one lane per non-empty texel, its 2n + 1 sums in registers.  Per
        segment (midpoint m, width du, angles a = 2 pi m, h = pi du) the float64 sincos of a
        and h (exact argument reduction, :func:`sincos_pi`) are rounded to float32 once, then
        float32 recurrences over k = 1..n (angle addition; Chebyshev U for sin(k h) / sin(h)):

            e^{ika} = e^{i(k-1)a} e^{ia},   q_k = q_{k-1} cos h + cos((k-1) h),
            cos(k h) = cos((k-1) h) cos h - q_{k-1} sin(h)^2,   sinc(k h) = q_k sinc(h) / k

        (q_k = sin(k h) / sin(h), finite at h = 0; sinc(h) in float64, :func:`sinc`): errors
        ~3.6 k eps (Higham 2002, sec. 3.6).  Float64 segments and more than
        :data:`RECURRENCE_HARMONICS` harmonics keep the base class' lanes."""
        seg = self.segments
        if seg.Float is not backend.types().Float32 or self.basis.n > RECURRENCE_HARMONICS:
            return super()._project_texels()
        Float = seg.Float
        Float64 = dr.float64_array_t(Float)
        T, n = seg.n_texels, self.basis.n
        K = 2 * n + 1
        flat = dr.zeros(Float, T * K)
        texel, first, stop = texel_lanes(seg)
        z0, z1, tau = seg.z0, seg.z1, seg.optical_depth
        near, span = self._range(texel if self._per_texel else None)

        def body(i, *acc):
            c0, c1, t_in, t_front = clip_segment(dr.gather(Float, z0, i), dr.gather(Float, z1, i),
                                                 dr.gather(Float, tau, i), near, span)
            du = Float64(c1 - c0)
            sa, ca = (Float(x) for x in sincos_pi(Float64(c0 + c1)))      # a = 2 pi m
            sh, ch = (Float(x) for x in sincos_pi(du))                   # h = pi du
            sinc_h = Float(sinc(math.pi * du))
            sh2 = sh * sh
            w_in, w_front = 2 * t_in, 2 * t_front
            out = [acc[0] + (w_in + w_front)]
            ck, sk, qk, chk = ca, sa, Float(1), ch              # k = 1: e^{ia}, q_1 = 1, cos h
            for k in range(1, n + 1):
                w = w_in * (sinc_h * qk) * (1 / k)
                out += [acc[2 * k - 1] + (w * ck + w_front), acc[2 * k] + w * sk]
                if k < n:
                    ck, sk = ck * ca - sk * sa, sk * ca + ck * sa
                    qk, chk = qk * ch + chk, chk * ch - qk * sh2
            return (i + 1, *out)

        state = (first, *[dr.zeros(Float, dr.width(texel)) for _ in range(K)])
        _, *acc = dr.while_loop(state, lambda i, *acc: i < stop, body, label="fom_project")
        dr.eval(*acc)       # one loop kernel (each scatter into flat would otherwise re-run it)
        for k in range(K):
            dr.scatter(flat, acc[k], texel * K + k)
        dr.eval(flat)
        return flat

    def _reconstruct_from(self, store, row, u):
        """D(u) (eq. 3) with one lane per receiver: one ``sincos`` of the half angle x = pi u
        (:func:`sincos_pi`, in the map's dtype: float32 unless it is float64), then the
        angle-addition recurrence (the Numba / Warp peers' lookup)::

            e^{i(k+1)x} = e^{ikx} e^{ix},   D = a'_0 u / 2 + sum_k (a'_k cos(kx) + b'_k sin(kx)) sin(kx) / (pi k)

        (sin(2 kx) = 2 sin(kx) cos(kx), 1 - cos(2 kx) = 2 sin(kx)^2: no cancellation); each
        term's error below (2 delta / pi) (|a'_k| + |b'_k|), delta ~ 12 u_r (Higham 2002, sec.
        3.6).  u = 0 and u = 1 are exact: T(near) = 1, T(far) = exp(-a'_0 / 2).  Blocks of
        :data:`LOOKUP_UNROLL_HARMONICS` beyond it; no symbolic loop (both AD modes)."""
        Float, UInt32 = self.Float, backend.types().UInt32
        n, L = self.basis.n, LOOKUP_UNROLL_HARMONICS
        blocks = n > L
        K = dr.opaque(UInt32, 2 * n + 1) if blocks else 2 * n + 1
        base = row * K
        s1, c1 = sincos_pi(u)                       # sin, cos of x = pi u
        D = dr.gather(Float, store, base) * (0.5 * u)
        sk, ck = s1, c1                             # sin, cos of k x (k = 1)
        for k0 in range(1, n + 1, L):
            if k0 > 1 and not dr.flag(dr.JitFlag.SymbolicScope):
                dr.eval(D, sk, ck, s1, c1, base)    # one kernel per block
            first = dr.opaque(UInt32, k0) if blocks else None
            for i in range(min(L, n - k0 + 1) if not blocks else L):
                # blocks: opaque k, the same kernel for every block and n
                k = first + i if blocks else k0 + i
                w = 1 / (math.pi * Float(k)) if blocks else 1 / (math.pi * k)
                on = k <= dr.opaque(UInt32, n) if blocks else True
                a = dr.gather(Float, store, base + (2 * k - 1), on)
                b = dr.gather(Float, store, base + 2 * k, on)
                D += (a * ck + b * sk) * (sk * w)
                sk, ck = sk * c1 + ck * s1, ck * c1 - sk * s1
        return D
