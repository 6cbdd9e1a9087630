"""The procedural scenes (cumulus, fog bank, Gaussian blobs, tall simulated column): they build,
are seeded, validate, and have the property each stands for (depth range, sharp top, soft
falloff in draw order, height)."""
from __future__ import annotations

import inspect
import math

import numpy as np
import pytest

from avsm_dr import builtin_scenes as B
from avsm_dr import procedural as P
from avsm_dr.groundtruth import sample_density, transmittance

#: Small builds (each well under a second).
SMALL = {"cumulus": dict(size=10), "fog_bank": dict(size=12), "gaussian_blobs": dict(n=30),
         "tall_column": dict(size=8)}


def _build(name, seed=0):
    return B.SCENES[name](seed=seed, **SMALL[name])


def _content(sc):
    """Density-like arrays that define the scene (for equality checks)."""
    if sc.density is not None:
        return [np.asarray(sc.density)]
    p = sc.particles
    return [np.asarray(p.centers), np.asarray(p.radii), np.asarray(p.density)]


@pytest.mark.parametrize("name", list(SMALL))
def test_registered_builds_validates_and_is_seeded(name):
    assert B.SCENES[name] is getattr(P, name) and B.get(name, **SMALL[name]).name == name
    a, a2, b = _build(name), _build(name), _build(name, seed=1)
    for x, y in zip(_content(a), _content(a2)):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a.receivers, a2.receivers)
    assert any(not np.array_equal(x, y) for x, y in zip(_content(a), _content(b)))
    for x in _content(a):
        assert np.all(np.isfinite(x))
    assert np.all(_content(a)[-1] >= 0)                          # extinction (grid or per particle)
    assert a.receivers.shape == (1024, 3) and np.all(np.isfinite(a.receivers))
    m, _ = transmittance(a, a.receivers, method="raymarch")       # validates the scene
    assert np.all((m >= 0) & (m <= 1))
    with pytest.raises(ValueError, match="^seed"):
        B.SCENES[name](seed=-1, **SMALL[name])


@pytest.mark.parametrize("name", list(SMALL))
def test_transmittance_decreases_along_the_light_and_optical_depth_is_sensible(name):
    """Along light rays through the content, ground-truth T is non-increasing with depth and
    ends in (0, 1); the median optical depth through the whole volume is in [0.5, 10]."""
    sc = _build(name)
    w = sc.light.direction
    vol = sc.receivers[:512]                                      # drawn in voxels with density > 0
    if sc.density is not None:                                    # fluid smoke: skip its faint haze
        vol = vol[sample_density(sc.density, sc.bbox, vol) > 0.05 * float(np.max(sc.density))]
    idx = np.random.default_rng(3).choice(len(vol), 40, replace=False)
    s = np.linspace(-4.0, 4.0, 81)                                # covers every scene's content
    pts = vol[idx][:, None, :] + s[None, :, None] * w
    T = transmittance(sc, pts.reshape(-1, 3), method="raymarch")[0].reshape(len(idx), len(s))
    # the float64 march's midpoint rule (step ~voxel / 8, rounded per path length) moves T by
    # < 1e-3 relative between neighbouring lengths (measured 7.4e-4): that much rise is allowed
    assert np.all(np.diff(T, axis=1) <= 2e-3 * T[:, :-1])
    assert np.allclose(T[:, 0], 1.0)                              # in front of all content
    assert np.all((T[:, -1] > 0) & (T[:, -1] < 1))
    tau = -np.log(T[:, -1])
    assert 0.5 <= np.median(tau) <= 10.0, np.median(tau)


def _depth_range(sc):
    d = np.asarray(sc.density)
    lo, hi = (np.asarray(b, float) for b in sc.bbox)
    nz, ny, nx = d.shape
    k, j, i = np.nonzero(d > 0)
    p = lo + (np.stack([i, j, k], 1) + 0.5) * (hi - lo) / np.array([nx, ny, nz])
    t = p @ sc.light.direction
    return t.max() - t.min()


def test_cumulus_depth_range_exceeds_every_other_grid_scene():
    cu = _depth_range(P.cumulus(size=8))
    others = {n: _depth_range(B.SCENES[n](size=8)) for n in
              ("plume", "three_columns", "hair_and_smoke", "smoke_over_table", "simulated_plume",
               "fog_bank", "tall_column")}
    assert cu > 1.25 * max(others.values()), (cu, others)


def test_fog_bank_top_is_a_sharp_one_voxel_boundary():
    """Every column holds fog up to its top and nothing above; the trilinear density falls from
    >= 0.75 x density_scale to 0 within one voxel height (the plume's softest fall spans many)."""
    sc = P.fog_bank(size=16, density_scale=5.0)
    d = np.asarray(sc.density)
    occ = d > 0
    top = occ.shape[1] - 1 - np.argmax(occ[:, ::-1, :], axis=1)  # highest fog voxel per column
    below = np.arange(occ.shape[1])[None, :, None] <= top[:, None, :]
    assert np.array_equal(occ, below)                            # fog fills each column to its top
    ztop = np.take_along_axis(d, top[:, None, :], axis=1)
    assert ztop.min() >= 0.75 * 5.0 - 1e-5
    lo, hi = (np.asarray(b, float) for b in sc.bbox)
    h = (hi[1] - lo[1]) / d.shape[1]
    x, z = 0.1, -0.2
    y = np.linspace(lo[1], hi[1], 4001)
    prof = sample_density(sc.density, sc.bbox, np.stack([np.full_like(y, x), y, np.full_like(y, z)], 1))
    peak = prof[y < 0.25].min()
    band = y[(prof > 0.1 * peak) & (prof < 0.9 * peak)]
    assert band.size and band.max() - band.min() <= h + 1e-9


def test_gaussian_blobs_are_nested_shells_in_draw_order_with_the_gaussian_chord():
    sc = P.gaussian_blobs(n=40, seed=2, density_scale=4.0)
    p, m = sc.particles, len(P.BLOB_SHELLS)
    c, r, s = (np.asarray(a, float) for a in (p.centers, p.radii, p.density))
    blob = sc.meta["blob"]
    assert np.array_equal(blob, np.repeat(np.arange(40), m))     # list order = emission order
    cb, rb, sb = c.reshape(40, m, 3), r.reshape(40, m), s.reshape(40, m)
    assert np.all(cb == cb[:, :1]) and np.all(np.diff(rb, axis=1) > 0) and np.all(sb > 0)
    w = rb[:, 1] / P.BLOB_SHELLS[1]
    assert np.all(np.diff(w) > 0)                                 # blobs grow with age
    for seed in range(5):                                         # the stated box holds every sphere
        q = P.gaussian_blobs(seed=seed).particles
        assert np.all(q.centers - q.radii[:, None] >= (-0.75, -0.1, -0.75))
        assert np.all(q.centers + q.radii[:, None] <= (0.75, 1.35, 0.75))
    depth = c[::m] @ sc.light.direction                           # draw order is not depth-sorted
    assert not (np.all(np.diff(depth) >= 0) or np.all(np.diff(depth) <= 0))
    # NumPy reference: the central chord of the Gaussian s0 exp(-x^2 / 2w^2), truncated at
    # 2.25 w, by the trapezoid rule (1e6 steps: relative error ~1e-12)
    peak = 4.0 * 0.04 / w
    x = np.linspace(-P.BLOB_SHELLS[-1], P.BLOB_SHELLS[-1], 1_000_001)
    ref = peak * w * np.trapezoid(np.exp(-0.5 * x * x), x)
    chord = (sb * 2 * rb).sum(1)                                   # nested spheres add up
    np.testing.assert_allclose(chord, ref, rtol=1e-9)
    # the untruncated Gaussian's chord is 2.4 % longer (the tail beyond +-2.25 w)
    assert math.isclose(chord[0] / (peak[0] * w[0] * math.sqrt(2 * math.pi)), math.erf(2.25 / math.sqrt(2)),
                        rel_tol=1e-9)


def test_tall_column_is_taller_and_finer_than_the_simulated_plume():
    dflt = lambda f, k: inspect.signature(f).parameters[k].default   # noqa: E731
    assert dflt(P.tall_column, "size") > dflt(B.simulated_plume, "size")
    tc, sp = P.tall_column(size=8), B.simulated_plume(size=8)
    assert tc.bbox[1][1] - tc.bbox[0][1] == 2 * (sp.bbox[1][1] - sp.bbox[0][1])
    d = np.asarray(tc.density)
    rows = np.nonzero((d > 0.01 * d.max()).any(axis=(0, 2)))[0]
    assert rows.max() * 3.0 / d.shape[1] > 1.5                    # smoke rises above the plume's box


def test_bad_arguments_name_the_argument():
    assert (P.MAX_SIZE, P.MAX_POINTS) == (B.MAX_SIZE, B.MAX_POINTS)
    with pytest.raises(ValueError, match="^size"):
        P.cumulus(size=2)
    with pytest.raises(ValueError, match="^density_scale"):
        P.fog_bank(density_scale=-1)
    with pytest.raises(ValueError, match="^n"):
        P.gaussian_blobs(n=0)
    with pytest.raises(ValueError, match="^light"):
        P.tall_column(size=8, light="sun")


def test_worley_is_a_nearest_feature_distance():
    """Worley F1 against a brute-force NumPy reference on a small lattice."""
    rng = np.random.default_rng(5)
    shape, cells = (6, 9, 12), 3
    got = P.worley(shape, cells, np.random.default_rng(5))
    c = [max(1, int(np.ceil(cells * n / 12))) for n in shape]
    pts = rng.random((c[0] + 2, c[1] + 2, c[2] + 2, 3))
    feat = (np.stack(np.meshgrid(*[np.arange(k + 2) - 1 for k in c], indexing="ij"), -1) + pts).reshape(-1, 3)
    vox = np.stack(np.meshgrid(*[(np.arange(n) + 0.5) / n * k for n, k in zip(shape, c)], indexing="ij"), -1)
    ref = np.sqrt(((vox.reshape(-1, 1, 3) - feat[None]) ** 2).sum(-1).min(1)).reshape(shape)
    np.testing.assert_allclose(got, np.minimum(ref, 1.0), rtol=1e-12, atol=1e-12)
    assert 0 <= P.perlin_worley(shape, 0).min() and P.perlin_worley(shape, 0).max() <= 1
