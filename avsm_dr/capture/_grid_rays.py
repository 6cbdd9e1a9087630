"""Texel rays of a grid capture: the rays of a light's camera that meet a grid's occupied box
(:func:`hit_lanes`) and the brick keys of the ``"submission"`` order (:func:`brick_keys`).
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from ..geometry import ray_box_dr
from .assembly import TexelRuns
from ._grid_volume import GridVolume


def candidate_texels(camera, lo, hi):
    """Dr.Jit UInt32 texels (ascending) of ``camera.footprint`` for one box ``[lo, hi]``:
    enumerated on the device when the footprint is one rectangle, on the host otherwise."""
    UInt32 = backend.types().UInt32
    rects = [r for r in camera.footprint_rects(lo[None], hi[None]) if r[1][0] >= r[0][0] and r[3][0] >= r[2][0]]
    if len(rects) != 1:
        _, cand = camera.footprint(lo[None], hi[None])
        return A.to_uint32(cand)
    x0, x1, y0, y1, offset = (int(np.asarray(v).reshape(-1)[0]) for v in rects[0])
    w = x1 - x0 + 1
    i = dr.arange(UInt32, w * (y1 - y0 + 1))
    row = i // dr.opaque(UInt32, w)
    return (dr.opaque(UInt32, offset + y0 * camera.res + x0) + row * dr.opaque(UInt32, camera.res)
            + (i - row * dr.opaque(UInt32, w)))


def hit_lanes(grid: GridVolume, camera, per_lane=None):
    """The texels whose ray meets the occupied box: (texels UInt32 ascending, origins,
    directions (lists of three Float64), t_in, t_out (Float64), extra) of the rays that meet
    the occupied box.  One kernel makes, clips and tests every candidate ray (and evaluates
    ``per_lane(o, d, t_in, t_out)``, a UInt32 per ray, returned as ``extra`` for the hit
    lanes; None without it), ``dr.compress`` keeps the hits; the hit lanes' rays are then
    recomputed lazily (fused into the kernel that reads them) rather than stored.  No hit:
    empty texels, and every other entry None."""
    UInt32 = backend.types().UInt32
    lo, hi = grid.occupied
    cand = candidate_texels(camera, lo, hi)
    if dr.width(cand) == 0:
        return cand, None, None, None, None, None
    o, d = camera.rays_device(cand)
    F64 = type(o[0])
    box = [[dr.opaque(F64, float(x)) for x in corner] for corner in (lo, hi)]   # one kernel for any box
    t_in, t_out, hit = ray_box_dr(o, d, *box, t_min=0.0)
    extra = dr.select(hit, per_lane(o, d, t_in, t_out), 0) if per_lane is not None else None
    dr.eval(cand, hit, extra)
    sel = dr.compress(hit)
    if dr.width(sel) == 0:
        return UInt32(), None, None, None, None, None
    lanes = dr.gather(UInt32, cand, sel)
    extra = dr.gather(UInt32, extra, sel) if extra is not None else None
    dr.eval(lanes, extra)                                   # one kernel
    o, d = camera.rays_device(lanes)
    t_in, t_out, _ = ray_box_dr(o, d, *box, t_min=0.0)
    return lanes, o, d, t_in, t_out, extra


#: Bricks of the ``"submission"`` order (:func:`brick_keys`): voxels per side.
SUBMISSION_BRICK = 8


def brick_keys(grid: GridVolume, camera, texels, z0, z1, brick: int = SUBMISSION_BRICK):
    """Draw position of every grid segment in the ``"submission"`` order: the index
    ``(b_z n_y + b_y) n_x + b_x`` (x fastest, the grid's memory order) of the ``brick^3``-voxel
    brick of the whole grid that holds the segment's midpoint ``o + (z0 + z1) / 2 d`` (clamped
    into the grid), as a renderer draws a bricked volume brick by brick, each brick marching
    its stretch of the ray front to back.  texels: (S,) :class:`~.assembly.TexelRuns` or int64
    NumPy; z0, z1: Dr.Jit (S,).  Returns a Dr.Jit UInt32 (S,)."""
    t = backend.types()
    F64, UInt32 = t.Float64, t.UInt32
    tex = texels.device() if isinstance(texels, TexelRuns) else A.to_uint32(np.asarray(texels, np.int64))
    o, d = camera.rays_device(tex)
    zm = 0.5 * (F64(dr.detach(z0)) + F64(dr.detach(z1)))
    nb = -(-np.array(grid.shape[::-1], np.int64) // int(brick))          # bricks along (x, y, z)
    side = grid.voxel * int(brick)
    key = dr.zeros(UInt32, dr.width(tex))
    for a in (2, 1, 0):                                                   # z slowest, x fastest
        lo_a, side_a = dr.opaque(F64, float(grid.bmin[a])), dr.opaque(F64, float(side[a]))
        b = dr.clip(dr.floor((o[a] + d[a] * zm - lo_a) / side_a), 0, dr.opaque(F64, float(nb[a] - 1)))
        key = key * dr.opaque(UInt32, int(nb[a])) + UInt32(b)
    return key
