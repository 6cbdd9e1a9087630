"""Storage precision: quantise a representation's stored buffers on store, dequantise on
lookup (``build(kind, seg, precision=...)``).

``precision``: None (default: the segments' own dtype), ``'float32'``, ``'float16'``,
``'unorm16'`` or ``'unorm8'``.  Each kind declares its stored buffers (:class:`Stored`) and
:func:`quantise` codes them once, after the build: ``unorm`` ``c = round(q M)``,
``M = 2^b - 1``, decoded ``c / M``; ``float16`` IEEE half.  The buffers keep the *decoded*
values in the segments' dtype (decoded in float64, rounded once), so every lookup kernel
stays as it is.  ``nbytes_per_texel`` counts the codes plus the per-texel ranges and scales
(float32, 4 bytes each); float64 data beyond float32's range, or depths (lengths) all below
float32's smallest normal number, raise ValueError naming ``precision``.

Encodings by meaning (``q`` the value quantised, in [0, 1] or [-1, 1]):

* ``depth``: ``'float32'``: the depth.  Otherwise ``q = (d - lo) / (hi - lo)`` over the
  texel's stored depths (float32, rounded outward; 8 bytes per texel; a ``texel`` layout:
  one global range).  Error <= (hi - lo) / (2 M) (unorm) or (hi - lo) 2^-12 (float16);
  monotone, so sorted nodes stay sorted.  The range costs what 2 float16 depths save: a
  variable-count kind (DSM) whose texels hold under 2 nodes on average, empty ones included, takes
  *more* dense bytes in float16 than in float32; the sparse layout charges ranges to non-empty texels.
* ``unit``: already in [0, 1] (avsm_march's relative depths): the code of q itself.
* ``transmittance``: T in [0, 1], zero-preserving (T = 0 stays 0, T > 0 stays positive).
  ``'float32'``/``'float16'``: T; ``'unorm16'``: linear, error <= 1 / (2 x 65535);
  ``'unorm8'``: **square-root optical depth** ``tau = -ln T`` over the texel's ``tau_max``
  (capped at :data:`TAU_CAP`; float32, 4 bytes), ``c = round(254 sqrt(tau / tau_max))``
  decoded ``exp(-tau_max (c / 254)^2)``, code 255 for T = 0.  ``|dtau| <= tau_max / 254``:
  relative T error ``<= exp(tau_max / 254) - 1``, absolute ``<= 0.0017 sqrt(tau_max)``.
* ``coefficient`` (basis kinds): scaled per texel by ``s = max_k |a_k|`` (float32, rounded
  up; 4 bytes; power moments ``s = b_0``).  Signed: unorm code of ``(a / s + 1) / 2``, error
  <= s / M; non-negative (``signed=False``): code of ``a / s``, error <= s / (2 M), monotone
  sequences stay monotone.  float16: ``fp16(a / s) s``.
* ``optical_depth`` (OSM's cumulative ``C_j``, non-negative, non-decreasing).  Floating
  formats: a non-negative ``coefficient``.  unorm: **capped square-root optical depth**, per
  texel (two float32) ``s`` the largest ``C_j <= TAU_CAP`` and ``F`` the first
  ``C_j > TAU_CAP`` (both rounded up, ``F >= s``); with ``S = M - 1``, ``C <= TAU_CAP`` has
  the code ``round(S sqrt(C / s))`` decoded ``s (c / S)^2``, the rest the top code ``M``
  decoded ``F``.  ``|dC| <= s / S`` (``T^ / T`` within ``exp(+-s / S)``) below the cap,
  ``|T^ - T| < exp(-TAU_CAP) = 2^-16`` past it; ``C = 0`` stays 0, order is kept.
* ``range``: per-texel ranges a kind stores itself: float32 whatever the precision.
* ``scalar``: a non-negative value scaling a ramp (beer's ``x``, ``T = exp(-x w)``, w in
  [0, 1]), one global scale; ``x^ / x`` in ``[1/r, r]`` gives ``|dT| <= (r - 1) / e``.
  ``'float16'``: ``fp16(x / 2^p) 2^p``, ``2^p`` the smallest power of two with
  ``max x / 2^p <= 65504``.  unorm: **logarithmic code** ``c = 1 + round((M - 1) ln(x / lo) /
  ln(hi / lo))``, decoded ``lo (hi / lo)^((c - 1) / (M - 1))``, ``hi = max x``,
  ``lo = max(min x > 0, hi 2^-LOG_OCTAVES)`` (float32, rounded outward); code 0 is 0, and
  ``x < lo`` takes the nearer of 0 and ``lo``; ``r = exp(ln(hi / lo) / (2 (M - 1)))``.

Gradients: straight-through, ``dr.replace_grad(decoded, x)`` (biased by at most the
quantisation error); ranges and scales are constants of the build.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import validation as V

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
#: Smallest normal float32: depths whose whole buffer lies below it have no float32 range.
FLOAT_TINY = float(np.finfo(np.float32).tiny)
#: Steps of the 8-bit optical-depth code (code 255 is reserved for T = 0).
T8_STEPS = 254
#: Smallest positive decoded T per format (float32: smallest normal, Dr.Jit flushes subnormals).
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
    """One stored buffer of a kind: attribute name, meaning (:data:`MEANINGS`) and layout:
    ``'nodes'`` N arrays of length T, ``'flat'`` K values per texel, texel-major, ``'csr'``
    grouped by texel with the kind's ``node_counts``, ``'texel'`` one value per texel.
    ``signed``: coefficients may be negative; ``length``: depth units (checked as depths)."""

    attr: str
    meaning: str
    layout: str
    signed: bool = True
    length: bool = False

    def __post_init__(self):
        V.one_of(self.meaning, "meaning", MEANINGS)
        V.one_of(self.layout, "layout", LAYOUTS)


# Host codecs: float64 NumPy in, float64 decoded values out.
def round_unit(q: np.ndarray, precision: str) -> np.ndarray:
    """q in [0, 1] (or [-1, 1] for float formats) through the code of ``precision``."""
    if precision in ("float32", "float16"):
        return q.astype(precision).astype(np.float64)
    M = UNORM_MAX[precision]
    return np.rint(np.clip(q, 0.0, 1.0) * M) / M


def float32_down(x: np.ndarray) -> np.ndarray:
    """Largest float32 <= x (float64 array)."""
    f = x.astype(np.float32)
    return np.where(f.astype(np.float64) > x, np.nextafter(f, np.float32(-np.inf)), f).astype(np.float64)


def float32_up(x: np.ndarray) -> np.ndarray:
    """Smallest float32 >= x (float64 array)."""
    return -float32_down(-x)


def _sqrt_code(x, scale, steps: int):
    """``scale (round(steps sqrt(x / scale)) / steps)^2``: x in [0, scale] (0 where scale is 0)."""
    q = np.sqrt(np.where(scale > 0, np.minimum(x / np.where(scale > 0, scale, 1.0), 1.0), 0.0))
    return scale * np.square(np.rint(q * steps) / steps)


def _texel_reduce(x: np.ndarray, tex: np.ndarray, n_tex: int, op, fill: float) -> np.ndarray:
    out = np.full(n_tex, fill)
    op.at(out, tex, x)
    return out


def _per_element(x, tex, n_tex, op, fill: float, rnd):
    """``rnd`` of ``op`` over each element's texel (over all of ``x`` where ``tex`` is None),
    at every element, and its bytes per texel (a float32, none for one global value)."""
    if tex is None:
        return np.full(x.shape, rnd(np.array([op.reduce(x, initial=fill)]))[0]), 0.0
    return rnd(_texel_reduce(x, tex, n_tex, op, fill))[tex], float(RANGE_BYTES)


def encode_depth(d, tex, n_tex, precision):
    """Decoded depths and the per-texel bytes (see the module docstring, ``depth``)."""
    lo_t, e_lo = _per_element(d, tex, n_tex, np.minimum, np.inf, float32_down)
    hi_t, e_hi = _per_element(d, tex, n_tex, np.maximum, -np.inf, float32_up)
    span = hi_t - lo_t
    q = np.where(span > 0, (d - lo_t) / np.where(span > 0, span, 1.0), 0.0)
    return np.clip(lo_t + round_unit(np.clip(q, 0.0, 1.0), precision) * span, lo_t, hi_t), e_lo + e_hi


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
    tmax, extra = _per_element(tau, tex, n_tex, np.maximum, 0.0, float32_down)
    # codes 0..254 of sqrt(tau / tau_max) over [0, 1]; code 255 is T = 0
    return np.where(zero, 0.0, np.exp(-_sqrt_code(tau, tmax, T8_STEPS))), extra


def encode_coefficient(a, tex, n_tex, precision, signed: bool):
    """Decoded coefficients and the per-texel bytes (module docstring)."""
    s, extra = _per_element(np.abs(a), tex, n_tex, np.maximum, 0.0, float32_up)
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
    return np.where(below, _sqrt_code(c, s[tex], steps), far[tex]), extra


def encode(meaning, x, tex, n_tex, precision, signed=True):
    """Decoded values (float64) and the per-texel bytes of ranges / scales for one buffer.
    ``tex``: the texel of each element, or None for one global range / scale."""
    if meaning == "range" or (precision == "float32" and meaning in ("depth", "coefficient", "optical_depth")):
        return round_unit(x, "float32"), 0.0        # ranges, and float32 depths / coefficients: the values
    if meaning == "coefficient":
        return encode_coefficient(x, tex, n_tex, precision, signed)
    if meaning in _BY_TEXEL:
        return _BY_TEXEL[meaning](x, tex, n_tex, precision)
    if meaning == "unit":
        return round_unit(np.clip(x, 0.0, 1.0), precision), 0.0
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


_BY_TEXEL = {"depth": encode_depth, "transmittance": encode_transmittance, "optical_depth": encode_optical_depth}


def code_bytes(meaning: str, precision: str) -> int:
    """Bytes of one stored element of ``meaning`` (ranges: always float32)."""
    return RANGE_BYTES if meaning == "range" else CODE_BYTES[precision]


def to_host(x) -> np.ndarray:
    """``x`` (a Dr.Jit array) detached, as a float64 NumPy array."""
    return np.asarray(dr.detach(x).numpy(), np.float64)


def to_device(rep, orig, dec: np.ndarray):
    """Decoded values as the kind's Float, carrying the gradient of ``orig`` (straight
    through)."""
    Float = rep.Float
    out = Float(A.aligned(dec.astype(rep.segments.dtype)))
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
            x = np.concatenate([to_host(b) for b in buf]) if buf else np.zeros(0)
            tex, per_texel = np.tile(np.arange(T), len(buf)), float(len(buf))
        else:       # elements per texel: flat K each, csr the kind's node_counts, texel None
            x = to_host(buf)
            counts = (np.full(T, x.size // max(T, 1)) if f.layout == "flat" else
                      np.asarray(rep.node_counts, np.int64) if f.layout == "csr" else None)
            tex = None if counts is None else np.repeat(np.arange(T), counts)
            per_texel = 1.0 if counts is None else float(counts.mean()) if counts.size else 0.0
        if f.meaning != "scalar" and x.size and np.abs(x).max() > FLOAT_MAX:
            raise ValueError(f"precision: {rep.kind!r} stores {f.attr} values up to {np.abs(x).max():.3g}, "
                             "beyond float32's range (codes, ranges and scales are float32 at most); "
                             "keep precision=None for such float64 data")
        if (f.meaning in ("depth", "range") or f.length) and x.size and 0 < np.abs(x).max() < FLOAT_TINY:
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
