"""Light-view capture: grids (vs a float64 NumPy march), particles, hair, opaque blockers,
cameras and lookups, gradients, bad input."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import avsm_dr as ad
import drjit as dr
from avsm_dr.capture import GridVolume, load_tfx, procedural_strands
from avsm_dr.capture._grid_volume import block_max
from avsm_dr.capture.hair import merge_crossings
from avsm_dr.io import read_vol, write_vol
from avsm_dr.scene import (DirectionalLight, Hair, OpaqueBox, OpaquePlane, OpaqueSphere, Particles,
                           PointLight, Scene, SpotLight)
from reference import capture_ref as R

BBOX = (np.array([-0.7, -0.4, -0.5]), np.array([0.7, 0.8, 0.5]))
LIGHTS = {
    "directional": DirectionalLight((1.0, -0.4, 0.3)),
    "spot": SpotLight((-2.0, 1.5, -1.0), (2.0, -1.5, 1.0), 50.0),
    "point": PointLight((-1.5, 1.2, -1.1)),
}


def small_grid(seed=1, shape=(10, 12, 14)):
    """Random densities up to 3 with empty slabs (x < 4 voxels, z < 3 voxels)."""
    rng = np.random.default_rng(seed)
    d = (rng.random(shape) * 3).astype(np.float32)
    d[:, :, :4] = 0
    d[:3] = 0
    return d


def grid_scene(light, density=None, receivers=None):
    density = small_grid() if density is None else density
    rec = np.zeros((1, 3)) if receivers is None else receivers
    return Scene("t", light, rec, density=density, bbox=BBOX)


def cumulative_errors(cap, density, n_texels=40, seed=2):
    """|cumulative captured tau - reference| at every segment end of random non-empty texels."""
    h = cap.segments.numpy()
    tex = np.flatnonzero(cap.segments.counts > 0)
    sel = np.random.default_rng(seed).choice(tex, min(n_texels, tex.size), replace=False)
    o, d = cap.camera.rays(sel)
    errs = []
    for k, t in enumerate(sel):
        s = slice(h["offsets"][t], h["offsets"][t + 1])
        ref = R.optical_depth_ref(density, BBOX, o[k], d[k], 0.0, h["z1"][s])
        errs.append(np.abs(np.cumsum(h["optical_depth"][s]) - ref))
    return np.concatenate(errs)


# ------------------------------------------------------------------ grid helpers
def test_sigma_ref_twins_agree():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.9, 0.9, (200, 3))
    d = small_grid()
    np.testing.assert_allclose(R._sigma_vec(d, BBOX, pts), R.sigma_ref(d, BBOX, pts), rtol=0, atol=1e-12)


@pytest.mark.parametrize("block", [1, 2, 3, 8, 20])
def test_block_max_is_max_over_dilated_block(block):
    rng = np.random.default_rng(block)
    d = rng.random((13, 9, 17)).astype(np.float32)
    d[d < 0.93] = 0
    occ = block_max(d, block)
    nz, ny, nx = d.shape
    for bz in range(occ.shape[0]):
        for by in range(occ.shape[1]):
            for bx in range(occ.shape[2]):
                sl = tuple(slice(max(b * block - 1, 0), min((b + 1) * block + 1, n))
                           for b, n in ((bz, nz), (by, ny), (bx, nx)))
                assert occ[bz, by, bx] == d[sl].max()


def test_grid_sample_matches_reference():
    """Float32 trilinear gathers vs float64 NumPy: |error| <= 1e-5 (float32 rounding of
    positions and weights, densities <= 3); 0 outside the box, clamped inside."""
    rng = np.random.default_rng(3)
    d = small_grid()
    pts = np.concatenate([rng.uniform(-0.9, 0.9, (400, 3)),
                          rng.uniform(BBOX[0], BBOX[1], (400, 3)),       # inside, edges included
                          np.array([BBOX[0], BBOX[1], [0.7, 0.8, 0.0]])])
    g = GridVolume.prepare(d, BBOX)
    np.testing.assert_allclose(g.sample(pts), R.sigma_ref(d, BBOX, pts), rtol=0, atol=1e-5)
    # a cropped window (padded grid) samples the same field
    big = np.zeros((20, 24, 28), np.float32)
    big[5:15, 6:18, 7:21] = d
    h = (BBOX[1] - BBOX[0]) / np.array([14, 12, 10])
    bb2 = (BBOX[0] - np.array([7, 6, 5]) * h, BBOX[0] + np.array([21, 18, 15]) * h)
    g2 = GridVolume.prepare(big, bb2)
    assert np.prod(g2.window_shape) < big.size
    np.testing.assert_allclose(g2.sample(pts), R.sigma_ref(big, bb2, pts), rtol=0, atol=1e-5)


# ------------------------------------------------------------------ grid capture
@pytest.mark.parametrize("light", list(LIGHTS) + ["axis_aligned"])
def test_grid_capture_matches_reference_march(light):
    """Fine step (voxel / 32): cumulative optical depth at every segment end vs a float64
    midpoint march (4000 steps per unit).  Measured max error 1e-5 (Simpson's O(h^2) at the
    lattice planes where the trilinear field's derivative jumps); bound 5e-5 on tau <= ~5."""
    lt = LIGHTS.get(light, DirectionalLight((0.0, 0.0, 1.0)))     # axis-aligned: zero direction components
    cap = ad.capture(grid_scene(lt), resolution=64, step=0.1 / 32, epsilon=1e-12, order="depth")
    if light == "point":
        assert (cap.width, cap.height) == (64, 6 * 64)
    err = cumulative_errors(cap, small_grid())
    assert err.size > 500
    assert err.max() < 5e-5


def test_capture_error_shrinks_with_step():
    """RMS error of the cumulative optical depth vs the reference falls at least 2x per
    halving of the step (Simpson's rule with kinks: O(h^2), i.e. ~4x)."""
    rms = []
    for step in (0.1, 0.05, 0.025, 0.0125):
        cap = ad.capture(grid_scene(LIGHTS["directional"]), resolution=64, step=step, epsilon=1e-12, order="depth")
        rms.append(np.sqrt(np.mean(cumulative_errors(cap, small_grid()) ** 2)))
    ratios = np.array(rms[1:]) / np.array(rms[:-1])
    assert np.all(ratios < 0.5), (rms, ratios)


@pytest.mark.parametrize("step, tol_volume, tol_behind", [(None, 6e-2, 5e-3), (0.0625 / 16, 1e-3, 1e-4)])
def test_exact_from_capture_matches_fine_march_at_receivers(step, tol_volume, tol_behind):
    """ad.build('exact', cap.segments) at the plume's receivers vs a float64 march along the
    ray of each receiver's texel to its depth (plume size 16: voxel 1/16, densities up to ~60).
    Measured max |dT| in the smoke / on the wall behind it: 3.0e-2 / 2.0e-3 at the default step
    (half a voxel), 3.4e-4 / 2.0e-5 at voxel / 16.  Behind the smoke only Simpson's O(h^2) error
    remains; inside it the exact curve also interpolates tau linearly within a segment (O(h)
    in tau for steep density).  Bounds: about twice the measured errors."""
    sc = ad.scenes.plume(size=16, n_receivers=400)
    cap = ad.capture(sc, resolution=64, step=step, epsilon=1e-6, order="depth")
    texel, depth = cap.lookup(sc.receivers)
    T = np.asarray(ad.build("exact", cap.segments).eval(texel, depth))
    o, d = cap.camera.rays(texel)
    ref = np.array([np.exp(-R.optical_depth_ref(sc.density, sc.bbox, o[k], d[k], 0.0, [depth[k]])[0])
                    for k in range(texel.size)])
    assert ref.min() < 0.01 and ref[200:].min() < 0.2          # the comparison covers deep shadow
    err = np.abs(T - ref)
    assert err[:200].max() < tol_volume                         # receivers in the smoke
    assert err[200:].max() < tol_behind                         # receivers on the wall behind


def test_epsilon_stops_the_march():
    """After T < epsilon nothing is captured: T_capture >= T_true and |dT| <= epsilon."""
    eps = 0.05
    dens = small_grid() * 4
    sc = grid_scene(LIGHTS["directional"], dens)
    fine = ad.capture(sc, resolution=64, step=0.01, epsilon=1e-12, order="depth")
    cut = ad.capture(sc, resolution=64, step=0.01, epsilon=eps, order="depth")
    assert cut.segments.n_segments < fine.segments.n_segments
    texels = np.arange(fine.segments.n_texels)
    far = np.full(texels.size, 100.0)
    Tf = np.asarray(ad.build("exact", fine.segments).eval(texels, far))
    Tc = np.asarray(ad.build("exact", cut.segments).eval(texels, far))
    assert Tf.min() < eps / 10                   # some rays go far below epsilon
    assert np.all(Tc >= Tf - 1e-6) and np.all(Tc - Tf <= eps)


def test_empty_space_does_not_change_the_result():
    """The same grid zero-padded (same voxels, same world place) gives the same shadows;
    without empty-space skipping too (zero steps add no optical depth).  The grid's own
    boundary voxels are 0, so padding does not change the field (clamp-to-edge = 0)."""
    d = small_grid()
    d[[0, -1]] = 0
    d[:, [0, -1]] = 0
    d[:, :, [0, -1]] = 0
    off = np.array([3, 8, 5])                              # (x, y, z) voxels of padding in front
    big = np.zeros((23, 29, 30), np.float32)
    big[5:15, 8:20, 3:17] = d
    h = (BBOX[1] - BBOX[0]) / np.array([14, 12, 10])
    bb2 = (BBOX[0] - off * h, BBOX[0] + (np.array([30, 29, 23]) - off) * h)
    rec = np.random.default_rng(4).uniform(-0.7, 1.2, (300, 3))
    light = LIGHTS["spot"]
    results = []
    for dens, bb, skip in ((d, BBOX, True), (big, bb2, True), (d, BBOX, False)):
        sc = Scene("t", light, rec, density=dens, bbox=bb)
        cap = ad.capture(sc, resolution=64, step=0.1 / 8, density=GridVolume.prepare(dens, bb, skip_empty=skip),
                         order="depth")
        results.append(np.asarray(cap.transmittance(ad.build("exact", cap.segments), rec)))
    assert results[0].min() < 0.5
    for other in results[1:]:
        # steps restart at other block faces: O(h^2) differences, measured <= 1.5e-4 at h = voxel / 8
        np.testing.assert_allclose(other, results[0], rtol=0, atol=3e-4)


def test_vol_file_density_and_roundtrip(tmp_path):
    d = small_grid()
    path = tmp_path / "g.vol"
    write_vol(path, d, BBOX)
    back, bb = read_vol(path, with_bbox=True)
    assert back.dtype == np.float32 and np.array_equal(back, d)
    np.testing.assert_allclose(bb[0], BBOX[0], atol=1e-7)
    sc = Scene("t", LIGHTS["directional"], np.zeros((1, 3)), density=str(path), bbox=None)
    a = ad.capture(sc, resolution=64, order="depth")
    b = ad.capture(grid_scene(LIGHTS["directional"]), resolution=64, order="depth")
    assert a.segments.n_segments == b.segments.n_segments
    np.testing.assert_allclose(a.segments.numpy()["optical_depth"], b.segments.numpy()["optical_depth"], atol=1e-6)
    (tmp_path / "bad.vol").write_bytes(b"NOPE" + bytes(60))
    with pytest.raises(ValueError, match="path"):
        read_vol(tmp_path / "bad.vol")


@pytest.mark.mitsuba
def test_vol_format_matches_mitsuba(tmp_path):
    import mitsuba as mi
    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    d = small_grid()
    write_vol(tmp_path / "ours.vol", d)
    assert np.array_equal(np.array(mi.VolumeGrid(str(tmp_path / "ours.vol"))).reshape(d.shape), d)
    mi.VolumeGrid(d).write(str(tmp_path / "mi.vol"))
    assert np.array_equal(read_vol(tmp_path / "mi.vol"), d)


@pytest.mark.mitsuba
def test_trilinear_convention_matches_mitsuba_gridvolume():
    """Inside the box our sigma equals Mitsuba's ``gridvolume`` (trilinear, to_world = box)
    to float32 rounding (measured 2.4e-6, bound 1e-5).  Outside the box Mitsuba's volume
    clamps, but its heterogeneous medium clips rays to the box: 0 there in both."""
    import mitsuba as mi
    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    d = small_grid()
    lo, hi = BBOX
    to_world = mi.ScalarTransform4f().translate(mi.ScalarPoint3f(*lo)) @ \
        mi.ScalarTransform4f().scale(mi.ScalarPoint3f(*(hi - lo)))
    vol = mi.load_dict({"type": "gridvolume", "grid": mi.VolumeGrid(d), "filter_type": "trilinear",
                        "to_world": to_world})
    pts = np.random.default_rng(9).uniform(lo, hi, (300, 3))
    it = mi.Interaction3f()
    ref = []
    for p in pts:
        it.p = mi.Point3f(*(float(c) for c in p))
        ref.append(float(np.asarray(vol.eval_1(it)).ravel()[0]))
    np.testing.assert_allclose(GridVolume.prepare(d, BBOX).sample(pts), ref, rtol=0, atol=1e-5)


# ------------------------------------------------------------------ gradients
def _loss(density_tensor, scene, method=None):
    cap = ad.capture(scene, resolution=64, density=density_tensor, epsilon=1e-12, bounds=BBOX, method=method,
                     order="depth")
    T = cap.transmittance(ad.build("exact", cap.segments), scene.receivers)
    return dr.sum(T), cap


@pytest.mark.parametrize("method", ["march", "exact"])
def test_gradient_wrt_density_matches_finite_differences(method):
    """d(sum of T at receivers)/d(voxel) by reverse-mode AD through the Simpson march and
    the exact dual-grid capture vs central differences in float64 (h = 1e-5: truncation
    ~h^2, rounding ~1e-11/h); relative tolerance 1e-5."""
    from drjit.llvm.ad import TensorXf64
    rng = np.random.default_rng(5)
    d = small_grid(shape=(6, 7, 8)).astype(np.float64)
    d[:, :, :2] = 0
    d[:2] = 0
    sc = grid_scene(LIGHTS["directional"], d, rng.uniform(-0.3, 0.9, (200, 3)))
    x = TensorXf64(d)
    dr.enable_grad(x)
    loss, cap = _loss(x, sc, method)
    assert cap.segments.dtype == "float64"
    dr.backward(loss)
    g = dr.grad(x).numpy()
    for idx in [(3, 3, 4), (4, 5, 6), (5, 1, 7), (3, 4, 5)]:
        fd = []
        for sign in (1, -1):
            dp = d.copy()
            dp[idx] += sign * 1e-5
            fd.append(float(_loss(TensorXf64(dp), sc, method)[0][0]))
        fd = (fd[0] - fd[1]) / 2e-5
        assert abs(fd) > 1e-3                      # the voxel matters
        assert abs(g[idx] - fd) <= 1e-5 * abs(fd), (idx, g[idx], fd)


def test_float32_gradient_flows_to_optical_depth():
    """Float32 tensor: d(sum tau)/d(voxel) equals the Simpson weight sum of that voxel, which a
    uniform unit field checks: sum tau is linear in the density, so scaling by 2 doubles it."""
    from drjit.llvm.ad import TensorXf
    d = small_grid()
    x = TensorXf(d)
    dr.enable_grad(x)
    cap = ad.capture(grid_scene(LIGHTS["directional"]), resolution=64, density=x, epsilon=1e-12, bounds=BBOX,
                     order="depth")
    s = dr.sum(cap.segments.optical_depth)
    dr.backward(s)
    g = dr.grad(x).numpy()
    assert np.all(g >= 0) and g.max() > 0
    # <grad, d> = sum tau (Euler: sum tau is homogeneous of degree 1 in the density)
    np.testing.assert_allclose(float((g * d).sum()), float(s[0]), rtol=1e-4)
    # zero voxels: only reached when zero steps are kept (keep_zero disables the skipping)
    inner_zero = (5, 5, 1)              # in the empty slab x < 4, > 1 voxel from non-zero density
    assert d[inner_zero] == 0 and g[inner_zero] == 0
    x2 = TensorXf(d)
    dr.enable_grad(x2)
    cap2 = ad.capture(grid_scene(LIGHTS["directional"]), resolution=64, density=x2, epsilon=1e-12,
                      keep_zero=True, bounds=BBOX, order="depth")             # same map (not fitted to the content)
    assert cap2.segments.n_segments > cap.segments.n_segments
    dr.backward(dr.sum(cap2.segments.optical_depth))
    g2 = dr.grad(x2).numpy()
    assert g2[inner_zero] > 0
    # same field, steps placed from another entry point: Simpson's O(h^2) differences (measured 1.7e-4)
    np.testing.assert_allclose(float(dr.sum(cap2.segments.optical_depth)[0]), float(s[0]), rtol=1e-3)


# ------------------------------------------------------------------ particles
@pytest.mark.parametrize("light", ["directional", "spot", "point"])
def test_particle_chords_are_exact(light):
    """Every texel ray through a sphere gets the chord (z0, z1) = b -+ sqrt(r^2 - dist^2) and
    tau = density x length (float32 storage: |error| <= 2e-6 x depth)."""
    c = np.array([[0.0, 0.1, 0.0], [0.3, -0.1, 0.2]])
    r = np.array([0.25, 0.1])
    s = np.array([4.0, 9.0])
    sc = Scene("p", LIGHTS[light], np.zeros((1, 3)), particles=Particles(c, r, s))
    cap = ad.capture(sc, resolution=64, order="depth")
    h = cap.segments.numpy()
    o, d = cap.camera.rays()
    hits = 0
    for t in range(cap.segments.n_texels):
        ref = [(R.chord_ref(o[t], d[t], c[i], r[i]), s[i]) for i in range(2)]
        ref = [(max(ch[0], 0.0), ch[1], si) for ch, si in ref if ch is not None and ch[1] > 0]  # ahead of the light
        ref = sorted((a0, a1, si * (a1 - a0)) for a0, a1, si in ref)
        got = list(zip(*(h[k][h["offsets"][t]:h["offsets"][t + 1]] for k in ("z0", "z1", "optical_depth"))))
        assert len(got) == len(ref), t
        for (a0, a1, at), (b0, b1, bt) in zip(got, ref):
            assert abs(a0 - b0) < 2e-6 * max(1, b1) and abs(a1 - b1) < 2e-6 * max(1, b1)
            assert abs(at - bt) < 1e-5 * max(1, bt)
        hits += len(ref)
    assert hits > 100


def test_particle_density_gradient():
    """d(sum tau)/d(density_i) = total chord length through particle i."""
    from drjit.llvm.ad import Float
    c = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
    r = np.array([0.2, 0.1])
    dens = Float([2.0, 3.0])
    dr.enable_grad(dens)
    sc = Scene("p", DirectionalLight((0, 0, 1)), np.zeros((1, 3)), particles=Particles(c, r, dens))
    cap = ad.capture(sc, resolution=128, order="depth")
    dr.backward(dr.sum(cap.segments.optical_depth))
    h = cap.segments.numpy()
    length = h["z1"] - h["z0"]
    mid_x = cap.camera.rays(np.repeat(np.arange(cap.segments.n_texels), cap.segments.counts))[0] @ cap.camera.u
    cx = c @ cap.camera.u
    owner = np.abs(mid_x - cx[1]) < np.abs(mid_x - cx[0])
    np.testing.assert_allclose(dr.grad(dens).numpy(), [length[~owner].sum(), length[owner].sum()], rtol=1e-5)


# ------------------------------------------------------------------ opaque blockers
@pytest.mark.parametrize("blocker", [
    OpaqueSphere(np.array([0.0, 0.0, 0.0]), 0.3),
    OpaqueBox(np.array([-0.3, -0.2, -0.25]), np.array([0.3, 0.2, 0.25])),
    OpaquePlane(np.array([0.0, 0.0, 0.0]), np.array([0.2, 1.0, 0.1]), 0.3),
])
@pytest.mark.parametrize("light", ["directional", "spot"])
def test_opaque_blocker_zero_behind_one_in_front(blocker, light):
    lt = (DirectionalLight((0.3, -1.0, 0.2)) if light == "directional"
          else SpotLight((0.6, 2.0, 0.4), (-0.3, -1.0, -0.2), 40))
    sc = Scene("o", lt, np.zeros((1, 3)), blockers=[blocker])
    cap = ad.capture(sc, resolution=64, order="depth")
    assert cap.segments.n_segments > 50
    rep = ad.build("exact", cap.segments)
    o, d = cap.camera.rays()
    tex = np.flatnonzero(cap.segments.counts > 0)
    h = cap.segments.numpy()
    z0 = h["z0"][h["offsets"][tex]]
    # on the lit surface (depth of the hit), in front of it, and well behind it
    for depth, expect in ((z0 - 1e-4, 1.0), (z0 - 0.1, 1.0), (z0 + 0.01, 0.0)):
        T = np.asarray(cap.transmittance(rep, o[tex] + depth[:, None] * d[tex]))
        np.testing.assert_array_equal(T, expect)
    # texels that miss the blocker stay lit at any depth
    miss = np.flatnonzero(cap.segments.counts == 0)
    assert np.all(np.asarray(rep.eval(miss, np.full(miss.size, 50.0))) == 1.0)


def _lit_surface_points(blocker, light_pos_or_dir, directional, n, rng):
    """Random points on the blocker's surface facing the light (cos of incidence > 0.5)."""
    out = []
    while sum(len(o) for o in out) < n:
        if isinstance(blocker, OpaqueSphere):
            nrm = rng.standard_normal((4 * n, 3))
            nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
            p = blocker.center + blocker.radius * nrm
        elif isinstance(blocker, OpaqueBox):
            p = rng.uniform(blocker.min, blocker.max, (4 * n, 3))
            ax = rng.integers(0, 3, 4 * n)
            side = rng.integers(0, 2, 4 * n)
            p[np.arange(4 * n), ax] = np.where(side, blocker.max[ax], blocker.min[ax])
            nrm = np.zeros((4 * n, 3))
            nrm[np.arange(4 * n), ax] = np.where(side, 1.0, -1.0)
        else:
            from avsm_dr.geometry import orthonormal_basis
            u, v, w = orthonormal_basis(blocker.normal)
            a, b = rng.uniform(-blocker.extent, blocker.extent, (2, 4 * n))
            p = blocker.point + a[:, None] * u + b[:, None] * v
            nrm = np.broadcast_to(w, p.shape)
        to_light = -np.asarray(light_pos_or_dir) if directional else np.asarray(light_pos_or_dir) - p
        to_light = to_light / np.linalg.norm(to_light, axis=-1, keepdims=True)
        cos = np.sum(nrm * to_light, axis=1)
        if isinstance(blocker, OpaquePlane):
            cos = np.abs(cos)                               # two-sided
        out.append(p[cos > 0.5])
    return np.concatenate(out)[:n]


@pytest.mark.parametrize("blocker", [
    OpaqueSphere(np.array([0.0, 0.0, 0.0]), 0.3),
    OpaqueBox(np.array([-0.3, -0.2, -0.25]), np.array([0.3, 0.2, 0.25])),
    OpaquePlane(np.array([0.0, 0.0, 0.0]), np.array([0.2, 1.0, 0.1]), 0.3),
])
@pytest.mark.parametrize("light", ["directional", "spot", "point"])
@pytest.mark.parametrize("filter", ["point", "bilinear"])
def test_receivers_on_a_lit_surface_are_not_self_shadowed(blocker, light, filter):
    """Slope-scaled bias: points anywhere on the surface facing the light (incidence under
    60 degrees) read T = 1 (1 - 1e-6 with bilinear weights rounded in float32)."""
    lt = {"directional": DirectionalLight((0.3, -1.0, 0.2)),
          "spot": SpotLight((0.6, 2.0, 0.4), (-0.3, -1.0, -0.2), 40),
          "point": PointLight((0.6, 2.0, 0.4))}[light]
    sc = Scene("o", lt, np.zeros((1, 3)), blockers=[blocker])
    cap = ad.capture(sc, resolution=64, order="depth")
    rng = np.random.default_rng(8)
    directional = light == "directional"
    pts = _lit_surface_points(blocker, lt.direction if directional else lt.position, directional, 400, rng)
    T = np.asarray(cap.transmittance(ad.build("exact", cap.segments), pts, filter=filter))
    assert np.all(T >= 1 - 1e-6), np.count_nonzero(T < 1 - 1e-6)


# ------------------------------------------------------------------ hair
def test_hair_single_straight_strand():
    """A strand along x, light along -y: rays within the radius get one segment with
    T = 1 - opacity spanning the chord 2 sqrt(r^2 - b^2); tessellating the strand into
    many collinear pieces gives the same crossings (joints are merged, not double counted)."""
    r, op = 0.02, 0.4
    two = np.array([[[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]]])
    many = np.stack([np.linspace(-0.5, 0.5, 23), np.zeros(23), np.zeros(23)], 1)[None]
    light = DirectionalLight((0.0, -1.0, 0.0))
    caps = []
    for strands in (two, many):
        sc = Scene("h", light, np.zeros((1, 3)), hair=Hair(strands, r, op))
        caps.append(ad.capture(sc, resolution=128, bounds=(np.array([-0.6, -0.1, -0.6]), np.array([0.6, 0.1, 0.6])),
                               order="depth"))
    a, b = (c.segments.numpy() for c in caps)
    assert np.array_equal(a["offsets"], b["offsets"])
    np.testing.assert_allclose(a["z0"], b["z0"], atol=1e-6)
    np.testing.assert_allclose(np.exp(-a["optical_depth"]), 1 - op, rtol=1e-6)
    cam = caps[0].camera
    o, d = cam.rays()
    tex = np.repeat(np.arange(cam.n_texels), caps[0].segments.counts)
    assert caps[0].segments.max_count == 1
    dist = np.abs(o[tex, 2])                                     # distance of the ray from the axis
    x = o[tex, 0]
    inner = np.abs(x) < 0.5
    np.testing.assert_allclose((a["z1"] - a["z0"])[inner], 2 * np.sqrt(r * r - dist[inner] ** 2), atol=2e-6)
    # and every ray that passes within the radius (away from the end caps) has its segment
    all_o = o[np.abs(o[:, 0]) < 0.45]
    assert np.count_nonzero(np.abs(all_o[:, 2]) < r) == np.count_nonzero(inner & (np.abs(x) < 0.45))


def test_merge_crossings_unions_overlaps_per_strand():
    texel = np.array([0, 0, 0, 0, 1])
    strand = np.array([0, 0, 0, 1, 0])
    t_in = np.array([1.0, 1.5, 3.0, 1.2, 1.0])
    t_out = np.array([2.0, 2.5, 3.5, 1.4, 2.0])
    tx, st, a, b = merge_crossings(texel, strand, t_in, t_out)
    assert list(zip(tx, st, a, b)) == [(0, 0, 1.0, 2.5), (0, 0, 3.0, 3.5), (0, 1, 1.2, 1.4), (1, 0, 1.0, 2.0)]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 2), st.integers(0, 2), st.floats(0, 10), st.floats(0, 2)),
                min_size=1, max_size=40))
def test_merge_crossings_matches_bruteforce_union(items):
    """Property: merged intervals = union of each (texel, strand)'s intervals (touching ones joined)."""
    tex = np.array([i[0] for i in items])
    strand = np.array([i[1] for i in items])
    a = np.array([i[2] for i in items])
    b = a + np.array([i[3] for i in items])
    want = []
    for key in sorted(set(zip(tex.tolist(), strand.tolist()))):
        m = (tex == key[0]) & (strand == key[1])
        cur = None
        for lo, hi in sorted(zip(a[m], b[m])):
            if cur is not None and lo <= cur[1]:
                cur[1] = max(cur[1], hi)
            else:
                if cur is not None:
                    want.append((*key, *cur))
                cur = [lo, hi]
        want.append((*key, *cur))
    got = list(zip(*(x.tolist() for x in merge_crossings(tex, strand, a, b))))
    assert got == want


def test_procedural_strands_deterministic():
    a = procedural_strands(50, 8, seed=3)
    assert a.shape == (50, 8, 3) and a.dtype == np.float32
    assert np.array_equal(a, procedural_strands(50, 8, seed=3))
    assert not np.array_equal(a, procedural_strands(50, 8, seed=4))
    seg = np.linalg.norm(np.diff(a, axis=1), axis=2)
    np.testing.assert_allclose(seg, 0.6 / 7, rtol=1e-5)


def test_tressfx_loader(shared_dir):
    path = shared_dir / "data" / "hair" / "Ratboy_mohawk.tfx"
    if not path.exists():
        pytest.skip("Ratboy_mohawk.tfx not present")
    s, w = load_tfx(path, return_w=True)
    assert s.shape == (2228, 32, 3)
    lo, hi = s.reshape(-1, 3).min(0), s.reshape(-1, 3).max(0)
    np.testing.assert_allclose(lo, [-0.095, 0.214, -0.336], atol=1e-3)
    np.testing.assert_allclose(hi, [0.117, 1.110, 0.271], atol=1e-3)
    assert np.all(w[:, 0] == 0) and np.all(w[:, -1] == 1)


def test_tressfx_bad_file(tmp_path):
    (tmp_path / "x.tfx").write_bytes(b"\x00" * 8)
    with pytest.raises(ValueError, match="path"):
        load_tfx(tmp_path / "x.tfx")


# ------------------------------------------------------------------ combining, lookups
def test_combined_content_is_product_of_parts():
    """Grid + hair + particles + blocker in one capture: per-texel segments sorted by depth,
    and T = product of the parts' T (optical depths add)."""
    rng = np.random.default_rng(6)
    hair = Hair(procedural_strands(40, 8, root_center=(0, -0.3, 0), length=0.6, seed=1), 0.01, 0.3)
    parts = Particles(rng.uniform(-0.3, 0.3, (20, 3)), rng.uniform(0.02, 0.08, 20), rng.uniform(1, 5, 20))
    box = OpaqueBox(np.array([-0.2, -0.3, 0.35]), np.array([0.2, 0.0, 0.45]))
    rec = rng.uniform(-0.6, 0.8, (500, 3))
    light = LIGHTS["spot"]
    full = Scene("all", light, rec, density=small_grid(), bbox=BBOX, hair=hair, particles=parts, blockers=[box])
    cap = ad.capture(full, resolution=64, order="depth")
    h = cap.segments.numpy()
    tex = np.repeat(np.arange(cap.segments.n_texels), cap.segments.counts)
    same = tex[1:] == tex[:-1]
    assert np.all(np.diff(h["z0"])[same] >= 0)
    T = np.asarray(cap.transmittance(ad.build("exact", cap.segments), rec))
    prod = np.ones(rec.shape[0])
    for kw in ({"density": small_grid(), "bbox": BBOX}, {"hair": hair}, {"particles": parts}, {"blockers": [box]}):
        c = ad.capture(Scene("p", light, rec, **kw), resolution=64, order="depth")
        prod *= np.asarray(c.transmittance(ad.build("exact", c.segments), rec))
    assert T.min() == 0.0 and T.max() == 1.0 and np.any((T > 0.05) & (T < 0.95))
    np.testing.assert_allclose(T, prod, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("light", list(LIGHTS))
def test_lookup_returns_the_texel_and_depth_of_its_ray(light):
    cap = ad.capture(grid_scene(LIGHTS[light]), resolution=64, order="depth")
    rng = np.random.default_rng(7)
    tex = rng.integers(0, cap.segments.n_texels, 500)
    if light == "point":                        # include texels on every cube-face edge
        r = 64
        edge = np.array([f * r * r + y * r + x for f in range(6) for (x, y) in ((0, 0), (r - 1, 5), (7, r - 1))])
        tex = np.concatenate([tex, edge])
    o, d = cap.camera.rays(tex)
    t = rng.uniform(0.5, 3.0, tex.size)
    p = o + t[:, None] * d
    texel, depth = cap.lookup(p)
    np.testing.assert_array_equal(texel, tex)
    np.testing.assert_allclose(depth, t, rtol=1e-12, atol=1e-12)
    coords, depth2 = cap.lookup(p, continuous=True)
    np.testing.assert_allclose(coords[:, 0], tex % cap.width + 0.5, atol=1e-9)
    np.testing.assert_allclose(coords[:, 1], tex // cap.width + 0.5, atol=1e-9)
    # bilinear at a texel centre reads only that texel
    rep = ad.build("exact", cap.segments)
    a = np.asarray(cap.transmittance(rep, p, filter="bilinear"))
    b = np.asarray(rep.eval(tex, t))
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_directional_map_has_empty_margin():
    """The fitted orthographic map keeps its edge texels empty, so lookups clamped from
    outside the map read T = 1."""
    cap = ad.capture(grid_scene(LIGHTS["directional"]), resolution=64, order="depth")
    c = cap.segments.counts.reshape(64, 64)
    assert c[0].sum() == c[-1].sum() == c[:, 0].sum() == c[:, -1].sum() == 0
    rows, cols = np.flatnonzero(c.any(axis=1)), np.flatnonzero(c.any(axis=0))
    assert max(np.ptp(rows), np.ptp(cols)) >= 0.8 * 64                # and the fit is tight


def test_capture_is_deterministic():
    sc = grid_scene(LIGHTS["point"])
    a, b = (ad.capture(sc, resolution=64, order="depth").segments.numpy(),
            ad.capture(sc, resolution=64, order="depth").segments.numpy())
    for k in a:
        assert np.array_equal(a[k], b[k])


# ------------------------------------------------------------------ bad input
def _scene(**kw):
    base = dict(name="b", light=LIGHTS["directional"], receivers=np.zeros((2, 3)), density=small_grid(), bbox=BBOX)
    base.update(kw)
    return Scene(**base)


@pytest.mark.parametrize("kwargs, capture_kw, name", [
    ({"density": np.full((4, 4, 4), np.nan, np.float32)}, {}, "density"),
    ({"density": -small_grid()}, {}, "density"),
    ({"density": np.zeros((4, 4), np.float32)}, {}, "density"),
    ({"bbox": (np.zeros(3), np.array([1.0, 0.0, 1.0]))}, {}, "bbox"),
    ({"bbox": None}, {}, "bbox"),
    ({"light": SpotLight((0.0, 0.1, 0.0), (1, 0, 0), 40)}, {}, "light"),
    ({"light": PointLight((0.0, 0.1, 0.0))}, {}, "light"),
    ({"receivers": np.zeros((3, 2))}, {}, "receivers"),
    ({"density": None, "bbox": None}, {}, "scene"),
    ({}, {"resolution": 32}, "resolution"),
    ({}, {"resolution": 2048}, "resolution"),
    ({}, {"resolution": 100.5}, "resolution"),
    ({}, {"step": 0.0}, "step"),
    ({}, {"step": float("nan")}, "step"),
    ({}, {"epsilon": 1.0}, "epsilon"),
    ({}, {"method": "simpson"}, "method"),
    ({}, {"method": "exact", "step": 0.01}, "step"),
    ({"density": None, "particles": Particles(np.zeros((2, 3)), np.ones(3), np.ones(2))}, {}, "particles.radii"),
    ({"density": None, "particles": Particles(np.zeros((2, 3)), np.ones(2), -np.ones(2))}, {}, "particles.density"),
    ({"density": None, "hair": Hair(np.zeros((3, 1, 3)), 0.1)}, {}, "hair.strands"),
    ({"density": None, "hair": Hair(np.zeros((3, 2, 3)), 0.1, opacity=1.5)}, {}, "hair.opacity"),
    ({"blockers": [OpaqueBox(np.zeros(3), np.zeros(3))]}, {}, "blockers[0].max"),
    ({"blockers": [OpaqueSphere(np.zeros(3), -1.0)]}, {}, "blockers[0].radius"),
    ({"blockers": ["wall"]}, {}, "blockers[0]"),
])
def test_bad_input_raises_value_error_naming_the_argument(kwargs, capture_kw, name):
    with pytest.raises(ValueError, match=r"^" + name.replace("[", r"\[").replace("]", r"\]")):
        ad.capture(_scene(**kwargs), **capture_kw)


def test_bad_lookup_points():
    cap = ad.capture(_scene(), resolution=64, order="depth")
    with pytest.raises(ValueError, match="^points"):
        cap.lookup(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="^points"):
        cap.lookup(np.array([[0.0, np.nan, 0.0]]))
