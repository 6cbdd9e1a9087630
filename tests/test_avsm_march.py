"""Engine-style AVSM (avsm_march.py) against the float64 reference
(tests/reference/avsm_march_ref.py): node placement by departure from the exponential
extrapolation, the cap with smallest-area removal, float16 depths relative to the
texel's range, compacted storage and its byte count."""
import numpy as np
import pytest

import avsm_dr as ad
from reference import avsm_march_ref as ref
from reference import exact_ref


def _random(rng, texels, max_count):
    counts = rng.integers(0, max_count + 1, texels)
    off = np.r_[0, np.cumsum(counts)]
    n = int(off[-1])
    z0 = rng.uniform(0, 0.8, n)
    z1 = np.where(rng.random(n) < 0.2, z0, z0 + rng.uniform(0, 0.3, n))
    return off, z0, z1, rng.exponential(0.5, n)


@pytest.mark.parametrize("cap, abs_error, rel_error", [(2, 1e-3, 0.0), (3, 1e-3, 0.01), (4, 0.05, 0.0),
                                                       (8, 1e-9, 0.0), (8, 0.0, 0.01)])
def test_matches_reference(backend, rng, cap, abs_error, rel_error):
    off, z0, z1, tau = _random(rng, 30, 7)
    seg = ad.Segments.from_arrays(off, z0, z1, optical_depth=tau, dtype="float64")
    rep = ad.build("avsm_march", seg, nodes=cap, abs_error=abs_error, rel_error=rel_error)
    depths, values = rep.node_depths(), np.asarray(rep.node_value.numpy())
    for t in range(30):
        s = slice(off[t], off[t + 1])
        nodes = ref.build(z0[s], z1[s], tau[s], cap, abs_error, rel_error)
        k = slice(rep.node_offsets[t], rep.node_offsets[t + 1])
        assert rep.node_counts[t] == len(nodes) <= cap
        if not nodes:
            continue
        lo, hi, q = ref.quantise(nodes)
        # float64 march on both sides: same decisions, same float16 depths, values to rounding
        np.testing.assert_allclose(np.c_[depths[k], values[k]], np.array(q), rtol=0, atol=1e-13)
        x = np.linspace(lo - 0.1, hi + 0.1, 41)
        got = np.asarray(rep.eval(np.full(x.size, t), x))
        np.testing.assert_allclose(got, [ref.lookup(q, xi) for xi in x], atol=1e-13)


def test_one_uniform_segment_is_two_exact_nodes():
    seg = ad.Segments.from_arrays([0, 1], [2.0], [5.0], optical_depth=[1.3], dtype="float64")
    rep = ad.build("avsm_march", seg, abs_error=0.0, rel_error=0.0)
    assert rep.node_counts.tolist() == [2]
    np.testing.assert_allclose(rep.node_depths(), [2.0, 5.0], rtol=0, atol=0)   # q = 0 and 1 are exact
    d = np.linspace(1, 6, 51)
    exact = [exact_ref.transmittance([2.0], [5.0], [1.3], x) for x in d]
    np.testing.assert_allclose(np.asarray(rep.eval(np.zeros(d.size, int), d)), exact, rtol=1e-13)


def test_nodes_only_where_the_extrapolation_fails():
    # two abutting uniform segments of different density, then a gap and a step
    z0, z1, tau = [0.0, 1.0, 3.0], [1.0, 2.0, 3.0], [0.5, 2.0, 0.4]
    seg = ad.Segments.from_arrays([0, 3], z0, z1, optical_depth=tau, dtype="float64")
    tight = ad.build("avsm_march", seg, nodes=16, abs_error=1e-6, rel_error=0.0)
    # entry, density change at 1, end of the dense part at 2, both sides of the step at 3
    np.testing.assert_allclose(tight.node_depths(), [0.0, 1.0, 2.0, 3.0, 3.0], atol=2 ** -12 * 3)
    loose = ad.build("avsm_march", seg, nodes=16, abs_error=1.0, rel_error=0.0)
    assert loose.node_counts.tolist() == [2]            # nothing departs by more than 1: first and last
    T = np.asarray(loose.eval([0, 0], [-1.0, 4.0]))
    np.testing.assert_allclose(T, [1.0, np.exp(-2.9)], rtol=1e-14)


def test_zero_tolerance_reproduces_the_curve_up_to_depth_quantisation(rng):
    off, z0, z1, tau = _random(rng, 20, 6)
    seg = ad.Segments.from_arrays(off, z0, z1, optical_depth=tau, dtype="float64")
    rep = ad.build("avsm_march", seg, nodes=64, abs_error=0.0, rel_error=0.0)
    for t in range(20):
        s = slice(off[t], off[t + 1])
        if off[t + 1] == off[t]:
            continue
        x = np.linspace(z0[s].min(), z1[s].max(), 200)
        got = np.asarray(rep.eval(np.full(x.size, t), x))
        exact = np.array([exact_ref.transmittance(z0[s], z1[s], tau[s], xi) for xi in x])
        # exponential pieces are reproduced exactly; only node depths move, by at most half a
        # float16 ulp of the range (2^-12 span), so T moves by at most max|dT/dz| of that shift
        span = z1[s].max() - z0[s].min()
        dens = max((tt / (b - a) for a, b, tt in zip(z0[s], z1[s], tau[s]) if b > a), default=0.0)
        steep = dens * len(tau[s])
        bad = np.abs(got - exact) > steep * span * 2 ** -12 + 1e-12
        # at steps the shifted node can sit on the other side of the receiver: exclude the
        # receivers within that shift of a step
        steps = z0[s][z1[s] == z0[s]]
        near_step = np.any(np.abs(x[:, None] - steps[None, :]) <= span * 2 ** -12, axis=1) if steps.size else False
        assert not np.any(bad & ~near_step), (t, np.abs(got - exact).max())


def test_relative_float16_depth_keeps_precision_far_from_the_light():
    # content 1 unit deep, 10^4 units from the light: absolute float16 depths would be off
    # by up to 4 (their ulp at 10^4 is 8); relative to the texel's range by <= 2^-12
    z0 = 1e4 + np.array([0.0, 0.3, 0.61])
    z1 = z0 + np.array([0.2, 0.1, 0.39])
    seg = ad.Segments.from_arrays([0, 3], z0, z1, optical_depth=[0.5, 1.0, 0.7], dtype="float64")
    rep = ad.build("avsm_march", seg, nodes=16, abs_error=1e-6, rel_error=0.0)
    assert rep.node_q.numpy().dtype == np.float16
    ends = np.unique(np.r_[z0, z1])
    got = rep.node_depths()
    true = ends[np.argmin(np.abs(ends[None, :] - got[:, None]), axis=1)]
    assert np.max(np.abs(got - true)) <= 1.0 * 2 ** -12                         # range 1.0
    # absolute float16 rounds all six depths to 10^4 (the whole content collapses)
    assert np.max(np.abs(true - true.astype(np.float16).astype(np.float64))) >= 1.0


@pytest.mark.parametrize("dtype, item", [("float32", 4), ("float64", 8)])
def test_bytes_count_offsets_ranges_and_nodes(rng, dtype, item):
    off, z0, z1, tau = _random(rng, 25, 6)
    seg = ad.Segments.from_arrays(off, z0, z1, optical_depth=tau, dtype=dtype)
    rep = ad.build("avsm_march", seg, nodes=4)
    assert rep.node_counts.max() <= 4
    mean = rep.node_counts.mean()
    # 4-byte CSR offset + range (lo, hi) + per node float16 depth and a T
    assert rep.nbytes_per_texel == pytest.approx(4 + 2 * item + mean * (2 + item), rel=1e-15)


def test_cap_two_keeps_first_and_last():
    off = [0, 3]
    seg = ad.Segments.from_arrays(off, [0.0, 0.4, 0.7], [0.3, 0.6, 1.0], optical_depth=[0.5, 2.0, 0.1],
                                  dtype="float64")
    rep = ad.build("avsm_march", seg, nodes=2, abs_error=0.0, rel_error=0.0)
    np.testing.assert_allclose(rep.node_depths(), [0.0, 1.0])
    np.testing.assert_allclose(rep.node_value.numpy(), [1.0, np.exp(-2.6)], rtol=1e-15)


@pytest.mark.parametrize("params, name", [({"abs_error": -0.1}, "abs_error"),
                                          ({"rel_error": float("nan")}, "rel_error"), ({"nodes": 1}, "nodes"),
                                          ({"interpolation": "cubic"}, "interpolation")])
def test_bad_parameters(params, name):
    seg = ad.Segments.from_arrays([0, 1], [0.1], [0.2], optical_depth=[1.0])
    with pytest.raises(ValueError, match=f"^{name}"):
        ad.build("avsm_march", seg, **params)
