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

Output and gradients as :func:`~avsm_dr.capture.grid.march` (a lane's slot bound: the dual
cells the clipped ray meets, + 3; gradients exact: a segment lies in one dual cell).
"""
from __future__ import annotations

import time

import drjit as dr
import numpy as np

from .. import backend
from ._grid_lanes import ROUND_CAPACITY, SLOT_BUDGET, hit_lanes, lane_output, slot_rounds, write_slots
from ._grid_volume import DualCorners, dual_grid

#: Parameter of a plane the ray never reaches (grazing axes); beyond every ray's end.
_FAR = 1e30
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
    inside occupied blocks).  Returns, gradients, ``runs``, ``capacity`` and ``slot_budget`` as
    :func:`~avsm_dr.capture.grid.march`."""
    t = backend.types()
    Float, UInt32, Int32 = grid.Float, t.UInt32, t.Int32
    clock = time.perf_counter()
    # ---- lane rays and constants (float64 on the device, one kernel), the hit lanes compacted
    lanes, o, d, t_in, t_out, cap = hit_lanes(grid, camera, lambda *r: lane_constants(grid, *r)[2])
    L = lanes.size
    if L == 0:
        return np.zeros(0, np.int64), Float(), Float(), Float(), dict.fromkeys(
            ("lanes", "iterations", "crossings", "segments", "max_iterations", "rounds"), 0)
    const, cell, _ = lane_constants(grid, o, d, t_in, t_out)
    times = {"lanes_s": time.perf_counter() - clock}

    wlen = np.array(grid.window_shape[::-1], np.int64)             # (wx, wy, wz)
    _, occ, (nbz, nby, nbx) = dual_grid(grid)
    bs = int(grid.block)
    # one cell per iteration and axis (cells never go back except when re-derived at a block
    # skip, at most one per skip), plus one iteration per block crossed
    max_iter = int(2 * (wlen.sum() + 3) + 4 * (nbx + nby + nbz) + 16)

    NBX, NBY = dr.opaque(Int32, int(nbx)), dr.opaque(Int32, int(nby))
    WX, WY, WZ = (dr.opaque(Int32, int(v) - 1) for v in wlen)      # last cell per axis
    tau_max = dr.opaque(Float, float(-np.log(epsilon)))
    it_max = dr.opaque(UInt32, max_iter)
    far = dr.opaque(Float, _FAR)

    corners = DualCorners(grid)

    def cubic(v, fx, fy, fz):
        """Trilinear interpolation of corners ``v[4 k + 2 j + i]`` at cell-local (fx, fy, fz) in [0, 1]."""
        x = [dr.fma(fx, v[2 * m + 1] - v[2 * m], v[2 * m]) for m in range(4)]
        y = [dr.fma(fy, x[2 * k + 1] - x[2 * k], x[2 * k]) for k in (0, 1)]
        return dr.fma(fz, y[1] - y[0], y[0])

    def run(cst, bufs, slot):
        """The loop body of the lanes of ``cst`` (their constants), writing segment ``n`` at
        slot ``slot + n`` of ``bufs``."""
        ux, uy, uz, dux, duy, duz, ivx, ivy, ivz, send, tin = cst
        psx, psy, psz = (dr.select(v > 0, Int32(1), Int32(0)) for v in (dux, duy, duz))

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
        return body

    sig_start = dr.maximum(cubic(corners(*cell, True), *(u - Float(c) for u, c in zip(const[:3], cell))), 0)
    state0 = [dr.zeros(Float, L),              # s: ray parameter - t_in of the current point
              *cell,                           # current dual cell (window voxel units)
              dr.zeros(Float, L),              # tau: optical depth integrated so far
              sig_start,                       # sig0: sigma at s
              dr.zeros(UInt32, L),             # it: iterations (safety bound)
              dr.zeros(UInt32, L)]             # nc: crossings integrated (occupied iterations)
    times["prep_s"] = time.perf_counter() - clock - times["lanes_s"]

    counts, (iters, cross), res, st = slot_rounds(run, const, state0, cap, (6, 7), slot_budget, capacity, times,
                                                  "grid_dda")
    return lane_output(grid, camera, lanes, counts, iters, max_iter, res,
                       {"crossings": int(cross.sum()), **st, **times}, runs)
