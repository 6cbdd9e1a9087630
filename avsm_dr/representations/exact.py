"""Uncompressed (exact) transmittance: the in-package ground truth.

    T(d) = prod_i exp(-tau_i * f_i(d)),   f_i(d) = clamp((d - z0_i) / (z1_i - z0_i), 0, 1)

with f_i(d) = [d >= z0_i] for zero-length segments (uniform density inside a
segment, seed 000 eq. 1).  One lane per receiver loops over its texel's
segments, accumulating optical depth; the loop stops early once the optical
depth reaches ``OPAQUE_OPTICAL_DEPTH`` (T is then exactly 0).  Reverse mode
recomputes the loop (sum-loop path), so it needs no memory per iteration.
"""
from __future__ import annotations

import drjit as dr

from .. import backend
from ..segments import OPAQUE_OPTICAL_DEPTH
from .registry import register
from .base import Representation
from .schema import Schema


def segment_fraction(depth, z0, z1):
    """f(d): fraction of a segment's optical depth in front of ``depth``."""
    length = z1 - z0
    safe = dr.select(length > 0, length, 1)
    return dr.select(depth >= z1, 1, dr.clip((depth - z0) / safe, 0, 1))


@register("exact")
class Exact(Representation):
    """Stores the segments themselves; ``nbytes_per_texel`` = 12 bytes x mean segment count
    (z0, z1, tau in the segments' dtype) plus the 4-byte CSR offset."""

    schema = Schema(summary="every occluder segment (uncompressed ground truth)", paper="-")

    @property
    def nbytes_per_texel(self) -> float:
        mean = self.segments.n_segments / max(self.segments.n_texels, 1)
        return 3 * self.segments.itemsize * mean + 4

    def _eval_texels(self, texel, depth):
        seg = self.segments
        Float, UInt32 = seg.Float, backend.types().UInt32
        if seg.n_segments == 0:
            return dr.full(Float, 1.0, dr.width(depth))
        offsets = seg.offsets_dr()
        i = dr.gather(UInt32, offsets, texel)          # current segment
        end = dr.gather(UInt32, offsets, texel + 1)    # one past the texel's last segment
        tau = dr.zeros(Float, dr.width(depth))         # optical depth accumulated in front of depth

        def cond(i, tau):
            return (i < end) & (tau < OPAQUE_OPTICAL_DEPTH)

        def body(i, tau):
            z0 = dr.gather(Float, seg.z0, i)
            z1 = dr.gather(Float, seg.z1, i)
            od = dr.gather(Float, seg.optical_depth, i)
            return i + 1, tau + od * segment_fraction(depth, z0, z1)

        # A sum loop (the increment does not read tau; the early exit only reads it in
        # the condition): max_iterations=-1 lets reverse mode re-run the loop instead of
        # storing a per-lane trajectory (checked against finite differences in the tests).
        i, tau = dr.while_loop((i, tau), cond, body, max_iterations=-1, label="exact_eval")
        return dr.exp(-tau)
