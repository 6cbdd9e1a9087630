"""Beer shadow map (Hillaire 2016, "Physically based sky, atmosphere and cloud rendering in
Frostbite", SIGGRAPH course, the clouds chapter's Beer shadow map): one homogeneous medium per
texel, three numbers.

Per texel, with ``a`` = first entry (min z0), ``b`` = last exit (max z1) and ``tau_max`` =
the texel's total optical depth, stored as ``a``, the extent ``e = b - a`` and ``tau_max``
('cloud') or ``exp(-tau_max)`` ('two_node'); with ``w = clamp((d - a) / e, 0, 1)``:

* ``variant='cloud'`` (the paper's: mean extinction ``sigma_mean = tau_max / e``, the total
  spread over the content, gaps included) ``T(d) = exp(-tau_max w)``, exact for one uniform
  segment; ``e = 0`` (only zero-length segments at one depth) is a step at ``a`` (a receiver
  at a step is behind it, as in :mod:`.exact`).
* ``variant='two_node'``: nodes ``(a, 1)`` and ``(b, exp(-tau_max))``, *linear* between them
  (exponential would be 'cloud'): ``T = 1 + w (exp(-tau_max) - 1)``.

No stored value carries depth units over extinction (a stored extinction would underflow or
saturate float16).  ``precision=`` (:mod:`._precision`): ``a`` relative to one global depth
range, ``e`` over the largest extent, ``tau_max`` a ``scalar``, ``exp(-tau_max)`` a
``transmittance`` (global ranges and scales count no bytes per texel).  Gradients flow to the
optical depths (``tau_max``: summed per texel in CSR order, scatter-added with gradients);
``a`` and ``e`` carry none.
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A
from .base import Representation
from ._loops import texel_sums
from ._precision import PRECISIONS, Stored
from .registry import register
from .schema import Param, Schema

VARIANTS = ("cloud", "two_node")


@register("beer")
class BeerShadowMap(Representation):
    """Beer shadow map (module docstring); per texel ``front`` (a), ``extent`` (e),
    ``tau_max``, ``t_back`` (``exp(-tau_max)``) and the property ``sigma_mean``."""

    schema = Schema(
        params=(Param("variant", "choice", "cloud", "'cloud': (front depth, mean extinction, max optical "
                      "depth), Hillaire 2016; 'two_node': (depth, T) at entry and exit, linear in between",
                      choices=VARIANTS),),
        examples=({"variant": "cloud"}, {"variant": "two_node"}),
        headline={"variant": "cloud"},
        summary="one homogeneous medium per texel: front depth, mean extinction, max optical depth",
        paper="Hillaire 2016")

    def _build(self):
        segments = self.segments
        Float = segments.Float
        lo, hi = segments.texel_bounds()
        empty = segments.counts == 0
        if self.precision is not None and segments.n_segments:
            # empty texels (T = 1 whatever their bounds) must not widen the global depth range
            lo[empty] = segments.bounds()[0]
        self.front, self.extent = Float(A.aligned(lo)), Float(A.aligned(np.where(empty, 0.0, hi - lo)))
        self.tau_max = dr.zeros(Float, segments.n_texels)
        if segments.n_segments and segments.requires_grad:
            dr.scatter_reduce(dr.ReduceOp.Add, self.tau_max, segments.optical_depth, segments.texel_of_segment())
        elif segments.n_segments:                 # CSR order: the same bits every run
            texel, (total,) = texel_sums(segments, lambda i, _t: [dr.gather(Float, segments.optical_depth, i)], 1,
                                         label="beer_tau")
            dr.scatter(self.tau_max, total, texel)
        self.t_back = dr.exp(-self.tau_max)
        dr.eval(self.tau_max, self.t_back)

    precisions = PRECISIONS

    @property
    def sigma_mean(self):
        """Mean extinction ``tau_max / extent`` per texel (0 where the extent is 0)."""
        e = self.extent
        return dr.select(e > 0, self.tau_max / dr.select(e > 0, e, 1), 0)

    def _stored(self):
        third = (Stored("tau_max", "scalar", "texel") if self.params["variant"] == "cloud"
                 else Stored("t_back", "transmittance", "texel"))
        return (Stored("front", "depth", "texel"), Stored("extent", "coefficient", "texel", signed=False, length=True),
                third)

    def _native_bytes(self) -> float:
        return 3 * self.segments.itemsize

    def _eval_texels(self, texel, depth):
        Float = self.Float
        a = dr.gather(Float, self.front, texel)
        e = dr.gather(Float, self.extent, texel)
        # fraction of the extent in front of the receiver; a step at a where e = 0
        # (content without extent: a receiver at a step is behind it)
        w = dr.clip((depth - a) / dr.select(e > 0, e, 1), 0, 1)
        w = dr.select(e > 0, w, dr.select(depth >= a, 1, 0))
        if self.params["variant"] == "cloud":
            return dr.exp(-dr.gather(Float, self.tau_max, texel) * w)
        return 1 + w * (dr.gather(Float, self.t_back, texel) - 1)
