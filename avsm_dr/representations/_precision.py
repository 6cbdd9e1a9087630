"""Storage precision: quantise a representation's stored buffers on store, dequantise on
lookup (``build(kind, seg, precision=...)``).

``precision``: None (default: the segments' own dtype, nothing quantised), ``'float32'``,
``'float16'``, ``'unorm16'`` or ``'unorm8'``.  Each kind declares its stored buffers
(:class:`Stored`: attribute, meaning, layout) and this module quantises them once, after
the build (:meth:`Representation._apply_precision`).  Codes are rounded to nearest
(``unorm``: ``c = round(q M)``, ``M = 2^b - 1``, decoded ``c / M``; ``float16``: IEEE
half, round to nearest even).  The buffers keep the *decoded* values in the segments'
dtype: decoding is an elementwise function of the code and the texel's stored range, so
this is bit for bit what decoding at lookup returns (computed in float64, rounded once),
and every lookup kernel stays as it is.  ``nbytes_per_texel`` counts the codes plus the
per-texel ranges and scales, which are stored in float32 (4 bytes each); float64 data
beyond float32's range is refused (ValueError naming ``precision``), and so are float64
depths (and lengths) that all lie below float32's smallest normal number (no float32 range
or scale holds them: they would decode to 0).

Encodings by meaning (``q`` the value quantised, in [0, 1] or [-1, 1]):

* ``depth``: ``'float32'``: the depth itself.  Otherwise relative to the texel's depth
  range ``q = (d - lo) / (hi - lo)`` (``lo``/``hi``: min/max of the texel's stored depths,
  float32 rounded outward; 8 bytes per texel; a ``texel`` layout, one depth per texel, uses
  one global range instead).  Error <= (hi - lo) / (2 M) (unorm) or (hi - lo) 2^-12 (float16:
  half an ulp of q <= 1), plus the final rounding to the dtype.  Rounding is monotone, so
  sorted nodes stay sorted; absolute float16 depths would err by up to |d| 2^-11.
* ``unit``: already in [0, 1] (e.g. avsm_march's relative depths): the code of q itself.
* ``transmittance``: T in [0, 1], zero-preserving (T = 0 stays 0, T > 0 stays positive:
  exponential interpolation falls back to linear next to a zero node, and a rounding
  across 0 would switch branch).  ``'float32'``/``'float16'``: T itself (float16 error
  <= 2^-12); ``'unorm16'``: linear, error <= 1 / (2 x 65535) (1 / 65535 for T below half a
  step, kept at the first code); ``'unorm8'``: **square-root optical depth**: ``tau = -ln
  T`` normalised by the texel's largest ``tau_max`` (capped at :data:`TAU_CAP`; float32,
  4 bytes per texel), codes ``c = round(254 sqrt(tau / tau_max))`` decoded
  ``exp(-tau_max (c / 254)^2)``, code 255 for T = 0.  A linear 8-bit T errs by up to 1/510
  absolute, i.e. 20 % of a T = 0.01 shadow.  With ``q = sqrt(tau / tau_max)``,
  ``|dtau| = tau_max |dq| (q + q^) <= tau_max (2 q + 1/508) / 508 <= tau_max / 254``: a
  *relative* T error <= ``exp(tau_max / 254) - 1`` (<= 4.5 % at the cap), and an absolute
  one ~ ``T |dtau| <= 2 exp(-tau) sqrt(tau tau_max) / 508 <= 0.0017 sqrt(tau_max)``
  (<= 0.0057 at the cap).  Codes linear in tau bound the relative error by half as much
  but err by up to ``tau_max / 508`` (0.022) where T ~ 1: one dark node (an opaque blocker,
  dense smoke) sets ``tau_max`` and coarsens the steps of the thin smoke in front (the
  failure mode of a per-texel maximum scale); the square root refines them where tau is
  small (measured, unorm8 / float32 RMSE: DSM 1.82 -> 1.26 on smoke over a table, 1.38 ->
  1.17 on the plume).  ``T = 1`` stays exact, the code is monotone in tau, and
  0 < T < ``exp(-TAU_CAP)`` decodes to ``exp(-tau_max)``.
* ``coefficient`` (basis kinds): scaled per texel by ``s = max_k |a_k|`` (float32, rounded
  up; 4 bytes per texel; for power moments ``s = b_0``).  Signed: ``q = a / s`` in [-1, 1],
  unorm code of ``(q + 1) / 2``, error <= s / M; non-negative (``signed=False``): code of
  ``a / s`` in [0, 1], error <= s / (2 M) and monotone sequences stay monotone.  float16:
  ``fp16(a / s) s`` (relative 2^-11, no overflow).
* ``optical_depth`` (OSM's cumulative optical depths ``C_j``, non-negative, non-decreasing
  per texel; ``T = exp(-D)`` with ``D`` interpolated linearly between two of them).
  ``'float32'``/``'float16'``: as a non-negative ``coefficient``.  ``'unorm16'``/``'unorm8'``:
  **capped square-root optical depth**.  A coefficient scale ``max_j C_j`` fails behind an
  opaque blocker (optical depth 1e4: every 8-bit step is 39, the smoke in front gets code 0
  and T = 1; measured 87x the float32 RMSE on smoke over a table).  Instead, per texel (two
  float32, 8 bytes): ``s`` the largest ``C_j <= TAU_CAP`` (rounded up) and ``F`` the first
  ``C_j > TAU_CAP`` (rounded up, at least ``s``; ``s`` where none).  With ``S = M - 1``
  steps, ``C <= TAU_CAP`` has the code ``c = round(S sqrt(C / s))`` decoded ``s (c / S)^2``
  and the rest the top code ``M``, decoded ``F``.  Error below the cap (as for
  ``transmittance``): ``|dC| <= s (2 sqrt(C / s) + 1 / (2 S)) / (2 S) <= s / S``, finer
  where C is small (a linear code errs by ``s / (2 S)`` everywhere; measured unorm8 /
  float32 RMSE with the table in a separate map 1.37 linear, 1.15 square root).  So
  wherever ``D`` is interpolated from two codes below the cap, or from one below and ``F``
  (the slice where D crosses the cap: exact at its far end), ``T^ / T`` is within
  ``exp(+-s / S)``: relative error <= ``exp(TAU_CAP / 254) - 1`` = 4.5 % (unorm8; far less
  in thin texels, where ``s`` is their largest optical depth), 1.7e-4 (unorm16).  Past the
  cap (both ends) ``D^ = F <= D``, so ``|T^ - T| < exp(-TAU_CAP) = 2^-16``.  Decoding the
  top code as an opaque D instead would err by up to ``T`` inside the crossing slice
  (0.29 measured, dense smoke crossing the cap).  ``C = 0`` stays 0 (``T = 1`` exact in
  front of the texel's content; a tiny positive ``C`` may round to 0: no lookup branches
  on ``C > 0``); the codes and ``F >= s`` keep a non-decreasing sequence non-decreasing,
  so T stays monotone.
* ``range``: per-texel ranges a kind stores itself (basis ``depth_range='texel'``,
  avsm_march): float32 whatever the precision.
* ``scalar``: an unbounded non-negative value per texel that *scales* a ramp (beer's
  optical depth ``x``, ``T = exp(-x w)``, w in [0, 1]), one global scale.  Then only a
  relative bound carries over to T: with ``x^ / x`` in ``[1/r, r]``,
  ``|dT| <= (r - 1) m w exp(-m w) <= (r - 1) / e`` (``m = min(x, x^)``).  ``'float32'``: x
  itself; ``'float16'``: ``fp16(x / 2^p) 2^p``, ``2^p`` the smallest power of two with
  ``max x / 2^p <= 65504`` (``p = 0`` unless the largest value would saturate): relative
  2^-11 down to ``2^(p - 14)``, absolute ``2^(p - 25)`` below.  Saturating instead would
  ramp a ``x = 1e6`` texel to 0 over 15x its length.  unorm: a **logarithmic code**
  ``c = 1 + round((M - 1) ln(x / lo) / ln(hi / lo))``, decoded ``lo (hi / lo)^((c - 1) /
  (M - 1))``, over the map's ``hi = max x`` and ``lo = max(min x > 0, hi 2^-LOG_OCTAVES)``
  (both float32, rounded outward); code 0 is 0 (x = 0 exact), and ``x < lo`` takes the
  nearer of 0 and ``lo`` (error <= lo / 2).  ``r = exp(ln(hi / lo) / (2 (M - 1)))``: at most
  3.3 % (unorm8, 24 octaves) and 3.4e-4 (unorm16, 64 octaves), so ``|dT| <= 0.012`` and
  ``1.3e-4``.  A linear code over ``max x`` would zero every thin texel of a map holding an
  opaque one (the failure a per-texel scale as large as the value would avoid, at 4 bytes).

Gradients: straight-through estimator, ``dr.replace_grad(decoded, x)``: the primal is
the decoded value, the derivative that of the unquantised ``x`` (rounding has zero
derivative almost everywhere; the estimator keeps differentiable kinds differentiable,
biased by at most the quantisation error).  Ranges and scales are constants of the build.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from .. import _arrays as A

#: Accepted values of ``precision`` (None: the segments' own dtype).
PRECISIONS = ("float32", "float16", "unorm16", "unorm8")
#: Bytes per code.
CODE_BYTES = {"float32": 4, "float16": 2, "unorm16": 2, "unorm8": 1}
#: unorm code maxima M = 2^b - 1.
UNORM_MAX = {"unorm16": 65535, "unorm8": 255}
#: Bytes of a stored per-texel range bound or scale (float32).
RANGE_BYTES = 4
#: Largest optical depth the 8-bit transmittance code spans (T floor 2^-16 ~ 1.5e-5).
TAU_CAP = 16 * float(np.log(2.0))
#: Octaves below the largest value that the logarithmic unorm code of ``scalar`` spans.
LOG_OCTAVES = {"unorm16": 64, "unorm8": 24}
#: Largest finite float16 / float32.
HALF_MAX = 65504.0
FLOAT_MAX = float(np.finfo(np.float32).max)
#: Smallest normal float32: float64 depths whose whole buffer lies below it (a scene at depth
#: scale 1e-150) have no float32 range or scale (they flush to 0 or become subnormal).
FLOAT_TINY = float(np.finfo(np.float32).tiny)
#: Steps of the 8-bit optical-depth code (code 255 is reserved for T = 0).
T8_STEPS = 254
#: Smallest positive decoded T per format (float32: smallest normal, since Dr.Jit's worker
#: threads flush subnormals; float16: smallest subnormal 2^-24, normal in the float32 store).
SMALLEST = {"float32": 2.0**-126, "float16": 2.0**-24, "unorm16": 1 / 65535, "unorm8": 0.0}
MEANINGS = ("depth", "unit", "transmittance", "coefficient", "optical_depth", "range", "scalar")
LAYOUTS = ("nodes", "flat", "csr", "texel")


def check_precision(value) -> str | None:
    """``value`` if it is None or one of :data:`PRECISIONS`, else ValueError naming it."""
    if value is None or (isinstance(value, str) and value in PRECISIONS):
        return value
    raise ValueError(f"precision: expected None or one of {PRECISIONS}, got {value!r}")


@dataclass(frozen=True)
class Stored:
    """One stored buffer of a kind: attribute name, meaning (:data:`MEANINGS`) and layout.

    Layouts: ``'nodes'`` a list of N arrays of length T (``[node][texel]``); ``'flat'`` one
    texel-major array of K values per texel; ``'csr'`` one array grouped by texel with the
    kind's ``node_counts`` (T,) per texel; ``'texel'`` one value per texel.
    ``signed``: coefficients may be negative (else non-negative, a [0, 1] code).
    ``length``: the values are in depth units although not depths (beer's extent): checked
    as depths are (:func:`quantise`)."""

    attr: str
    meaning: str
    layout: str
    signed: bool = True
    length: bool = False

    def __post_init__(self):
        if self.meaning not in MEANINGS:
            raise ValueError(f"meaning: expected one of {MEANINGS}, got {self.meaning!r}")
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout: expected one of {LAYOUTS}, got {self.layout!r}")


# ----------------------------------------------------------------------------
# Host codecs (float64 NumPy in, float64 decoded values out)
# ----------------------------------------------------------------------------
def round_unit(q: np.ndarray, precision: str) -> np.ndarray:
    """q in [0, 1] (or [-1, 1] for float formats) through the code of ``precision``."""
    if precision == "float32":
        return q.astype(np.float32).astype(np.float64)
    if precision == "float16":
        return q.astype(np.float16).astype(np.float64)
    M = UNORM_MAX[precision]
    return np.rint(np.clip(q, 0.0, 1.0) * M) / M


def float32_down(x: np.ndarray) -> np.ndarray:
    """Largest float32 <= x (float64 array)."""
    f = x.astype(np.float32)
    return np.where(f.astype(np.float64) > x, np.nextafter(f, np.float32(-np.inf)), f).astype(np.float64)


def float32_up(x: np.ndarray) -> np.ndarray:
    """Smallest float32 >= x (float64 array)."""
    f = x.astype(np.float32)
    return np.where(f.astype(np.float64) < x, np.nextafter(f, np.float32(np.inf)), f).astype(np.float64)


def _texel_reduce(x: np.ndarray, tex: np.ndarray, n_tex: int, op, fill: float) -> np.ndarray:
    out = np.full(n_tex, fill)
    op.at(out, tex, x)
    return out


def encode_depth(d, tex, n_tex, precision):
    """Decoded depths and the per-texel bytes (see the module docstring, ``depth``)."""
    if precision == "float32":
        return round_unit(d, "float32"), 0.0
    if tex is None:                                  # one global range
        lo = float32_down(np.array([d.min()]))[0] if d.size else 0.0
        hi = float32_up(np.array([d.max()]))[0] if d.size else 0.0
        lo_t, hi_t, extra = lo, hi, 0.0
    else:
        lo = float32_down(_texel_reduce(d, tex, n_tex, np.minimum, np.inf))
        hi = float32_up(_texel_reduce(d, tex, n_tex, np.maximum, -np.inf))
        lo_t, hi_t, extra = lo[tex], hi[tex], 2.0 * RANGE_BYTES
    span = hi_t - lo_t
    q = np.where(span > 0, (d - lo_t) / np.where(span > 0, span, 1.0), 0.0)
    return np.clip(lo_t + round_unit(np.clip(q, 0.0, 1.0), precision) * span, lo_t, hi_t), extra


def encode_transmittance(t, tex, n_tex, precision):
    """Decoded transmittances and the per-texel bytes (module docstring).  Zero-preserving:
    T = 0 decodes to 0 and T > 0 to a positive value (the smallest positive code where it
    would round to 0), so exponential interpolation, which falls back to linear next to a
    zero node, takes the same branch as with the native values."""
    t = np.clip(t, 0.0, 1.0)
    if precision != "unorm8":
        dec = round_unit(t, precision)
        return np.where((t > 0) & (dec == 0), SMALLEST[precision], dec), 0.0
    zero = t == 0
    with np.errstate(divide="ignore"):
        tau = np.where(zero, 0.0, np.minimum(-np.log(np.where(zero, 1.0, t)), TAU_CAP))
    if tex is None:
        tmax = np.full(t.shape, float32_down(np.array([tau.max(initial=0.0)]))[0])
        extra = 0.0
    else:
        tmax = float32_down(_texel_reduce(tau, tex, n_tex, np.maximum, 0.0))[tex]
        extra = float(RANGE_BYTES)
    q = np.sqrt(np.where(tmax > 0, np.minimum(tau / np.where(tmax > 0, tmax, 1.0), 1.0), 0.0))
    # codes 0..254 of sqrt(tau / tau_max) over [0, 1]; code 255 is T = 0
    return np.where(zero, 0.0, np.exp(-tmax * np.square(np.rint(q * T8_STEPS) / T8_STEPS))), extra


def encode_coefficient(a, tex, n_tex, precision, signed: bool):
    """Decoded coefficients and the per-texel bytes (module docstring)."""
    if precision == "float32":
        return round_unit(a, "float32"), 0.0
    if tex is None:
        s = np.full(a.shape, float32_up(np.array([np.abs(a).max(initial=0.0)]))[0])
        extra = 0.0
    else:
        s = float32_up(_texel_reduce(np.abs(a), tex, n_tex, np.maximum, 0.0))[tex]
        extra = float(RANGE_BYTES)
    q = np.where(s > 0, a / np.where(s > 0, s, 1.0), 0.0)
    if not signed:
        q = np.clip(q, 0.0, 1.0)
    if precision == "float16" or not signed:
        return round_unit(q, precision) * s, extra
    return (2.0 * round_unit(0.5 * (q + 1.0), precision) - 1.0) * s, extra


def encode_optical_depth(c, tex, n_tex, precision):
    """Decoded cumulative optical depths and the per-texel bytes (module docstring,
    ``optical_depth``): unorm codes of sqrt(tau / s), ``s`` the texel's largest
    tau <= :data:`TAU_CAP`, the top code for the texel's first tau beyond the cap;
    floating formats as :func:`encode_coefficient` (non-negative)."""
    if precision not in UNORM_MAX:
        return encode_coefficient(c, tex, n_tex, precision, signed=False)
    steps = UNORM_MAX[precision] - 1                 # the top code is "beyond the cap"
    c = np.maximum(c, 0.0)
    below = c <= TAU_CAP
    if tex is None:                                  # one global scale and far value
        tex, n_tex, extra = np.zeros(c.shape, np.int64), 1, 0.0
    else:
        extra = 2.0 * RANGE_BYTES
    s = float32_up(_texel_reduce(np.where(below, c, 0.0), tex, n_tex, np.maximum, 0.0))
    first = _texel_reduce(np.where(below, np.inf, c), tex, n_tex, np.minimum, np.inf)
    far = np.maximum(float32_up(np.where(np.isfinite(first), first, 0.0)), s)     # >= s: monotone
    s_t = s[tex]
    q = np.sqrt(np.where(s_t > 0, np.minimum(c / np.where(s_t > 0, s_t, 1.0), 1.0), 0.0))
    return np.where(below, s_t * np.square(np.rint(q * steps) / steps), far[tex]), extra


def encode(meaning, x, tex, n_tex, precision, signed=True):
    """Decoded values (float64) and the per-texel bytes of ranges / scales for one buffer.
    ``tex``: the texel of each element, or None for one global range / scale."""
    if meaning == "depth":
        return encode_depth(x, tex, n_tex, precision)
    if meaning == "transmittance":
        return encode_transmittance(x, tex, n_tex, precision)
    if meaning == "coefficient":
        return encode_coefficient(x, tex, n_tex, precision, signed)
    if meaning == "optical_depth":
        return encode_optical_depth(x, tex, n_tex, precision)
    if meaning == "unit":
        return round_unit(np.clip(x, 0.0, 1.0), precision), 0.0
    if meaning == "range":
        return round_unit(x, "float32"), 0.0
    return encode_scalar(x, precision), 0.0


def encode_scalar(x: np.ndarray, precision: str) -> np.ndarray:
    """Decoded non-negative values under one global scale (module docstring, ``scalar``)."""
    x = np.minimum(np.maximum(x, 0.0), FLOAT_MAX)
    top = float(x.max(initial=0.0))
    if precision == "float32":
        return round_unit(x, "float32")
    if precision == "float16":
        p = 0
        while top > HALF_MAX * 2.0**p:                  # smallest 2^p without saturation
            p += 1
        return round_unit(x * 2.0**-p, "float16") * 2.0**p
    if top == 0:
        return np.zeros_like(x)
    steps = UNORM_MAX[precision] - 1                    # code 0 is x = 0
    hi = float32_up(np.array([top]))[0]
    lo = float32_down(np.array([x[x > 0].min()]))[0]
    lo = max(lo, float32_up(np.array([hi * 2.0**-LOG_OCTAVES[precision]]))[0])
    span = np.log(hi / lo)
    q = np.log(np.maximum(x, lo) / lo) / span if span > 0 else np.zeros_like(x)
    dec = lo * np.exp(span * np.rint(np.clip(q, 0.0, 1.0) * steps) / steps)
    return np.where(x >= lo, np.minimum(dec, hi), np.where(x >= 0.5 * lo, lo, 0.0))


def code_bytes(meaning: str, precision: str) -> int:
    """Bytes of one stored element of ``meaning`` (ranges: always float32)."""
    return RANGE_BYTES if meaning == "range" else CODE_BYTES[precision]


# ----------------------------------------------------------------------------
# Applying it to a representation
# ----------------------------------------------------------------------------
def to_host(x) -> np.ndarray:
    """``x`` (a Dr.Jit array) detached, as a float64 NumPy array."""
    return np.asarray(dr.detach(x).numpy(), np.float64)


def to_device(rep, orig, dec: np.ndarray):
    """Decoded values as the kind's Float, carrying the gradient of ``orig`` (straight
    through)."""
    Float = rep.Float
    dt = np.float32 if rep.segments.dtype == "float32" else np.float64
    out = Float(A.aligned(dec.astype(dt)))
    if dr.grad_enabled(orig):
        out = dr.replace_grad(out, Float(orig))
    return out


def quantise(rep, fields) -> float:
    """Quantise ``rep``'s stored buffers ``fields`` (:class:`Stored`) in place to
    ``rep.precision``; returns their bytes per texel (codes + ranges / scales)."""
    precision, T = rep.precision, rep.n_texels
    total = 0.0
    for f in fields:
        buf = getattr(rep, f.attr)
        if f.layout == "nodes":
            N = len(buf)
            x = np.concatenate([to_host(b) for b in buf]) if N else np.zeros(0)
            tex = np.tile(np.arange(T), N)
            per_texel = float(N)
        elif f.layout == "flat":
            x = to_host(buf)
            K = x.size // max(T, 1)
            tex = np.repeat(np.arange(T), K)
            per_texel = float(K)
        elif f.layout == "csr":
            x = to_host(buf)
            counts = np.asarray(rep.node_counts, np.int64)
            tex = np.repeat(np.arange(T), counts)
            per_texel = float(counts.mean()) if counts.size else 0.0
        else:   # texel
            x = to_host(buf)
            tex = None
            per_texel = 1.0
        if f.meaning != "scalar" and x.size and np.abs(x).max() > FLOAT_MAX:
            raise ValueError(f"precision: {rep.kind!r} stores {f.attr} values up to {np.abs(x).max():.3g}, "
                             "beyond float32's range (codes, ranges and scales are float32 at most); "
                             "keep precision=None for such float64 data")
        if (f.meaning in ("depth", "range") or f.length) and x.size and 0 < np.abs(x).max() < FLOAT_TINY:
            # measured: float64 segments at depth scale 1e-150, precision='float32' (any code):
            # every depth decoded to 0 (T = 0.0044 where the exact T is 1)
            raise ValueError(f"precision: {rep.kind!r} stores {f.attr} values (depth units) of at most "
                             f"{np.abs(x).max():.3g}, below float32's smallest normal number {FLOAT_TINY:.3g} "
                             "(depth ranges and scales are float32): they would decode to 0; rescale the depths "
                             "or keep precision=None for such float64 data")
        dec, extra = encode(f.meaning, x, tex, T, precision, f.signed)
        total += per_texel * code_bytes(f.meaning, precision) + extra
        if f.layout == "nodes":
            setattr(rep, f.attr, [to_device(rep, b, dec[k * T:(k + 1) * T]) for k, b in enumerate(buf)])
        else:
            setattr(rep, f.attr, to_device(rep, buf, dec))
    return total
