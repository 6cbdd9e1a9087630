"""Render an area-light scene with one of three methods, timing each phase.

* ``naive_exact``  -- one pass per VPL; visibility by casting a ray to the VPL at every
  Riemann step and surface point (full resolution); no scan.
* ``naive_voxel``  -- one pass per VPL (voxelized shadow volumes, Wyman 2011, applied per
  VPL): exact texel-ray voxelization of an R^3 grid, scan, nearest-voxel gather.
* ``imperfect``    -- imperfect VSVs (Wyman and Dai 2013): all K grids in one buffer, populated by
  splatting per-VPL random surface points, one scan over the whole buffer, one gather over
  (pixel, VPL) lanes with bilinear interpolation only at shadow boundaries.

Phases (seconds around ``dr.eval`` + ``dr.sync_thread``): ``t_visibility`` (voxelize / ray
cast), ``t_scan`` (prefix-OR, boundary mask), ``t_gather`` (camera rays, Riemann sums); a
configuration's first call includes JIT compilation.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import drjit as dr
import numpy as np

from .. import _arrays as A
from .gather import boundary_correction, exact_visibility, gather
from .geometry import LIGHT_FRONT, Kit, camera_hits, kit
from .area_scene import AreaLightScene
from .visibility import (boundary_mask, interleave, lookup_bilinear, lookup_point, lookup_point_edge,
                         project, scan, voxelize_points, voxelize_rays)
from .. import validation as V
from .vpl import fit_grid, sample_vpls

METHODS = ("naive_exact", "naive_voxel", "imperfect")
INTERPOLATIONS = ("none", "boundary", "full")
VOXELIZATIONS = ("points", "rays")


@dataclass
class AreaLightRender:
    """image: (H, W) float64 radiance; timings: seconds per phase; params: the call's
    parameters; stats: grid and boundary-lookup counts."""
    image: np.ndarray
    timings: dict
    params: dict
    stats: dict = field(default_factory=dict)

    @property
    def total_time(self) -> float:
        return float(sum(self.timings.values()))


class _Clock:
    def __init__(self):
        self.t = {"t_visibility": 0.0, "t_scan": 0.0, "t_gather": 0.0}

    def __call__(self, phase: str, fn):
        dr.sync_thread()
        t0 = time.perf_counter()
        out = fn()
        dr.eval(out)
        dr.sync_thread()
        self.t[phase] += time.perf_counter() - t0
        return out


def render(scene: AreaLightScene, method: str = "imperfect", vpls: int = 16, resolution: int = 128,
           steps: int = 128, interpolation: str | None = None, voxelization: str | None = None,
           points_per_vpl: int | None = None, splat_coverage: float = 1.5,
           surface_bias: float | None = None,
           jitter: bool = False, seed: int = 0, dtype: str = "float32") -> AreaLightRender:
    """Single-scattering image of ``scene`` lit by ``vpls`` = K VPLs on its quad light.

    Parameters
    ----------
    resolution
        R, texels per side and depth bins of each VPL's grid (R^3 voxels; ignored
        by ``naive_exact``), >= 2.
    steps
        N, Riemann steps per camera ray.
    interpolation
        'none' (nearest voxel), 'boundary' (bilinear only where the boundary
        mask is set; the default of ``imperfect``) or 'full' (bilinear at every step, the
        slow reference that 'boundary' must equal).
    voxelization
        'points' (imperfect splats; default of ``imperfect``) or 'rays' (exact
        texel rays; the only choice of ``naive_voxel``; ``imperfect`` with 'rays' isolates
        the effect of the splats).
    points_per_vpl
        M, surface points splatted per VPL (default 4 R^2).
    splat_coverage
        c, splat discs cover c times the occluder area (:func:`~.visibility.splat_radius`), > 0.
    surface_bias
        offset along the surface normal for surface shadow lookups
        (default: one depth bin for voxel methods, 1e-4 x scene size for exact).
    jitter, seed
        jittered VPL strata; seed of the random surface points."""
    if not isinstance(scene, AreaLightScene):
        raise ValueError(f"scene: expected AreaLightScene, got {type(scene).__name__}")
    V.one_of(method, "method", METHODS)
    if interpolation is None:
        interpolation = "boundary" if method == "imperfect" else "none"
    if voxelization is None:
        voxelization = "points" if method == "imperfect" else "rays"
    V.one_of(interpolation, "interpolation", INTERPOLATIONS)
    V.one_of(voxelization, "voxelization", VOXELIZATIONS)
    if method == "naive_exact" and interpolation != "none":
        raise ValueError("interpolation: naive_exact has exact visibility, nothing to interpolate")
    if method == "naive_voxel" and voxelization != "rays":
        raise ValueError("voxelization: naive_voxel voxelizes with exact texel rays ('rays')")
    K, R, N = (V.integer(v, name, lo) for v, name, lo in ((vpls, "vpls", 1), (resolution, "resolution", 2),
                                                          (steps, "steps", 1)))
    M = 4 * R * R if points_per_vpl is None else V.integer(points_per_vpl, "points_per_vpl", 1)
    c = V.real(splat_coverage, "splat_coverage", 0.0, open_min=True)
    if surface_bias is not None:
        V.real(surface_bias, "surface_bias", 0.0)
    A.float_type(dtype)  # raises ValueError naming dtype
    k = kit(dtype)
    cam = scene.camera
    P_np = sample_vpls(scene.light, K, jitter, seed)
    P = k.vec_array(P_np)
    grid = fit_grid(scene, P_np, R)
    frame = tuple(k.vec(v) for v in scene.light.frame())
    intensity = dr.opaque(k.Float, scene.light.radiance * scene.light.area / K)
    if surface_bias is None:
        surface_bias = 1e-4 * scene.extent if method == "naive_exact" else grid.dr_bin
    bias = float(surface_bias)
    clock = _Clock()
    voxels, splats = method != "naive_exact", method == "imperfect" and voxelization == "points"
    params = dict(method=method, vpls=K, resolution=R if voxels else None, steps=N, interpolation=interpolation,
                  voxelization=voxelization if voxels else None, points_per_vpl=M if splats else None,
                  splat_coverage=c if splats else None, surface_bias=bias, jitter=jitter, seed=seed,
                  dtype=dtype, width=cam.width, height=cam.height)

    hits = clock("t_gather", lambda: camera_hits(scene, k))
    image = k.Float(dr.select(hits.kind == LIGHT_FRONT,
                              scene.light.radiance * dr.exp(-scene.medium.sigma_t * hits.t_end), 0))
    boundary = dr.zeros(k.UInt32, 1)

    # imperfect: one pass over all K VPLs; naive: one pass per VPL (width 1, same kernel for every i)
    passes = [(P, K)] if method == "imperfect" else ((dr.gather(k.Vec3, P, dr.opaque(k.UInt32, i)), 1)
                                                      for i in range(K))
    for p, n in passes:
        thunk = (_exact_pass(scene, k, hits, p, N, intensity, bias, clock) if method == "naive_exact" else
                 _render_batched(scene, k, grid, frame, hits, p, n, N, M, intensity, bias, interpolation,
                                 voxelization, seed, c, clock))
        image, boundary = clock("t_gather", lambda: _accumulate(k, image, boundary, thunk, n))

    img = np.asarray(image.numpy(), dtype=np.float64).reshape(cam.height, cam.width)
    stats = dict(grid=grid.__dict__.copy() if voxels else None,
                 boundary_lookups=int(np.asarray(boundary.numpy()).ravel()[0]),
                 lookups=cam.width * cam.height * K * N)
    return AreaLightRender(img, dict(clock.t), params, stats)


def _accumulate(k: Kit, image, boundary, thunk, K: int):
    """Run a gather thunk (radiance per lane, boundary-step count), then add to the image.
    With K > 1 the lanes are VPL-major (lane = k n_pix + pixel), summed per pixel."""
    L, nb = thunk()
    dr.eval(L, nb)
    if K > 1:
        n_pix = dr.width(image)
        acc = dr.zeros(k.Float, n_pix)
        dr.scatter_reduce(dr.ReduceOp.Add, acc, L, dr.arange(k.UInt32, dr.width(L)) % n_pix)
        L = acc
    return image + L, boundary + nb


def _exact_pass(scene, k: Kit, hits, p, N, intensity, bias, clock):
    """One naive_exact pass for a single VPL at p: ray-cast visibility now, the gather as a
    thunk (so that the caller times it)."""
    pix = dr.arange(k.UInt32, dr.width(hits.t_end))
    Vm, Vs = clock("t_visibility", lambda: exact_visibility(scene, k, hits, p, N, bias))

    def vis_medium(x, j):       # the ray-cast visibility of step j
        return dr.gather(k.Float, Vm, pix * N + j), None

    def thunk():
        L, _ = gather(scene, k, hits, pix, p, N, intensity, vis_medium, lambda x: dr.gather(k.Float, Vs, pix), 0.0)
        return L, k.UInt32(0)
    return thunk


def _render_batched(scene, k: Kit, grid, frame, hits, P, K, N, M, intensity, bias, interpolation,
                    voxelization, seed, coverage, clock):
    """Voxel methods: one buffer for the K grids (imperfect VSVs; naive_voxel: K = 1 per pass), one
    scan, one (pixel, VPL) gather as a thunk."""
    words = clock("t_visibility", lambda: voxelize_points(scene, grid, k, frame, P, K, M, seed, coverage)
                  if voxelization == "points" else voxelize_rays(scene, grid, k, frame, P, K))
    S = clock("t_scan", lambda: scan(words, grid, k))
    stride = 2 if interpolation == "boundary" else 1
    if stride == 2:                     # the boundary mask interleaved with S (S words at 2 * index)
        S = clock("t_scan", lambda: interleave(S, boundary_mask(S, grid, k), k))

    n_pix = dr.width(hits.t_end)

    def lane_info(lane):
        # VPL-major lanes: a SIMD packet holds neighbouring pixels of one VPL, so its voxel
        # gathers stay within one grid (pixel-major lanes are slower)
        vpl = lane // n_pix
        pix = lane - vpl * n_pix
        return pix, vpl, dr.gather(k.Vec3, P, vpl)

    def thunk():
        """The gather with voxel visibility: nearest texel ('none'), bilinear at every step ('full'),
        or nearest plus the compacted pass over the boundary steps ('boundary')."""
        pix, vpl, p = lane_info(dr.arange(k.UInt32, n_pix * K))

        def vis(x, bilinear: bool):
            lookup = lookup_bilinear if bilinear else lookup_point
            return lookup(grid, k, S, vpl, project(grid, k, frame, x, p), stride=stride)

        def vis_medium(x, j):
            if interpolation == "boundary":
                return lookup_point_edge(grid, k, S, vpl, project(grid, k, frame, x, p))
            return vis(x, interpolation == "full"), None

        L, flags = gather(scene, k, hits, pix, p, N, intensity, vis_medium, lambda x: vis(x, interpolation != "none"),
                          bias, boundaries=interpolation == "boundary")
        if flags is None:
            return L, k.UInt32(0)
        dr.eval(L, *flags)

        def vis_delta(x, vpl_, p_):
            c = project(grid, k, frame, x, p_)
            return (lookup_bilinear(grid, k, S, vpl_, c, stride=stride)
                    - lookup_point(grid, k, S, vpl_, c, stride=stride))

        corr = boundary_correction(scene, k, hits, N, intensity, flags, lane_info, vis_delta)
        nb = sum((dr.sum(dr.popcnt(f)) for f in flags), k.UInt32(0))
        return L + corr, nb
    return thunk
