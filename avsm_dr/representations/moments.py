"""Moment-based transmittance: 4, 6 or 8 power moments of the absorbance with the
Hamburger bound (Peters and Klein 2015, "Moment Shadow Mapping", algorithm 2; Peters et al.
2016/2017, "Beyond Hard Shadows", I3D / JCGT; Muenstermann, Krumpen, Klein, Peters 2018,
"Moment-Based Order-Independent Transparency" (MBOIT), secs. 3-4, on optical depth as there).

Depth warp (``warp=``): ``u = (z - near) / (far - near)`` ('linear') or
``u = (ln z - ln near) / (ln far - ln near)`` ('log', MBOIT's; needs ``near > 0``), ranges and
clipping as :mod:`.basis`; then ``x = 2 u - 1`` in [-1, 1].  A texel stores ``2n + 1`` values
(``moments = 2n``) ::

    b_0 = sum_i tau_i,    b_k = sum_i tau_i E_i[x^k]  (k = 1..2n),

``E_i`` the mean over segment ``i`` with its optical depth uniform in ``z`` (a zero-length
segment: ``x_i^k``).

* linear warp: ``E[x^k] = sum_{j=0..k} x1^(k-j) x0^j / (k + 1)`` (no cancellation);
* log warp: uniform in z is the density ``~ e^{lambda x}`` in x (``lambda =
  (ln far - ln near) / 2``), so with ``x = mid + h tau``, ``tau`` in [-1, 1],
  ``E[x^k] = sum_j C(k, j) mid^(k-j) h^j mu_j(kappa)``, ``kappa = lambda h`` and
  ``mu_j(kappa) = int tau^j e^{kappa tau} / int e^{kappa tau}``: for ``kappa < KAPPA_SWITCH``
  the positive series ``int_{-1}^{1} tau^j e^{kappa tau} = sum_{i + j even} kappa^i / i!
  2 / (i + j + 1)``, else the recurrence ``mu_j = c_j - (j / kappa) mu_{j-1}`` (``c_j = 1``
  for even j, ``coth kappa`` for odd j; its error grows by ``prod_{i<=j} i / kappa < 1``).

Reconstruction: :func:`._moment_bounds.hankel_bound` with bias ``alpha`` and
``beta = overestimation`` (0: the lower bound, light; 1: the upper bound, dark; MBOIT: 0.25),
``T = exp(-D)``; ``T = 1`` at and in front of near, ``T = exp(-b_0)`` at and behind far.

Bias (``bias`` alpha, ``bias_target`` m*): target :data:`MBOIT_TARGET` (positive definite
Hankel matrices, checked at import; :data:`UNIFORM_TARGET`: the uniform distribution's);
alpha by storage precision (``self.precision``, else the segments' dtype) from
:data:`DEFAULT_BIAS` (MBOIT's 32-bit / 16-bit values; float64 and unorm8 ours),
:data:`MSM_UNORM16_BIAS` for 'msm' in 'unorm16'; trigonometric: :data:`DEFAULT_TRIG_BIAS`.

16-bit storage (``quantization``, 4 power moments in 'float16' / 'unorm16'): 'scaled' codes
the moments over the per-texel scale ``b_0`` (:mod:`._precision`); 'msm' (default in 'unorm16')
the optimised transform of Peters and Klein 2015, sec. 5 (Peters, Muenstermann, Wetzstein and
Klein 2017, JCGT): for a texel's normalised moments of ``u``, ``mu = (E u, .., E u^4)``, it
stores ``q = mu @ MSM_MATRIX + MSM_OFFSET`` (row vectors, the published constants; every
point moment vector ``(z, .., z^4)``, z in [0, 1], maps into [0, 1]^4, so by convexity every
distribution does), from ``E u^j = 2^-j sum_k C(j, k) E x^k`` and back by
``E x^k = sum_j C(k, j) 2^j (-1)^(k-j) E u^j`` (:func:`encode_msm`).  Family
'trigonometric' (n = 2, 3, 4 complex moments, 2n + 1 reals): :mod:`._trig_moments`.
``monotone`` False (the bounds are non-decreasing in exact arithmetic only).
"""
from __future__ import annotations

import math

import drjit as dr
import numpy as np

from . import _trig_moments as TM
from ._moment_bounds import hankel_bound, hankel_pivots
from ._precision import quantise, round_unit, to_device, to_host
from .basis import MIN_SPAN_REL, BasisRepresentation
from .basis_functions import Basis, clip_segment, register_basis
from .registry import register
from .schema import DEPTH_RANGE, FAR, NEAR, Param, Schema

FAMILIES = {"power": (4, 6, 8), "trigonometric": (2, 3, 4)}
WARPS = ("linear", "log")
#: MBOIT's float32 bias targets m*_1..m*_2n by moment count (module docstring).
MBOIT_TARGET = {4: (0.0, 0.375, 0.0, 0.375),
                6: (0.0, 0.48, 0.0, 0.451, 0.0, 0.45),
                8: (0.0, 0.75, 0.0, 0.67666666666666664, 0.0, 0.63, 0.0, 0.60030303030303034)}
#: Moments of the uniform distribution on [-1, 1].
UNIFORM_TARGET = {n: tuple(0.0 if k % 2 else 1.0 / (k + 1) for k in range(1, n + 1)) for n in (4, 6, 8)}
#: Default alpha by moment count and storage (MBOIT's 32-bit, 16-bit; module docstring).
_MBOIT_ALPHA = {4: (5e-7, 6e-5), 6: (5e-6, 6e-4), 8: (5e-5, 2.5e-3)}
_FLOAT64_ALPHA = {4: 1e-9, 6: 1e-8, 8: 1e-7}
DEFAULT_BIAS = {n: {"float32": a32, "float16": a16, "unorm16": a16, "unorm8": min(a16 * 256, 0.5),
                    "float64": _FLOAT64_ALPHA[n]} for n, (a32, a16) in _MBOIT_ALPHA.items()}
#: Trigonometric moments: 32-bit and 16-bit alpha as transcribed for MBOIT (not corroborated).
_MBOIT_TRIG_ALPHA = {2: (4e-7, 4e-4), 3: (4e-7, 6.5e-4), 4: (4e-7, 8.5e-4)}
DEFAULT_TRIG_BIAS = {n: {"float32": a32, "float16": a16, "unorm16": a16, "unorm8": min(a16 * 256, 0.5),
                         "float64": 1e-9} for n, (a32, a16) in _MBOIT_TRIG_ALPHA.items()}
#: Storage where 4 power moments default to the MSM transform, and its default alpha (ours).
MSM_DEFAULT_PRECISION = "unorm16"
MSM_UNORM16_BIAS = 5e-6
#: Below this kappa = ln(z1 / z0) / 2 the log-warp segment means use the series.
KAPPA_SWITCH = 4.0
_SERIES_TERMS = {"float32": 12, "float64": 17}     # terms in kappa^2

for _n, _t in MBOIT_TARGET.items():                 # positive definite (raises otherwise)
    hankel_pivots(_t)

#: MSM transform (module docstring; Peters and Klein 2015, sec. 5), row-vector convention
#: q = mu @ M + c, and its inverse in float64.
MSM_MATRIX = np.array([[-2.07224649, 13.7948857237, 0.105877704, 9.7924062118],
                       [32.23703778, -59.4683975703, -1.9077466311, -33.7652110555],
                       [-68.571074599, 82.0359750338, 9.3496555107, 47.9456096605],
                       [39.3703274134, -35.364903257, -6.6543490743, -23.9728048165]])
MSM_OFFSET = np.array([0.035955884801, 0.0, 0.0, 0.0])
MSM_INVERSE = np.linalg.inv(MSM_MATRIX)
#: Storage precisions the transform applies to (16-bit codes), the ``quantization`` values.
MSM_PRECISIONS = ("float16", "unorm16")
QUANTIZATIONS = ("scaled", "msm")
#: Bytes per texel: four 16-bit codes and b_0 in float32.
MSM_BYTES = 4 * 2 + 4
# x -> u and u -> x moment maps as (5, 5) matrices on (1, m_1, .., m_4) (row vectors)
_X_TO_U = np.array([[math.comb(j, k) * 2.0 ** -j if k <= j else 0.0 for j in range(5)] for k in range(5)])
_U_TO_X = np.array([[math.comb(k, j) * 2.0 ** j * (-1.0) ** (k - j) if j <= k else 0.0 for k in range(5)]
                    for j in range(5)])


def x_to_u(m: np.ndarray) -> np.ndarray:
    """(..., 4) moments E x^k, k = 1..4 -> E u^j, j = 1..4 (u = (x + 1) / 2)."""
    m = np.asarray(m, np.float64)
    return (np.concatenate([np.ones(m.shape[:-1] + (1,)), m], axis=-1) @ _X_TO_U)[..., 1:]


def u_to_x(mu: np.ndarray) -> np.ndarray:
    """(..., 4) moments E u^j -> E x^k (x = 2u - 1)."""
    mu = np.asarray(mu, np.float64)
    return (np.concatenate([np.ones(mu.shape[:-1] + (1,)), mu], axis=-1) @ _U_TO_X)[..., 1:]


def msm_forward(m: np.ndarray) -> np.ndarray:
    """q = mu @ MSM_MATRIX + MSM_OFFSET from the x-moments m (..., 4)."""
    return x_to_u(m) @ MSM_MATRIX + MSM_OFFSET


def msm_inverse(q: np.ndarray) -> np.ndarray:
    """x-moments (..., 4) from q: mu = (q - MSM_OFFSET) @ MSM_INVERSE."""
    return u_to_x((np.asarray(q, np.float64) - MSM_OFFSET) @ MSM_INVERSE)


def encode_msm(b: np.ndarray, precision: str) -> np.ndarray:
    """Decoded moments (T, 5) from the texels' (T, 5) ``b_0..b_4`` (float64): q as 4 codes of
    ``precision`` ('unorm16': ``round(q 65535)``, q clipped to [0, 1]; 'float16': IEEE half)
    and ``b_0`` as float32 (:data:`MSM_BYTES`), decoded (``q -> mu -> x-moments -> b_k = b_0
    E x^k``) once, in float64 (the inverse by ``numpy.linalg.inv``); empty texels (``b_0 <=
    0``) store zeros.  The caller rounds them to the store's dtype."""
    if precision not in MSM_PRECISIONS:
        raise ValueError(f"precision: the MSM quantisation takes {MSM_PRECISIONS}, got {precision!r}")
    b = np.asarray(b, np.float64)
    b0 = b[:, 0].astype(np.float32).astype(np.float64)
    full = b[:, 0] > 0
    m = b[:, 1:] / np.where(full, b[:, 0], 1.0)[:, None]
    q = round_unit(msm_forward(m), precision)
    out = np.zeros_like(b)
    out[:, 0] = b0
    out[:, 1:] = b0[:, None] * msm_inverse(q)
    out[~full] = 0.0
    return out


@register_basis("power_moments")
class PowerMomentBasis(Basis):
    """f_k(u) = (2u - 1)^k, k = 0..n (n power moments plus the total; not orthonormal:
    only the projection is used)."""

    arg = "moments"

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


@register_basis("trigonometric_moments")
class TrigMomentBasis(Basis):
    """f = [1, cos(k phi), sin(k phi)], k = 1..n, phi = (pi/2)(2u - 1) (2n + 1 functions;
    only the projection is used)."""

    arg = "moments"

    @property
    def n_coefficients(self) -> int:
        return 2 * self.n + 1

    def f(self, u):
        phi = (math.pi / 2) * (2 * u - 1)
        return [1 + 0 * u] + [x for k in range(1, self.n + 1) for x in dr.sincos(k * phi)[::-1]]   # cos, sin

    def average(self, u0, u1):
        return TM.trig_means(2 * u0 - 1, 2 * u1 - 1, self.n)


def exp_tilted_moments(kappa, n: int, dtype: str):
    """mu_j(kappa) = int_{-1}^{1} tau^j e^{kappa tau} / int e^{kappa tau}, j = 0..n, for
    kappa >= 0 (module docstring: series below KAPPA_SWITCH, recurrence above)."""
    terms = _SERIES_TERMS[dtype]
    ks = dr.minimum(kappa, KAPPA_SWITCH)           # series argument (no overflow when unused)
    k2 = ks * ks

    def series(j):
        # even j: sum_l k^(2l)/(2l)! 2/(2l+j+1);  odd j: k sum_l k^(2l)/(2l+1)! 2/(2l+j+2)
        odd = j % 2
        coef = [2.0 / (math.factorial(2 * l + odd) * (2 * l + odd + j + 1)) for l in range(terms)]
        acc = coef[-1] + 0 * k2
        for c in reversed(coef[:-1]):
            acc = acc * k2 + c
        return acc * ks if odd else acc

    N0 = series(0)
    low = [1 + 0 * kappa] + [series(j) / N0 for j in range(1, n + 1)]
    kr = dr.maximum(kappa, KAPPA_SWITCH)           # recurrence argument (no division by 0)
    coth = 1 / dr.tanh(kr)
    high = [1 + 0 * kappa]
    for j in range(1, n + 1):
        high.append((coth if j % 2 else 1) - (j / kr) * high[-1])
    big = kappa >= KAPPA_SWITCH
    return [dr.select(big, h, lo) for h, lo in zip(high, low)]


def log_warp_means(x0, x1, lam, n: int, dtype: str):
    """E[x^k], k = 0..n, over [x0, x1] for optical depth uniform in z under the log warp
    (density ~ e^{lam x}); lam = (ln far - ln near) / 2 (module docstring)."""
    mid, h = 0.5 * (x0 + x1), 0.5 * (x1 - x0)
    mu = exp_tilted_moments(lam * h, n, dtype)
    mp, hp = [1 + 0 * mid], [1 + 0 * h]
    for _ in range(n):
        mp.append(mp[-1] * mid)
        hp.append(hp[-1] * h)
    return [sum(math.comb(k, j) * mp[k - j] * hp[j] * mu[j] for j in range(k + 1)) for k in range(n + 1)]


def _moment_count_rule(p: dict) -> str | None:
    """Schema constraint: the moment count must be one the family takes, and the MSM
    quantisation applies to 4 power moments only."""
    allowed = FAMILIES[p["family"]]
    if p["moments"] not in allowed:
        return f"moments: family {p['family']!r} takes {allowed}, got {p['moments']}"
    if p.get("quantization") == "msm" and (p["family"] != "power" or p["moments"] != 4):
        return (f"quantization: 'msm' applies to family='power' with moments=4, got family={p['family']!r}, "
                f"moments={p['moments']}")
    return None


@register("moments")
class MomentShadowMap(BasisRepresentation):
    """Power or trigonometric moments of the absorbance with their bound (module docstring)."""

    PRESET = dict(BasisRepresentation.PRESET, overestimation=0.45)
    schema = Schema(
        params=(
            Param("moments", "int", 4, "power: 4, 6 or 8 real moments; trigonometric: 2, 3 or 4 complex "
                  "moments (stored as 2n + 1 reals)", min=2, max=8),
            Param("family", "choice", "power", "moment family: 'power' (Hankel / Hamburger bound) or "
                  "'trigonometric' (Toeplitz, unit circle)", choices=tuple(FAMILIES)),
            Param("warp", "choice", "linear", "depth warp before the moments: 'linear' or 'log' "
                  "(ln z normalised to [near, far]; needs near > 0)", choices=WARPS),
            Param("bias", "float", None, "alpha: weight of the bias target (default: MBOIT's value for the "
                  "storage precision and moment count; keeps the Hankel matrix positive definite)",
                  min=0.0, max=1.0, open_min=True, nullable=True),
            Param("bias_target", "object", None, "target moments m*_1..m*_2n (default: MBOIT's published "
                  "vector, e.g. (0, 0.375, 0, 0.375) for 4 moments)", nullable=True),
            Param("overestimation", "float", 0.25, "beta: 0 = lower bound (light), 1 = upper bound (dark)",
                  min=0.0, max=1.0),
            Param("quantization", "choice", None, "16-bit storage of 4 power moments: 'scaled' (per-texel "
                  "scale, as every basis kind) or 'msm' (Peters & Klein 2015's optimised transform, b_0 in "
                  "float32); None: 'msm' for 4 power moments in unorm16, else 'scaled'", choices=QUANTIZATIONS,
                  nullable=True),
            NEAR, FAR, DEPTH_RANGE,
        ),
        size="moments",
        sweep=(4, 6, 8),
        quick_sweep=(4, 8),
        examples=({"moments": 8}, {"family": "trigonometric", "moments": 3}),
        headline={"moments": 4},
        constraint=_moment_count_rule,
        summary="4/6/8 power or 2/3/4 trigonometric moments of the absorbance, bounds (MBOIT)",
        paper="Peters & Klein 2015; Peters et al. 2016; Muenstermann et al. 2018")

    def _make_basis(self):
        n = self.params["moments"]        # one the family takes (schema constraint)
        return TrigMomentBasis(n) if self._trig else PowerMomentBasis(n)

    def _resolve(self):
        """``quantization``, the bias target and its pivots, the basis and depth range (base
        class), ``near > 0`` for the log warp, ``bias`` (None: the default for the storage)."""
        P = self.params
        n = P["moments"]
        self._trig = P["family"] == "trigonometric"
        self._log = P["warp"] == "log"
        if P["quantization"] is None:                   # module docstring, "16-bit storage"
            msm = (P["family"], n, self.precision) == ("power", 4, MSM_DEFAULT_PRECISION)
            P["quantization"] = "msm" if msm else "scaled"
        elif P["quantization"] == "msm" and self.precision not in MSM_PRECISIONS:
            raise ValueError(f"quantization: 'msm' needs precision in {MSM_PRECISIONS}, "
                             f"got precision={self.precision!r}")
        if self._trig:
            if P["bias_target"] is not None:
                raise ValueError("bias_target: the trigonometric family biases toward the uniform "
                                 "distribution on the circle (no other target)")
            self._cayley = TM.cayley_matrix(n)
            self._pivots = hankel_pivots(self._cayley[1:, 0], self._cayley[0, 0])   # of the uniform distribution
        else:
            target = MBOIT_TARGET[n] if P["bias_target"] is None else P["bias_target"]
            try:
                target = tuple(float(v) for v in target)
            except (TypeError, ValueError):
                raise ValueError(f"bias_target: expected {n} real numbers, got {target!r}") from None
            if len(target) != n or not all(math.isfinite(v) for v in target):
                raise ValueError(f"bias_target: expected {n} finite real numbers, got {target!r}")
            self._target, self._floors = target, hankel_pivots(target)
        super()._resolve()
        if self._log and self._per_texel:             # near > 0 for the log warp; empty texels get (1, 2)
            near, far = np.asarray(self.near, np.float64), np.asarray(self.far, np.float64)
            empty = self.segments.counts == 0
            if np.any(near[~empty] <= 0):
                raise ValueError(f"near: warp='log' needs depths > 0; texel near bounds go down to "
                                 f"{near[~empty].min():g}")
            near, far = np.where(empty, 1.0, near), np.where(empty, 2.0, far)
            self.near, self.far = self.Float(near), self.Float(far)
        elif self._log and not self.near > 0:
            raise ValueError(f"near: warp='log' needs near > 0, got near={self.near:g}")
        if P["bias"] is None and P["quantization"] == "msm" and self.precision == MSM_DEFAULT_PRECISION:
            P["bias"] = MSM_UNORM16_BIAS
        elif P["bias"] is None:
            P["bias"] = (DEFAULT_TRIG_BIAS if self._trig else DEFAULT_BIAS)[n][self.precision or self.segments.dtype]

    def _apply_precision(self) -> None:
        """'msm': the flat (T x 5) moment store replaced by its :func:`encode_msm` values
        (straight-through gradient, as :mod:`._precision`), ranges as the base class."""
        if self.params["quantization"] != "msm":
            return super()._apply_precision()
        buf = self._coef
        self._coef = to_device(self, buf, encode_msm(to_host(buf).reshape(-1, 5), self.precision).ravel())
        self._stored_nbytes = MSM_BYTES + quantise(self, self._stored()[1:])       # the ranges (basis' _stored)

    def _log_range(self, texel=None):
        """(ln near, ln far - ln near floored at MIN_SPAN_REL[dtype]) for the texels, or global."""
        near, far = self._bounds(texel)
        ln_near = dr.log(near)
        return ln_near, dr.maximum(dr.log(far) - ln_near, MIN_SPAN_REL[self.segments.dtype])

    def normalized_depth(self, texel, depth):
        """u in [0, 1] of each receiver under the warp (linear: the basis' u)."""
        if not self._log:
            return super().normalized_depth(texel, depth)
        near, _ = self._range(texel)
        ln_near, ls = self._log_range(texel)
        return dr.clip((dr.log(dr.maximum(depth, near)) - ln_near) / ls, 0, 1)

    def _list_terms(self):
        """Linear warp: the basis' terms.  Log warp: :func:`log_warp_means` per segment."""
        if not self._log:
            return super()._list_terms()          # the basis' average: power or trigonometric
        seg = self.segments
        K = self.basis.n_coefficients
        # f_k at x = -1 (phi = -pi/2 for the trigonometric family): the part in front of near
        at_near = ([1.0] + [f(-k * math.pi / 2) for k in range(1, self.basis.n + 1) for f in (math.cos, math.sin)]
                   if self._trig else [(-1.0) ** k for k in range(K)])

        def terms(z0, z1, tau, texel):
            near, span = self._range(texel)          # global ranges ignore the texel
            _, _, tau_in, tau_front = clip_segment(z0, z1, tau, near, span)
            far = near + span
            ln_near, ls = self._log_range(texel)
            x0, x1 = (dr.clip(2 * ((dr.log(dr.clip(z, near, far)) - ln_near) / ls) - 1, -1, 1) for z in (z0, z1))
            x1 = dr.maximum(x1, x0)
            if self._trig:
                means = TM.trig_means(x0, x1, self.basis.n, 0.5 * ls)
            else:
                means = log_warp_means(x0, x1, 0.5 * ls, K - 1, seg.dtype)
            return [tau_in * means[k] + tau_front * at_near[k] for k in range(K)]

        return terms

    def bounds(self, texel, depth):
        """(lower, upper) bounds of the absorbance fraction in front of each receiver."""
        return self._bounded(self._store, texel, self.normalized_depth(texel, depth))[1:]

    def _bounded(self, store, row, u):
        """(D, lower, upper) from moments read from a flat store ``store[row * K + k]``."""
        Float = self.Float
        K = self.basis.n_coefficients
        b = [dr.gather(Float, store, row * K + k) for k in range(K)]
        alpha = self.params["bias"]
        beta = dr.opaque(Float, self.params["overestimation"])     # one kernel for every beta
        if self._trig:
            D, lo, up = TM.trig_bound(b, 2 * u - 1, alpha, beta, self._cayley, self._pivots)
        else:
            D, lo, up = hankel_bound(b, 2 * u - 1, alpha, beta, self._target, self._floors)
        D = dr.select(u <= 0, 0, dr.select(u >= 1, b[0], D))
        return D, lo, up

    def _reconstruct_from(self, store, row, u):
        return self._bounded(store, row, u)[0]
