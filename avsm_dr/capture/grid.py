"""Density grids: light-ray marching into segments (``method='march'``, the default grid capture).

Grid convention (Mitsuba ``gridvolume``, :mod:`._grid_volume`): voxel values of extinction
``sigma`` at cell centres, trilinear in between, clamped to the edge inside ``bbox``.

One Dr.Jit lane per texel ray, clipped to the occupied part of the box, walks the coarse
block grid (``block^3`` voxels per block) with a 3-D DDA [Amanatides & Woo 1987].  An empty
block (max of every voxel that influences it is 0) is crossed in one iteration; in an
occupied block the ray takes steps of length ``h = step`` (the last one up to the block's
exit), and each step ``[t_a, t_b]`` becomes one segment whose optical depth is Simpson's rule ::

    tau = (t_b - t_a) / 6 * (sigma(t_a) + 4 sigma((t_a + t_b) / 2) + sigma(t_b))

(exact for the cubic that trilinear interpolation gives inside one lattice cell; O(h^2) at
the lattice planes where its derivative jumps).  Steps with tau = 0 emit nothing.  A ray
stops once its accumulated optical depth exceeds ``-ln(epsilon)``.

Output: each lane writes its segments into its own slots, a bound of its segments (steps
plus block faces crossed), or in rounds (:func:`~._grid_lanes.slot_rounds`).  With a
grad-enabled density the optical depths are recomputed per segment from differentiable
gathers (:func:`~._grid_volume.segment_tau`); segment boundaries and counts are piecewise
constant in the density and not differentiated.  ``method='exact'`` is :mod:`.dda`.
"""
from __future__ import annotations

import time

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from .. import validation as V
from ._grid_lanes import ROUND_CAPACITY, SLOT_BUDGET, hit_lanes, lane_output, slot_rounds, write_slots
from ._grid_volume import DualCorners, GridVolume, MarchKernel


#: Grid capture methods: 'exact' integrates each dual-cell crossing exactly (:mod:`.dda`),
#: 'march' takes Simpson steps of a given length (this module).
METHODS = ("exact", "march")


def check_method(method, step) -> str:
    """The grid capture method, 'march' when None (its segments span half a voxel, the exact
    capture's a whole dual cell); ValueError naming ``method`` (unknown) or ``step`` (given
    with 'exact', which has no step)."""
    if method is None:
        return "march"
    if V.one_of(method, "method", METHODS) == "exact" and step is not None:
        raise ValueError("step: the 'exact' grid capture has no step (one segment per dual-cell "
                         "crossing); pass method='march' to march with a step")
    return method


def march(grid: GridVolume, camera, step: float | None, epsilon: float, keep_zero: bool = False,
          runs: bool = False, capacity: int = ROUND_CAPACITY, slot_budget: int = SLOT_BUDGET):
    """March every texel ray of ``camera`` through ``grid``: (texel (S,) int64 NumPy in texel
    order, z0, z1, tau Dr.Jit Floats of ``grid.dtype``, stats dict), each texel's segments in
    depth order (gradients: module docstring).

    Parameters
    ----------
    keep_zero
        also emit steps with tau = 0 (gradients can then reach voxels that are still 0 inside
        occupied blocks; ``GridVolume.prepare(..., skip_empty=False)`` reaches every voxel).
    runs
        the texels as :class:`~avsm_dr.capture.assembly.TexelRuns` (one run per ray).
    capacity, slot_budget
        segments a lane writes per round (:data:`~._grid_lanes.ROUND_CAPACITY`); most slots of
        the one-round layout (:data:`~._grid_lanes.SLOT_BUDGET`; 0 forces rounds)."""
    t = backend.types()
    Float, UInt32, Int32 = grid.Float, t.UInt32, t.Int32
    clock = time.perf_counter()
    nb = np.array(grid.occupancy.shape[::-1], np.int64)               # (nbx, nby, nbz)
    bs = grid.voxel * grid.block                                        # block size (x, y, z)

    def slots(o, d, t_in, t_out):
        """Bound on a lane's segments: its steps (ceil(length / step), plus one cut short per
        block face crossed) and its block faces crossed (+1 each for rounding), + 4."""
        F64 = type(t_in)
        n = dr.ceil((t_out - t_in) / dr.opaque(F64, float(step))) + 4
        for a in range(3):
            lo_a, bs_a = dr.opaque(F64, float(grid.bmin[a])), dr.opaque(F64, float(bs[a]))
            faces = dr.abs(dr.floor((o[a] + d[a] * t_out - lo_a) / bs_a) - dr.floor((o[a] + d[a] * t_in - lo_a) / bs_a))
            n += 2 * (faces + 1)
        return UInt32(dr.select(dr.isfinite(n), n, 0))

    lanes, o, d, t_in, t_out, cap = hit_lanes(grid, camera, slots)
    L = lanes.size
    if L == 0:
        return np.zeros(0, np.int64), Float(), Float(), Float(), {"lanes": 0, "iterations": 0}
    times = {"lanes_s": time.perf_counter() - clock}

    # ---- DDA initialisation over the block grid (float64 on the device)
    F64 = type(t_in)
    b, tmax, tdelta, sgn = [], [], [], []
    eps = 1e-6 * float(bs.min())
    for a in range(3):
        lo_a, bs_a = dr.opaque(F64, float(grid.bmin[a])), dr.opaque(F64, float(bs[a]))
        p = o[a] + d[a] * (t_in + dr.opaque(F64, eps))
        ba = Int32(dr.clip(dr.floor((p - lo_a) / bs_a), 0, dr.opaque(F64, float(nb[a] - 1))))
        nxt = lo_a + (F64(ba) + dr.select(d[a] > 0, 1.0, 0.0)) * bs_a
        b.append(ba)
        tmax.append(dr.select(d[a] != 0, (nxt - o[a]) / d[a], 1e30))
        tdelta.append(dr.select(d[a] != 0, bs_a / dr.abs(d[a]), 1e30))
        sgn.append(dr.select(d[a] < 0, Int32(-1), Int32(1)))
    # steps + one iteration per block face crossed (+ zero-length ones at edges and corners)
    max_iter = int(np.ceil(float(dr.max(t_out - t_in)[0]) / step)) + 3 * int(nb.sum()) + 16

    const = [Float(v) for v in (*o, *d, t_out, *tdelta)] + sgn
    occ = A.to_uint32((grid.occupancy > 0).ravel())
    nbx, nby, nbz = (dr.opaque(Int32, int(v)) for v in nb)
    kern = MarchKernel(grid)
    h = dr.opaque(Float, float(step))
    snap = dr.opaque(Float, 1e-3 * float(step))
    tau_max = dr.opaque(Float, float(-np.log(epsilon)))
    it_max = dr.opaque(UInt32, max_iter)
    corners = DualCorners(grid)

    def sigma(cst, tt, active):
        ox, oy, oz, dx, dy, dz = cst[:6]
        return kern.trilinear_corners(corners, ox + dx * tt, oy + dy * tt, oz + dz * tt, active)

    def run(cst, bufs, slot):
        """The loop body of the lanes of ``cst``, writing segment ``n`` at slot ``slot + n`` of ``bufs``."""
        t_end, tdx, tdy, tdz, sx, sy, sz = cst[6:]

        def body(t_, bx, by, bz, mx, my, mz, tau, s0, it, n, done):
            blk_exit = dr.minimum(dr.minimum(mx, my), dr.minimum(mz, t_end))
            bidx = UInt32((bz * nby + by) * nbx + bx)
            occupied = dr.gather(UInt32, occ, bidx) > 0
            t_step = t_ + h
            take = occupied & (t_step < blk_exit - snap)
            t1 = dr.select(take, t_step, blk_exit)
            sm = sigma(cst, 0.5 * (t_ + t1), occupied)
            s1 = sigma(cst, t1, occupied)
            seg = dr.select(occupied, (t1 - t_) * (s0 + 4 * sm + s1) * (1.0 / 6.0), 0)
            emit = occupied if keep_zero else occupied & (seg > 0)
            write_slots(bufs, (t_, t1, seg), slot + n, emit)
            n = n + dr.select(emit, 1, 0)
            tau = tau + seg
            s0 = dr.select(occupied, s1, 0)
            # DDA: leave the block through the face with the smallest exit time
            crossed = ~take
            ax = crossed & (mx <= my) & (mx <= mz)
            ay = crossed & ~ax & (my <= mz)
            az = crossed & ~ax & ~ay
            bx = bx + dr.select(ax, sx, 0)
            by = by + dr.select(ay, sy, 0)
            bz = bz + dr.select(az, sz, 0)
            mx = mx + dr.select(ax, tdx, 0)
            my = my + dr.select(ay, tdy, 0)
            mz = mz + dr.select(az, tdz, 0)
            it = it + 1
            outside = (bx < 0) | (by < 0) | (bz < 0) | (bx >= nbx) | (by >= nby) | (bz >= nbz)
            done = (t1 >= t_end) | (tau > tau_max) | outside | (it >= it_max)
            return t1, bx, by, bz, mx, my, mz, tau, s0, it, n, done
        return body

    t0 = Float(t_in)
    state0 = [t0, b[0], b[1], b[2],            # t: the current ray parameter; the current block
              Float(tmax[0]), Float(tmax[1]), Float(tmax[2]),    # next block face per axis
              dr.zeros(Float, L),              # tau: optical depth marched so far
              sigma(const, t0, True),          # s0: sigma at the current t
              dr.zeros(UInt32, L)]             # it: iterations (safety bound)
    times["prep_s"] = time.perf_counter() - clock - times["lanes_s"]

    counts, (iters,), res, st = slot_rounds(run, const, state0, cap, (9,), slot_budget, capacity, times, "grid_march")
    return lane_output(grid, camera, lanes, counts, iters, max_iter, res, {**st, **times}, runs)
