"""Exact light-ray integration of a trilinear density grid: one segment per dual-cell crossing.

In the *dual grid* of a :class:`~avsm_dr.capture.grid.GridVolume` (cells whose corners are
8 neighbouring voxel centres, plus the half-voxel band at the box's edge where the lookup
clamps) ``sigma`` is one trilinear polynomial, so along a ray ``o + t d`` inside one dual
cell it is a cubic in ``t`` and Simpson's rule over the crossing ``[t_a, t_b]`` ::

    tau = (t_b - t_a) / 6 * (sigma(t_a) + 4 sigma((t_a + t_b) / 2) + sigma(t_b))

is exact.  The ray's breakpoints are its crossings of the voxel-centre planes and of the
faces of the occupied part of the box (outside which sigma is 0).

Traversal: one Dr.Jit lane per texel ray, a 3-D DDA [Amanatides & Woo, "A Fast Voxel
Traversal Algorithm for Ray Tracing", Eurographics 1987] over the dual cells, an empty
``block^3`` block crossed in one iteration.  Robust in float32:

* the cell index is an integer per axis; an iteration moves one axis by one cell (or to
  the next block), so the loop is bounded by the number of cells (checked);
* the next plane's ray parameter is computed afresh from its integer index,
  ``s_b = (plane_b - u_b) / du_b`` (no accumulated ``tMax += tDelta`` drift), and the
  new crossing end is ``max(s, min_b s_b)``: rounding gives zero-length crossings,
  never a step back;
* axes the ray crosses less than :data:`_GRAZING_CELLS` cells along are never chosen;
* sigma inside a crossing is evaluated with the cell's own 8 corners, so the polynomial is
  the cell's even where rounding puts a sample a few ulps across a plane.

Output as :func:`~avsm_dr.capture.grid.march` (slots: one per dual cell the clipped ray
meets, + 3); above :data:`SLOT_BUDGET` slots, rounds of :data:`ROUND_CAPACITY` segments per
unfinished lane, each resuming from the saved state.  Gradients as the march's (exact: a
segment lies in one dual cell).
"""
from __future__ import annotations

import time

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from ._grid_lanes import compact_slots, hit_lanes, lane_output, new_slots, read_slots, write_slots
from ._grid_volume import corner_table, dual_block_max, dual_grid  # noqa: F401

#: Parameter of a plane the ray never reaches (grazing axes); beyond every ray's end.
_FAR = 1e30
#: Most output slots of the one-round layout (one per dual cell a ray meets); above it, rounds.
SLOT_BUDGET = 1 << 25
#: Segments a lane writes per round into its own slots; lanes with more go on in another round.
ROUND_CAPACITY = 16
#: Axes along which a ray moves less than this many cells over its whole length are
#: treated as parallel (never crossed): the cell polynomial is then evaluated at most
#: this far outside its cell, a change of sigma far below float32 rounding.
_GRAZING_CELLS = 1e-6
def lane_constants(grid, o, d, t_in, t_out):
    """Per-lane constants of the traversal from device float64 rays (lists of three Float64,
    clipped to ``[t_in, t_out]``), the float64 formulas then rounded to ``grid.Float``:
    (u_in (3), du (3), inv (3), s_end, t_in) as Floats, the first cell (3 Int32) and the
    slot bound (UInt32: dual cells the ray meets + 3, for float32 rounding at its ends).

    Position in window dual-cell units ``u = (p - lo) / h - 1/2``, its rate ``du = d / h``,
    the first cell (on a plane and moving down: the lower one) and ``1 / du`` (0: an axis
    the ray crosses less than :data:`_GRAZING_CELLS` cells along, never crossed)."""
    t = backend.types()
    F64, Float = type(t_in), grid.Float
    h = grid.voxel
    wlo = grid.bmin + (grid.window_lo + 0.5) * h                   # u = 0: window voxel 0's centre
    wlen = np.array(grid.window_shape[::-1], np.int64)             # (wx, wy, wz)
    s_end = t_out - t_in
    u_in, du, inv, cell = [], [], [], []
    cap = dr.zeros(F64, dr.width(t_in)) + 3
    for a in range(3):
        h_a = dr.opaque(F64, float(h[a]))
        ua = (o[a] + d[a] * t_in - dr.opaque(F64, float(wlo[a]))) / h_a
        dua = d[a] / h_a
        flat = dr.abs(dua) * s_end < _GRAZING_CELLS
        ca = dr.floor(ua)
        ca = dr.select((dua < 0) & ~flat & (ca == ua), ca - 1, ca)
        inv.append(Float(dr.select(flat, 0.0, 1.0 / dua)))
        u_in.append(Float(ua))
        du.append(Float(dua))
        cell.append(t.Int32(dr.clip(ca, -1, dr.opaque(F64, float(wlen[a] - 1)))))
        cap += dr.abs(dr.floor(ua + dua * s_end) - dr.floor(ua))
    return u_in + du + inv + [Float(s_end), Float(t_in)], cell, t.UInt32(dr.select(dr.isfinite(cap), cap, 0))


def traverse(grid, camera, epsilon: float, keep_zero: bool = False, capacity: int = ROUND_CAPACITY,
             slot_budget: int = SLOT_BUDGET, runs: bool = False):
    """Integrate every texel ray of ``camera`` through ``grid`` exactly, one segment per
    dual-cell crossing with non-zero optical depth (with ``keep_zero`` also those of tau = 0
    inside occupied blocks).  Returns, gradients and ``runs`` as
    :func:`~avsm_dr.capture.grid.march`; ``capacity``: segments a lane writes per round
    (:data:`ROUND_CAPACITY`); ``slot_budget``: most slots of the one-round layout
    (:data:`SLOT_BUDGET`; 0 forces rounds)."""
    t = backend.types()
    Float, UInt32, Int32, Bool = grid.Float, t.UInt32, t.Int32, t.Bool
    stats0 = {"lanes": 0, "iterations": 0, "crossings": 0, "segments": 0, "max_iterations": 0, "rounds": 0}
    empty = (np.zeros(0, np.int64), Float(), Float(), Float(), stats0)
    if grid.occupied is None:
        return empty
    clock = time.perf_counter()
    # ---- lane rays and constants (float64 on the device, one kernel), the hit lanes compacted
    lanes_d, o, d, t_in, t_out, cap = hit_lanes(grid, camera, lambda *r: lane_constants(grid, *r)[2])
    L = dr.width(lanes_d)
    if L == 0:
        return empty
    lanes = np.asarray(lanes_d.numpy(), np.int64)
    const, cell, _ = lane_constants(grid, o, d, t_in, t_out)
    times = {"lanes_s": time.perf_counter() - clock}

    wlen = np.array(grid.window_shape[::-1], np.int64)             # (wx, wy, wz)
    pad, occ, (nbz, nby, nbx) = dual_grid(grid)
    bs = int(grid.block)
    # one cell per iteration and axis (cells never go back except when re-derived at a block
    # skip, at most one per skip), plus one iteration per block crossed
    max_iter = int(2 * (wlen.sum() + 3) + 4 * (nbx + nby + nbz) + 16)
    K = int(capacity)

    PX, PY = dr.opaque(Int32, int(wlen[0] + 2)), dr.opaque(Int32, int(wlen[1] + 2))
    NBX, NBY = dr.opaque(Int32, int(nbx)), dr.opaque(Int32, int(nby))
    WX, WY, WZ = (dr.opaque(Int32, int(v) - 1) for v in wlen)      # last cell per axis
    tau_max = dr.opaque(Float, float(-np.log(epsilon)))
    it_max = dr.opaque(UInt32, max_iter)
    far = dr.opaque(Float, _FAR)

    table = corner_table(grid)
    ArrX = t.ArrayXf if Float is t.Float else t.ArrayXf64
    CX, CY = dr.opaque(Int32, int(wlen[0] + 1)), dr.opaque(Int32, int(wlen[1] + 1))

    def corners(cx, cy, cz, active):
        """The dual cell's 8 corner voxels c[k][j][i] (edge-padded window: no clamping)."""
        if table is not None:
            v = dr.gather(ArrX, table, UInt32(((cz + 1) * CY + (cy + 1)) * CX + (cx + 1)), active,
                          shape=(8, dr.width(cx)))
            return [[[v[4 * k + 2 * j + i] for i in (0, 1)] for j in (0, 1)] for k in (0, 1)]
        base = UInt32(((cz + 1) * PY + (cy + 1)) * PX + (cx + 1))
        sy, sz = UInt32(PX), UInt32(PX * PY)
        return [[[dr.gather(Float, pad, base + k * sz + j * sy + i, active) for i in (0, 1)]
                 for j in (0, 1)] for k in (0, 1)]

    def cubic(c, fx, fy, fz):
        """Trilinear interpolation of corners ``c`` at cell-local (fx, fy, fz) in [0, 1]."""
        x = [[dr.fma(fx, c[k][j][1] - c[k][j][0], c[k][j][0]) for j in (0, 1)] for k in (0, 1)]
        y = [dr.fma(fy, x[k][1] - x[k][0], x[k][0]) for k in (0, 1)]
        return dr.fma(fz, y[1] - y[0], y[0])

    def run(cst, state, bufs, slot, cap):
        """One round for the lanes of ``cst`` (their constants) from ``state``: each lane
        writes up to ``cap`` segments at ``slot + n`` of ``bufs`` = (z0, z1, tau) and stops."""
        ux, uy, uz, dux, duy, duz, ivx, ivy, ivz, send, tin = cst
        n_lanes = dr.width(send)
        psx, psy, psz = (dr.select(v > 0, Int32(1), Int32(0)) for v in (dux, duy, duz))

        def cond(s, cx, cy, cz, tau, sig0, it, nc, n, done):
            return ~done & (n < cap)

        def body(s, cx, cy, cz, tau, sig0, it, nc, n, done):
            # ---- the block of the current cell; next plane: the cell's exit face or the block's
            bx, by, bz = (cx + 1) // bs, (cy + 1) // bs, (cz + 1) // bs
            occupied = dr.gather(UInt32, occ, UInt32((bz * NBY + by) * NBX + bx)) > 0
            px = dr.select(occupied, cx + psx, bs * (bx + psx) - 1)
            py = dr.select(occupied, cy + psy, bs * (by + psy) - 1)
            pz = dr.select(occupied, cz + psz, bs * (bz + psz) - 1)
            sx = dr.select(ivx != 0, (Float(px) - ux) * ivx, far)
            sy = dr.select(ivy != 0, (Float(py) - uy) * ivy, far)
            sz = dr.select(ivz != 0, (Float(pz) - uz) * ivz, far)
            m = dr.minimum(dr.minimum(sx, sy), sz)
            s1 = dr.maximum(dr.minimum(m, send), s)
            # ---- exact integral over [s, s1]: Simpson on the cell's cubic
            c = corners(cx, cy, cz, occupied)
            fx, fy, fz = ux - Float(cx), uy - Float(cy), uz - Float(cz)    # cell-local u at s = 0
            sm = 0.5 * (s + s1)
            sig_m = cubic(c, dr.fma(sm, dux, fx), dr.fma(sm, duy, fy), dr.fma(sm, duz, fz))
            sig1 = dr.maximum(cubic(c, dr.fma(s1, dux, fx), dr.fma(s1, duy, fy), dr.fma(s1, duz, fz)), 0)
            seg = dr.select(occupied, dr.maximum((s1 - s) * (sig0 + 4 * sig_m + sig1) * (1.0 / 6.0), 0), 0)
            emit = occupied & ((s1 > s) if keep_zero else (seg > 0))
            write_slots(bufs, (tin + s, tin + s1, seg), slot + n, emit)
            n = n + dr.select(emit, 1, 0)
            nc = nc + dr.select(occupied, 1, 0)
            tau = tau + seg
            sig0 = dr.select(occupied, sig1, 0)
            # ---- DDA: the axis whose plane comes first crosses it; after an empty block
            # the other axes are re-derived from the position (clamped into the block)
            ax = (sx <= sy) & (sx <= sz)
            ay = ~ax & (sy <= sz)
            az = ~ax & ~ay

            def move(win, p, pos_, c_, b_, u_, du_, last):
                here = dr.clip(Int32(dr.floor(dr.fma(s1, du_, u_))),
                               dr.maximum(bs * b_ - 1, -1), dr.minimum(bs * b_ + bs - 2, last))
                return dr.select(win, p + pos_ - 1, dr.select(occupied, c_, here))

            cx = move(ax, px, psx, cx, bx, ux, dux, WX)
            cy = move(ay, py, psy, cy, by, uy, duy, WY)
            cz = move(az, pz, psz, cz, bz, uz, duz, WZ)
            it = it + 1
            outside = (cx < -1) | (cy < -1) | (cz < -1) | (cx > WX) | (cy > WY) | (cz > WZ)
            done = (m >= send) | (tau > tau_max) | outside | (it >= it_max)
            return s1, cx, cy, cz, tau, sig0, it, nc, n, done

        return dr.while_loop(tuple(state) + (dr.zeros(UInt32, n_lanes), dr.zeros(Bool, n_lanes)),
                             cond, body, label="grid_dda")

    times["prep_s"], clock = time.perf_counter() - clock - times["lanes_s"], time.perf_counter()
    cx0, cy0, cz0 = cell
    c0 = corners(cx0, cy0, cz0, True)
    sig_start = dr.maximum(cubic(c0, const[0] - Float(cx0), const[1] - Float(cy0), const[2] - Float(cz0)), 0)
    state0 = [dr.zeros(Float, L),              # s: ray parameter - t_in of the current point
              cx0, cy0, cz0,                   # current dual cell (window voxel units)
              dr.zeros(Float, L),              # tau: optical depth integrated so far
              sig_start,                       # sig0: sigma at s
              dr.zeros(UInt32, L),             # it: iterations (safety bound)
              dr.zeros(UInt32, L)]             # nc: crossings integrated (occupied iterations)

    def finish(counts, iters, cross, n_rounds, z0, z1, tau):
        S = int(counts.sum())
        stats = {"lanes": L, "iterations": int(iters.sum()), "crossings": int(cross.sum()), "segments": S,
                 "max_iterations": int(iters.max()), "rounds": n_rounds, **times}
        if stats["max_iterations"] >= max_iter:
            raise RuntimeError(f"grid traversal: a ray hit the iteration bound {max_iter} (DDA did not advance)")
        if S == 0:
            return empty[:4] + (stats,)
        return lane_output(grid, camera, lanes, counts, z0, z1, tau, stats, runs)

    # ---- one round with a slot per possible crossing (cells the clipped ray meets, + 3 for
    # float32 rounding at its ends); lane i's segments fill its first counts[i] slots
    dr.eval(cap)
    n_slots = int(dr.sum(t.UInt64(cap))[0])
    if n_slots <= slot_budget:
        bufs = new_slots(Float, n_slots)
        slot = dr.prefix_sum(cap)
        out = run(const, state0, bufs, slot, cap)
        dr.eval(out, bufs)
        if bool(dr.all(out[9])):
            counts, iters, cross = (np.asarray(v.numpy(), np.int64) for v in (out[8], out[6], out[7]))
            times["rounds_s"], clock = time.perf_counter() - clock, time.perf_counter()
            z0, z1, tau = compact_slots(bufs, slot, out[8], int(counts.sum()))
            times["compact_s"] = time.perf_counter() - clock
            return finish(counts, iters, cross, 1, z0, z1, tau)
        clock = time.perf_counter()                          # a lane overflowed its bound: rounds

    # ---- rounds: every unfinished lane writes up to K segments into its own K slots
    state = state0
    active = np.arange(L, dtype=np.int64)      # lanes of this round (indices into 0..L-1)
    cst = const
    rounds = []                                # (lanes, n per lane, buffers)
    counts = np.zeros(L, np.int64)
    iters = np.zeros(L, np.int64)
    cross = np.zeros(L, np.int64)
    while active.size:
        bufs = new_slots(Float, active.size * K)
        out = run(cst, state, bufs, dr.arange(UInt32, active.size) * K, K)
        dr.eval(out, bufs)
        n_r = np.asarray(out[8].numpy(), np.int64)
        done = np.asarray(out[9].numpy(), bool)
        rounds.append((active, n_r, bufs))
        counts[active] += n_r
        keep = np.flatnonzero(~done)
        fin = active[done]
        iters[fin] = np.asarray(out[6].numpy(), np.int64)[done]
        cross[fin] = np.asarray(out[7].numpy(), np.int64)[done]
        active = active[keep]
        if active.size:
            k_sel = A.to_uint32(keep)
            state = [dr.gather(type(v), v, k_sel) for v in out[:8]]
            a_sel = A.to_uint32(active)
            cst = [dr.gather(Float, v, a_sel) for v in const]
    times["rounds_s"], clock = time.perf_counter() - clock, time.perf_counter()
    if not counts.any():
        return finish(counts, iters, cross, len(rounds), Float(), Float(), Float())

    # ---- compaction: slot j < n of lane i of a round -> offset[i] + (segments of earlier rounds) + j
    S = int(counts.sum())
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    written = np.zeros(L, np.int64)
    z0, z1, tau = dr.zeros(Float, S), dr.zeros(Float, S), dr.zeros(Float, S)
    for lanes_r, n_r, bufs in rounds:
        base = A.to_uint32(start[lanes_r] + written[lanes_r])
        written[lanes_r] += n_r
        slot = dr.arange(UInt32, lanes_r.size * K)
        i = slot // K
        j = slot - i * K
        ok = j < dr.gather(UInt32, A.to_uint32(n_r), i)
        dst = dr.gather(UInt32, base, i, ok) + j
        for src, dst_buf in zip(read_slots(bufs, slot, ok), (z0, z1, tau)):
            dr.scatter(dst_buf, src, dst, ok)
    dr.eval(z0, z1, tau)
    dr.sync_thread()
    times["compact_s"] = time.perf_counter() - clock
    return finish(counts, iters, cross, len(rounds), z0, z1, tau)

