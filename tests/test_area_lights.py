"""Area lights: imperfect voxelized shadow volumes (avsm_dr.area_lights;
Wyman and Dai 2013, "Imperfect Voxelized Shadow Volumes", HPG).

References: tests/reference/area_lights_ref.py (float64 NumPy, independent), an
adaptive-quadrature single-scattering integral, and Mitsuba 3 volpath (marker mitsuba).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import avsm_dr  # noqa: F401  (libLLVM before drjit)
import drjit as dr
from avsm_dr import area_lights as al
from avsm_dr.area_lights import geometry as G
from avsm_dr.area_lights import visibility as V
from avsm_dr.area_lights import vpl as VP
from reference import area_lights_ref as ref

METHODS = [("naive_exact", {}), ("naive_voxel", {"resolution": 32}), ("imperfect", {"resolution": 32})]


def small_scene(w=16, h=16, occluders=True, g=0.0, **kw):
    return al.default_scene(w, h, occluders=occluders, g=g, **kw)


def rmse(a, b):
    return float(np.sqrt(np.mean((a - b) ** 2)))


# ------------------------------------------------------------------ analytic point light
@pytest.mark.parametrize("g", [0.0, 0.6])
@pytest.mark.parametrize("method,kw", METHODS)
def test_point_light_matches_single_scattering_integral(method, kw, g):
    """K = 1 and no occluders: every method reduces to the single-scattering integral of
    one (cosine-lobed) point light, computed here by adaptive quadrature (epsrel 1e-10).

    Tolerance 1e-5 relative per pixel: the midpoint rule with N = 512 steps is off by
    6e-7 (measured in float64) and float32 rounding of 512 terms adds about
    sqrt(512) * 6e-8 = 1.4e-6 (measured max 2e-6).  A missing factor (4 pi, a cosine,
    one exp) would be off by > 10 %."""
    scene = small_scene(12, 12, occluders=False, g=g)
    expect = ref.point_light_quadrature(scene)
    got = al.render(scene, method, vpls=1, steps=512, **kw).image
    assert np.all(expect > 0)
    np.testing.assert_allclose(got, expect, rtol=1e-5, atol=0)


def test_riemann_sum_converges_at_second_order():
    """Midpoint rule: quadrupling N cuts the error by about 16 (12 to 20 allowed)."""
    scene = small_scene(8, 8, occluders=False)
    expect = ref.point_light_quadrature(scene)
    e = [np.abs(al.render(scene, "naive_exact", vpls=1, steps=n, dtype="float64").image - expect).max()
         for n in (16, 64)]
    assert 12 < e[0] / e[1] < 20


# --------------------------------------------------------------- NumPy reference, exact
def test_naive_exact_matches_numpy_reference_float64():
    """Occluders, K = 4 VPLs, N = 24 steps: the Dr.Jit kernel in float64 equals the
    float64 NumPy reference up to rounding (rtol 1e-9; a visibility flip would be 1e-2)."""
    scene = small_scene(10, 9)
    eps = 1e-4 * scene.extent
    expect = ref.render_exact(scene, 4, 24, eps)
    got = al.render(scene, "naive_exact", vpls=4, steps=24, dtype="float64").image
    assert np.count_nonzero(expect) > 0.9 * expect.size
    np.testing.assert_allclose(got, expect, rtol=1e-9, atol=1e-14)


def test_camera_rays_match_reference():
    cam = small_scene(7, 5).camera
    np.testing.assert_allclose(cam.rays(), ref.camera_rays(cam), rtol=0, atol=1e-14)


def test_vpls_are_cell_centres_and_inside_the_quad():
    L = small_scene().light
    np.testing.assert_allclose(al.sample_vpls(L, 16), ref.vpl_positions(L, 16), atol=1e-14)
    for K in (1, 7, 30):  # non-squares: Hammersley points
        P = al.sample_vpls(L, K, jitter=True, seed=3)
        ab = np.linalg.lstsq(np.stack([L.edge_u, L.edge_v], 1), (P - L.center).T, rcond=None)[0]
        assert P.shape == (K, 3) and np.all(np.abs(ab) <= 0.5)
    np.testing.assert_allclose(al.sample_vpls(L, 1)[0], L.center)


# ------------------------------------------------------------------------- scan (bits)
def _scan_bits(occ_bits: np.ndarray) -> np.ndarray:
    n, R = occ_bits.shape
    k = G.kit()
    grid = VP.LightGrid(R, -1, 1, -1, 1, 0, 1)
    S = V.scan(k.UInt32(ref.pack_bits(occ_bits)), grid, k)
    return ref.unpack_bits(np.asarray(S.numpy()), n, R)


@pytest.mark.parametrize("R", [2, 5, 31, 32, 33, 64, 100, 128])
def test_scan_matches_reference(R, rng):
    """Exclusive prefix-OR along each ray, word boundaries included; adversarial rows:
    empty, full, one bit at 0, 31, 32 and R - 1."""
    occ = rng.random((200, R)) < rng.choice([0.002, 0.02, 0.2], (200, 1))
    occ[0] = False
    occ[1] = True
    for row, b in zip(range(2, 6), (0, 31, 32, R - 1)):
        occ[row] = False
        occ[row, min(b, R - 1)] = True
    np.testing.assert_array_equal(_scan_bits(occ), ref.scan_exclusive(occ))


@settings(max_examples=30, deadline=None)
@given(st.integers(2, 70), st.lists(st.integers(0, 69), max_size=6))
def test_scan_property(R, bins):
    """S_b = 1 iff an occupied bin lies strictly before b (monotone along the ray)."""
    occ = np.zeros((1, R), bool)
    for b in bins:
        occ[0, b % R] = True
    S = _scan_bits(occ)[0]
    first = np.argmax(occ[0]) if occ.any() else R
    np.testing.assert_array_equal(S, np.arange(R) > first)


def test_boundary_mask_matches_reference(rng):
    K, R = 3, 9
    grid = VP.LightGrid(R, -1, 1, -1, 1, 0, 1)
    k = G.kit()
    occ = rng.random((K * R * R, R)) < 0.05
    S_bits = ref.scan_exclusive(occ)
    E = V.boundary_mask(k.UInt32(ref.pack_bits(S_bits)), grid, k)
    got = ref.unpack_bits(np.asarray(E.numpy()), K * R * R, R).reshape(K, R, R, R)
    expect = ref.boundary_mask(S_bits.reshape(K, R, R, R))
    assert expect.any() and (~expect).any()
    np.testing.assert_array_equal(got, expect)


# ------------------------------------------------------------------------- voxelization
def test_voxelize_rays_matches_reference():
    scene = small_scene()
    P = al.sample_vpls(scene.light, 4)
    R = 12
    grid = al.fit_grid(scene, P, R)
    k = G.kit("float64")
    frame = tuple(k.vec(v) for v in scene.light.frame())
    words = V.voxelize_rays(scene, grid, k, frame, k.vec_array(P), len(P))
    got = ref.unpack_bits(np.asarray(words.numpy()), len(P) * R * R, R).reshape(len(P), R, R, R)
    expect = ref.voxelize_rays(scene, P, grid)
    assert expect.sum() > 20
    np.testing.assert_array_equal(got, expect)


def test_surface_points_lie_on_occluders_uniformly_by_area():
    scene = small_scene()
    k = G.kit("float64")
    n = 40000
    x = np.stack([np.asarray(c.numpy()) for c in V.surface_points(scene, k, n, seed=1)], 1)
    owner = np.full(n, -1)
    for i, o in enumerate(scene.occluders):
        if isinstance(o, al.Sphere):
            on = np.abs(np.linalg.norm(x - o.center, axis=1) - o.radius) < 1e-5
        else:
            inside = np.all((x >= o.min - 1e-6) & (x <= o.max + 1e-6), 1)
            face = np.any(np.isclose(x, o.min, atol=1e-6) | np.isclose(x, o.max, atol=1e-6), 1)
            on = inside & face
        owner[on & (owner < 0)] = i
    assert np.all(owner >= 0)
    areas = np.array([o.area for o in scene.occluders])
    frac = np.bincount(owner, minlength=len(areas)) / n
    p = areas / areas.sum()
    # binomial standard error sqrt(p (1-p) / n) <= 0.0025; 5 sigma
    tol = 5 * np.sqrt(p * (1 - p) / n)
    assert np.all(np.abs(frac - p) <= tol), (frac, p, tol)


def test_grid_contains_every_occluder_point():
    """All occluder surface points of all VPLs project inside the fitted frustum, in
    depth bins 0 .. R - 2 (bin R - 1 is 'beyond every occluder')."""
    scene = small_scene()
    P = al.sample_vpls(scene.light, 9)
    R = 16
    grid = al.fit_grid(scene, P, R)
    k = G.kit("float64")
    frame = tuple(k.vec(v) for v in scene.light.frame())
    x = V.surface_points(scene, k, 5000, seed=2)
    for p in P:
        c = V.project(grid, k, frame, x, k.vec(p))
        assert bool(dr.all(c.inside))
        r = np.linalg.norm(np.stack([np.asarray(v.numpy()) for v in x], 1) - p, axis=1)
        fb = (r - grid.r_near) / grid.dr_bin
        assert fb.min() >= 0 and fb.max() < R - 1


# ------------------------------------------------------------------------ interpolation
@pytest.mark.parametrize("method", ["imperfect", "naive_voxel"])
def test_boundary_interpolation_equals_bilinear_everywhere(method):
    """Wyman and Dai 2013: interpolating only at shadow boundaries gives the same Riemann sum as
    interpolating at every step (the other terms cancel).  float32: 1e-5 of the max."""
    scene = small_scene(16, 16)
    kw = dict(vpls=9, resolution=24, steps=64)
    full = al.render(scene, method, interpolation="full", **kw)
    bound = al.render(scene, method, interpolation="boundary", **kw)
    none = al.render(scene, method, interpolation="none", **kw)
    scale = full.image.max()
    assert np.abs(none.image - full.image).max() > 1e-3 * scale      # interpolation matters
    np.testing.assert_allclose(bound.image, full.image, rtol=0, atol=1e-5 * scale)
    assert 0 < bound.stats["boundary_lookups"] < 0.5 * bound.stats["lookups"]


# -------------------------------------------------------------------------- convergence
def test_voxel_methods_converge_to_exact_with_resolution():
    """Against the naive exact method with the same VPLs: error falls as R grows."""
    scene = small_scene(24, 24)
    exact = al.render(scene, "naive_exact", vpls=16, steps=64).image
    for method in ("naive_voxel", "imperfect"):
        errs = [rmse(al.render(scene, method, vpls=16, steps=64, resolution=R).image, exact)
                for R in (8, 32, 128)]
        assert errs[0] > errs[1] > errs[2], (method, errs)
        assert errs[2] < 0.25 * errs[0]


@pytest.mark.mitsuba
def test_converges_to_mitsuba_as_resolution_and_vpls_grow():
    """Mitsuba volpath (single scattering, 4096 spp, per-pixel standard error about
    8e-4) as ground truth: the RMSE of imperfect VSVs falls along (R, K) = (16, 1),
    (32, 16), (64, 64), and the noise-corrected RMSE (MSE minus the mean squared
    standard error) falls too; the dense exact render matches the mean within 1 %."""
    scene = small_scene(24, 24)
    gt, se = al.render_mitsuba(scene, spp=4096, seed=5)
    noise2 = float(np.mean(se ** 2))
    errs, debiased = [], []
    for R, K in ((16, 1), (32, 16), (64, 64)):
        img = al.render(scene, "imperfect", vpls=K, resolution=R, steps=128).image
        errs.append(rmse(img, gt))
        debiased.append(math.sqrt(max(errs[-1] ** 2 - noise2, 0)))
    assert errs[0] > errs[1] > errs[2], errs
    assert debiased[0] > debiased[1] > debiased[2], debiased
    dense = al.render(scene, "naive_exact", vpls=256, steps=128).image
    assert abs(dense.mean() / gt.mean() - 1) < 0.01
    assert rmse(dense, gt) < 1.2 * math.sqrt(noise2)  # at the Monte Carlo noise level


@pytest.mark.mitsuba
def test_mitsuba_scene_matches_unoccluded_hg_medium():
    """Units and phase convention (g = 0.5, forward scattering) against Mitsuba: mean
    within 1 %, per-pixel error at the noise level."""
    scene = small_scene(16, 16, occluders=False, g=0.5)
    gt, se = al.render_mitsuba(scene, spp=4096, seed=1)
    img = al.render(scene, "naive_exact", vpls=256, steps=128).image
    assert abs(img.mean() / gt.mean() - 1) < 0.01
    assert rmse(img, gt) < 1.3 * math.sqrt(float(np.mean(se ** 2)))


# ---------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("kwargs,name", [
    (dict(vpls=0), "vpls"), (dict(vpls=2.5), "vpls"), (dict(resolution=1), "resolution"),
    (dict(steps=0), "steps"), (dict(method="magic"), "method"), (dict(interpolation="cubic"), "interpolation"),
    (dict(method="naive_exact", interpolation="boundary"), "interpolation"),
    (dict(voxelization="mesh"), "voxelization"), (dict(points_per_vpl=0), "points_per_vpl"),
    (dict(splat_coverage=0.0), "splat_coverage"), (dict(surface_bias=-1.0), "surface_bias"),
    (dict(dtype="float16"), "dtype"), (dict(surface_bias="x"), "surface_bias"),
    (dict(method="naive_voxel", voxelization="points"), "voxelization"),
])
def test_render_rejects_bad_arguments(kwargs, name):
    scene = small_scene(4, 4)
    with pytest.raises(ValueError, match=name):
        al.render(scene, **kwargs)


@pytest.mark.parametrize("make,name", [
    (lambda: al.Medium(sigma_s=1.0, sigma_t=0.5), "sigma_s"),
    (lambda: al.Medium(sigma_s=-0.1, sigma_t=0.5), "sigma_s"),
    (lambda: al.Medium(sigma_s=0.1, sigma_t=-0.5), "sigma_t"),
    (lambda: al.Medium(sigma_s=0.1, sigma_t=float("nan")), "sigma_t"),
    (lambda: al.Medium(0.1, 0.5, g=1.0), "g"),
    (lambda: al.QuadLight([0, 1, 0], [1, 0, 0], [2, 0, 0]), "edge_u"),
    (lambda: al.QuadLight([0, 1, 0], [1, 0, 0], [0, 0, 1], radiance=-1), "radiance"),
    (lambda: al.Sphere([0, 0, 0], 0.0), "radius"),
    (lambda: al.Box([0, 0, 0], [1, -1, 1]), "max"),
    (lambda: al.PinholeCamera([0, 0, 0], [0, 0, -1], width=0), "width"),
    (lambda: al.PinholeCamera([0, 0, 0], [0, 0, -1], fov=180), "fov"),
])
def test_scene_objects_reject_bad_arguments(make, name):
    with pytest.raises(ValueError, match=name):
        make()


def test_scene_rejects_occluder_behind_the_light_and_camera_outside():
    s = small_scene(4, 4)
    with pytest.raises(ValueError, match="occluders"):
        al.AreaLightScene(s.medium, s.light, s.camera, s.bounds, [al.Sphere([0, 2.3, 0], 0.05)])
    with pytest.raises(ValueError, match="camera"):
        cam = al.PinholeCamera([0, 1, 5], [0, 1, 0], width=4, height=4)
        al.AreaLightScene(s.medium, s.light, cam, s.bounds, [])
    with pytest.raises(ValueError, match="spp"):
        al.render_mitsuba(s, spp=0)


def test_accepts_package_opaque_blockers():
    from avsm_dr.scene import OpaqueBox, OpaqueSphere
    s = small_scene(4, 4)
    sc = al.AreaLightScene(s.medium, s.light, s.camera, s.bounds,
                           [OpaqueSphere(np.array([0.0, 1.0, 0.0]), 0.2),
                            OpaqueBox(np.array([0.3, 0.2, 0.0]), np.array([0.5, 0.4, 0.2]))])
    assert isinstance(sc.occluders[0], al.Sphere) and isinstance(sc.occluders[1], al.Box)


# --------------------------------------------------------------------------- experiment
@pytest.mark.mitsuba
def test_experiment_writes_table_images_and_meta(tmp_path, monkeypatch):
    """A tiny configuration of the experiment: CSV columns, PNG, meta.json, and skipping
    existing results unless forced."""
    import json

    from experiments import _common
    from experiments import area_lights as exp
    for k, v in dict(width=12, height=10, steps=16, vpls=[1, 4], r_coarse=8, r_high=16, spp=64, k_dense=16,
                     repeats=1).items():
        monkeypatch.setitem(exp.QUICK, k, v)          # the declared quick parameters (STUDY.quick)
    out = exp.run(quick=True, out=tmp_path / "al")
    rows = _common.read_csv(out["csv"])
    need = {"method", "resolution", "vpls", "t_visibility", "t_scan", "t_gather", "rmse_vs_mitsuba",
            "t_jit", "cost_vs_hard", "rmse_vs_dense"}
    assert need <= set(rows[0])
    assert len(rows) == 2 * 5
    assert all(("naive" in r["method"]) or ("imperfect" in r["method"]) for r in rows)
    assert all(float(r["t_gather"]) > 0 and float(r["rmse_vs_mitsuba"]) > 0 for r in rows)
    hard = [r for r in rows if r["method"] == "naive_voxel" and r["resolution"] == "16" and r["vpls"] == "1"]
    assert len(hard) == 1 and float(hard[0]["cost_vs_hard"]) == 1.0
    assert (tmp_path / "al" / "images.png").stat().st_size > 1000
    meta = json.loads((tmp_path / "al" / "meta.json").read_text())
    assert meta["params"]["vpls"] == [1, 4] and "mitsuba_noise_rmse" in meta["summary"]
    again = exp.run(quick=True, out=tmp_path / "al")
    assert again["cached"] is True and again["summary"] == meta["summary"]


def test_import_does_not_load_mitsuba():
    """The Mitsuba variant is set inside functions only, never at import time."""
    import subprocess
    import sys
    code = "import avsm_dr.area_lights, sys; print('mitsuba' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
