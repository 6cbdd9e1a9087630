"""The bases of the linear kinds (:mod:`.basis`): projection functions ``f_k`` on [0, 1],
antiderivatives ``F_k = int_0^u f_k`` and reconstruction integrals ``g_k`` (Jansen and Bavoil
2010, "Fourier Opacity Mapping", I3D, sec. 5), their registry, exactly periodic trigonometry,
and a segment's clipped place on the normalised depth range.  An orthonormal basis needs
``f`` and ``F`` (lists of Dr.Jit arrays, one per coefficient)::

    @register_basis("cosine")
    class CosineBasis(Basis):
        def f(self, u):   # 1, sqrt(2) cos(pi k u)
            return [1 + 0 * u] + [SQRT2 * sincos_pi(k * u)[1] for k in range(1, self.n)]
        def F(self, u):   # u, sqrt(2) sin(pi k u) / (pi k)
            return [u] + [SQRT2 * sincos_pi(k * u)[0] / (math.pi * k) for k in range(1, self.n)]

    rep = ad.build("basis", seg, basis="cosine", n=8)    # or basis=CosineBasis(8)
"""
from __future__ import annotations

import math

import drjit as dr

from .. import validation as V

SQRT2 = math.sqrt(2.0)
#: Segment length (in u) below which Basis.average integrates f by quadrature instead of
#: differencing F (balances eps / du against the quadrature error for ~12 cosines).
SHORT = {"float32": 2e-2, "float64": 2e-3}
#: List path (bases without indexed forms) beyond LIST_UNROLL coefficients: evaluated every
#: LIST_CHUNK coefficients with per-k constants as opaque scalars (one kernel per chunk).
LIST_UNROLL = 32
LIST_CHUNK = 8

BASES: dict[str, type] = {}


def register_basis(name: str):
    """Class decorator adding a :class:`Basis` under ``name`` (for ``basis="name"``)."""
    def deco(cls):
        cls.name = name
        BASES[name] = cls
        return cls
    return deco


# Exactly periodic trigonometry: the argument is reduced before the multiply by pi, so
# integer arguments give sin = 0 exactly (T exact at far, Jansen and Bavoil 2010, eq. 3).
def sincos_pi(y):
    """(sin(pi y), cos(pi y)) with y reduced to r = y - floor(y) in [0, 1) first."""
    n = dr.floor(y)
    r = y - n
    sign = 1 - 2 * (n - 2 * dr.floor(0.5 * n))    # (-1)^n
    s, c = dr.sincos(math.pi * r)
    return sign * s, sign * c


def sinc(x):
    """sin(x) / x for x >= 0; Taylor series to x^12 below 0.1 (error < x^14/15! ~ 1e-26)
    so that neither the value nor its derivative cancels."""
    x2 = x * x
    taylor = 1.0
    for j in (13, 11, 9, 7, 5, 3):      # 1 - x^2/3! + x^4/5! - ... + x^12/13!
        taylor = 1 - x2 * taylor / (j * (j - 1))
    safe = dr.select(x > 0.1, x, 1)
    return dr.select(x > 0.1, dr.sin(safe) / safe, taylor)


class Basis:
    """``n_coefficients`` projection functions on [0, 1] (``n``: the size parameter).

    Subclasses give ``f`` and ``F``, or, when the reconstruction is not ``F``, ``g`` and
    ``average`` (also overridden where a cancellation-free segment mean is known).  Below
    LIST_UNROLL coefficients ``f`` and ``average`` are traced inside the projection's
    per-texel loop (:meth:`BasisRepresentation._sum_per_texel`): no ``dr.eval`` there.
    """

    name = "base"
    #: True when every a_k >= 0 for tau >= 0 and every g_k is non-decreasing (T monotone).
    monotone = False
    #: True when the subclass gives the indexed forms ``f_at`` / ``F_at`` (closed forms in
    #: the coefficient index): projection and reconstruction then run over (item,
    #: coefficient) lanes, a trace whose size does not depend on K (module docstring).
    indexed = False

    #: The size parameter's name in messages.
    arg = "n"

    def __init__(self, n: int):
        self.n = V.integer(n, self.arg, 1)

    @property
    def n_coefficients(self) -> int:
        return self.n

    def f(self, u) -> list:
        """Projection functions f_k(u)."""
        raise NotImplementedError

    def F(self, u) -> list:
        """Antiderivatives F_k(u) = int_0^u f_k."""
        raise NotImplementedError

    def g(self, u) -> list:
        """Reconstruction integrals, D(u) = sum_k a_k g_k(u); orthonormal: g = F."""
        return self.F(u)

    def average(self, u0, u1) -> list:
        """Mean of f_k over [u0, u1] (u0 <= u1): (F_k(u1) - F_k(u0)) / (u1 - u0), or, for
        segments shorter than SHORT (where the quotient loses eps / du), 3-point
        Gauss-Legendre on f (error ~ du^6 f^(6) / 2e6; = f(u0) when u1 = u0, the delta)."""
        du = u1 - u0
        big = du > (SHORT["float32"] if dr.type_v(du) == dr.VarType.Float32 else SHORT["float64"])
        safe = dr.select(big, du, 1)
        F0, F1 = self.F(u0), self.F(u1)
        m, h = 0.5 * (u0 + u1), (0.5 * math.sqrt(0.6)) * du
        fl, fm, fr = self.f(m - h), self.f(m), self.f(m + h)
        return [dr.select(big, (b - a) / safe, (5 * p + 8 * q + 5 * r) * (1 / 18))
                for a, b, p, q, r in zip(F0, F1, fl, fm, fr)]

    # ---- indexed forms: ``j`` a UInt32 array of coefficient indices, one per lane of u
    def f_at(self, j, u):
        """f_j(u), lane by lane (indexed bases only)."""
        raise NotImplementedError

    def F_at(self, j, u):
        """F_j(u), lane by lane (indexed bases only)."""
        raise NotImplementedError

    def g_at(self, j, u):
        """g_j(u), lane by lane (default F_j)."""
        return self.F_at(j, u)

    def average_at(self, j, u0, u1):
        """Mean of f_j over [u0, u1], lane by lane: the formula of :meth:`average`."""
        du = u1 - u0
        big = du > (SHORT["float32"] if dr.type_v(du) == dr.VarType.Float32 else SHORT["float64"])
        safe = dr.select(big, du, 1)
        m, h = 0.5 * (u0 + u1), (0.5 * math.sqrt(0.6)) * du
        quad = (5 * self.f_at(j, m - h) + 8 * self.f_at(j, m) + 5 * self.f_at(j, m + h)) * (1 / 18)
        return dr.select(big, (self.F_at(j, u1) - self.F_at(j, u0)) / safe, quad)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.n})"


@register_basis("cosine")
class CosineBasis(Basis):
    """Cosine (DCT-like) basis, orthonormal on [0, 1]: f_0 = 1, f_k = sqrt(2) cos(pi k u),
    k < n.  F_k(1) = 0 for k >= 1, so T(far) = exp(-total tau) exactly."""

    def f(self, u):
        return [1 + 0 * u] + [SQRT2 * sincos_pi(k * u)[1] for k in range(1, self.n)]

    def F(self, u):
        return [u + 0] + [SQRT2 / (math.pi * k) * sincos_pi(k * u)[0] for k in range(1, self.n)]

    indexed = True

    def f_at(self, j, u):
        k = type(u)(j)
        return dr.select(j == 0, 1.0, SQRT2 * sincos_pi(k * u)[1])

    def F_at(self, j, u):
        k = type(u)(j)
        return dr.select(j == 0, u, (SQRT2 / math.pi) / dr.maximum(k, 1) * sincos_pi(k * u)[0])


@register_basis("legendre")
class LegendreBasis(Basis):
    """Shifted Legendre polynomials, orthonormal on [0, 1]: f_k = sqrt(2k+1) P_k(2u - 1),
    k < n;  F_k = (P_{k+1}(x) - P_{k-1}(x)) / (2 sqrt(2k+1)) (k >= 1), F_0 = u.
    P_k(+-1) = (+-1)^k exactly, so T(near) = 1 and T(far) = exp(-total tau)."""

    def _const(self, u):
        """Per-k constants as literals, or, beyond LIST_UNROLL coefficients, as opaque
        scalars: every chunk of the recurrence is then the same kernel (compiled once)."""
        if self.n + 1 > LIST_UNROLL:
            return lambda v: dr.opaque(type(u), v)
        return lambda v: v

    def _legendre(self, u, m):
        x = 2 * u - 1
        c = self._const(u)
        p = [1 + 0 * x, x + 0]
        for k in range(1, m - 1):       # (k+1) P_{k+1} = (2k+1) x P_k - k P_{k-1}
            p.append((c(2 * k + 1) * x * p[k] - c(k) * p[k - 1]) * c(1 / (k + 1)))
            if m > LIST_UNROLL and k % LIST_CHUNK == 0:
                dr.eval(p[k], p[k + 1])   # bounded kernels: the chain is not recomputed
        return p[:m]

    def f(self, u):
        p, c = self._legendre(u, self.n), self._const(u)
        return [c(math.sqrt(2 * k + 1)) * p[k] for k in range(self.n)]

    def F(self, u):
        p, c = self._legendre(u, self.n + 1), self._const(u)
        return [u + 0] + [(p[k + 1] - p[k - 1]) * c(0.5 / math.sqrt(2 * k + 1))
                          for k in range(1, self.n)]


#: Registered projection-only bases (no reconstruction integrals) and the build that uses them.
PROJECTION_ONLY = {"trigonometric_moments": "build('moments', segments, family='trigonometric', moments=n)"}


def _reconstructs(cls) -> bool:
    """True when ``cls`` has the reconstruction integrals (``g``/``F``) the ``basis`` kind needs."""
    return cls.indexed or cls.F is not Basis.F or cls.g is not Basis.g


def _check_reconstructs(cls, what: str) -> None:
    if not _reconstructs(cls):
        use = PROJECTION_ONLY.get(getattr(cls, "name", ""), "the kind that defines it")
        raise ValueError(f"basis: {what} has projection functions only (no reconstruction integrals F), "
                         f"so the basis kind cannot use it; use {use}")


def make_basis(basis, n=None) -> Basis:
    """A Basis from an instance, or a registered name with size ``n``."""
    usable = sorted(k for k, c in BASES.items() if _reconstructs(c))
    if isinstance(basis, Basis):
        if n is not None:
            raise ValueError("n: give n= only with a basis name, not with a Basis instance")
        _check_reconstructs(type(basis), type(basis).__name__)
        return basis
    if isinstance(basis, str):
        if basis not in BASES:
            raise ValueError(f"basis: unknown basis {basis!r}; known: {usable}")
        _check_reconstructs(BASES[basis], repr(basis))
        if n is None:
            raise ValueError(f"n: basis {basis!r} needs its size n=")
        return BASES[basis](n)
    raise ValueError(f"basis: expected a Basis instance or one of {usable}, got {basis!r}")


def clip_segment(z0, z1, tau, near, span):
    """(c0, c1, tau_in, tau_front) of segments [z0, z1] with optical depth tau against the
    range [near, near + span]: normalised depths clipped to [0, 1], the optical depth inside
    the range and in front of near (behind far: dropped).  Both projection paths call it,
    so their contributions are the same float operations."""
    u0 = (z0 - near) / span                     # normalised entry depth
    u1 = (z1 - near) / span                     # normalised exit depth
    c0, c1 = dr.clip(u0, 0, 1), dr.clip(u1, 0, 1)
    du = u1 - u0
    safe = dr.select(du > 0, du, 1)
    inside = dr.select(du > 0, (c1 - c0) / safe, dr.select((u0 >= 0) & (u0 <= 1), 1, 0))
    front = dr.select(du > 0, (dr.minimum(u1, 0) - dr.minimum(u0, 0)) / safe, dr.select(u0 < 0, 1, 0))
    return c0, c1, tau * inside, tau * front
