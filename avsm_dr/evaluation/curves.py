"""The depth-uniform L2 error of a whole transmittance curve against the exact curve.

For each non-empty texel t with depth range ``[a_t, b_t]`` (its first entry ``min z0`` and
last exit ``max z1``) and ``n`` midpoints ``z_tj = a_t + (j + 1/2) (b_t - a_t) / n``::

    L2_t     = sqrt( (1/n) sum_j (T_rep(t, z_tj) - T_exact(t, z_tj))^2 )
    depth_l2 = sqrt( mean_t L2_t^2 )       (RMS over the non-empty texels)

i.e. the midpoint rule of ``(1 / (b - a)) int_a^b (T_rep - T_exact)^2 dz`` per texel.  Unlike
the receiver RMSE it weighs every depth of a texel's range alike, wherever the receivers
are: per texel, the cost ``norm='l2'`` of the ``optimal`` kind minimises (up to the
normalisation by the range).  Empty texels (T = 1 for every kind) do not count.
"""
from __future__ import annotations

import numpy as np

from .. import validation as V

#: Midpoints per texel of :func:`depth_l2`.
DEPTHS = 64
#: Lanes (texels x depths) per ``eval`` call: bounds the device memory of one call.
CHUNK_LANES = 1 << 22


def _nonempty(segments, texels=None):
    """(texels, a, b): the non-empty texels (all, or of ``texels``) and their depth ranges."""
    nz = np.flatnonzero(segments.counts > 0)
    if texels is not None:
        nz = np.intersect1d(nz, np.asarray(texels, np.int64))
    a, b = segments.texel_bounds()
    return nz, a[nz], b[nz]


def curve_values(rep, segments, n_depths: int = DEPTHS, texels=None) -> np.ndarray:
    """(T', n_depths) float64 values ``rep.eval(t, z_tj)`` on the midpoint grid of the
    module docstring, for the T' non-empty texels of ``segments`` (or of ``texels``, in
    increasing order); ``rep`` is any object with ``eval(texel, depth)`` built on
    ``segments`` (e.g. composed with an opaque depth map)."""
    n = V.integer(n_depths, "n_depths", 1)
    tex, a, b = _nonempty(segments, texels)
    out = np.empty((tex.size, n))
    frac = (np.arange(n) + 0.5) / n
    per = max(1, CHUNK_LANES // n)
    for s in range(0, tex.size, per):
        e = min(tex.size, s + per)
        depth = a[s:e, None] + frac[None, :] * (b[s:e] - a[s:e])[:, None]
        t = np.repeat(tex[s:e], n).astype(np.uint32)
        out[s:e] = np.asarray(rep.eval(t, depth.ravel()), np.float64).reshape(e - s, n)
    return out


def depth_l2(rep, segments, exact=None, n_depths: int = DEPTHS, texels=None, per_texel: bool = False):
    """Depth-uniform L2 of ``rep``'s curve against the exact one (module docstring).

    rep: a representation built on ``segments`` (anything with ``eval(texel, depth)``).
    exact: the reference - None (``build('exact', segments)``), a representation, or its
        :func:`curve_values` on the same grid (reused across many ``rep``).
    n_depths: midpoints per texel (default :data:`DEPTHS`).
    texels: restrict to these texels (default: every non-empty one).
    Returns the float RMS over non-empty texels (NaN when there is none), or with
    ``per_texel`` the (T',) array of ``L2_t``.
    """
    n = V.integer(n_depths, "n_depths", 1)
    if exact is None:
        from ..representations import build
        exact = build("exact", segments)
    ref = exact if isinstance(exact, np.ndarray) else curve_values(exact, segments, n, texels)
    est = curve_values(rep, segments, n, texels)
    if ref.shape != est.shape:
        raise ValueError(f"exact: expected curve values of shape {est.shape}, got {ref.shape}")
    l2 = np.sqrt(np.mean(np.square(est - ref), axis=1))
    if per_texel:
        return l2
    return float(np.sqrt(np.mean(np.square(l2)))) if l2.size else float("nan")
