"""Transmittance along light paths through the density grid: ratio tracking and ray march.

Grid term, ``method='ratio_tracking'`` (Novak, Selle and Jarosz, "Residual ratio tracking for
estimating attenuation in participating media", 2014, sec. 3): collisions ``s_i`` drawn by
Mitsuba's ``Medium.sample_interaction`` with the majorant ``mu = f * max(sigma_t)`` weigh
``T_hat = prod_i (1 - sigma_t(s_i) / mu)``, ``E[T_hat] = T`` (unbiased); stderr = sample std
over ``spp`` independent paths / ``sqrt(spp)``.  Mitsuba's own majorant is ``max(sigma_t)``
(delta tracking in uniform regions, variance ``T (1 - T)``), so rays are traced in ``u = f s``
(direction ``d / f``); ``majorant_factor = f = 2`` by default (variance ``T^2 (exp(tau / f) - 1)``
in a homogeneous medium).

Grid term, ``method='raymarch'`` (:func:`march`, also the single-scattering integral of
:mod:`avsm_dr.shading`): float64 midpoint rule with step ``h`` (default: smallest voxel side / 8).
The trilinear field is cubic along the ray in each lattice cell, so the optical-depth error is at
most ``L h^2 max|sigma''| / 24`` plus ``h^2 |jump sigma'| / 8`` per lattice plane crossed;
``stderr`` is zeros.  Samples go in chunks of :data:`MAX_CHUNK` (memory bounded); a step needing
more than :data:`MAX_SAMPLES` samples in one call is refused.
"""
from __future__ import annotations

import math

import numpy as np

from .. import validation as V
from ..geometry import ray_box
from ..scene import Scene
from .content import blocked_paths, checked_paths, hair_tau, particles_tau
from .media import check_grid, medium_dict, mitsuba, sample_grid

METHODS = ("ratio_tracking", "raymarch")

#: Upper bound on Dr.Jit lanes (receivers x spp) of one ratio-tracking launch; also the
#: largest ``spp`` (one receiver's paths run in one launch).
MAX_LANES = 1 << 22
#: Ray-march samples per chunk (host memory: ~150 bytes per sample, 600 MB).
MAX_CHUNK = 1 << 22
#: Most ray-march samples one call evaluates (2^28: minutes on one core).
MAX_SAMPLES = 1 << 28


# ===================================================================== ray march
def default_step(grid, lo, hi, fraction: float = 1 / 8) -> float:
    """``fraction`` of the smallest voxel side of the (nz, ny, nx) grid over [lo, hi]."""
    return float(np.min((hi - lo) / np.array(grid.shape[::-1]))) * fraction


def _sample_counts(length, step: float) -> np.ndarray:
    """Midpoint samples per ray, ``ceil(length / step)``; ValueError when the total is
    more than :data:`MAX_SAMPLES`."""
    with np.errstate(over="ignore"):
        n = np.ceil(length / step)
    total = float(n.sum())
    if not total <= MAX_SAMPLES:
        fits = float(length.sum()) / max(MAX_SAMPLES - length.size, 1)
        raise ValueError(f"step: {step:.3g} needs {total:.3g} ray-march samples over {length.size} "
                         f"ray(s) of total length {float(length.sum()):.3g}; at most {MAX_SAMPLES} "
                         f"(2^28) fit one call: use step >= {fits:.3g} or fewer points")
    return n.astype(np.int64)


def march(g, lo, hi, o, d, L, step: float, integrand=None):
    """Midpoint rule along rays ``o + t d`` (|d| = 1), t in [0, L] clipped to the box.

    g: float64 (nz, ny, nx) grid over [lo, hi]; o, d (K, 3); L (K,); step: world units.
    Each clipped ray is cut into ``ceil(length / step)`` equal pieces ``h_j <= step``.
    Returns ``(tau, acc)``: tau (K,) = sum_j sigma(x_j) h_j, and, when ``integrand`` is
    given, acc (K,) = sum_j integrand(x_j, sigma_j, h_j, tau_j) with ``tau_j`` the optical
    depth from the ray's start to the middle of piece j (``acc`` is None otherwise).
    ``integrand`` receives (N, 3), (N,), (N,), (N,) arrays and returns (N,) values.
    """
    K = o.shape[0]
    t0, t1, _ = ray_box(o, d, lo, hi)
    t0 = np.maximum(t0, 0.0)
    t1 = np.minimum(t1, L)
    length = np.where(t1 > t0, t1 - t0, 0.0)
    n = _sample_counts(length, step)
    h = np.where(n > 0, length / np.maximum(n, 1), 0.0)
    tau = np.zeros(K)
    acc = None if integrand is None else np.zeros(K)
    rays = np.nonzero(n)[0]
    if rays.size == 0:
        return tau, acc
    end = np.cumsum(n[rays])                          # global sample offsets of the listed rays
    first = end - n[rays]
    for a in range(0, int(end[-1]), MAX_CHUNK):
        s = np.arange(a, min(a + MAX_CHUNK, int(end[-1])))
        k = np.searchsorted(end, s, side="right")      # listed ray of each sample (ascending)
        k0 = int(k[0])
        m = int(k[-1]) - k0 + 1
        r = rays[k0:k0 + m]                           # this chunk's rays (first/last may be partial)
        rid = k - k0
        hh = h[r][rid]
        t = t0[r][rid] + (s - first[k] + 0.5) * hh
        x = o[r][rid] + t[:, None] * d[r][rid]
        sig = sample_grid(g, lo, hi, x)
        od = sig * hh
        if integrand is not None:
            # optical depth to the middle of each piece: earlier chunks (tau so far) + the
            # earlier pieces of this chunk + half of its own
            c = np.cumsum(od)
            start = np.searchsorted(rid, np.arange(m))
            before = tau[r][rid] + (c - od) - (c[start] - od[start])[rid]
            acc[r] += np.bincount(rid, integrand(x, sig, hh, before + 0.5 * od), minlength=m)
        tau[r] += np.bincount(rid, od, minlength=m)
    return tau, acc


def raymarch_optical_depth(density, bbox, o, d, L, step: float | None = None) -> np.ndarray:
    """:func:`march`'s optical depth of the grid along rays o + t d, t in [0, L] (float64): o, d
    (K, 3) origins and directions (normalised here), L (K,) lengths >= 0; default step = min
    voxel side / 8."""
    g, lo, hi = check_grid(density, bbox)
    o = V.points(o, "o")
    d = V.points(d, "d")
    L = V.array(L, "L").reshape(-1)
    if not (d.shape == o.shape and L.shape == (o.shape[0],)):
        raise ValueError(f"L: expected o (K, 3), d (K, 3), L (K,), got {o.shape}, {d.shape}, {L.shape}")
    if np.any(L < 0):
        raise ValueError("L: negative path length")
    nd = np.linalg.norm(d, axis=1)
    if not np.all(nd > 0):
        raise ValueError("d: zero-length direction")
    step = default_step(g, lo, hi) if step is None else V.real(step, "step", 0.0, open_min=True)
    return march(g.astype(np.float64), lo, hi, o, d / nd[:, None], L, step)[0]


# ================================================================ ratio tracking
def ratio_tracking(grid, lo, hi, o, d, L, spp: int, seed: int, f: float):
    """Per-receiver mean and standard error of the ratio-tracking estimator (float64)."""
    mi = mitsuba()
    import drjit as dr
    K = o.shape[0]
    mean = np.ones(K)
    se = np.zeros(K)
    if float(grid.max()) == 0.0:
        return mean, se
    t0, t1, _ = ray_box(o, d, lo, hi)
    todo = np.nonzero((t0 <= t1) & (t1 > 0) & (t0 < L) & (L > 0))[0]
    if todo.size == 0:
        return mean, se
    medium = mi.load_dict(medium_dict(mi, grid, lo, hi, 0.0))
    Float, UInt32 = mi.Float, mi.UInt32
    chunk = max(1, MAX_LANES // spp)
    seed_a, seed_b = (UInt32(int(v)) for v in mi.sample_tea_32(seed & 0xFFFFFFFF, 0x5EED))
    for a in range(0, todo.size, chunk):
        rec = todo[a:a + chunk]
        n = rec.size * spp
        lane = dr.arange(UInt32, n)
        rid = lane // spp
        # Start where the path enters the box (float32 precision is then local to the box).
        s0 = np.maximum(t0[rec], 0.0)
        org = o[rec] + s0[:, None] * d[rec]
        rem = (np.minimum(L[rec], t1[rec]) - s0) * f                  # remaining parameter length
        g = [dr.gather(Float, Float(org[:, i].astype(np.float32)), rid) for i in range(3)]
        dv = [dr.gather(Float, Float((d[rec, i] / f).astype(np.float32)), rid) for i in range(3)]
        D = mi.Vector3f(*dv)
        maxt = dr.gather(Float, Float(rem.astype(np.float32)), rid)
        # PCG32 state and stream hashed (TEA) from (receiver index, sample index, seed),
        # as Mitsuba's independent sampler does: independent of chunking and of `todo`.
        r_id = dr.gather(UInt32, UInt32(rec.astype(np.uint32)), rid)
        s_id = lane - rid * spp
        # (seed() directly: the PCG32 constructor would add arange(n), i.e. the lane index)
        rng = mi.PCG32(n)
        rng.seed(mi.sample_tea_64(r_id, s_id ^ seed_a), mi.sample_tea_64(s_id, r_id ^ seed_b))
        Tr = dr.ones(Float, n)
        active = dr.full(mi.Bool, True, n)
        ch = UInt32(0)

        def cond(p, maxt, Tr, active, rng):
            return active

        def body(p, maxt, Tr, active, rng):
            ray = mi.Ray3f(p, D)
            ray.maxt = maxt
            mei = medium.sample_interaction(ray, rng.next_float32(), ch, active)
            hit = active & mei.is_valid()
            w = 1.0 - mei.sigma_t.x / (f * mei.combined_extinction.x)
            Tr = dr.select(hit, Tr * w, Tr)
            p = dr.select(hit, mei.p, p)
            maxt = dr.select(hit, maxt - mei.t, maxt)
            return p, maxt, Tr, hit & (Tr > 0), rng

        _, _, Tr, _, _ = dr.while_loop((mi.Point3f(*g), maxt, Tr, active, rng), cond, body, label="ratio_tracking")
        samples = np.asarray(Tr.numpy(), np.float64).reshape(rec.size, spp)
        mean[rec] = samples.mean(axis=1)
        se[rec] = samples.std(axis=1, ddof=1) / math.sqrt(spp) if spp > 1 else np.inf
    return mean, se


# ====================================================================== public
def transmittance(scene: Scene, points, spp: int = 256, seed: int = 0, method: str = "ratio_tracking",
                  step: float | None = None, majorant_factor: float = 2.0):
    """Transmittance from ``scene.light`` to each point: ``(mean, stderr)``, (K,) float64 NumPy.

    points: (K, 3) world positions.  spp: ratio-tracking paths per point (1 .. :data:`MAX_LANES`;
    ``stderr`` is inf for spp = 1).  seed: RNG seed (results do not depend on batching).  method:
    'ratio_tracking' (unbiased) or 'raymarch' (float64 midpoint rule with ``step``, stderr 0), as
    the module docstring states.  majorant_factor: f >= 1.  Particles, hair and blockers are
    analytic factors (:mod:`avsm_dr.groundtruth.content`).
    """
    content, p, o, d, L = checked_paths(scene, points)
    V.one_of(method, "method", METHODS)
    spp = V.integer(spp, "spp", 1, MAX_LANES)
    seed = V.integer(seed, "seed")
    f = V.real(majorant_factor, "majorant_factor", 1.0)
    if step is not None:
        step = V.real(step, "step", 0.0, open_min=True)
    K = p.shape[0]
    mean, se = np.ones(K), np.zeros(K)
    if content["grid"] is not None:
        grid, lo, hi = content["grid"]
        if method == "raymarch":
            h = default_step(grid, lo, hi) if step is None else step
            mean = np.exp(-march(grid.astype(np.float64), lo, hi, o, d, L, h)[0])
        else:
            mean, se = ratio_tracking(grid, lo, hi, o, d, L, spp, seed, f)
    tau = np.zeros(K)
    if content["particles"] is not None:
        tau += particles_tau(content["particles"], o, d, L)
    if content["hair"] is not None:
        tau += hair_tau(content["hair"], o, d, L)
    factor = np.exp(-tau)
    if content["blockers"]:
        factor = np.where(blocked_paths(scene, content, p, o, d, L), 0.0, factor)
    return mean * factor, se * factor
