"""A toy representation registered at run time (tests/conftest.py): the worked example of
docs/extending.md ("Adding a representation"), kept here so the test suite proves that a kind
defined outside the package joins every registry-driven test and experiment sweep.

``toy_beer``: one uniform medium per texel between its first entry ``a`` and last exit
``b`` holding the texel's total optical depth ``tau``:

    T(d) = exp(-tau clamp((d - a) / (b - a), 0, 1))      (3 floats per texel)

Exact for a single uniform segment; monotone; T = 1 in front of ``a``; differentiable in
the optical depths (a scatter-add), with ``a``/``b`` held fixed.
"""
import drjit as dr

import avsm_dr as ad
from avsm_dr.representations import Param, Representation, Schema


class ToyBeer(Representation):
    """Beer-law toy: one uniform medium per texel between first entry and last exit."""

    schema = Schema(
        params=(Param("scale", "float", 1.0, "multiplies the stored optical depth", min=0.0),),
        examples=({"scale": 1.0},),
        headline={},
        summary="toy: one uniform medium per texel (tests only)",
        paper="-",
    )

    def _build(self):
        segments = self.segments
        Float = segments.Float
        lo, hi = segments.texel_bounds()
        self.front, self.back = Float(lo), Float(hi)
        self.tau = dr.zeros(Float, segments.n_texels)
        if segments.n_segments:
            dr.scatter_reduce(dr.ReduceOp.Add, self.tau, segments.optical_depth * self.params["scale"],
                              segments.texel_of_segment())

    @property
    def nbytes_per_texel(self) -> float:
        return 3 * self.segments.itemsize

    def _eval_texels(self, texel, depth):
        Float = self.Float
        a, b = dr.gather(Float, self.front, texel), dr.gather(Float, self.back, texel)
        tau = dr.gather(Float, self.tau, texel)
        span = b - a
        frac = dr.select(span > 0, dr.clip((depth - a) / dr.select(span > 0, span, 1), 0, 1),
                         dr.select(depth >= a, 1, 0))
        return dr.exp(-tau * frac)


def register():
    """Register ``toy_beer`` (idempotent)."""
    ad.register("toy_beer")(ToyBeer)
