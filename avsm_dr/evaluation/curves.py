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


#: Host bytes per (texel, depth) of :func:`depth_l2` (the float64 curves of the kind and of
#: the reference, and the depth grid of one chunk), checked before allocating.
BYTES_PER_DEPTH = 24


def _check(rep, segments, n_depths, texels):
    """The validated arguments shared by :func:`curve_values` and :func:`depth_l2`:
    (n_depths, texels as int64 or None); ValueError naming the argument."""
    from ..segments import Segments
    if not isinstance(segments, Segments):
        raise ValueError(f"segments: expected avsm_dr.Segments, got {type(segments).__name__}")
    if not callable(getattr(rep, "eval", None)):
        raise ValueError(f"rep: expected a representation (an object with eval(texel, depth)), "
                         f"got {type(rep).__name__}")
    if getattr(rep, "n_texels", segments.n_texels) != segments.n_texels:
        raise ValueError(f"rep: built on {rep.n_texels} texels, the segments have {segments.n_texels}")
    n = V.integer(n_depths, "n_depths", 1)
    if texels is not None:
        t = V.array(texels, "texels")
        if t.ndim != 1 or np.any(t != np.round(t)) or np.any(t < 0) or np.any(t >= segments.n_texels):
            raise ValueError(f"texels: expected a 1-D array of texel indices in [0, {segments.n_texels})")
        texels = t.astype(np.int64)
    rows = int(np.count_nonzero(segments.counts > 0)) if texels is None else int(np.unique(texels).size)
    V.check_memory("n_depths", n, lambda m: float(m) * max(rows, 1) * BYTES_PER_DEPTH, lo=1,
                   what=f"depths on {rows} texels")
    return n, texels


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
    n, texels = _check(rep, segments, n_depths, texels)
    tex, a, b = _nonempty(segments, texels)
    out = np.empty((tex.size, n))
    frac = (np.arange(n) + 0.5) / n
    per = max(1, CHUNK_LANES // n)
    for s in range(0, tex.size, per):
        e = min(tex.size, s + per)
        depth = a[s:e, None] + frac[None, :] * (b[s:e] - a[s:e])[:, None]
        t = np.repeat(tex[s:e], n).astype(np.uint32)
        got = np.asarray(rep.eval(t, depth.ravel()), np.float64).ravel()
        if got.size != t.size:
            raise ValueError(f"rep: eval returned {got.size} values for {t.size} receivers")
        out[s:e] = got.reshape(e - s, n)
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
    n, texels = _check(rep, segments, n_depths, texels)
    if exact is None:
        from ..representations import build
        exact = build("exact", segments)
    if callable(getattr(exact, "eval", None)):
        ref = curve_values(exact, segments, n, texels)
    else:                               # curve values: finite numbers, checked below for shape
        ref = V.array(exact, "exact")
    est = curve_values(rep, segments, n, texels)
    if ref.shape != est.shape:
        raise ValueError(f"exact: expected curve values of shape {est.shape}, got {ref.shape}")
    l2 = np.sqrt(np.mean(np.square(est - ref), axis=1))
    if per_texel:
        return l2
    return float(np.sqrt(np.mean(np.square(l2)))) if l2.size else float("nan")
