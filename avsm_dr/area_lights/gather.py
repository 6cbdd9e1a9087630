"""Final gather: single scattering along camera rays by a Riemann sum (Wyman and Dai 2013,
"Imperfect Voxelized Shadow Volumes", HPG, sec. 2).

For a camera ray ``x(t) = o + t d`` ending at ``t_end`` (first surface or medium
boundary) and VPL k at ``p_k`` with intensity ``I_k(w) = I max(0, n . w)``,
``I = L_e A / K``, the airlight is the midpoint Riemann sum over N steps,
``dt = t_end / N``, ``t_j = (j + 1/2) dt``::

    L_k = sum_j V_k(x_j) sigma_s p(cos theta_j) I max(0, n . w_j) / r_j^2
                 exp(-sigma_t (t_j + r_j)) dt,

``r_j = |x_j - p_k|``, ``w_j = (x_j - p_k) / r_j``, ``cos theta_j = -w_j . d`` (angle
between the light's and the scattered light's directions of travel), plus the lit
surface at ``x_s = x(t_end)`` with normal ``n_s`` and albedo ``rho``::

    exp(-sigma_t t_end) rho / pi I max(0, n . w_s) max(0, -n_s . w_s) / r_s^2
        exp(-sigma_t r_s) V_k(x_s + bias n_s).

The visibility ``V_k`` comes from a callback (exact ray casting, a voxel lookup, or
the boundary-interpolated voxel lookup).  One lane per (pixel, VPL); a symbolic
``dr.while_loop`` over the steps.
"""
from __future__ import annotations

import math

import drjit as dr

from .geometry import DIFFUSE, CameraHits, Kit, occluded
from .area_scene import AreaLightScene


def phase_hg(cos_theta, g: float):
    """Henyey-Greenstein phase function (1 - g^2) / (4 pi (1 + g^2 - 2 g cos)^(3/2))."""
    if g == 0:
        return 1.0 / (4.0 * math.pi)
    denom = 1.0 + g * g - 2.0 * g * cos_theta
    return (1.0 - g * g) / (4.0 * math.pi) * dr.rsqrt(denom * denom * denom)


def light_terms(ln, x, p):
    """(w, r, max(0, n . w) / r^2): direction from the VPL, distance, cosine falloff."""
    v = x - p
    r2 = dr.squared_norm(v)
    r2 = dr.select(r2 > 0, r2, 1)
    r = dr.sqrt(r2)
    w = v / r
    return w, r, dr.maximum(dr.dot(ln, w), 0) / r2


def _step(k: Kit, med, ln, o, d, dt, j, p):
    """(x_j, f_j) of Riemann step j: its point and ``sigma_s p(cos) max(0, n . w) / r^2
    exp(-sigma_t (t_j + r_j))`` (the module docstring's sum without ``V`` and ``I dt``)."""
    t = (k.Float(j) + 0.5) * dt
    x = o + t * d
    w, r, falloff = light_terms(ln, x, p)
    return x, med.sigma_s * phase_hg(-dr.dot(w, d), med.g) * falloff * dr.exp(-med.sigma_t * (t + r))


def gather(scene: AreaLightScene, k: Kit, hits: CameraHits, pix, p, steps: int, intensity,
           vis_medium, vis_surface, bias: float, boundaries: bool = False):
    """Radiance of each (pixel ``pix``, VPL at ``p``) lane, without the emitter itself.

    vis_medium(x, j) -> (V, on_boundary Bool or None) at Riemann step j; vis_surface(x) -> V.
    intensity: I = L_e A / K (Float, opaque: K does not recompile kernels).  Returns (L Float
    per lane, flags): with ``boundaries``, ceil(N / 32) UInt32 arrays whose bit ``j & 31`` of
    word ``j >> 5`` marks a boundary at step j (for :func:`boundary_correction`), else None."""
    med = scene.medium
    ln = k.vec(scene.light.normal)
    o = hits.o
    d = dr.gather(k.Vec3, hits.d, pix)
    t_end = dr.gather(k.Float, hits.t_end, pix)
    dt = t_end * (1.0 / steps)
    n_lanes = dr.width(pix)
    n_words = (steps + 31) // 32 if boundaries else 0

    # ---------------------------------------------------------------- airlight
    j = dr.zeros(k.UInt32, n_lanes)      # Riemann step
    L = dr.zeros(k.Float, n_lanes)       # sum of V f over the steps so far
    # boundary steps (bits); opaque, as Dr.Jit's constant propagation otherwise trips on a
    # literal-zero state that stays zero when the volume itself is a literal (no occluders)
    flags = [dr.opaque(k.UInt32, 0, n_lanes) for _ in range(n_words)]

    def cond(j, L, *flags):
        return j < steps

    def body(j, L, *flags):
        x, f = _step(k, med, ln, o, d, dt, j, p)
        V, on_edge = vis_medium(x, j)
        if boundaries:
            bit = dr.select(on_edge, k.UInt32(1) << (j & 31), 0)
            word = j >> 5
            flags = tuple(dr.select(word == i, fw | bit, fw) for i, fw in enumerate(flags))
        return (j + 1, L + V * f) + tuple(flags)

    out = dr.while_loop((j, L) + tuple(flags), cond, body, max_iterations=steps, label="vpl_gather")
    L = out[1] * dt
    flags = list(out[2:]) if boundaries else None

    # ----------------------------------------------------------------- surface
    kind = dr.gather(k.UInt32, hits.kind, pix)
    ns = dr.gather(k.Vec3, hits.n, pix)
    rho = dr.gather(k.Float, hits.albedo, pix)
    xs = o + t_end * d
    w, r, falloff = light_terms(ln, xs, p)
    cos_s = dr.maximum(-dr.dot(ns, w), 0)
    lit = (kind == DIFFUSE) & (cos_s > 0) & (falloff > 0)
    Vs = dr.select(lit, vis_surface(xs + bias * ns), 0)
    Ls = rho * (1.0 / math.pi) * falloff * cos_s * dr.exp(-med.sigma_t * (t_end + r)) * Vs
    return (L + dr.select(lit, Ls, 0)) * intensity, flags


def boundary_correction(scene: AreaLightScene, k: Kit, hits: CameraHits, steps: int, intensity,
                        flags: list, lane_info, vis_delta):
    """Second gather pass over the boundary steps only (Wyman and Dai 2013's interpolation):
    ``L = L_point + sum over flagged steps of (V_bilinear - V_point) f_j dt``.  The flagged
    (lane, word) pairs are compacted (``dr.compress``) and each walks its set bits (``tzcnt``):
    work ~ boundary crossings, not N.  lane_info(lane) -> (pix, vpl, p); vis_delta(x, vpl, p) ->
    V_bilinear - V_point.  Returns the correction per lane (Float, width of the flag arrays)."""
    n_words = len(flags)
    n_lanes = dr.width(flags[0])
    F = dr.zeros(k.UInt32, n_lanes * n_words)
    base = dr.arange(k.UInt32, n_lanes) * n_words
    for i, fw in enumerate(flags):
        dr.scatter(F, fw, base + i)
    idx = dr.compress(F != 0)
    corr = dr.zeros(k.Float, n_lanes)
    if dr.width(idx) == 0:
        return corr
    word = dr.gather(k.UInt32, F, idx)
    lane = idx // n_words
    w = idx - lane * n_words
    pix, vpl, p = lane_info(lane)
    ln = k.vec(scene.light.normal)
    o = hits.o
    d = dr.gather(k.Vec3, hits.d, pix)
    dt = dr.gather(k.Float, hits.t_end, pix) * (1.0 / steps)
    acc = dr.zeros(k.Float, dr.width(idx))

    def cond(word, acc):
        return word != 0

    def body(word, acc):
        x, f = _step(k, scene.medium, ln, o, d, dt, w * 32 + dr.tzcnt(word), p)
        return word & (word - 1), acc + vis_delta(x, vpl, p) * f

    word, acc = dr.while_loop((word, acc), cond, body, max_iterations=32, label="vpl_boundary")
    dr.scatter_reduce(dr.ReduceOp.Add, corr, acc * dt * intensity, lane)
    return corr


def exact_visibility(scene: AreaLightScene, k: Kit, hits: CameraHits, p, steps: int, eps: float):
    """Naive full-resolution visibility (ray cast to the VPL at every Riemann step).

    Returns (V_medium Float of n_pix * steps, lane pix * steps + j; V_surface Float of
    n_pix at the biased surface point ``x_s + eps n_s``)."""
    n_pix = dr.width(hits.t_end)
    lane = dr.arange(k.UInt32, n_pix * steps)
    pix = lane // steps
    j = lane - pix * steps
    d = dr.gather(k.Vec3, hits.d, pix)
    t_end = dr.gather(k.Float, hits.t_end, pix)
    x = hits.o + (k.Float(j) + 0.5) * (t_end * (1.0 / steps)) * d
    Vm = dr.select(occluded(scene, k, x, p, eps), 0.0, 1.0)
    xs = hits.o + hits.t_end * hits.d + eps * hits.n
    Vs = dr.select(occluded(scene, k, xs, p, eps), 0.0, 1.0)
    return k.Float(Vm), k.Float(Vs)
