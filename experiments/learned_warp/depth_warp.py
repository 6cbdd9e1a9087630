"""A learnable monotone depth warp shared by all texels, applied to segments and receivers.

Linear representations (FOM, OSM, moments, any basis) spend their resolution uniformly in
the normalised depth ``u = (z - near) / (far - near)``.  A monotone warp ``w`` re-spends it:
build the representation on the warped segments and look receivers up at ``w(z)``.  The
moment-based OIT paper warps depth logarithmically by hand (Muenstermann, Krumpen, Klein
and Peters 2018, "Moment-Based Order-Independent Transparency", sec. 5); here ``w`` is
piecewise linear with ``K`` knot intervals and its parameters are learned by gradient
descent (:mod:`experiments.learned_warp`, the one study using it; moved out of the package).

Parameterisation: ``K`` uniform knot intervals ``[c_k, c_{k+1}]``, ``c_k = near + k h``,
``h = (far - near) / K``; logits ``theta`` (K,) give positive increments
``d = softmax(theta)`` (``sum d = 1``) and knot values ``W_k = sum_{j<k} d_j``, so ::

    w(z) = W_k + d_k (z - c_k) / h,   k = clamp(floor((z - near) / h), 0, K - 1)

is strictly increasing by construction, ``w(near) = 0``, ``w(far) = 1``, and extends
linearly beyond ``[near, far]`` with the end slopes (strictly increasing everywhere, so the
exact curve is invariant: see below).  ``theta = 0`` is the identity ``w(z) = u``.

Warping segments (:meth:`DepthWarp.segments`): a segment of uniform density in ``z`` is split
at the knots it crosses; on each piece ``w`` is linear, so the piece has uniform density in
``w`` and keeps its share of the optical depth, ``tau_piece = tau (b - a) / (z1 - z0)``
(a zero-length segment stays one step at ``w(z0)``).  The total optical depth is preserved
and the exact transmittance is unchanged, ``T_w(w(z)) = T(z)`` for every depth: only the
representation's resolution moves.  Gradients flow from the warped ``z0``/``z1`` (and the
receivers' ``w(z)``) to ``theta``; the piece structure (which knots a segment crosses) is a
constant of the warp's knot grid, not of ``theta``.
"""
from __future__ import annotations

from avsm_dr import _arrays as A   # avsm_dr first: it picks Dr.Jit's libLLVM
from avsm_dr import backend
from avsm_dr import validation as V
from avsm_dr.segments import Segments

import drjit as dr
import numpy as np

#: Most knot intervals a warp may have (a segment is split into at most K + 2 pieces).
MAX_KNOTS = 4096


class DepthWarp:
    """Monotone piecewise-linear depth warp (module docstring).

    Parameters
    ----------
    near, far
        the depth range mapped to [0, 1] (finite, near < far).
    theta
        (K,) logits of the knot increments (NumPy or Dr.Jit; a Dr.Jit array keeps its
        AD graph, so gradients reach it), or None with ``knots=K`` for the identity.
    dtype
        'float32' | 'float64' (default: the segments' dtype when built by
        :meth:`for_segments`, else float32).
    """

    def __init__(self, near: float, far: float, theta=None, knots: int | None = None, dtype: str = "float32"):
        self.near = V.real(near, "near")
        self.far = V.real(far, "far")
        if not self.far > self.near:
            raise ValueError(f"far: expected far > near = {self.near:g}, got {self.far:g}")
        self.dtype = V.one_of(dtype, "dtype", ("float32", "float64"))
        Float = A.float_type(self.dtype)
        if theta is None:
            if knots is None:
                raise ValueError("theta: give theta= (logits) or knots= (identity warp)")
            knots = V.integer(knots, "knots", 1, MAX_KNOTS)
            theta = Float(np.zeros(knots))
        else:
            host = A.host(theta, "theta")
            if host.ndim != 1 or not 1 <= host.size <= MAX_KNOTS:
                raise ValueError(f"theta: expected a 1-D array of 1..{MAX_KNOTS} logits, got shape {host.shape}")
            A.check_finite(host, "theta")
            if knots is not None and V.integer(knots, "knots", 1, MAX_KNOTS) != host.size:
                raise ValueError(f"knots: {knots} does not match len(theta) = {host.size}")
            theta = A.to_float(theta if A.is_drjit(theta) else host, Float)
        self.theta = theta
        self.K = dr.width(theta)
        self.h = (self.far - self.near) / self.K
        # ---- increments d = softmax(theta) and knot values W_k = sum_{j<k} d_j (AD kept)
        e = dr.exp(theta - dr.max(dr.detach(theta)))
        self.d = e / dr.sum(e)                      # slope of interval k, in units of 1/h
        self.W = dr.prefix_sum(self.d)              # exclusive: W_0 = 0

    # ---------------------------------------------------------------- builders
    @classmethod
    def for_segments(cls, seg: Segments, theta=None, knots: int | None = None) -> "DepthWarp":
        """A warp over the global depth range of ``seg`` (:meth:`Segments.bounds`, the
        basis kinds' default ``near``/``far``), in the segments' dtype."""
        if not isinstance(seg, Segments):
            raise ValueError(f"seg: expected avsm_dr.Segments, got {type(seg).__name__}")
        near, far = seg.bounds()
        if not far > near:
            far = near + max(abs(near), 1.0) * 1e-6
        return cls(near, far, theta=theta, knots=knots, dtype=seg.dtype)

    @staticmethod
    def logits_for(values) -> np.ndarray:
        """Logits theta (K,) whose warp takes the knot values ``values`` (K + 1,) strictly
        increasing from 0 to 1 (e.g. a logarithmic warp sampled at the knots)."""
        v = V.array(values, "values")
        if v.ndim != 1 or v.size < 2:
            raise ValueError(f"values: expected a 1-D array of K + 1 >= 2 knot values, got shape {v.shape}")
        if abs(v[0]) > 1e-12 or abs(v[-1] - 1) > 1e-12 or np.any(np.diff(v) <= 0):
            raise ValueError("values: must increase strictly from 0 to 1")
        return np.log(np.diff(v))

    # ---------------------------------------------------------------- evaluate
    def _interval(self, z_host: np.ndarray) -> np.ndarray:
        """Knot interval of each depth, clamped to [0, K - 1] (host, int)."""
        k = np.floor((z_host - self.near) / self.h)
        return np.clip(np.nan_to_num(k), 0, self.K - 1).astype(np.uint32)

    def _at(self, z, k: np.ndarray):
        """w(z) for Dr.Jit depths z whose interval index is k (host array)."""
        Float = type(self.theta)
        kk = A.to_uint32(k)
        c = Float(self.near + k.astype(np.float64) * self.h)
        w = dr.gather(Float, self.W, kk) + dr.gather(Float, self.d, kk) * ((z - c) * (1.0 / self.h))
        # w maps [near, far] into [0, 1]; the rounded sums can leave it by an ulp (W_K = 1 +
        # 2e-16), which an explicit range [0, 1] refuses (representations/base.py): snap
        # those to the bound (a select, so in-range values keep their gradients)
        inside = (z >= self.near) & (z <= self.far)
        return dr.select(inside & (w > 1), 1.0, dr.select(inside & (w < 0), 0.0, w))

    def __call__(self, z):
        """w(z) for depths ``z`` (scalar or 1-D, NumPy or Dr.Jit); a Dr.Jit Float of the
        warp's dtype (AD graph kept from ``z`` and ``theta``)."""
        host = np.atleast_1d(A.host(z, "z"))
        if host.ndim != 1:
            raise ValueError(f"z: expected a scalar or a 1-D array, got shape {host.shape}")
        A.check_finite(host, "z")
        Float = type(self.theta)
        zd = A.to_float(z, Float) if A.is_drjit(z) else Float(host)
        return self._at(zd, self._interval(host))

    def knot_values(self) -> np.ndarray:
        """(K + 1,) float64 host copy of w at the knots, 0 .. 1."""
        W = A.host(dr.detach(self.W), "W")
        return np.append(W, W[-1] + float(A.host(dr.detach(self.d), "d")[-1]))

    def segments(self, seg: Segments) -> Segments:
        """``seg`` in warped depth (module docstring): each segment split at the knots it
        crosses, pieces mapped through ``w`` with their share of the optical depth."""
        if not isinstance(seg, Segments):
            raise ValueError(f"seg: expected avsm_dr.Segments, got {type(seg).__name__}")
        if seg.dtype != self.dtype:
            raise ValueError(f"seg: dtype {seg.dtype} does not match the warp's {self.dtype}")
        Float, Bool = seg.Float, backend.types().Bool
        if seg.n_segments == 0:
            return Segments(seg.offsets.copy(), Float(), Float(), Float(), seg.dtype)
        z0h, z1h = A.host(dr.detach(seg.z0), "z0"), A.host(dr.detach(seg.z1), "z1")
        # ---- piece structure (host): intervals -1 (in front of near) .. K (behind far)
        r0, r1 = (z0h - self.near) / self.h, (z1h - self.near) / self.h
        k0 = np.clip(np.floor(r0), -1, self.K).astype(np.int64)           # interval holding z0
        k1 = np.clip(np.ceil(r1) - 1, -1, self.K).astype(np.int64)        # interval ending at z1
        k1 = np.maximum(k1, k0)          # zero-length, or z1 exactly on the knot z0 sits on
        n = k1 - k0 + 1                                                   # pieces per segment
        src = np.repeat(np.arange(seg.n_segments), n)                     # source segment of a piece
        first = np.r_[0, np.cumsum(n)[:-1]]
        j = np.arange(src.size) - np.repeat(first, n)                     # piece index in its segment
        k = k0[src] + j                                                   # interval of the piece
        is_first, is_last = j == 0, j == n[src] - 1
        tex = np.repeat(np.arange(seg.n_texels), seg.counts)
        offsets = np.r_[0, np.cumsum(np.bincount(tex[src], minlength=seg.n_texels))].astype(np.int64) \
            if src.size else seg.offsets.copy()
        # ---- pieces (Dr.Jit, AD kept): [a, b] = [z0, z1] cut at the knots c_k, c_{k+1}
        i = A.to_uint32(src)
        z0, z1 = dr.gather(Float, seg.z0, i), dr.gather(Float, seg.z1, i)
        tau = dr.gather(Float, seg.optical_depth, i)
        cl = Float(self.near + k.astype(np.float64) * self.h)
        a = dr.select(Bool(is_first), z0, cl)
        b = dr.select(Bool(is_last), z1, cl + self.h)
        length = z1 - z0
        frac = dr.select(length > 0, (b - a) / dr.select(length > 0, length, 1), 1)
        ki = np.clip(k, 0, self.K - 1).astype(np.uint32)
        wa, wb = self._at(a, ki), self._at(b, ki)
        wb = dr.maximum(wb, wa)          # one piece, one linear map: only rounding can cross
        return Segments(offsets, wa, wb, tau * frac, seg.dtype)

    def __repr__(self) -> str:
        return f"DepthWarp(near={self.near:g}, far={self.far:g}, knots={self.K}, dtype={self.dtype})"


def log_values(knots: int, ratio: float = 100.0) -> np.ndarray:
    """(K + 1,) knot values of the logarithmic warp ``w(u) = ln(1 + (r - 1) u) / ln r`` at
    ``u = k / K`` (``r`` = ``ratio`` > 1: the slope at u = 0 over the slope at u = 1); the
    form of the log warp of Muenstermann et al. 2018, sec. 5, ``ln(z / near) / ln(far / near)``
    with ``far / near = r``."""
    knots = V.integer(knots, "knots", 1, MAX_KNOTS)
    ratio = V.real(ratio, "ratio", 1.0, open_min=True)
    u = np.arange(knots + 1) / knots
    return np.log1p((ratio - 1) * u) / np.log(ratio)


__all__ = ["DepthWarp", "log_values", "MAX_KNOTS"]
