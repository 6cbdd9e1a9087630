"""Beer shadow map (beer.py) against the float64 reference (tests/reference/beer_ref.py):
both variants, exactness for one uniform segment, the definition of the mean extinction,
content without extent, storage."""
import numpy as np
import pytest

import avsm_dr as ad
from cases import random_segments, to_segments
from reference import beer_ref, exact_ref


@pytest.mark.parametrize("variant", ["cloud", "two_node"])
def test_matches_reference(backend, rng, variant):
    data = random_segments(rng, texels=40, max_count=12)
    seg = to_segments(data, "float64")
    rep = ad.build("beer", seg, variant=variant)
    depth = np.linspace(-0.2, 1.3, 61)
    tex = np.repeat(np.arange(40), depth.size)
    got = np.asarray(rep.eval(tex, np.tile(depth, 40))).reshape(40, -1)
    off = data["offsets"]
    tau = np.minimum(data["tau"], ad.OPAQUE_OPTICAL_DEPTH)
    for t in range(40):
        s = slice(off[t], off[t + 1])
        ref = [beer_ref.transmittance(data["z0"][s], data["z1"][s], tau[s], d, variant) for d in depth]
        # float64 throughout: rounding only (sums of <= 12 optical depths)
        np.testing.assert_allclose(got[t], ref, rtol=1e-12, atol=1e-14)


def test_cloud_is_exact_for_one_uniform_segment(backend):
    seg = ad.Segments.from_arrays([0, 1, 2], [0.25, 3.0], [0.75, 7.0], optical_depth=[1.7, 0.4], dtype="float64")
    beer = ad.build("beer", seg)
    for t, (a, b, tau) in enumerate([(0.25, 0.75, 1.7), (3.0, 7.0, 0.4)]):
        d = np.linspace(a - 1, b + 1, 101)
        ref = [exact_ref.transmittance([a], [b], [tau], x) for x in d]
        np.testing.assert_allclose(np.asarray(beer.eval(np.full(d.size, t), d)), ref, rtol=1e-13, atol=1e-15)


def test_mean_extinction_spreads_the_total_over_the_content():
    # two segments with a gap: sigma_mean = (0.6 + 0.9) / (1.0 - 0.0), gaps included
    seg = ad.Segments.from_arrays([0, 2], [0.0, 0.8], [0.2, 1.0], optical_depth=[0.6, 0.9], dtype="float64")
    rep = ad.build("beer", seg)
    assert float(rep.sigma_mean.numpy()[0]) == pytest.approx(1.5, rel=1e-15)
    assert float(rep.tau_max.numpy()[0]) == pytest.approx(1.5, rel=1e-15)
    T = np.asarray(rep.eval([0, 0, 0], [0.5, 1.0, 2.0]))
    np.testing.assert_allclose(T, np.exp([-0.75, -1.5, -1.5]), rtol=1e-14)


@pytest.mark.parametrize("variant", ["cloud", "two_node"])
def test_content_without_extent_is_a_step(variant):
    # only zero-length segments at one depth: T = 1 in front, exp(-tau) at and behind it
    seg = ad.Segments.from_arrays([0, 2], [0.5, 0.5], [0.5, 0.5], optical_depth=[0.3, 0.4], dtype="float64")
    T = np.asarray(ad.build("beer", seg, variant=variant).eval([0, 0, 0], [0.49, 0.5, 0.9]))
    np.testing.assert_allclose(T, [1.0, np.exp(-0.7), np.exp(-0.7)], rtol=1e-15)


def test_two_node_interpolates_linearly_between_entry_and_exit():
    seg = ad.Segments.from_arrays([0, 1], [1.0], [3.0], optical_depth=[2.0], dtype="float64")
    T = np.asarray(ad.build("beer", seg, variant="two_node").eval([0] * 4, [0.5, 1.0, 2.0, 3.0]))
    tb = np.exp(-2.0)
    np.testing.assert_allclose(T, [1.0, 1.0, 0.5 * (1 + tb), tb], rtol=1e-15)


@pytest.mark.parametrize("dtype, size", [("float32", 12), ("float64", 24)])
def test_storage_is_three_floats(dtype, size):
    seg = ad.Segments.from_arrays([0, 1, 1], [0.1], [0.2], optical_depth=[1.0], dtype=dtype)
    for variant in ("cloud", "two_node"):
        assert ad.build("beer", seg, variant=variant).nbytes_per_texel == size


def test_bad_variant():
    seg = ad.Segments.from_arrays([0, 1], [0.1], [0.2], optical_depth=[1.0])
    with pytest.raises(ValueError, match="^variant"):
        ad.build("beer", seg, variant="clouds")
