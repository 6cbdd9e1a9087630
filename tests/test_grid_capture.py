"""Exact grid capture (avsm_dr.capture.dda): one segment per dual-cell crossing, checked
against an independent float64 quadrature (tests/reference/grid_quadrature_ref.py), on
hand-made grazing rays, the built-in scenes and random grids; gradients; bad input."""
from __future__ import annotations

import numpy as np
import pytest

import avsm_dr as ad
from helpers import compiled_kernels
import drjit as dr
from avsm_dr.capture import GridVolume
from avsm_dr.capture.camera import make_camera
from avsm_dr.capture._grid_volume import dual_block_max
from avsm_dr.capture.dda import traverse
from avsm_dr.scene import DirectionalLight, Scene
from reference import capture_ref as R
from reference import grid_quadrature_ref as Q
from test_capture import BBOX, LIGHTS, grid_scene, small_grid


def _camera(grid, light, res=64):
    return make_camera(light, res, np.array([grid.occupied[0]]), np.array([grid.occupied[1]]))


def _per_ray(tex):
    """Yield (texel, slice) of each ray's run of segments."""
    ut, start = np.unique(tex, return_index=True)
    end = np.r_[start[1:], tex.size]
    for t, a, b in zip(ut, start, end):
        yield t, slice(a, b)


def _errors(density, bbox, cam, tex, z1, tau, n_rays=60, seed=0):
    """(|cumulative tau - reference|, reference, float32 depth-rounding floor) at every segment
    end of up to ``n_rays`` random rays."""
    runs = list(_per_ray(tex))
    pick = np.random.default_rng(seed).choice(len(runs), min(n_rays, len(runs)), replace=False)
    o, d = cam.rays(np.array([runs[i][0] for i in pick]))
    out = []
    for k, i in enumerate(pick):
        s = runs[i][1]
        ref = Q.optical_depth_pieces(density, bbox, o[k], d[k], 0.0, z1[s])
        # the stored float32 depth z1 is within half an ulp of the ray parameter the optical
        # depth was integrated to; sigma <= max(density) turns that into an optical-depth error
        floor = float(np.max(density)) * np.spacing(np.float32(np.abs(z1[s]).max()))
        out.append(np.c_[np.abs(np.cumsum(tau[s]) - ref), ref, np.full(ref.size, floor)])
    return np.concatenate(out)


def _host(*arrays):
    return [np.asarray(a.numpy(), np.float64) for a in arrays]


# ------------------------------------------------------------------ the reference itself
def test_quadrature_reference_agrees_with_fine_midpoint_march():
    """The piecewise Gauss-Legendre reference vs the independent midpoint march (4000 steps per
    unit, O(h^2) at the kinks): measured max difference 2.2e-7; bound 1e-6."""
    d = small_grid()
    rng = np.random.default_rng(1)
    for _ in range(20):
        o = rng.uniform(-2, 2, 3)
        target = rng.uniform(BBOX[0], BBOX[1])
        dirn = (target - o) / np.linalg.norm(target - o)
        depths = np.linspace(0, 5, 23)
        a = Q.optical_depth_pieces(d, BBOX, o, dirn, 0.0, depths)
        b = R.optical_depth_ref(d, BBOX, o, dirn, 0.0, depths)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)


@pytest.mark.parametrize("block", [1, 2, 3, 8])
def test_dual_block_max_is_max_over_the_blocks_corners(block):
    rng = np.random.default_rng(block)
    d = rng.random((9, 7, 11)).astype(np.float32)
    d[d < 0.9] = 0
    pad = np.pad(d, 1, mode="edge")
    occ = dual_block_max(pad, block)
    for b in np.ndindex(occ.shape):
        sl = tuple(slice(bi * block, min((bi + 1) * block + 1, n)) for bi, n in zip(b, pad.shape))
        assert occ[b] == pad[sl].max()
        assert b[0] * block <= d.shape[0] and b[2] * block <= d.shape[2]        # no empty trailing block


# ------------------------------------------------------------------ exactness
@pytest.mark.parametrize("light", list(LIGHTS) + ["axis_aligned"])
def test_exact_capture_matches_float64_quadrature(light):
    """Cumulative optical depth at every segment end vs the float64 quadrature.  Float32:
    |error| <= 1e-5 x tau + the depth-rounding floor (measured <= 0.18 of that bound; relative
    error 5e-7 where tau > 1).  Float64: relative 1e-12 (measured 3e-14): the method is exact,
    what remains in float32 is rounding."""
    lt = LIGHTS.get(light, DirectionalLight((0.0, 0.0, 1.0)))
    d = small_grid()
    for dtype, rel in (("float32", 1e-5), ("float64", 1e-12)):
        g = GridVolume.prepare(d, BBOX, dtype=dtype)
        cam = _camera(g, lt)
        tex, z0, z1, tau, st = traverse(g, cam, 1e-12)
        z0, z1, tau = _host(z0, z1, tau)
        assert st["segments"] == tex.size > 3000 and np.all(tau > 0) and np.all(z1 >= z0)
        e = _errors(d, BBOX, cam, tex, z1, tau)
        floor = e[:, 2] if dtype == "float32" else 0.0
        assert np.all(e[:, 0] <= rel * e[:, 1] + floor + 1e-15), np.max(e[:, 0] / (rel * e[:, 1] + floor + 1e-15))
        if dtype == "float32":
            big = e[:, 1] > 1
            assert big.sum() > 50 and np.max(e[big, 0] / e[big, 1]) < 1e-5


@pytest.mark.parametrize("name", ["plume", "three_columns", "hair_and_smoke", "smoke_over_table",
                                  "random_dense", "random_sparse"])
def test_exact_capture_on_scenes_and_random_grids(name):
    """Built-in scenes (densities up to ~60) and random grids - dense (no empty margin: the
    clamp band and the box faces carry density) and sparse (block skipping, isolated voxels):
    the same bound as above; the spot light of a random grid crosses it at oblique angles."""
    rng = np.random.default_rng(len(name))
    if name.startswith("random"):
        shape = (9, 13, 11)
        d = rng.random(shape).astype(np.float32) * 5
        if name == "random_sparse":
            d[rng.random(shape) < 0.85] = 0
        bbox = (np.array([-0.5, -0.3, -0.6]), np.array([0.4, 0.9, 0.5]))
        light = LIGHTS["spot"]
    else:
        sc = ad.scenes.get(name)
        d, bbox, light = sc.density, sc.bbox, sc.light
    g = GridVolume.prepare(d, bbox)
    cam = _camera(g, light)
    tex, z0, z1, tau, st = traverse(g, cam, 1e-12)
    _, z1, tau = _host(z0, z1, tau)
    e = _errors(d, bbox, cam, tex, z1, tau, n_rays=40)
    assert e.shape[0] > 300
    assert np.all(e[:, 0] <= 1e-5 * e[:, 1] + e[:, 2]), np.max(e[:, 0] / (1e-5 * e[:, 1] + e[:, 2]))


def test_segments_are_single_dual_cell_crossings():
    """Every segment lies in one dual cell (its midpoint's cell contains both ends, to float32
    rounding), segments of a ray do not overlap, and a ray's crossings cover the cells it meets."""
    d = small_grid()
    g = GridVolume.prepare(d, BBOX)
    cam = _camera(g, LIGHTS["spot"])
    tex, z0, z1, tau, _ = traverse(g, cam, 1e-12)
    z0, z1, _ = _host(z0, z1, tau)
    o, dd = cam.rays(tex)
    h = g.voxel
    u = lambda t: (o + dd * t[:, None] - g.bmin) / h - 0.5             # noqa: E731
    cell = np.floor(u(0.5 * (z0 + z1)))
    tol = 1e-5 * np.max(np.abs(u(z1)))
    for end in (z0, z1):
        ue = u(end)
        assert np.all((ue >= cell - tol) & (ue <= cell + 1 + tol))
    same = tex[1:] == tex[:-1]
    assert np.all(z0[1:][same] >= z1[:-1][same])


def test_exact_capture_takes_fewer_samples_than_the_half_voxel_march():
    """Density evaluations (two per iteration in both) and voxel reads per ray: one iteration
    per dual cell crossed (|d_x| + |d_y| + |d_z| per voxel of path) vs two steps per voxel."""
    sc = ad.scenes.plume(size=16)
    a = ad.capture(sc, resolution=64, method="march", order="depth").stats["grid"]
    b = ad.capture(sc, resolution=64, method="exact", order="depth").stats["grid"]
    assert a["lanes"] == b["lanes"] > 1000
    assert b["iterations"] < 0.8 * a["iterations"]
    assert b["segments"] < a["segments"]


# ------------------------------------------------------------------ robust traversal
def _grazing_rays(g):
    """Hand-made rays: on voxel-centre planes, along an edge of four dual cells, nearly
    parallel to an axis (1e-9), starting on a plane and moving down, and through corners."""
    h, lo = g.voxel, g.bmin
    centre = lo + (np.array([6, 7, 5]) + 0.5) * h                       # a voxel centre
    o, d = [], []
    for axis in range(3):
        dirn = np.zeros(3)
        dirn[axis] = 1.0
        for off in (np.zeros(3), 0.3 * h, np.where(np.arange(3) == (axis + 1) % 3, 0.5 * h, 0.0)):
            p = centre + off
            p[axis] = lo[axis] - 0.5
            o.append(p)
            d.append(dirn)
        tilt = dirn.copy()
        tilt[(axis + 1) % 3] = 1e-9
        o.append(centre - 2 * dirn)
        d.append(tilt / np.linalg.norm(tilt))
        o.append(centre + 2 * dirn)                                      # moving down along the axis
        d.append(-dirn)
    for sgn in (1, -1):
        diag = np.array([1.0, 1.0, 1.0]) * sgn / np.sqrt(3)
        o.append(centre - 3 * diag)
        d.append(diag)
        o.append(centre + np.array([0.0, 0.5, 0.5]) * h - 3 * diag)       # through dual-cell edges
        d.append(diag)
    o, d = np.array(o), np.array(d)
    from avsm_dr.geometry import ray_box
    t0, t1, hit = ray_box(o, d, *g.occupied, t_min=0.0)
    assert hit.all()
    return np.arange(len(o)), o, d, t0, t1


class _RayCamera:
    """A light camera whose texel k shoots the hand-made ray ``(o[k], d[k])``: one row of texels."""

    def __init__(self, o, d):
        self.o, self.d, self.res = o, d, len(o)

    def footprint_rects(self, lo, hi):
        zero = np.zeros(1, np.int64)
        return [(zero, zero + self.res - 1, zero, zero, 0)]

    def rays_device(self, texels):
        F64 = ad.backend.types().Float64
        return tuple([dr.gather(F64, F64(np.ascontiguousarray(v[:, a])), texels) for a in range(3)]
                     for v in (self.o, self.d))


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_grazing_rays_terminate_and_are_exact(dtype):
    """Rays on voxel-centre planes and dual-cell edges, nearly parallel rays and rays starting on
    a plane: the traversal ends well inside its iteration bound and matches the quadrature."""
    rng = np.random.default_rng(4)
    d = (rng.random((12, 14, 13)) * 3).astype(np.float32)
    bbox = (np.array([-0.6, -0.7, -0.65]), np.array([0.7, 0.7, 0.6]))
    g = GridVolume.prepare(d, bbox, dtype=dtype)
    lanes = _grazing_rays(g)
    tex, z0, z1, tau, st = traverse(g, _RayCamera(lanes[1], lanes[2]), 1e-12)
    _, z1, tau = _host(z0, z1, tau)
    assert np.all(np.isfinite(tau)) and np.unique(tex).size == lanes[0].size
    assert st["max_iterations"] <= 2 * sum(d.shape) + 8
    rel = 1e-5 if dtype == "float32" else 1e-12
    for t, s in _per_ray(tex):
        ref = Q.optical_depth_pieces(d, bbox, lanes[1][t], lanes[2][t], 0.0, z1[s])
        floor = 3.0 * np.spacing(np.float32(np.abs(z1[s]).max())) if dtype == "float32" else 0.0
        assert np.all(np.abs(np.cumsum(tau[s]) - ref) <= rel * ref + floor + 1e-15), t


@pytest.mark.parametrize("keep_zero", [False, True])
def test_rounds_give_the_same_segments_as_one_round(keep_zero):
    """The one-round layout (a slot per dual cell a ray meets, then dr.compress) and rounds of
    2 slots per lane (lanes that fill them continue from where they stopped, then a scatter
    into CSR order) write exactly the same segments."""
    d = small_grid()
    g = GridVolume.prepare(d, BBOX, skip_empty=not keep_zero)
    cam = _camera(g, LIGHTS["point"])
    a = traverse(g, cam, 1e-4, keep_zero=keep_zero, capacity=2, slot_budget=0)
    b = traverse(g, cam, 1e-4, keep_zero=keep_zero)
    assert a[4]["rounds"] > 5 and b[4]["rounds"] == 1
    assert np.array_equal(a[0], b[0])
    for x, y in zip(_host(*a[1:4]), _host(*b[1:4])):
        assert np.array_equal(x, y)


@pytest.mark.parametrize("light", list(LIGHTS))
def test_device_ray_setup_matches_the_host_bit_for_bit(light):
    """Rays, slab clipping and candidate texels made on the device in float64 (no host round
    trip: 0.45 s of a 1.2 s plume capture at 1024^2 was host ray setup) equal the host's."""
    from avsm_dr.capture._grid_lanes import candidate_texels
    from avsm_dr.geometry import ray_box, ray_box_dr
    g = GridVolume.prepare(small_grid(), BBOX)
    cam = _camera(g, LIGHTS[light], res=48)
    lo, hi = g.occupied
    cand = np.asarray(candidate_texels(cam, lo, hi).numpy(), np.int64)
    assert np.array_equal(cand, np.concatenate([t for _, t in cam.footprint_chunks(lo[None], hi[None])]))
    o, d = cam.rays(cand)
    od, dd = cam.rays_device(ad.backend.types().UInt32(cand.astype(np.uint32)))
    for a in range(3):
        assert np.array_equal(np.asarray(od[a].numpy()), o[:, a])
        assert np.array_equal(np.asarray(dd[a].numpy()), d[:, a])
    t0, t1, hit = ray_box(o, d, lo, hi, t_min=0.0)
    t0d, t1d, hitd = ray_box_dr(od, dd, lo, hi, t_min=0.0)
    assert np.array_equal(np.asarray(hitd.numpy()), hit) and 0 < hit.sum() < hit.size
    for x, y in ((t0d, t0), (t1d, t1)):
        assert np.array_equal(np.asarray(x.numpy())[hit], y[hit])


@pytest.mark.parametrize("method", ["exact", "march"])
def test_corner_table_and_gathers_give_the_same_segments(monkeypatch, method):
    """The packet load of a dual cell's 8 corners from the corner table reads the same values
    as 8 gathers from the padded window (the fallback for windows above the table budget;
    the march crashed there before it shared the exact capture's corner reader)."""
    from avsm_dr.capture import _grid_volume
    from avsm_dr.capture.grid import march
    d = small_grid()
    out = []
    for cells in (_grid_volume.CORNER_TABLE_CELLS, 0):
        monkeypatch.setattr(_grid_volume, "CORNER_TABLE_CELLS", cells)
        g = GridVolume.prepare(d, BBOX)
        cam = _camera(g, LIGHTS["spot"])
        tex, z0, z1, tau, _ = traverse(g, cam, 1e-4) if method == "exact" else march(g, cam, 0.02, 1e-4)
        out.append([tex] + _host(z0, z1, tau))
        assert (g._dual_cache["table"] is None) == (cells == 0)
    for other in out[1:]:
        for x, y in zip(out[0], other):
            assert np.array_equal(x, y)


@pytest.mark.parametrize("method", ["exact", "march"])
def test_capture_at_a_new_resolution_compiles_nothing(method):
    """The grid captures' kernels take every size-, camera- and grid-dependent value as an
    opaque scalar: a new resolution or light compiles nothing.  (A ``scatter_add`` in Auto
    mode baked its target's size into the compaction kernel: a compile per capture.)"""
    sc = grid_scene(LIGHTS["directional"])

    def compiled(**kw):
        # a kernel not in memory after the warm-up is new (compiled now, or earlier to disk)
        return compiled_kernels(lambda: ad.capture(sc, method=method, **kw, order="depth").segments.z0,
                                disk_hits_are_new=True)

    compiled(resolution=64)
    assert [compiled(resolution=r) for r in (67, 71)] == [0, 0]
    sc = Scene("t", DirectionalLight((0.3, -1.0, 0.5)), sc.receivers, density=sc.density, bbox=sc.bbox)
    assert compiled(resolution=73) == 0


@pytest.mark.parametrize("keep_zero", [False, True])
def test_march_one_pass_equals_rounds(keep_zero):
    """The march's one pass into slots (a bound of each lane's segments, then compaction) writes
    exactly the segments of rounds of 2 slots per lane (its fallback when the slots exceed the
    budget or a lane fills its slots; lanes continue from where they stopped)."""
    from avsm_dr.capture import grid as G
    g = GridVolume.prepare(small_grid(), BBOX, skip_empty=not keep_zero)
    cam = _camera(g, LIGHTS["point"])
    out = []
    for budget in (G.SLOT_BUDGET, 0):
        tex, z0, z1, tau, st = G.march(g, cam, 0.02, 1e-4, keep_zero=keep_zero, capacity=2, slot_budget=budget)
        assert ("slots" in st) == (budget > 0) and st["segments"] > 100 and (st["rounds"] > 5) == (budget == 0)
        out.append([tex] + _host(z0, z1, tau) + [st["iterations"]])
    for other in out[1:]:
        for x, y in zip(out[0], other):
            assert np.array_equal(x, y)


def test_light_that_misses_the_grid_gives_no_segments():
    """No candidate texel (a spot light facing away) or no hitting ray: empty captures."""
    from avsm_dr.scene import SpotLight
    for light in (SpotLight((-2.0, 1.5, -1.0), (-2.0, 1.5, -1.0), 30.0),       # facing away
                  SpotLight((-2.0, 0.2, 0.0), (0.0, 0.0, -1.0), 30.0)):        # box across its plane: all miss
        for method in ("exact", "march"):
            cap = ad.capture(grid_scene(light), resolution=64, method=method, order="depth")
            assert cap.segments.n_segments == 0 and cap.stats["grid"]["lanes"] == 0


def test_padding_with_empty_space_changes_nothing():
    """The same grid zero-padded (same voxels, same place): the window and block layout differ,
    the crossings do not; optical depths agree to float32 rounding (1e-6 on tau <= ~5)."""
    d = small_grid()
    d[[0, -1]] = 0
    d[:, [0, -1]] = 0
    d[:, :, [0, -1]] = 0
    off = np.array([3, 8, 5])
    big = np.zeros((23, 29, 30), np.float32)
    big[5:15, 8:20, 3:17] = d
    h = (BBOX[1] - BBOX[0]) / np.array([14, 12, 10])
    bb2 = (BBOX[0] - off * h, BBOX[0] + (np.array([30, 29, 23]) - off) * h)
    rec = np.random.default_rng(4).uniform(-0.7, 1.2, (300, 3))
    out = []
    for dens, bb in ((d, BBOX), (big, bb2)):
        sc = Scene("t", LIGHTS["spot"], rec, density=dens, bbox=bb)
        cap = ad.capture(sc, resolution=64, method="exact", order="depth")
        out.append(np.asarray(cap.transmittance(ad.build("exact", cap.segments), rec)))
    assert out[0].min() < 0.5
    np.testing.assert_allclose(out[1], out[0], rtol=0, atol=1e-6)


def test_exact_default_march_and_method_errors():
    sc = grid_scene(LIGHTS["directional"])
    assert "crossings" not in ad.capture(sc, resolution=64, order="depth").stats["grid"]          # default: the march
    assert "crossings" in ad.capture(sc, resolution=64, method="exact", order="depth").stats["grid"]
    with pytest.raises(ValueError, match="^method"):
        ad.capture(sc, resolution=64, method="simpson")
    with pytest.raises(ValueError, match="^step"):
        ad.capture(sc, resolution=64, method="exact", step=0.01)


# ------------------------------------------------------------------ gradients
def _loss(x, scene, **kw):
    cap = ad.capture(scene, resolution=64, density=x, epsilon=1e-12, bounds=BBOX, method="exact", **kw, order="depth")
    return dr.sum(cap.transmittance(ad.build("exact", cap.segments), scene.receivers)), cap


def test_exact_capture_gradient_reaches_zero_voxels_with_keep_zero():
    """sum tau is linear in the density: <grad, d> = sum tau; a zero voxel inside the empty
    slab gets a gradient only when zero crossings are kept (keep_zero also disables skipping)."""
    from drjit.llvm.ad import TensorXf
    d = small_grid()
    sc = grid_scene(LIGHTS["directional"])
    sums, grads = [], []
    for keep in (False, True):
        x = TensorXf(d)
        dr.enable_grad(x)
        cap = ad.capture(sc, resolution=64, density=x, epsilon=1e-12, keep_zero=keep, bounds=BBOX,
                         method="exact", order="depth")
        s = dr.sum(cap.segments.optical_depth)
        dr.backward(s)
        sums.append(float(s[0]))
        grads.append(dr.grad(x).numpy())
        np.testing.assert_allclose(float((grads[-1] * d).sum()), sums[-1], rtol=1e-4)
    inner_zero = (5, 5, 1)
    assert d[inner_zero] == 0 and grads[0][inner_zero] == 0 and grads[1][inner_zero] > 0
    # the same exact integrals either way (float32 summation order only)
    np.testing.assert_allclose(sums[1], sums[0], rtol=1e-5)
