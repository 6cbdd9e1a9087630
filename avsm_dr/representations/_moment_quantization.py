"""Optimised 16-bit quantisation of 4 power moments (Peters and Klein 2015, "Moment Shadow
Mapping", I3D, sec. 5; Peters, Muenstermann, Wetzstein and Klein 2017, JCGT).

For a texel's normalised moments of the warped depth ``u`` in [0, 1],
``mu = (E u, E u^2, E u^3, E u^4)``, the stored vector is ``q = mu @ MSM_MATRIX + MSM_OFFSET``
(row vectors, the published constants; every point moment vector ``(z, .., z^4)``, z in
[0, 1], maps into [0, 1]^4, so by convexity every distribution does).  Our moments are of
``x = 2u - 1`` (:mod:`.moments`): ``E u^j = 2^-j sum_k C(j, k) E x^k`` and
``E x^k = sum_j C(k, j) 2^j (-1)^(k-j) E u^j``.

Storage (:func:`encode_msm`): q as 4 codes of ``precision`` ('unorm16': ``round(q 65535)``,
q clipped to [0, 1]; 'float16': IEEE half) and ``b_0`` as float32, 12 bytes per texel;
decoded (``q -> mu -> x-moments -> b_k = b_0 E x^k``) once, in float64 (the inverse by
``numpy.linalg.inv``), and rounded to the store's dtype; empty texels (``b_0 <= 0``) store zeros.
"""
from __future__ import annotations

import math

import numpy as np

from ._precision import to_device, to_host, round_unit

#: The published transform (Peters and Klein 2015, sec. 5), row-vector convention q = mu @ M + c.
MSM_MATRIX = np.array([[-2.07224649, 13.7948857237, 0.105877704, 9.7924062118],
                       [32.23703778, -59.4683975703, -1.9077466311, -33.7652110555],
                       [-68.571074599, 82.0359750338, 9.3496555107, 47.9456096605],
                       [39.3703274134, -35.364903257, -6.6543490743, -23.9728048165]])
MSM_OFFSET = np.array([0.035955884801, 0.0, 0.0, 0.0])
#: Its inverse in float64.
MSM_INVERSE = np.linalg.inv(MSM_MATRIX)
#: Storage precisions the transform applies to (16-bit codes).
MSM_PRECISIONS = ("float16", "unorm16")
#: Values of the moments kind's ``quantization`` parameter.
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
    full = np.concatenate([np.ones(m.shape[:-1] + (1,)), m], axis=-1)
    return (full @ _X_TO_U)[..., 1:]


def u_to_x(mu: np.ndarray) -> np.ndarray:
    """(..., 4) moments E u^j -> E x^k (x = 2u - 1)."""
    mu = np.asarray(mu, np.float64)
    full = np.concatenate([np.ones(mu.shape[:-1] + (1,)), mu], axis=-1)
    return (full @ _U_TO_X)[..., 1:]


def msm_forward(m: np.ndarray) -> np.ndarray:
    """q = mu @ MSM_MATRIX + MSM_OFFSET from the x-moments m (..., 4)."""
    return x_to_u(m) @ MSM_MATRIX + MSM_OFFSET


def msm_inverse(q: np.ndarray) -> np.ndarray:
    """x-moments (..., 4) from q: mu = (q - MSM_OFFSET) @ MSM_INVERSE."""
    return u_to_x((np.asarray(q, np.float64) - MSM_OFFSET) @ MSM_INVERSE)


def encode_msm(b: np.ndarray, precision: str) -> np.ndarray:
    """Decoded moments (T, 5) from the texels' (T, 5) ``b_0..b_4`` (float64) stored as
    4 ``precision`` codes of q and ``b_0`` in float32 (module docstring)."""
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


def quantise_store(rep, attr: str, precision: str) -> int:
    """Replace ``rep``'s flat (T x 5) moment store ``attr`` by its MSM-decoded values
    (straight-through gradient, as in :mod:`._precision`); returns its bytes per texel."""
    buf = getattr(rep, attr)
    b = to_host(buf).reshape(-1, 5)
    setattr(rep, attr, to_device(rep, buf, encode_msm(b, precision).ravel()))
    return MSM_BYTES
