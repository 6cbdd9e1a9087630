"""The Mitsuba integrator ``avsm_single_scatter`` (avsm_dr.mitsuba).

Monte Carlo comparison with ``volpath`` (max_depth = 2), same scene and light: each
integrator renders it R = 8 times (32 spp, independent seeds); per 6 x 6 pixel block
(16 blocks of a 24 x 24 image) the difference of the two mean block values is divided
by its standard error, estimated from the runs' spread (Welch, ~14 degrees of freedom;
floors for noise-free blocks in :func:`block_z`).  Every block must have |z| <= 5 (a t
statistic with 14 dof exceeds 5 with probability ~2e-4; 16 blocks: ~0.3 %), the whole
image |z| <= 4, and the image mean's relative standard error must be below 0.5 % so
that a 2 % bias could not hide (measured: AVSM with 2 nodes, 1.5-1.7 % brighter, gives
|z| ~ 20).  Our estimator's view transmittance is a 32-piece midpoint rule (O(h^2) bias,
below the MC error here: 8 pieces still pass) and the shadow map is 256^2 for a 16^3 grid.
"""
import inspect
import json
import re
import subprocess
import sys

import numpy as np
import pytest

import avsm_dr as ad  # noqa: F401  (sets up libLLVM before drjit)
import drjit as dr
from avsm_dr import groundtruth as gt
from avsm_dr.scene import DirectionalLight, PointLight, SpotLight

pytestmark = pytest.mark.mitsuba

am = pytest.importorskip("avsm_dr.mitsuba")
KEY = "vol.interior_medium.sigma_t.data"


@pytest.fixture(scope="module")
def mi():
    """Mitsuba with the package's variant (llvm_ad_rgb here); the plugin re-registers on change."""
    return gt.mitsuba()


def blob(n=16, peak=12.0):
    """Two Gaussian puffs over [-1, 1]^3, one behind the other along the test light (the light's
    transmittance drops twice: a curve that a 2-node AVSM cannot follow), (n, n, n) float32."""
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n)] * 3, indexing="ij")
    g = 0.0
    for c in ((-0.2, 0.45, 0.13), (0.2, -0.45, -0.13)):
        g = g + peak * np.exp(-10 * ((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2))
    return g.astype(np.float32)


def scene_dict(mi, integrator, size=24, albedo=0.8, plane=True, light=None):
    """Smoke blob in a null-BSDF cube above a diffuse ground plane, lit by a directional light."""
    lo, hi = np.array([-1.0, -1.0, -1.0]), np.array([1.0, 1.0, 1.0])
    d = {"type": "scene", "integrator": integrator,
         "sensor": {"type": "perspective", "fov": 45,
                    "to_world": mi.ScalarTransform4f().look_at(origin=[0.5, 1.0, 4.5], target=[0, -0.3, 0],
                                                               up=[0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}}},
         "light": light or {"type": "directional", "direction": [0.4, -1.0, -0.3], "irradiance": 3.0},
         "vol": {"type": "cube", "bsdf": {"type": "null"},
                 "interior": gt.media.medium_dict(mi, blob(), lo, hi, albedo)}}
    if plane:
        d["plane"] = {"type": "rectangle", "bsdf": {"type": "diffuse"},
                      "to_world": mi.ScalarTransform4f().translate([0, -1.3, 0]).rotate([1, 0, 0], -90)
                      .scale([3, 3, 1])}
    return d


def ours(**props):
    """The integrator's dict; 32 march pieces unless given (8 still match volpath here)."""
    return {"type": "avsm_single_scatter", "march_steps": 32, **props}


def renders(mi, scene, runs, spp, seed0=0):
    """(runs, H, W) red channels of independent renders."""
    return np.stack([np.asarray(mi.render(scene, spp=spp, seed=seed0 + r), np.float64)[..., 0]
                     for r in range(runs)])


def block_z(a, b, block=6, floor=1e-4, floor_abs=1e-3):
    """Welch z of the per-block mean difference of run stacks a, b (R, H, W); and of the image.

    Added to the standard error in quadrature: ``floor`` times the block value (blocks without
    noise, the ground plane outside any shadow, differ only by float32 rounding, measured
    ~1e-7 relative) and ``floor_abs`` times the brightest block (blocks at the smoke's faint
    edge, where volpath's free-flight sampling almost never scatters: its R runs there can
    all be exactly 0, a sample variance of 0 that understates its error)."""
    def blocks(x):
        R, H, W = x.shape
        return x.reshape(R, H // block, block, W // block, block).mean(axis=(2, 4)).reshape(R, -1)
    za = []
    for fa, fb in ((blocks(a), blocks(b)), (a.mean(axis=(1, 2))[:, None], b.mean(axis=(1, 2))[:, None])):
        se = np.sqrt(fa.var(axis=0, ddof=1) / len(fa) + fb.var(axis=0, ddof=1) / len(fb)
                     + (floor * np.abs(fb.mean(axis=0))) ** 2 + (floor_abs * np.abs(fb.mean(axis=0)).max()) ** 2)
        diff = fa.mean(axis=0) - fb.mean(axis=0)
        za.append(np.where(se > 0, diff / np.where(se > 0, se, 1.0), np.where(diff == 0, 0.0, np.inf)))
    return za[0], float(za[1][0]), blocks(b).mean(axis=0)


# ------------------------------------------------------------------------------ tests
def test_import_resolves_real_mitsuba_and_package_stays_lazy():
    assert am.mi.__name__ == "mitsuba" and hasattr(am.mi, "load_dict")
    code = "import sys, avsm_dr; import avsm_dr.groundtruth, avsm_dr.shading; print('mitsuba' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_exact_matches_volpath(mi):
    runs, spp = 8, 32
    a = renders(mi, mi.load_dict(scene_dict(mi, ours(resolution=256))), runs, spp)
    b = renders(mi, mi.load_dict(scene_dict(mi, {"type": "volpath", "max_depth": 2})), runs, spp, seed0=100)
    z_blocks, z_image, ref = block_z(a, b)
    lit = ref > 1e-3 * ref.max()
    assert lit.sum() >= 8                        # the blocks test something
    assert np.all(np.abs(z_blocks) <= 5.0), np.round(z_blocks, 2)
    assert abs(z_image) <= 4.0
    # power: the run-to-run noise is small enough that a 2 % bias would show (>= 4 SE)
    rel_se = b.mean(axis=(1, 2)).std(ddof=1) / np.sqrt(runs) / b.mean()
    assert rel_se < 0.005


def test_nonexact_kind_differs_but_is_close(mi):
    # same seed -> the same camera samples: the difference is the representation's alone
    # (the configuration of test_exact_matches_volpath: its kernels are reused)
    scene = mi.load_dict(scene_dict(mi, ours(resolution=256)))
    exact = np.asarray(mi.render(scene, spp=32, seed=7), np.float64)[..., 0]
    avsm = mi.load_dict(ours(representation="avsm", nodes=4, resolution=256))
    img = np.asarray(mi.render(scene, integrator=avsm, spp=32, seed=7), np.float64)[..., 0]
    rel = np.abs(img - exact).sum() / exact.sum()
    assert rel > 1e-4                            # float32 rounding of identical paths is ~1e-7
    assert rel < 0.02                            # measured 0.33 % (AVSM-8: 0.068 %)


def test_load_dict_properties_and_errors(mi):
    integ = mi.load_dict(ours(representation="avsm", nodes=6, sort=True, resolution=64, filter="point"))
    assert integ.kind == "avsm" and integ.params == {"nodes": 6, "sort": True} and integ.resolution == 64
    bad = [({"representation": "nope"}, "representation: unknown kind"),
           ({"representation": "avsm", "nodez": 4}, "nodez: unknown parameter of 'avsm'"),
           ({"representation": "avsm", "nodes": 1}, "nodes"),
           ({"max_depth": 3}, "max_depth:"),
           ({"resolution": 10}, "resolution:"),
           ({"filter": "cubic"}, "filter:"),
           ({"march_steps": 0}, "march_steps:")]
    for props, msg in bad:
        # Mitsuba's parser wraps the plugin's ValueError in a RuntimeError quoting it (no traceback)
        with pytest.raises(RuntimeError, match="ValueError: " + msg) as err:
            mi.load_dict(ours(**props))
        assert "Traceback" not in str(err.value)
        p = mi.Properties(am.NAME)
        for k, v in props.items():
            p[k] = v
        with pytest.raises(ValueError, match="^" + msg):
            am.integrator_class()(p)


def test_scene_errors(mi):
    two_lights = scene_dict(mi, ours(resolution=64), size=8)
    two_lights["light2"] = {"type": "point", "position": [0, 3, 0]}
    homogeneous = scene_dict(mi, ours(resolution=64), size=8)
    homogeneous["vol"]["interior"] = {"type": "homogeneous", "sigma_t": 1.0}
    for d, msg in ((two_lights, "scene: .*exactly one emitter, found 2$"),
                   (homogeneous, "scene: the medium must be 'heterogeneous'")):
        scene = mi.load_dict(d)
        with pytest.raises(ValueError, match="^" + msg):
            scene.integrator().render(scene, spp=1)
        # mi.render runs the integrator inside a Dr.Jit custom op, whose RuntimeError says only
        # "(see above)"; avsm_dr.mitsuba's mi.render raises the ValueError itself
        for integrator in (None, scene.integrator()):
            with pytest.raises(ValueError, match="^" + msg) as err:
                mi.render(scene, integrator=integrator, spp=1)
            assert "see above" not in str(err.value)


@pytest.mark.parametrize("light", [DirectionalLight((0.3, -1.0, 0.2)), PointLight((0.5, 2.0, -1.0)),
                                   SpotLight((0.5, 2.0, -1.0), (0.1, -1.0, 0.3), 50.0)])
def test_light_of_inverts_to_mitsuba(mi, light):
    back = am.light_of(mi.load_dict(light.to_mitsuba(mi)))
    assert type(back) is type(light)
    for f in ("direction", "position", "fov"):
        if hasattr(light, f):
            np.testing.assert_allclose(getattr(back, f), getattr(light, f), rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="^emitter: .*got "):
        am.light_of(mi.load_dict({"type": "constant"}))


def test_render_passes_other_integrators_errors_through(mi):
    """The mi.render wrapper re-raises only avsm_single_scatter's errors: another Python
    integrator's ValueError stays Dr.Jit's RuntimeError, its __cause__ untouched."""
    class Failing(mi.SamplingIntegrator):
        def render(self, *args, **kwargs):
            raise ValueError("failing integrator")
    assert "integrator" in inspect.signature(mi.render).parameters        # functools.wraps keeps it
    scene = mi.load_dict(scene_dict(mi, ours(resolution=64), size=8))
    with pytest.raises(RuntimeError, match="see above") as err:
        mi.render(scene, integrator=Failing(mi.Properties()), spp=1)
    assert str(err.value.__cause__) == "failing integrator"


def test_property_typo_is_reported_first_and_readably_at_load_dict(mi):
    """What mi.load_dict says: Mitsuba's prefix, then the plugin's ValueError on one line (no
    traceback), the unknown name before any bad value, private switches accepted, never listed."""
    prefix = r'failed to instantiate \w+ plugin of type "avsm_single_scatter": ValueError: '
    known = r"known: \['nodes', 'sort', 'interpolation', 'insertion', 'near', 'far', 'precision', 'reverse', 'chunk'\]"
    for props, msg in (
            ({"representation": "avsm", "precison": "float16", "resolution": 10},   # the typo first
             r"precison: unknown parameter of 'avsm'; " + known + r"; did you mean 'precision'\?$"),
            ({"representation": "avsm", "resolutoin": 64},
             r"resolutoin: unknown parameter of 'avsm'; " + known
             + r"; avsm_single_scatter properties: \[.*'resolution'.*\]; did you mean 'resolution'\?$"),
            ({"representaton": "avsm", "nodes": 4},      # kind defaults to 'exact': the typo, not 'nodes'
             r"representaton: unknown parameter of 'exact'; known: \['precision', 'reverse', 'chunk'\]; "
             r"avsm_single_scatter properties: \[.*\]; did you mean 'representation'\?$"),
            ({"representation": "avsm", "_compactt": True},
             r"_compactt: unknown parameter of 'avsm'; " + known + r"; avsm_single_scatter properties: [^;]*\]$")):
        with pytest.raises(RuntimeError) as err:
            mi.load_dict({"type": "scene", "integrator": ours(**props)})
        text = str(err.value)
        assert re.search(prefix + msg, text), text
        assert "Traceback" not in text and "\n" not in text
        assert "_compact'" not in text and "_split" not in text and "_group" not in text
    integ = mi.load_dict(ours(representation="avsm", nodes=4, _compact=False, resolution=64))
    assert integ.params == {"nodes": 4, "_compact": False}


VARIANT_SCRIPT = r"""
import json, sys
import avsm_dr
import mitsuba as mi
out = {}
def load(integrator):
    try:
        mi.load_dict({"type": "scene", "integrator": integrator})
        return "ok"
    except Exception as e:
        return type(e).__name__ + ": " + str(e)
mi.set_variant("scalar_rgb")                   # set before the import: the import registers for it
import avsm_dr.mitsuba as am
out["scalar_first"] = load({"type": am.NAME, "representation": "avsm", "nodes": 4})
try:
    am.integrator_class()
except ValueError as e:
    out["integrator_class"] = str(e)
mi.set_variant("llvm_ad_rgb")                  # the variant callback registers the integrator
out["llvm"] = load({"type": am.NAME, "representation": "avsm", "nodes": 4, "resolution": 64})
mi.set_variant("scalar_spectral")              # a switch after the import: the callback refuses it
out["scalar_after"] = load({"type": am.NAME})
print(json.dumps(out))
"""


def test_non_jit_variant_names_the_variant_to_set():
    """Under a scalar variant mi.load_dict says which variant to set, not Mitsuba's
    'Plugin "avsm_single_scatter" not found!'.  In a subprocess: the variant switches."""
    run = subprocess.run([sys.executable, "-c", VARIANT_SCRIPT], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    need = (r"ValueError: avsm_single_scatter needs a JIT variant of Mitsuba with autodiff \(llvm_ad_rgb, or "
            r"cuda_ad_rgb on an NVIDIA GPU; any llvm_ad_\* / cuda_ad_\*\), the current variant is '{}': call "
            r"mi.set_variant\('llvm_ad_rgb'\)")
    for key, variant in (("scalar_first", "scalar_rgb"), ("scalar_after", "scalar_spectral")):
        text = out[key]
        assert text.startswith("RuntimeError: ") and re.search(need.format(variant), text), text
        assert "not found" not in text and "Traceback" not in text
    assert re.match(need.format("scalar_rgb")[len("ValueError: "):], out["integrator_class"])
    assert out["llvm"] == "ok"


def test_build_parameters_pass_and_messages_list_public_names(mi):
    """``precision`` (and ``reverse``/``chunk``), which ``ad.build`` takes for every kind, pass
    through the integrator; an unknown name lists the public parameters, never the private
    ablation switches (``_compact``, ...)."""
    integ = mi.load_dict(ours(representation="avsm", nodes=4, precision="float16", resolution=64))
    assert integ.params == {"nodes": 4, "precision": "float16"}
    scene = mi.load_dict(scene_dict(mi, ours(resolution=64), size=8))
    _, rep, _, _ = integ.prepare_shadow(scene)
    assert rep.precision == "float16"
    for props, msg in (({"representation": "avsm", "nodez": 4},
                        r"nodez: unknown parameter of 'avsm'; known: \['nodes', .*'precision', 'reverse', 'chunk'\]; "
                        r"did you mean 'nodes'\?$"),
                       ({"representation": "fom", "precision": "float64"}, "precision: kind 'fom' accepts None or"),
                       ({"representation": "exact", "precision": "float16"},
                        "precision: kind 'exact' accepts only None")):
        p = mi.Properties(am.NAME)
        for k, v in props.items():
            p[k] = v
        with pytest.raises(ValueError, match="^" + msg) as err:
            am.integrator_class()(p)
        assert "_compact" not in str(err.value) and "_split" not in str(err.value)


@pytest.mark.parametrize("bad, msg", [(np.nan, "contains 1 NaN or inf"), (np.inf, "contains 1 NaN or inf"),
                                      (-1.0, "negative extinction -1")])
def test_bad_density_grid_is_named_not_blamed_on_to_world(mi, bad, msg):
    scene = mi.load_dict(scene_dict(mi, ours(resolution=64), size=8))
    params = mi.traverse(scene)
    g = np.array(params[KEY], np.float32)
    g[3, 4, 5, 0] = bad
    params[KEY] = mi.TensorXf(g)
    params.update()
    with pytest.raises(ValueError, match=r"^scene: the medium's sigma_t grid \(scale \* data\): " + msg) as err:
        scene.integrator().render(scene, spp=1)
    assert "to_world" not in str(err.value)


SPOT = {"type": "spot", "cutoff_angle": 35.0, "intensity": 12.0,
        "to_world": None}        # set in the test (needs mi for the transform)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["point", "spot"])
def test_point_and_spot_lights_match_volpath(mi, kind):
    if kind == "point":
        light = {"type": "point", "position": [1.5, 2.5, 1.0], "intensity": 6.0}
    else:
        light = dict(SPOT, to_world=mi.ScalarTransform4f().look_at(origin=[1.5, 2.5, 1.0], target=[0, -0.5, 0],
                                                                    up=[0, 1, 0]))
    runs, spp = 8, 32
    a = renders(mi, mi.load_dict(scene_dict(mi, ours(resolution=256), light=light)), runs, spp)
    b = renders(mi, mi.load_dict(scene_dict(mi, {"type": "volpath", "max_depth": 2}, light=light)),
                runs, spp, seed0=100)
    z_blocks, z_image, _ = block_z(a, b)
    assert np.all(np.abs(z_blocks) <= 5.0), np.round(z_blocks, 2)
    assert abs(z_image) <= 4.0


def test_gradient_matches_finite_difference(mi):
    """Directional derivatives of loss(data + eps v) = mean image: dr.backward vs central differences,
    along v = data (a global density scale) and v = data * U(0, 2) per voxel.

    Same seed on both sides: the samples (scattering distances, emitter samples) do not
    depend on the density, so the rendered image is a smooth function of it and the MC
    noise cancels; what remains is the FD truncation error O(eps^2 tau^2) (eps = 1e-2) and
    float32 rounding of the loss (~1e-7 / (2 eps) relative): 2e-3 relative.
    """
    scene = mi.load_dict(scene_dict(mi, ours(resolution=64), size=12))
    params = mi.traverse(scene)
    data = mi.TensorXf(params[KEY])
    rng = np.random.default_rng(1)
    dirs = [data, data * mi.TensorXf(rng.uniform(0, 2, data.shape).astype(np.float32))]
    dr.enable_grad(params[KEY])
    params.update()
    dr.backward(dr.mean(mi.render(scene, params=params, spp=8, seed=3, seed_grad=5), axis=None))
    grad = np.asarray(dr.grad(params[KEY]), np.float64)
    dr.disable_grad(params[KEY])

    def loss(x):
        p = mi.traverse(scene)
        p[KEY] = x
        p.update()
        return float(np.asarray(mi.render(scene, spp=8, seed=5), np.float64).mean())
    eps = 1e-2
    for v in dirs:
        ad_dir = float(np.sum(grad * np.asarray(v, np.float64)))
        fd = (loss(data + eps * v) - loss(data - eps * v)) / (2 * eps)
        assert ad_dir < 0 and fd < 0                # more smoke, darker ground: a real signal
        assert abs(ad_dir - fd) <= 2e-3 * abs(fd), (ad_dir, fd)
