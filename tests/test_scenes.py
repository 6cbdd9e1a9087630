"""Built-in scenes: well-formed, deterministic, and shadowing their receivers."""
from __future__ import annotations

import numpy as np
import pytest

import avsm_dr as ad
from avsm_dr.scene import DirectionalLight, PointLight, Scene, SpotLight

SMALL = {
    "plume": dict(size=12),
    "three_columns": dict(size=10),
    "hair_and_smoke": dict(size=12, n_strands=80),
    "particles": dict(n=60),
    "smoke_over_table": dict(size=12),
}


def exact_T(scene, resolution=128, **kw):
    cap = ad.capture(scene, resolution=resolution, **kw, order="depth")
    return np.asarray(cap.transmittance(ad.build("exact", cap.segments), scene.receivers)), cap


@pytest.mark.parametrize("name", sorted(SMALL))
def test_scene_is_well_formed_and_deterministic(name):
    sc = ad.scenes.get(name, **SMALL[name])
    assert isinstance(sc, Scene) and sc.name == name
    assert sc.receivers.ndim == 2 and sc.receivers.shape[1] == 3 and np.all(np.isfinite(sc.receivers))
    assert sc.receivers.shape[0] == 1024
    point, normal, half = sc.receiver_plane
    assert np.shape(point) == (3,) and abs(np.linalg.norm(normal) - 1) < 1e-12 and half > 0
    if sc.density is not None:
        assert sc.density.dtype == np.float32 and sc.density.ndim == 3
        assert np.all(np.isfinite(sc.density)) and sc.density.min() == 0 and sc.density.max() > 0
        lo, hi = sc.bbox
        assert np.all(np.asarray(hi) > np.asarray(lo))
    again = ad.scenes.get(name, **SMALL[name])
    assert np.array_equal(again.receivers, sc.receivers)
    if sc.density is not None:
        assert np.array_equal(again.density, sc.density)
        other = ad.scenes.get(name, **SMALL[name], seed=1)
        assert not np.array_equal(other.density, sc.density)


def test_size_sets_the_grid_resolution():
    assert ad.scenes.plume(size=8).density.shape == (8, 12, 8)
    assert ad.scenes.plume(size=16).density.shape == (16, 24, 16)
    assert ad.scenes.three_columns(size=10).density.shape == (10, 10, 30)


@pytest.mark.parametrize("name", ["plume", "three_columns"])
def test_default_scenes_shadow_their_receivers(name):
    """Default plume and three_columns: exact transmittance well below 0.5 somewhere (on the
    wall behind the smoke too), and lit receivers exist, so errors are meaningful."""
    sc = ad.scenes.get(name)
    T, _ = exact_T(sc, resolution=256)
    wall = T[sc.receivers.shape[0] // 2:]
    assert T.min() < 0.05 and wall.min() < 0.2
    assert wall.max() > 0.95
    assert np.mean(wall < 0.5) > 0.05


def test_three_columns_cast_on_each_other():
    """A light ray through the middle of the map crosses three separate smoke columns:
    its segments fall into three depth clusters separated by empty gaps > 0.3."""
    sc = ad.scenes.three_columns(size=12)
    cap = ad.capture(sc, resolution=64, order="depth")
    h = cap.segments.numpy()
    found = 0
    for t in np.argsort(cap.segments.counts)[::-1][:50]:
        s = slice(h["offsets"][t], h["offsets"][t + 1])
        gaps = h["z0"][s][1:] - h["z1"][s][:-1]
        found += np.count_nonzero(gaps > 0.3) == 2
    assert found > 10


def test_hair_and_smoke_has_hair_steps():
    """Hair crossings are short segments of T = 1 - opacity inside smooth smoke (Salvi et al. 2010, fig. 6)."""
    sc = ad.scenes.hair_and_smoke(**SMALL["hair_and_smoke"])
    T, cap = exact_T(sc, resolution=128)
    assert cap.stats["hair"]["segments"] > 100 and cap.stats["grid"]["segments"] > 1000
    h = cap.segments.numpy()
    hair = np.isclose(np.exp(-h["optical_depth"]), 1 - sc.hair.opacity, rtol=1e-6)
    assert hair.sum() >= cap.stats["hair"]["segments"]
    assert np.median((h["z1"] - h["z0"])[hair]) <= 2 * sc.hair.radius * 5
    assert T.min() < 0.5


def test_hair_and_smoke_with_tressfx(shared_dir):
    path = shared_dir / "data" / "hair" / "Ratboy_mohawk.tfx"
    if not path.exists():
        pytest.skip("Ratboy_mohawk.tfx not present")
    sc = ad.scenes.hair_and_smoke(size=12, tfx_path=path)
    assert sc.hair.strands.shape == (2228, 32, 3)
    lo, hi = sc.hair.strands.reshape(-1, 3).min(0), sc.hair.strands.reshape(-1, 3).max(0)
    assert np.all(lo >= sc.bbox[0]) and np.all(hi <= sc.bbox[1])
    T, cap = exact_T(sc, resolution=64)
    assert cap.stats["hair"]["segments"] > 1000 and T.min() < 0.5


def test_particles_scene_shadows():
    sc = ad.scenes.particles(**SMALL["particles"])
    T, _ = exact_T(sc)
    assert T[:512].mean() < 0.9 and T.min() < 0.2 and T.max() == 1.0


def test_content_bounds_enclose_particles_and_hair():
    p = ad.scenes.particles(**SMALL["particles"]).particles
    lo, hi = p.bounds()
    np.testing.assert_array_equal(lo, np.min(p.centers - p.radii[:, None], axis=0))
    assert np.all(p.centers + p.radii[:, None] <= hi) and np.any(p.centers + p.radii[:, None] == hi)
    h = ad.scenes.hair_and_smoke(**SMALL["hair_and_smoke"]).hair
    lo, hi = h.bounds()
    pts = h.strands.reshape(-1, 3)
    np.testing.assert_allclose(lo, pts.min(0) - h.radius)
    np.testing.assert_allclose(hi, pts.max(0) + h.radius)


def test_smoke_over_table():
    """Table-top receivers are lit (no self-shadowing through the opaque table), shadowed only
    by the smoke; a point beneath the table is black."""
    sc = ad.scenes.smoke_over_table(**SMALL["smoke_over_table"])
    T, cap = exact_T(sc)
    top = T[512:]
    assert np.all(top > 0) and top.max() == 1.0 and top.min() < 0.5
    texel, depth = cap.lookup(np.array([[0.9, -0.1, 0.9], [0.9, 0.01, 0.9]]))
    under, above = np.asarray(ad.build("exact", cap.segments).eval(texel, depth))
    assert under == 0.0 and above == 1.0


@pytest.mark.parametrize("light", [SpotLight((-3.0, 1.5, 0.2), (1.0, -0.3, 0.0), 40.0), PointLight((-3.0, 1.5, 0.2))])
def test_scene_light_can_be_replaced(light):
    sc = ad.scenes.plume(size=12, light=light)
    T, cap = exact_T(sc, resolution=64)
    assert cap.segments.n_segments > 0 and T.min() < 0.5


def test_bad_scene_arguments():
    with pytest.raises(ValueError, match="^name"):
        ad.scenes.get("fog")
    with pytest.raises(ValueError, match="^size"):
        ad.scenes.plume(size=2)
    with pytest.raises(ValueError, match="^n_receivers"):
        ad.scenes.three_columns(n_receivers=0)
    with pytest.raises(ValueError, match="^n"):
        ad.scenes.particles(n=0)
    with pytest.raises(ValueError, match="^direction"):
        ad.scenes.plume(light=DirectionalLight((0, 0, 0)))
