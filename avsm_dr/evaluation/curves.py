"""The depth-uniform L2 error of a whole transmittance curve against the exact curve.

For each texel t with content, its depth range ``[a_t, b_t]`` runs from its first entry
``min z0`` to its last *visible* exit: ``max z1`` over its segments, where an opaque segment
(optical depth >= ``OPAQUE_OPTICAL_DEPTH``: a blocker's slab) counts with its front face
``z0``.  With ``n`` midpoints ``z_tj = a_t + (j + 1/2) (b_t - a_t) / n`` and ``D_t`` those not
strictly inside an opaque segment::

    L2_t     = sqrt( (1/|D_t|) sum_{j in D_t} (T_rep(t, z_tj) - T_exact(t, z_tj))^2 )
    depth_l2 = sqrt( mean_t L2_t^2 )       (RMS over the texels counted)

i.e. the midpoint rule of ``(1 / |D|) int_D (T_rep - T_exact)^2 dz`` per texel: every depth
of a texel's range weighs alike, wherever the receivers are (per texel, the cost
``norm='l2'`` of the ``optimal`` kind minimises, up to the normalisation by the range).
Not counted: empty texels (T = 1 for every kind), texels whose range is a single depth
(only opaque faces: zero measure) and opaque interiors (a blocker's slab, where no
receiver can be).
"""
from __future__ import annotations

import numpy as np

from .. import validation as V
from ..representations import build
from ..segments import OPAQUE_OPTICAL_DEPTH, Segments

#: Midpoints per texel of :func:`depth_l2`.
DEPTHS = 64
#: Lanes (texels x depths) per ``eval`` call: bounds the device memory of one call.
CHUNK_LANES = 1 << 22
#: Host bytes per (texel, depth) of :func:`depth_l2` (the float64 curves of the kind and of
#: the reference, and the depth grid of one chunk), checked before allocating.
BYTES_PER_DEPTH = 24


def _check(rep, segments, n_depths, texels):
    """(n_depths, texels as int64 or None) checked for ``segments`` and ``rep`` (None: no
    representation); ValueError naming the argument."""
    if not isinstance(segments, Segments):
        raise ValueError(f"segments: expected avsm_dr.Segments, got {type(segments).__name__}")
    if rep is not None and not callable(getattr(rep, "eval", None)):
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


def _domain(segments, texels=None):
    """(texels, a, b): the texels counted (module docstring; all, or of ``texels``, in
    increasing order) and their depth ranges, opaque segments cut to their front face."""
    c = segments.counts
    nz = c > 0
    a, _ = segments.texel_bounds()
    b = np.full(segments.n_texels, -np.inf)
    if nz.any():
        h = segments.numpy()
        visible = np.where(h["optical_depth"] >= OPAQUE_OPTICAL_DEPTH, h["z0"], h["z1"]).astype(np.float64)
        b[nz] = np.maximum.reduceat(visible, segments.offsets[:-1][nz])
    keep = np.flatnonzero(nz & (b > a))
    if texels is not None:
        keep = np.intersect1d(keep, np.asarray(texels, np.int64))
    return keep, a[keep], b[keep]


def rms(x) -> float:
    """``sqrt(mean x^2)`` of an array (NaN when empty)."""
    return float(np.sqrt(np.mean(np.square(x)))) if np.size(x) else float("nan")


def _grid(a, b, n):
    """(T', n) midpoints of ``[a, b]`` per row."""
    return a[:, None] + ((np.arange(n) + 0.5) / n)[None, :] * (b - a)[:, None]


def _counted(segments, tex, a, b, n) -> np.ndarray:
    """(T', n) bool: the midpoints of :func:`_grid` not strictly inside an opaque segment."""
    keep = np.ones((tex.size, n), bool)
    h = segments.numpy()
    op = h["optical_depth"] >= OPAQUE_OPTICAL_DEPTH
    ot = np.repeat(np.arange(segments.n_texels), segments.counts)[op]
    o0, o1 = h["z0"][op].astype(np.float64), h["z1"][op].astype(np.float64)
    row = np.searchsorted(tex, ot)
    hit = (row < tex.size) & (tex[np.minimum(row, tex.size - 1)] == ot) if tex.size else row < 0
    if hit.any():
        row, o0, o1 = row[hit], o0[hit], o1[hit]
        z = _grid(a[row], b[row], n)
        inside = (z > o0[:, None]) & (z < o1[:, None])
        np.logical_and.at(keep, row, ~inside)
    return keep


def depth_grid(segments, n_depths: int = DEPTHS, texels=None):
    """The grid :func:`depth_l2` measures on: ``(texels, depths, counted)``, the T' texels
    counted (increasing, the rows of :func:`curve_values` and ``depth_l2(per_texel=True)``),
    their (T', n_depths) midpoints and the bool mask of those not inside an opaque segment."""
    n, texels = _check(None, segments, n_depths, texels)
    tex, a, b = _domain(segments, texels)
    return tex, _grid(a, b, n), _counted(segments, tex, a, b, n)


def curve_values(rep, segments, n_depths: int = DEPTHS, texels=None) -> np.ndarray:
    """(T', n_depths) float64 values ``rep.eval(t, z_tj)`` on the midpoint grid of the
    module docstring, for the T' texels counted (of ``segments``, or of ``texels``, in
    increasing order); ``rep`` is any object with ``eval(texel, depth)`` built on
    ``segments`` (e.g. composed with an opaque depth map)."""
    n, texels = _check(rep, segments, n_depths, texels)
    tex, a, b = _domain(segments, texels)
    out = np.empty((tex.size, n))
    per = max(1, CHUNK_LANES // n)
    for s in range(0, tex.size, per):
        e = min(tex.size, s + per)
        depth = _grid(a[s:e], b[s:e], n)
        t = np.repeat(tex[s:e], n).astype(np.uint32)
        got = np.asarray(rep.eval(t, depth.ravel()), np.float64).ravel()
        if got.size != t.size:
            raise ValueError(f"rep: eval returned {got.size} values for {t.size} receivers")
        out[s:e] = got.reshape(e - s, n)
    return out


def depth_l2(rep, segments, exact=None, n_depths: int = DEPTHS, texels=None, per_texel: bool = False):
    """Depth-uniform L2 of ``rep``'s curve against the exact one (module docstring): the RMS
    over the texels counted (NaN when there is none), or with ``per_texel`` the (T',) array
    of ``L2_t``.

    rep: built on ``segments`` (anything with ``eval(texel, depth)``).  exact: the reference,
    None (``build('exact', segments)``), a representation, or its :func:`curve_values` on
    the same grid (reused across many ``rep``).  n_depths: midpoints per texel.  texels:
    restrict to these texels (default: every non-empty one)."""
    n, texels = _check(rep, segments, n_depths, texels)
    if exact is None:
        exact = build("exact", segments)
    if callable(getattr(exact, "eval", None)):
        ref = curve_values(exact, segments, n, texels)
    else:                               # curve values: finite numbers, checked below for shape
        ref = V.array(exact, "exact")
    est = curve_values(rep, segments, n, texels)
    if ref.shape != est.shape:
        raise ValueError(f"exact: expected curve values of shape {est.shape}, got {ref.shape}")
    keep = _counted(segments, *_domain(segments, texels), n)
    l2 = np.sqrt(np.sum(np.square(est - ref) * keep, axis=1) / np.maximum(keep.sum(axis=1), 1))
    return l2 if per_texel else rms(l2)
