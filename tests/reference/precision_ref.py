"""Storage-precision codecs in plain float64 NumPy, one texel at a time (checks
avsm_dr/representations/_precision.py): float16 rounding written out from the binary
exponent (no float16 cast), unorm codes, per-texel ranges and scales, and each codec's
stated error bound."""
from __future__ import annotations

import math

import numpy as np

UNORM_MAX = {"unorm16": 65535, "unorm8": 255}
TAU_CAP = 16 * math.log(2.0)


def half(x: np.ndarray) -> np.ndarray:
    """Round to the nearest IEEE half (ties to even) from the exponent: ulp = 2^(e - 10)
    for |x| in [2^e, 2^(e+1)), e >= -14; subnormals ulp = 2^-24; |x| <= 65504 assumed."""
    x = np.asarray(x, np.float64)
    out = np.empty_like(x)
    for i, v in np.ndenumerate(x):
        a = abs(v)
        e = max(math.frexp(a)[1] - 1, -14) if a > 0 else -14
        ulp = 2.0 ** (e - 10)
        out[i] = math.copysign(float(np.round(a / ulp)) * ulp, v)
    return out


def code(q: np.ndarray, precision: str) -> np.ndarray:
    """q through the code of ``precision`` (unorm: q clipped to [0, 1])."""
    if precision == "float32":
        return np.asarray(q, np.float32).astype(np.float64)
    if precision == "float16":
        return half(q)
    M = UNORM_MAX[precision]
    return np.round(np.clip(q, 0, 1) * M) / M


def code_bound(precision: str) -> float:
    """Largest |code(q) - q| for q in [0, 1]: half an ulp (float16: 2^-12 below 1; float32:
    2^-25) or half a step 1 / (2 M)."""
    return {"float32": 2.0**-25, "float16": 2.0**-12}.get(precision) or 0.5 / UNORM_MAX[precision]


def f32_down(v: float) -> float:
    f = float(np.float32(v))
    return f if f <= v else float(np.nextafter(np.float32(v), np.float32(-np.inf)))


def f32_up(v: float) -> float:
    f = float(np.float32(v))
    return f if f >= v else float(np.nextafter(np.float32(v), np.float32(np.inf)))


def depths(d: np.ndarray, precision: str):
    """One texel's depths: (decoded, error bound).  float32: the depth itself; otherwise
    relative to the texel's float32 range [lo, hi]."""
    d = np.asarray(d, np.float64)
    if precision == "float32":
        return code(d, precision), 2.0**-24 * np.abs(d).max(initial=0.0)
    lo, hi = f32_down(d.min()), f32_up(d.max())
    span = hi - lo
    q = (d - lo) / span if span > 0 else np.zeros_like(d)
    return lo + code(q, precision) * span, code_bound(precision) * span


def transmittances(t: np.ndarray, precision: str):
    """One texel's transmittances: (decoded, error bound: absolute, unorm8 relative).
    unorm8: the square root of the optical depth over the texel's (capped) maximum,
    |dtau| <= tau_max / 254 (half a step of sqrt(tau / tau_max) times q + q^ <= 2): relative
    error exp(tau_max / 254) - 1, plus exp(-TAU_CAP) absolute for T below the cap."""
    t = np.clip(np.asarray(t, np.float64), 0, 1)
    if precision != "unorm8":
        smallest = {"float32": 2.0**-126, "float16": 2.0**-24, "unorm16": 1 / 65535}[precision]
        dec = np.array([max(c, smallest) if v > 0 else c for v, c in zip(t, code(t, precision))])
        return dec, max(code_bound(precision), smallest)
    tau = np.array([min(-math.log(v), TAU_CAP) if v > 0 else 0.0 for v in t])
    tmax = f32_down(tau.max(initial=0.0))
    dec = np.array([math.exp(-tmax * (round(254 * math.sqrt(min(s / tmax, 1.0)) if tmax > 0 else 0) / 254) ** 2)
                    if v > 0 else 0.0 for v, s in zip(t, tau)])
    return dec, math.expm1(tmax / 254) + math.exp(-TAU_CAP)


def coefficients(a: np.ndarray, precision: str, signed: bool = True):
    """One texel's coefficients: (decoded, error bound) with the scale s = max |a_k|."""
    a = np.asarray(a, np.float64)
    if precision == "float32":
        return code(a, precision), 2.0**-24 * np.abs(a).max(initial=0.0)
    s = f32_up(np.abs(a).max(initial=0.0))
    q = a / s if s > 0 else np.zeros_like(a)
    if precision == "float16":
        return code(q, precision) * s, 2.0**-12 * s
    if signed:
        return (2 * code((q + 1) / 2, precision) - 1) * s, 2 * code_bound(precision) * s
    return code(q, precision) * s, code_bound(precision) * s


def optical_depths(c: np.ndarray, precision: str):
    """One texel's cumulative optical depths (non-decreasing): (decoded, error bound of the
    values <= TAU_CAP, far value).  Floating formats: as non-negative coefficients (far:
    None).  unorm: s = largest C <= TAU_CAP (float32 up), S = M - 1 steps, codes
    round(S sqrt(C / s)) decoded s (code / S)^2, so |dC| <= s |dq| (q + q^) <= s / S; every
    C > TAU_CAP decodes to F, the first such C (float32 up, at least s)."""
    c = np.asarray(c, np.float64)
    if precision not in UNORM_MAX:
        dec, bound = coefficients(c, precision, signed=False)
        return dec, bound, None
    steps = UNORM_MAX[precision] - 1
    low = [v for v in c if v <= TAU_CAP]
    high = [v for v in c if v > TAU_CAP]
    s = f32_up(max(low)) if low else 0.0
    far = max(f32_up(min(high)), s) if high else s
    dec = np.array([s * (round(steps * math.sqrt(v / s)) / steps) ** 2 if v <= TAU_CAP and s > 0 else
                    (0.0 if v <= TAU_CAP else far) for v in c])
    return dec, s / steps, far
