"""Lanes of a grid capture: the rays of a light's camera that meet a grid's occupied box
(:func:`hit_lanes`), the brick keys of the ``"submission"`` order (:func:`brick_keys`), and
the slot buffers of :mod:`.grid` and :mod:`.dda` (:func:`slot_rounds`): every lane writes its
segments (z0, z1, tau) into its own run of slots (a slot is 4 floats, one packet store or load
per segment), then the filled slots are gathered into CSR order.
"""
from __future__ import annotations

import time

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from ..geometry import ray_box_dr
from .assembly import TexelRuns
from ._grid_volume import GridVolume, segment_tau


def candidate_texels(camera, lo, hi):
    """Dr.Jit UInt32 candidate texels (ascending) of ``camera`` for one box ``[lo, hi]``:
    enumerated on the device when the footprint is one rectangle, on the host otherwise."""
    UInt32 = backend.types().UInt32
    rects = [r for r in camera.footprint_rects(lo[None], hi[None]) if r[1][0] >= r[0][0] and r[3][0] >= r[2][0]]
    if len(rects) != 1:
        cand = [t for _, t in camera.footprint_chunks(lo[None], hi[None])]
        return A.to_uint32(np.concatenate(cand) if cand else np.zeros(0, np.int64))
    x0, x1, y0, y1, offset = (int(np.asarray(v).reshape(-1)[0]) for v in rects[0])
    w = x1 - x0 + 1
    i = dr.arange(UInt32, w * (y1 - y0 + 1))
    row = i // dr.opaque(UInt32, w)
    return (dr.opaque(UInt32, offset + y0 * camera.res + x0) + row * dr.opaque(UInt32, camera.res)
            + (i - row * dr.opaque(UInt32, w)))


def hit_lanes(grid: GridVolume, camera, per_lane):
    """(texels int64 NumPy ascending, origins, directions (lists of three Float64), t_in, t_out
    (Float64), extra) of the rays that meet the grid's occupied box, ``extra`` the UInt32
    ``per_lane(o, d, t_in, t_out)`` evaluated in the kernel that makes, clips and tests every
    candidate ray.  No hit (or an all-zero grid): empty texels, and every other entry None."""
    UInt32 = backend.types().UInt32
    none = (np.zeros(0, np.int64),) + (None,) * 5
    if grid.occupied is None:
        return none
    lo, hi = grid.occupied
    cand = candidate_texels(camera, lo, hi)
    if dr.width(cand) == 0:
        return none
    o, d = camera.rays_device(cand)
    F64 = type(o[0])
    box = [[dr.opaque(F64, float(x)) for x in corner] for corner in (lo, hi)]   # one kernel for any box
    t_in, t_out, hit = ray_box_dr(o, d, *box, t_min=0.0)
    extra = dr.select(hit, per_lane(o, d, t_in, t_out), 0)
    dr.eval(cand, hit, extra)
    sel = dr.compress(hit)
    if dr.width(sel) == 0:
        return none
    lanes = dr.gather(UInt32, cand, sel)
    extra = dr.gather(UInt32, extra, sel)
    dr.eval(lanes, extra)                                   # one kernel
    o, d = camera.rays_device(lanes)
    t_in, t_out, _ = ray_box_dr(o, d, *box, t_min=0.0)
    return np.asarray(lanes.numpy(), np.int64), o, d, t_in, t_out, extra


def lane_output(grid: GridVolume, camera, lanes, counts, iters, max_iter: int, res, stats: dict, runs: bool):
    """``(texel, z0, z1, tau, stats)`` of a grid capture whose lane ``i`` (texel ``lanes[i]``)
    holds ``counts[i]`` segments ``res`` = (z0, z1, tau), in lane order, after ``iters[i]``
    iterations (RuntimeError at ``max_iter``): ``tau`` recomputed from differentiable gathers
    (:func:`~._grid_volume.segment_tau`) when the grid's data has gradients; texels as
    :class:`~.assembly.TexelRuns` with ``runs``, else one int64 each (empty without segments)."""
    S = int(counts.sum())
    stats.update(lanes=lanes.size, iterations=int(iters.sum()), segments=S, max_iterations=int(iters.max()))
    if stats["max_iterations"] >= max_iter:
        raise RuntimeError(f"grid capture: a ray hit the iteration bound {max_iter} (DDA did not advance)")
    z0, z1, tau = res
    if S == 0:
        return np.zeros(0, np.int64), z0, z1, tau, stats
    if dr.grad_enabled(grid.data):
        o, d = camera.rays(lanes)
        tau = segment_tau(grid, *([A.to_float(np.ascontiguousarray(v[:, i]), grid.Float) for i in range(3)]
                                  for v in (o, d)), counts, z0, z1)
    texel = TexelRuns(lanes, counts) if runs else np.repeat(lanes.astype(np.int64), counts)
    return texel, z0, z1, tau, stats


#: Bricks of the ``"submission"`` order (:func:`brick_keys`): voxels per side.
SUBMISSION_BRICK = 8


def brick_keys(grid: GridVolume, camera, texels, z0, z1):
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
    nb = -(-np.array(grid.shape[::-1], np.int64) // SUBMISSION_BRICK)    # bricks along (x, y, z)
    side = grid.voxel * SUBMISSION_BRICK
    key = dr.zeros(UInt32, dr.width(tex))
    for a in (2, 1, 0):                                                   # z slowest, x fastest
        lo_a, side_a = dr.opaque(F64, float(grid.bmin[a])), dr.opaque(F64, float(side[a]))
        b = dr.clip(dr.floor((o[a] + d[a] * zm - lo_a) / side_a), 0, dr.opaque(F64, float(nb[a] - 1)))
        key = key * dr.opaque(UInt32, int(nb[a])) + UInt32(b)
    return key


def _arr4(Float):
    t = backend.types()
    return t.Array4f if Float is t.Float else t.Array4f64


def write_slots(buf, values, idx, active) -> None:
    """Write (z0, z1, tau) ``values`` at slots ``idx`` of a slot buffer (4 floats per slot)."""
    dr.scatter(buf, _arr4(type(values[0]))(*values, 0), idx, active)


def read_slots(buf, idx, active=True) -> list:
    """(z0, z1, tau) at slots ``idx`` of a slot buffer."""
    v = dr.gather(_arr4(type(buf)), buf, idx, active)
    return [v[0], v[1], v[2]]


def compact_slots(buf, slot, counts, n_segments: int):
    """The first ``counts[i]`` slots from ``slot[i]`` of every lane i of the slot buffer
    ``buf``, in lane order (CSR).  Output segment k of lane i reads slot
    ``k + slot[i] - off[i]`` (``off``: exclusive prefix sum of ``counts``); that shift is
    built without a per-segment lookup of the lane: a ``scatter_add`` at every lane's
    offset of the change of shift from the previous lane (``cap - count`` of that lane,
    ``cap`` = the slot gap), then an inclusive prefix sum (modulo 2^32)."""
    UInt32 = type(counts)
    Float = type(buf)
    if n_segments == 0:
        return Float(), Float(), Float()
    n = dr.width(counts)
    off = dr.prefix_sum(counts)
    i = dr.arange(UInt32, n)
    prev = dr.maximum(i, 1) - 1
    step = dr.select(i > 0, slot - dr.gather(UInt32, slot, prev) - dr.gather(UInt32, counts, prev), 0)
    shift = dr.zeros(UInt32, n_segments)
    # Direct (atomic) mode: Auto may pick Expand on the LLVM backend, which bakes the target's
    # size into the kernel (a new compile for every capture)
    dr.scatter_add(shift, step, off, off < dr.opaque(UInt32, n_segments), mode=dr.ReduceMode.Direct)
    src = dr.arange(UInt32, n_segments) + dr.cumsum(shift)
    out = read_slots(buf, src)
    dr.eval(out)
    dr.sync_thread()
    return out


#: Most output slots of the one-round layout of :func:`slot_rounds`; above it, rounds.
SLOT_BUDGET = 1 << 25
#: Segments a lane writes per round into its own slots; lanes with more go on in another round.
ROUND_CAPACITY = 16


def slot_rounds(body, const, state, cap, tally, slot_budget: int, capacity: int, times: dict, label: str):
    """Run a lane loop to the end and gather its segments in CSR (lane) order.

    ``body(const, bufs, slot)`` is the body of loop ``label`` over ``(*state, n, done)`` for the
    lanes of ``const`` (per-lane constants), writing segment ``n`` (z0, z1, tau) at slot ``slot
    + n`` of ``bufs``; a round resumes every lane from ``state`` and runs it until it is done or
    has written ``cap`` segments.  One round with ``cap`` slots
    per lane (a bound of its segments) and :func:`compact_slots` while they fit ``slot_budget``;
    otherwise, or when a lane overflowed its bound, rounds of ``capacity`` slots per unfinished
    lane, each resuming from the saved state (the same segments).  Returns ``(counts, final,
    (z0, z1, tau), stats)``: ``final`` the int64 NumPy final ``state[i]`` of every lane for ``i``
    in ``tally``; ``stats`` the rounds (and the slots of the one-round layout)."""
    t = backend.types()
    UInt32, Float = t.UInt32, type(state[0])
    L, K = dr.width(cap), int(capacity)

    def run(cst, state, bufs, slot, cap):
        n = dr.width(state[0])
        return dr.while_loop(tuple(state) + (dr.zeros(UInt32, n), dr.zeros(t.Bool, n)),
                             lambda *s: ~s[-1] & (s[-2] < cap), body(cst, bufs, slot), label=label)
    clock = time.perf_counter()
    dr.eval(cap)
    n_slots = int(dr.sum(t.UInt64(cap))[0])
    if n_slots <= slot_budget:
        bufs = dr.empty(Float, 4 * n_slots)
        slot = dr.prefix_sum(cap)
        out = run(const, state, bufs, slot, cap)
        dr.eval(out, bufs)
        if bool(dr.all(out[-1])):
            counts = np.asarray(out[-2].numpy(), np.int64)
            times["rounds_s"], clock = time.perf_counter() - clock, time.perf_counter()
            res = compact_slots(bufs, slot, out[-2], int(counts.sum()))
            times["compact_s"] = time.perf_counter() - clock
            return counts, [np.asarray(out[i].numpy(), np.int64) for i in tally], res, {"rounds": 1, "slots": n_slots}
        clock = time.perf_counter()                          # a lane overflowed its bound: rounds

    active = np.arange(L, dtype=np.int64)      # lanes of this round (indices into 0..L-1)
    cst = const
    rounds = []                                # (lanes, n per lane, buffers)
    counts = np.zeros(L, np.int64)
    final = [np.zeros(L, np.int64) for _ in tally]
    while active.size:
        bufs = dr.empty(Float, 4 * active.size * K)
        out = run(cst, state, bufs, dr.arange(UInt32, active.size) * K, K)
        dr.eval(out, bufs)
        n_r = np.asarray(out[-2].numpy(), np.int64)
        done = np.asarray(out[-1].numpy(), bool)
        rounds.append((active, n_r, bufs))
        counts[active] += n_r
        for f, i in zip(final, tally):
            f[active[done]] = np.asarray(out[i].numpy(), np.int64)[done]
        keep = np.flatnonzero(~done)
        active = active[keep]
        if active.size:
            k_sel, a_sel = A.to_uint32(keep), A.to_uint32(active)
            state = [dr.gather(type(v), v, k_sel) for v in out[:-2]]
            cst = [dr.gather(type(v), v, a_sel) for v in const]
    times["rounds_s"], clock = time.perf_counter() - clock, time.perf_counter()

    # ---- compaction: slot j < n of lane i of a round -> offset[i] + (segments of earlier rounds) + j
    S = int(counts.sum())
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    written = np.zeros(L, np.int64)
    res = [dr.zeros(Float, S) for _ in range(3)]
    for lanes_r, n_r, bufs in rounds:
        base = A.to_uint32(start[lanes_r] + written[lanes_r])
        written[lanes_r] += n_r
        slot = dr.arange(UInt32, lanes_r.size * K)
        i = slot // K
        j = slot - i * K
        ok = j < dr.gather(UInt32, A.to_uint32(n_r), i)
        dst = dr.gather(UInt32, base, i, ok) + j
        for src, dst_buf in zip(read_slots(bufs, slot, ok), res):
            dr.scatter(dst_buf, src, dst, ok)
    dr.eval(res)
    dr.sync_thread()
    times["compact_s"] = time.perf_counter() - clock
    return counts, final, res, {"rounds": len(rounds)}
