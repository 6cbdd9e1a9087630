"""Beer shadow map (Hillaire 2016, "Physically based sky, atmosphere and cloud rendering in
Frostbite", SIGGRAPH 2016 course "Physically Based Shading in Theory and Practice", the
clouds chapter's Beer shadow map): one homogeneous medium per texel, three numbers.

Per texel, with ``a`` = first entry (min z0), ``b`` = last exit (max z1) and
``tau_max`` = the texel's total optical depth (sum of its segments' tau):

* ``variant='cloud'`` (the paper's): front depth ``a``, mean extinction
  ``sigma_mean = tau_max / (b - a)`` (the total optical depth spread uniformly over the
  texel's content, empty gaps included) and ``tau_max``;

      T(d) = exp(-min(tau_max, sigma_mean * max(0, d - a)))

  exact for one uniform segment.  A texel whose content has no extent (``b = a``: only
  zero-length segments at one depth) stores ``sigma_mean = 0`` and is a step at ``a``
  (``T(a) = exp(-tau_max)``: a receiver at a step is behind it, as in :mod:`.exact`).
* ``variant='two_node'``: nodes ``(a, 1)`` and ``(b, exp(-tau_max))`` (depth and T at the
  entry and exit of the texel's content) stored as ``a, b, exp(-tau_max)``, *linear*
  interpolation between them (with exponential interpolation it would be the cloud
  variant), ``T = 1`` in front, ``exp(-tau_max)`` behind.

Storage: 3 floats per texel in the segments' dtype (``nbytes_per_texel = 3 itemsize``);
``precision='float32'|'float16'`` stores them in that format, depths relative to one
global range (:mod:`._precision`); the unorm formats are refused.
Gradients flow to the optical depths (``tau_max`` is a scatter-add); ``a`` and ``b`` are
taken from the segments' depths without gradients.
"""
from __future__ import annotations

import drjit as dr

from .. import _arrays as A
from .base import Representation
from ._precision import Stored
from .registry import register
from .schema import Param, Schema

VARIANTS = ("cloud", "two_node")


@register("beer")
class BeerShadowMap(Representation):
    """Beer shadow map: front depth, mean extinction and maximum optical depth per texel
    (``variant='cloud'``), or two (depth, T) nodes with linear interpolation
    (``variant='two_node'``); see the module docstring.

    Attributes: ``front``, ``back`` (Dr.Jit, texel content bounds), ``tau_max`` (total
    optical depth per texel), ``sigma_mean`` (``tau_max / (back - front)``, 0 where
    ``back = front``).
    """

    schema = Schema(
        params=(Param("variant", "choice", "cloud", "'cloud': (front depth, mean extinction, max optical "
                      "depth), Hillaire 2016; 'two_node': (depth, T) at entry and exit, linear in between",
                      choices=VARIANTS),),
        examples=({"variant": "cloud"}, {"variant": "two_node"}),
        headline={"variant": "cloud"},
        summary="one homogeneous medium per texel: front depth, mean extinction, max optical depth",
        paper="Hillaire 2016",
    )

    def __init__(self, segments, **params):
        super().__init__(segments, **params)
        Float = segments.Float
        lo, hi = segments.texel_bounds()
        if self.precision is not None and segments.n_segments:
            # empty texels (T = 1 whatever their bounds) must not widen the global depth range
            empty = segments.counts == 0
            lo[empty], hi[empty] = segments.bounds()
        self.front, self.back = Float(A.aligned(lo)), Float(A.aligned(hi))
        # tau_max: total optical depth of the texel (one lane per segment, scatter-add)
        self.tau_max = dr.zeros(Float, segments.n_texels)
        if segments.n_segments:
            dr.scatter_reduce(dr.ReduceOp.Add, self.tau_max, segments.optical_depth,
                              segments.texel_of_segment())
        span = self.back - self.front
        safe = dr.select(span > 0, span, 1)
        self.sigma_mean = dr.select(span > 0, self.tau_max / safe, 0)
        self.t_back = dr.exp(-self.tau_max)
        dr.eval(self.tau_max, self.sigma_mean, self.t_back)

    @property
    def variant(self) -> str:
        """'cloud' or 'two_node'."""
        return self.params["variant"]

    # precision: floating formats only (see _precision_note)
    precisions = ("float32", "float16")
    _precision_note = ("; beer's mean extinction and optical depth are unbounded per-texel scalars, and a "
                       "fixed-point code would need a per-texel scale as large as the value itself")

    def _stored(self):
        """Depths relative to one global range; 'cloud': sigma_mean, tau_max (float16
        saturates at 65504, where T = 0 anyway); 'two_node': T behind."""
        if self.variant == "cloud":
            return (Stored("front", "depth", "texel"), Stored("sigma_mean", "scalar", "texel"),
                    Stored("tau_max", "scalar", "texel"))
        return (Stored("front", "depth", "texel"), Stored("back", "depth", "texel"),
                Stored("t_back", "transmittance", "texel"))

    @property
    def nbytes_per_texel(self) -> float:
        if self.precision is not None:
            return self._stored_nbytes
        return 3 * self.segments.itemsize

    def _eval_texels(self, texel, depth):
        Float = self.Float
        a = dr.gather(Float, self.front, texel)
        if self.variant == "cloud":
            sigma = dr.gather(Float, self.sigma_mean, texel)
            tau_max = dr.gather(Float, self.tau_max, texel)
            x = dr.maximum(depth - a, 0)
            # sigma = 0 with tau_max > 0 only for content without extent: a step at a
            od = dr.select(sigma > 0, dr.minimum(tau_max, sigma * x), dr.select(depth >= a, tau_max, 0))
            return dr.exp(-od)
        b = dr.gather(Float, self.back, texel)
        tb = dr.gather(Float, self.t_back, texel)
        span = b - a
        w = dr.clip((depth - a) / dr.select(span > 0, span, 1), 0, 1)
        w = dr.select(span > 0, w, dr.select(depth >= a, 1, 0))
        return 1 + w * (tb - 1)
