"""Uncompressed (exact) transmittance: the in-package ground truth.

The transmittance at depth ``d`` of a texel's segments (uniform density inside a segment,
Salvi et al. 2010, "Adaptive Volumetric Shadow Maps", eq. 1)::

    T(d) = prod_i exp(-tau_i * f_i(d)),   f_i(d) = clamp((d - z0_i) / (z1_i - z0_i), 0, 1)

with f_i(d) = [d >= z0_i] for zero-length segments; summed in float64 whatever the storage
dtype, stopping at ``OPAQUE_OPTICAL_DEPTH`` (T exactly 0).
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from ..segments import OPAQUE_OPTICAL_DEPTH
from .registry import register
from .base import Representation
from .schema import Schema


@register("exact")
class Exact(Representation):
    """Stores the segments themselves (z0, z1, tau in the segments' dtype, a CSR offset)."""

    schema = Schema(summary="every occluder segment (uncompressed ground truth)", paper="-")
    _precision_note = ("; 'exact' is the uncompressed ground truth and reads the segments in their own "
                       "dtype (build the Segments in the dtype wanted)")

    variable_size = True

    def texel_payload_bytes(self):
        """Sparse layout: a texel's segments (z0, z1, tau)."""
        return self._csr_payload(self.segments.counts, 3 * self.segments.itemsize)

    def _native_bytes(self) -> float:
        return 3 * self.segments.itemsize * (self.segments.n_segments / max(self.segments.n_texels, 1)) + 4

    def _eval_texels(self, texel, depth):
        seg = self.segments
        if seg.n_segments == 0:
            return dr.full(seg.Float, 1.0, dr.width(depth))
        UInt32, offsets = backend.types().UInt32, seg.offsets_dr()
        tau = optical_depth_in_front(seg, dr.gather(UInt32, offsets, texel), dr.gather(UInt32, offsets, texel + 1),
                                     depth, backend.types().Float64, stop=True, label="exact_eval")
        return seg.Float(dr.exp(-tau))


def optical_depth_in_front(seg, i, end, depth, Acc, left=None, stop: bool = False, label: str = "exact"):
    """Optical depth in front of ``depth`` summed in ``Acc`` over segments ``[i, end)`` (one lane
    per receiver; ``left``: left limits, a step at the depth not counted; ``stop``: at
    ``OPAQUE_OPTICAL_DEPTH``).  A sum loop (tau only read by the condition): reverse mode
    re-runs it (:mod:`._loops`)."""
    Float = seg.Float

    def cond(i, tau):
        return (i < end) & (tau < OPAQUE_OPTICAL_DEPTH) if stop else i < end

    def body(i, tau):
        z0, z1, od = (dr.gather(Float, x, i) for x in (seg.z0, seg.z1, seg.optical_depth))
        length = z1 - z0
        f = dr.select(depth >= z1, 1, dr.clip((depth - z0) / dr.select(length > 0, length, 1), 0, 1))   # f_i(d)
        if left is not None:
            f = dr.select(left & (z0 == z1) & (depth == z0), 0.0, f)   # T(z^-) before a step
        return i + 1, tau + Acc(od * f)

    return dr.while_loop((i, dr.zeros(Acc, dr.width(depth))), cond, body, max_iterations=-1, label=label)[1]


def exact_values(segments, texel: np.ndarray, z: np.ndarray, left: np.ndarray):
    """``T`` of the exact curve at depths ``z`` of texels ``texel`` (left limits where
    ``left``), as a Dr.Jit Float of the segments' type carrying their AD graph."""
    seg, t = segments, backend.types()
    i = t.UInt32(seg.offsets[texel].astype(np.uint32))
    end = t.UInt32(seg.offsets[texel + 1].astype(np.uint32))
    zd = seg.Float(A.aligned(np.asarray(z, np.dtype(seg.dtype).type)))
    is_left = t.Bool(A.aligned(np.asarray(left, bool)))
    return dr.exp(-optical_depth_in_front(seg, i, end, zd, seg.Float, is_left, label="curve_exact_values"))
