"""Error decomposition of a shadow-map lookup against the true transmittance.

For a receiver ``x`` at light-space depth ``z`` with bilinear taps ``(texel_i, w_i)``,
``i = 1..4`` (the filter of :mod:`avsm_dr.filtering`)::

    e_total       = T_rep(x) - T(x)                                      vs the truth
    e_compression = sum_i w_i [T_rep(texel_i, z) - T_exact(texel_i, z)]  the representation
    e_capture     = sum_i w_i [T_exact(texel_i, z) - T(r_i(z))]          the segments vs the
                    true integral along the texel's own ray r_i, to the receiver's depth
    e_spatial     = sum_i w_i T(r_i(z)) - T(x)                           one ray per texel and
                    the filter, vs the receiver's own light path

so ``e_total = e_compression + e_capture + e_spatial`` receiver by receiver.  ``T`` is
:func:`avsm_dr.groundtruth.transmittance` with ``method='raymarch'``: a float64 midpoint
rule through the same trilinear grid (step = 1/8 voxel), times the analytic particle,
hair and blocker factors.

Points the light map does not cover get T = 1 from every representation (the border
convention of :meth:`avsm_dr.capture.Capture.lookup`); there the taps are unused and
``e_capture = 0``.
"""
from __future__ import annotations

import copy
import dataclasses

import numpy as np

from ..capture.opaque_map import compose
from ..filtering import bilinear_taps
from ..receivers import marched
from ..representations import build, describe


def truth(scene, points, step_fraction: float = 0.125) -> np.ndarray:
    """(K,) float64 true transmittance ``T`` (module docstring) at world points."""
    return marched(scene, points, step_fraction)


class Probe:
    """One receiver set seen through one capture: bilinear taps, the truth at the receivers
    and (on the first ``n_decomp`` receivers) at the taps' texel rays; :meth:`lookup` through
    it, :meth:`terms` of the module docstring."""

    def __init__(self, cap, scene, points, n_decomp: int, truth_at_points=None):
        self.cap = cap
        p = np.asarray(points, np.float64)
        self.k = p.shape[0]
        coords, self.depth = cap.lookup(p, continuous=True)
        self.inside = cap.covers(p)
        self.tex, self.weights = bilinear_taps(coords, cap.width, cap.height)     # (4, K) int64, float64
        self.truth = truth(scene, p) if truth_at_points is None else np.asarray(truth_at_points, np.float64)
        # truth along each tap's texel ray to the receiver's depth, on the first n_decomp receivers
        m = self.n_decomp = min(int(n_decomp), self.k)
        o, d = cap.camera.rays(self.tex[:, :m].ravel())
        q = o + np.tile(self.depth[:m], 4)[:, None] * d
        t_taps = truth(scene, q).reshape(4, m)
        self.truth_taps = np.where(self.inside[:m], np.sum(self.weights[:, :m] * t_taps, axis=0), 1.0)

    def with_capture(self, cap) -> "Probe":
        """The same receivers through another capture with the same light camera (e.g. the
        ``opaque='separate'`` capture of the same scene): taps and truth are reused."""
        if (cap.width, cap.height) != (self.cap.width, self.cap.height):
            raise ValueError("cap: expected a capture with the same light camera")
        other = copy.copy(self)
        other.cap = cap
        return other

    def lookup(self, rep) -> np.ndarray:
        """(K,) float64 bilinear lookup at the receivers (1 outside the map) of ``rep``: a
        representation built on the whole map of the capture (composed with its opaque depth
        map), or a :class:`Built`."""
        tex = self.tex
        if isinstance(rep, Built):
            tex = rep.remap[tex]
            rep = compose(rep.rep, rep.opaque_depth)
        else:
            rep = compose(rep, self.cap.opaque_depth)
        T = np.asarray(rep.eval(tex.ravel(), np.tile(self.depth, 4)), np.float64).reshape(4, self.k)
        return np.where(self.inside, np.sum(self.weights * T, axis=0), 1.0)

    def terms(self, estimate, exact) -> dict:
        """Signed per-receiver errors: ``total``, ``compression`` (K,); ``capture``,
        ``spatial``, ``total_decomp`` on the first ``n_decomp`` receivers (their sum with
        ``compression[:n_decomp]`` is ``total_decomp`` to float64 rounding)."""
        m = self.n_decomp
        return {"total": estimate - self.truth, "compression": estimate - exact,
                "capture": exact[:m] - self.truth_taps, "spatial": self.truth_taps - self.truth[:m],
                "total_decomp": estimate[:m] - self.truth[:m]}


@dataclasses.dataclass
class Built:
    """A representation built on a subset of a map's texels: ``rep`` over the subset,
    ``remap`` (full texel index -> subset index, -1 elsewhere), its opaque depth map."""
    rep: object
    remap: np.ndarray
    opaque_depth: np.ndarray | None


class SubsetBuilder:
    """Builds representations on only the texels some probes touch.

    Every kind's kernel works per texel; what a kind takes from the whole map is its global
    depth range, so kinds whose schema has ``near``/``far`` get the full map's bounds
    (unless ``depth_range='texel'`` or given).  Lookups through :class:`Probe` then equal
    those of a build on the whole map; ``nbytes_per_texel`` of variable-size kinds is the
    mean over the subset."""

    def __init__(self, segments, texels, opaque_depth=None):
        self.texels = np.unique(np.asarray(texels, np.int64))
        self.segments = segments.select_texels(self.texels)
        self.remap = np.full(segments.n_texels, -1, np.int64)
        self.remap[self.texels] = np.arange(self.texels.size)
        self.near, self.far = segments.bounds()
        self.opaque_depth = None if opaque_depth is None else np.asarray(opaque_depth)[self.texels]

    def params(self, kind, params: dict) -> dict:
        """``params`` with the full map's near/far added where ``kind`` (a registered name or
        a :class:`~avsm_dr.Representation` subclass) takes a global range."""
        schema = kind.schema.describe()["params"] if isinstance(kind, type) else describe(kind)["params"]
        p = dict(params)
        if "near" in schema and "far" in schema and p.get("depth_range", "global") == "global" \
                and p.get("near") is None and p.get("far") is None:
            p.update(near=self.near, far=self.far)
        return p

    def build(self, kind, params: dict) -> Built:
        """``kind`` (a registered name or a :class:`~avsm_dr.Representation` subclass) with
        ``params`` on the subset."""
        p = self.params(kind, params)
        rep = kind(self.segments, **p) if isinstance(kind, type) else build(kind, self.segments, **p)
        return Built(rep, self.remap, self.opaque_depth)
