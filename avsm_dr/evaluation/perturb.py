"""Perturbations of captured segments that probe a representation's depth range: a faint
segment behind every texel's content stretches the depth spread within the texel while the
transmittance in front of it does not change (:func:`with_faint_segments`)."""
from __future__ import annotations

import numpy as np


def with_faint_segments(segments, stretch: float, optical_depth: float = 0.01):
    """Segments with one faint segment appended to every non-empty texel, at
    ``near_t + stretch (far_t - near_t)`` (its own bounds), of length ``0.01 (far_t - near_t)``
    and optical depth ``optical_depth``: the depth spread *within* a texel grows
    ``stretch`` times while T in front of ``far_t`` does not change."""
    from ..segments import Segments
    h = segments.numpy()
    off, c = h["offsets"], segments.counts
    near, far = segments.texel_bounds()
    nz = np.nonzero(c > 0)[0]
    span = far[nz] - near[nz]
    z0f = near[nz] + stretch * span
    ins = off[1:][nz]                                   # insert at the end of each texel
    z0 = np.insert(h["z0"], ins, z0f)
    z1 = np.insert(h["z1"], ins, z0f + 0.01 * span)
    tau = np.insert(h["optical_depth"], ins, optical_depth)
    add = np.zeros(segments.n_texels + 1, np.int64)
    add[1:] = np.cumsum(c > 0)
    return Segments.from_arrays(off + add, z0, z1, optical_depth=tau, dtype=segments.dtype)
