"""Hostile input to scenes, capture, ground truth, shading and I/O.

Crash and memory cases run in a subprocess, so a regression fails one test instead of
killing the run.
"""
import struct
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import avsm_dr as ad
from avsm_dr import groundtruth as gt
from avsm_dr import io, shading
from avsm_dr.groundtruth import tracking
from avsm_dr.scene import DirectionalLight, Hair, Particles, PointLight, Scene, SpotLight

UNIT = (np.zeros(3), np.ones(3))


def run_python(code: str, timeout: float = 180) -> str:
    """Run ``code`` in a fresh interpreter; return its stdout (fails on a non-zero exit)."""
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                         text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


def slab_scene(light, sigma=0.5):
    """Homogeneous slab x in [-2, 2] (y, z in [-5, 5]) of extinction ``sigma``."""
    return Scene("slab", light, np.zeros((1, 3)), density=np.full((20, 20, 8), sigma, np.float32),
                 bbox=(np.array([-2.0, -5.0, -5.0]), np.array([2.0, 5.0, 5.0])))


# ====================================================== outside the light's map
def test_points_behind_or_beside_a_spot_light_are_lit():
    # Light at (-3, 0, 0) looking along +x; the slab fills its whole frustum.  A receiver
    # behind the light and one outside the cone are not shadowed (their paths miss the
    # slab; ground truth 1); before the fix they read a clamped edge texel's shadow.
    scene = slab_scene(SpotLight((-3.0, 0.0, 0.0), (1.0, 0.0, 0.0), fov=60.0))
    cap = ad.capture(scene, resolution=64, order="depth")
    pts = np.array([[-6.0, 0.0, 0.0], [-2.5, 3.0, 0.0], [-6.0, 2.0, 1.0], [1.0, 0.0, 0.0]])
    truth = gt.transmittance(scene, pts, method="raymarch")[0]
    np.testing.assert_array_equal(truth[:3], 1.0)
    np.testing.assert_array_equal(cap.covers(pts), [False, False, False, True])
    texel, depth = cap.lookup(pts)
    exact = ad.build("exact", cap.segments)
    # what the old lookup read: the corner texel at the receiver's real distance (3)
    assert float(np.asarray(exact.eval(np.array([0]), np.array([3.0])))[0]) < 0.5
    for kind in ad.kinds():
        rep = ad.build(kind, cap.segments)
        for T in (rep.eval(texel, depth), cap.transmittance(rep, pts),
                  cap.transmittance(rep, pts, filter="bilinear")):
            np.testing.assert_array_equal(np.asarray(T)[:3], 1.0, err_msg=kind)
    # the covered receiver behind 3 units of slab: exp(-1.5), float32 depths (1e-5)
    np.testing.assert_allclose(np.asarray(cap.transmittance(exact, pts))[3], truth[3], atol=1e-5)


def test_directional_map_outside_its_window():
    # Default fit: points beside the content are off the map and lit (ground truth 1).
    scene = slab_scene(DirectionalLight((1.0, 0.0, 0.0)))
    pts = np.array([[3.0, 9.0, 0.0], [3.0, 0.0, -20.0], [3.0, 0.0, 0.0]])
    cap = ad.capture(scene, resolution=64, order="depth")
    np.testing.assert_array_equal(cap.covers(pts), [False, False, True])
    T = np.asarray(cap.transmittance(ad.build("exact", cap.segments), pts))
    truth = gt.transmittance(scene, pts, method="raymarch")[0]
    np.testing.assert_allclose(T, truth, atol=1e-5)     # float32 depths
    # A map fitted to user bounds smaller than the content does not see the rest: points
    # outside its window are lit by the border convention (documented), not clamped.
    cap = ad.capture(scene, resolution=64, bounds=([-2, -1, -1], [2, 1, 1]), order="depth")
    assert not cap.covers(pts[:1])[0]
    assert float(np.asarray(cap.transmittance(ad.build("exact", cap.segments), pts[:1]))[0]) == 1.0


def test_cube_map_covers_every_direction():
    scene = slab_scene(PointLight((-3.0, 0.0, 0.0)))
    cap = ad.capture(scene, resolution=64, order="depth")
    rng = np.random.default_rng(5)
    u = rng.normal(size=(400, 3))
    pts = np.array([-3.0, 0.0, 0.0]) + 0.8 * u / np.linalg.norm(u, axis=1, keepdims=True)
    pts = np.concatenate([pts, [[-3.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])   # at the light; through the slab
    assert cap.covers(pts).all()
    T = np.asarray(cap.transmittance(ad.build("exact", cap.segments), pts))
    np.testing.assert_array_equal(T[:-1], 1.0)          # within 0.8 of the light: in front of the slab
    truth = gt.transmittance(scene, pts[-1:], method="raymarch")[0]
    # the texel's ray is up to half a texel (0.011 rad on a 90-degree face of 64) off the
    # receiver's: its depth-4 point lies 4 (1 - cos) ~ 2.4e-4 short, T higher by ~3e-5
    np.testing.assert_allclose(T[-1], truth, atol=1e-4)


# ================================================= ray march memory and time
def test_raymarch_refuses_a_step_that_cannot_fit():
    out = run_python("""
        import avsm_dr, numpy as np
        from avsm_dr import groundtruth as gt
        from avsm_dr.scene import Scene, DirectionalLight
        sc = Scene("box", DirectionalLight((0.2, -0.1, 1.0)), np.zeros((1, 3)),
                   density=np.full((4, 4, 4), 2.0, np.float32), bbox=(np.zeros(3), np.ones(3)))
        try:
            gt.transmittance(sc, np.array([[0.5, 0.5, 0.9]]), method="raymarch", step=1e-9)
        except ValueError as e:
            print(e)
    """)
    assert out.startswith("step: 1e-09 needs") and "use step >=" in out, out


def test_ray_march_chunks_within_rays(monkeypatch):
    # Chunks of 7 samples split every ray: tau and the integral (here the view-attenuated
    # scattering sum_j h sigma exp(-tau_j) of a homogeneous box, whose midpoint sum is
    # 1 - exp(-sigma L) to O(h^2)) equal the unchunked march to float64 rounding.
    g = np.full((4, 4, 4), 2.0)
    o = np.array([[0.5, 0.5, -1.0], [0.2, 0.3, -0.5], [0.5, 0.5, 2.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.1, 0.05, 1.0], [0.0, 0.0, -1.0]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    L = np.array([3.0, 1.0, 1.5])

    def integrand(x, sig, h, tau):
        return h * sig * np.exp(-tau)

    ref_tau, ref_acc = tracking.march(g, *UNIT, o, d, L, 0.01, integrand)
    monkeypatch.setattr(tracking, "MAX_CHUNK", 7)
    tau, acc = tracking.march(g, *UNIT, o, d, L, 0.01, integrand)
    np.testing.assert_allclose(tau, ref_tau, rtol=1e-13)
    np.testing.assert_allclose(acc, ref_acc, rtol=1e-13)
    np.testing.assert_allclose(tau[0], 2.0, rtol=1e-13)               # chord 1 through the box
    np.testing.assert_allclose(acc, 1 - np.exp(-tau), rtol=1e-4)      # midpoint rule, h = 0.01


def test_shading_single_scattering_uses_the_ground_truth_march(monkeypatch):
    # shading._single_scattering is the ground truth's march with an integrand: a chunk
    # size that splits rays leaves it unchanged.
    scene = Scene("box", DirectionalLight((0.0, -1.0, 0.0)), np.zeros((1, 3)),
                  density=np.full((4, 4, 4), 2.0, np.float32), bbox=UNIT)
    content = gt.content.check_scene(scene)
    o = np.array([[0.5, 0.5, -1.0], [0.2, 0.7, -1.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    t_end = np.array([3.0, 1.5])

    def light_T(x):
        return np.exp(-2.0 * (1.0 - x[:, 1]))

    ref = shading._single_scattering(scene, content, o, d, t_end, light_T, 0.8, 0.05)
    monkeypatch.setattr(tracking, "MAX_CHUNK", 5)
    np.testing.assert_allclose(shading._single_scattering(scene, content, o, d, t_end, light_T, 0.8, 0.05),
                               ref, rtol=1e-13)
    assert np.all(ref > 0)


# =============================================================== unclear messages
def test_zero_particles_and_zero_strands_are_named():
    empty = Particles(np.zeros((0, 3)), np.zeros(0), np.zeros(0))
    scene = Scene("p", DirectionalLight((0, -1, 0)), np.zeros((1, 3)), particles=empty)
    with pytest.raises(ValueError, match="^particles.centers: no particles"):
        ad.capture(scene, 64)
    with pytest.raises(ValueError, match="^particles.centers: no particles"):
        gt.transmittance(scene, np.zeros((1, 3)))
    scene = Scene("h", DirectionalLight((0, -1, 0)), np.zeros((1, 3)), hair=Hair(np.zeros((0, 4, 3)), 0.01))
    for fn in (lambda: ad.capture(scene, 64), lambda: gt.transmittance(scene, np.zeros((1, 3)))):
        with pytest.raises(ValueError, match=r"^hair.strands: expected shape \(S, V, 3\)"):
            fn()


@pytest.mark.parametrize("make", [
    lambda d: DirectionalLight(d),
    lambda d: SpotLight((-3.0, 0.5, 0.5), d, 60.0),
])
def test_light_direction_whose_norm_overflows_just_works(make):
    # (1e300, 0, 0) has an infinite float64 norm; it is the direction +x all the same.
    a, b = make((1e300, 1e-300, 0.0)), make((1.0, 0.0, 0.0))
    np.testing.assert_array_equal(a.direction, b.direction)
    scene = Scene("box", a, np.zeros((1, 3)), density=np.full((4, 4, 4), 2.0, np.float32), bbox=UNIT)
    cap = ad.capture(scene, 64, order="depth")
    pts = np.array([[1.5, 0.5, 0.5], [0.5, 0.4, 0.6]])
    T = np.asarray(cap.transmittance(ad.build("exact", cap.segments), pts))
    assert np.all(np.isfinite(T)) and T[0] < 0.2
    with pytest.raises(ValueError, match="^direction: must be non-zero"):
        make((0.0, 0.0, 0.0))


def test_truncated_vol_files_are_named(tmp_path):
    path = tmp_path / "grid.vol"
    io.write_vol(path, np.ones((3, 4, 5), np.float32))
    raw = path.read_bytes()
    path.write_bytes(raw[:30])
    with pytest.raises(ValueError, match=r"^path: .*grid.vol.* truncated .vol header \(30 of 48 bytes\)"):
        io.read_vol(path)
    # a header announcing 2^48 values (1 PiB) over a 3-value file: refused before allocating
    huge = raw[:4] + struct.pack("<5i", 1, 1 << 16, 1 << 16, 1 << 16, 1) + raw[24:60]
    path.write_bytes(huge)
    out = run_python(f"""
        import avsm_dr
        from avsm_dr.io import read_vol
        try:
            read_vol({str(path)!r})
        except ValueError as e:
            print(e)
    """)
    assert out.startswith("path: ") and "truncated (3 of the 281474976710656 values" in out, out


BOX = Scene("box", DirectionalLight((0.0, 0.0, 1.0)), np.zeros((1, 3)),
            density=np.full((4, 4, 4), 2.0, np.float32), bbox=UNIT)


@pytest.mark.parametrize("bad", [np.array([2.0]), True, "2", float("nan")])
@pytest.mark.parametrize("name,call", [
    ("fov", lambda v: SpotLight((0, 0, 0), (1, 0, 0), fov=v)),
    ("intensity", lambda v: PointLight((0, 0, 0), intensity=v)),
    ("irradiance", lambda v: DirectionalLight((0, 0, 1), irradiance=v)),
    ("step", lambda v: gt.transmittance(BOX, [[0.5, 0.5, 2.0]], method="raymarch", step=v)),
    ("majorant_factor", lambda v: gt.transmittance(BOX, [[0.5, 0.5, 2.0]], majorant_factor=v)),
    ("step", lambda v: ad.capture(BOX, 64, step=v)),
    ("epsilon", lambda v: ad.capture(BOX, 64, epsilon=v)),
    ("opaque_slope_bias", lambda v: ad.capture(BOX, 64, opaque_slope_bias=v)),
    ("albedo", lambda v: shading.shade_receivers(BOX, [1.0], albedo=v)),
    ("density_scale", lambda v: ad.scenes.plume(size=4, density_scale=v, n_receivers=4)),
    ("hair_radius", lambda v: ad.scenes.hair_and_smoke(size=4, n_strands=2, hair_radius=v)),
    ("hair.opacity", lambda v: ad.capture(Scene("h", DirectionalLight((0, -1, 0)), np.zeros((1, 3)),
                                                hair=Hair(np.zeros((1, 2, 3)), 0.01, opacity=v)), 64)),
])
def test_scalars_follow_one_rule(name, call, bad):
    # real numbers only: no arrays, bool, str or NaN (the validation's "one rule")
    with pytest.raises(ValueError, match=f"^{name}: expected a finite real number"):
        call(bad)


@pytest.mark.parametrize("bad", [True, 2.0, "2"])
@pytest.mark.parametrize("name,call", [
    ("n_receivers", lambda v: ad.scenes.plume(size=4, n_receivers=v)),
    ("n", lambda v: ad.scenes.particles(n=v)),
    ("seed", lambda v: ad.scenes.three_columns(size=4, seed=v)),
    ("spp", lambda v: gt.transmittance(BOX, [[0.5, 0.5, 2.0]], spp=v)),
    ("seed", lambda v: gt.transmittance(BOX, [[0.5, 0.5, 2.0]], seed=v)),
    ("resolution", lambda v: ad.capture(BOX, v)),
])
def test_counts_follow_one_rule(name, call, bad):
    with pytest.raises(ValueError, match=f"^{name}: expected an integer"):
        call(bad)


# ============================================================ more of the same classes
def test_huge_sizes_are_refused_before_allocating():
    cases = [
        (lambda: ad.scenes.plume(size=100_000), "^size: expected an integer in \\[4, 256\\]"),
        (lambda: ad.scenes.particles(n=2 ** 40), "^n: expected an integer in"),
        (lambda: gt.transmittance(BOX, [[0.5, 0.5, 2.0]], spp=2 ** 30), "^spp: expected an integer in"),
        (lambda: gt.render_reference(BOX, 100_000, 8), "^width: expected an integer in"),
        (lambda: ad.capture(BOX, 64, step=1e-9), "^step: 1e-09 is below 1/1024 of the smallest voxel"),
    ]
    for call, match in cases:
        with pytest.raises(ValueError, match=match):
            call()


def test_particle_footprints_too_large_to_enumerate():
    # 10^5 particles of radius 100 at 1024^2 texels: 1e11 (particle, texel) pairs.
    out = run_python("""
        import avsm_dr as ad, numpy as np
        from avsm_dr.scene import Scene, DirectionalLight, Particles
        n = 100_000
        sc = Scene("p", DirectionalLight((0, -1, 0)), np.zeros((1, 3)),
                   particles=Particles(np.random.default_rng(0).random((n, 3)), np.full(n, 100.0), np.ones(n)))
        try:
            ad.capture(sc, 1024)
        except ValueError as e:
            print(e)
    """)
    assert out.startswith("particles: the footprints cover 1.04e+11"), out


def test_coordinates_beyond_the_storage_dtype():
    # depths of content at 1e38 overflow float32 storage: refused, and float64 works
    sc = Scene("p", DirectionalLight((0, -1, 0)), np.zeros((1, 3)),
               particles=Particles(np.array([[1e38, 0.0, 0.0]]), [1.0], [1.0]))
    with pytest.raises(ValueError, match="^scene: content or light coordinates reach 1e\\+38.*float64"):
        ad.capture(sc, 64)
    cap = ad.capture(sc, 64, dtype="float64", order="depth")
    p = np.array([[1e38, -5.0, 0.0]])
    T = np.asarray(cap.transmittance(ad.build("exact", cap.segments), p))
    o, d = cap.camera.rays(cap.lookup(p)[0])       # the texel's ray passes b off the centre
    b = np.linalg.norm(np.cross(np.array([1e38, 0.0, 0.0]) - o[0], d[0]))
    np.testing.assert_allclose(T, np.exp(-2.0 * np.sqrt(1 - b * b)), rtol=1e-9)
    with pytest.raises(ValueError, match="^position: expected 3 finite numbers"):
        PointLight((np.inf, 0, 0))


def test_bad_planes_cameras_and_images():
    no_plane = Scene("b", DirectionalLight((0, 0, 1)), np.zeros((1, 3)), density=np.ones((2, 2, 2)), bbox=UNIT,
                     receiver_plane=(np.zeros(3), np.zeros(3), 1.0))
    with pytest.raises(ValueError, match="^scene.receiver_plane.normal: must be non-zero"):
        gt.default_camera(no_plane)
    plane = Scene("b", DirectionalLight((0, 0, 1)), np.zeros((1, 3)), density=np.ones((2, 2, 2)), bbox=UNIT,
                  receiver_plane=(np.array([0.5, 0.5, 2.0]), np.array([0, 0, 1.0]), 1.0))
    with pytest.raises(ValueError, match="^direction: must be non-zero"):
        gt.default_camera(plane, direction=(0, 0, 0))
    with pytest.raises(ValueError, match="^camera.fov"):
        gt.check_camera(plane, {"origin": [0, 0, 5], "target": [0, 0, 0], "up": [0, 1, 0], "fov": "40"})
    with pytest.raises(ValueError, match="^camera: expected a dict"):
        gt.check_camera(plane, [0, 0, 5])
    with pytest.raises(ValueError, match="^supersample: expected an integer"):
        shading.render_plane(plane, lambda p: np.ones(len(p)), 8, 8, supersample=2.5)
    with pytest.raises(ValueError, match="^normals: zero-length normal"):
        shading.shade_receivers(plane, [1.0], points=[[0.5, 0.5, 2.0]], normals=[0, 0, 0])


def test_write_vol_bad_bbox(tmp_path):
    with pytest.raises(ValueError, match=r"^bbox: expected \(min_xyz, max_xyz\)"):
        io.write_vol(tmp_path / "a.vol", np.ones((2, 2, 2)), bbox=([0, 0], [1, 1, 1]))
    with pytest.raises(ValueError, match="^bbox: beyond the float32 range"):
        io.write_vol(tmp_path / "a.vol", np.ones((2, 2, 2)), bbox=([0, 0, 0], [1e39, 1, 1]))
