"""Bytes counted the same way for every kind: the sparse layout (one occupancy bit per
texel, each non-empty texel's payload, a 4-byte CSR offset per non-empty texel for the
variable-size kinds) against the dense ``nbytes_per_texel``, driven by the registry."""
import numpy as np
import pytest

import avsm_dr as ad
from cases import case_id, random_segments, representations, to_segments

CASES = representations()

#: Hand counts of a variable-size kind's payload per texel (float32: 4-byte items), from
#: its module docstring's storage line; a new variable-size kind fails until it has one.
VARIABLE_PAYLOAD = {
    "dsm": lambda rep, seg: 8.0 * rep.node_counts,                       # (depth, value) pairs
    "avsm_adaptive": lambda rep, seg: 8.0 * rep.node_counts,             # (depth, value) nodes
    "avsm_march": lambda rep, seg: 8.0 + 6.0 * rep.node_counts,          # range + (uint16 depth, value)
    "exact": lambda rep, seg: 12.0 * seg.counts,                         # (z0, z1, tau)
}
#: Bytes the dense count holds beyond 4 per texel of offsets (avsm_adaptive: T + 1 offsets).
DENSE_EXTRA_OFFSET = {"avsm_adaptive": 4.0}


def _small_map():
    """6 texels, 3 empty: 1, 2 and 3 disjoint segments in the others."""
    offsets = [0, 0, 1, 1, 3, 3, 6]
    z0 = [0.1, 0.2, 0.5, 0.1, 0.4, 0.7]
    z1 = [0.3, 0.3, 0.6, 0.2, 0.5, 0.9]
    return ad.Segments.from_arrays(offsets, z0, z1, optical_depth=[0.5, 0.3, 1.0, 0.2, 0.4, 2.0],
                                   dtype="float32")


def _full_map(rng):
    case = random_segments(rng, texels=32, max_count=6, empty_fraction=0.0)
    case["offsets"] = np.concatenate([[0], np.cumsum(np.maximum(np.diff(case["offsets"]), 1))])
    n = int(case["offsets"][-1])
    case["z0"] = rng.uniform(0.0, 0.8, n)
    case["z1"] = case["z0"] + rng.uniform(0.01, 0.2, n)
    case["tau"] = rng.exponential(0.4, n)
    return to_segments(case)


def test_every_variable_size_kind_has_a_hand_count():
    variable = {k for k in ad.kinds() if ad.REGISTRY[k].variable_size}
    assert variable == set(VARIABLE_PAYLOAD)


@pytest.mark.parametrize("case", CASES, ids=case_id)
def test_sparse_at_most_dense_plus_an_occupancy_bit(case, rng):
    kind, params = case
    seg = to_segments(random_segments(rng, texels=48, max_count=8, empty_fraction=0.4))
    assert np.count_nonzero(seg.counts == 0) > 0
    rep = ad.build(kind, seg, **params)
    T = seg.n_texels
    # totals of byte counts; the dense mean is one float64 division (rounding ~1e-16 relative)
    assert rep.nbytes_sparse <= rep.nbytes_per_texel * T + T / 8 + 1e-9
    assert rep.nbytes_sparse_per_texel == pytest.approx(rep.nbytes_sparse / T, rel=1e-15)


@pytest.mark.parametrize("kind", ad.kinds())
def test_sparse_equals_the_hand_count_with_empty_texels(kind):
    seg = _small_map()
    rep = ad.build(kind, seg)
    occupied = seg.counts > 0
    if kind in VARIABLE_PAYLOAD:
        pay = np.asarray(VARIABLE_PAYLOAD[kind](rep, seg), np.float64)
        hand = 6 / 8 + pay[occupied].sum() + 4 * 3
    else:
        hand = 6 / 8 + 3 * rep.nbytes_per_texel
    assert rep.nbytes_sparse == pytest.approx(hand, rel=1e-12)
    assert rep.nbytes_sparse < rep.nbytes_per_texel * 6 + 6 / 8


@pytest.mark.parametrize("kind", ad.kinds())
def test_a_map_without_empty_texels_costs_dense_plus_one_eighth(kind, rng):
    seg = _full_map(rng)
    assert np.all(seg.counts > 0)
    rep = ad.build(kind, seg)
    T = seg.n_texels
    expected = rep.nbytes_per_texel * T + T / 8 - DENSE_EXTRA_OFFSET.get(kind, 0.0)
    assert rep.nbytes_sparse == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("kind", [k for k in ad.kinds() if ad.describe(k)["precisions"]])
def test_quantised_sparse_bytes_follow_the_same_rule(kind, rng):
    """With a precision the payload is the quantised one: dense + 1/8 on a full map, the
    non-empty texels' share (and their own entry counts) otherwise."""
    prec = "unorm16" if "unorm16" in ad.describe(kind)["precisions"] else ad.describe(kind)["precisions"][0]
    full = ad.build(kind, _full_map(rng), precision=prec)
    T = full.n_texels
    assert full.nbytes_sparse == pytest.approx(full.nbytes_per_texel * T + T / 8, rel=1e-12)
    seg = to_segments(random_segments(rng, texels=48, max_count=8, empty_fraction=0.4))
    rep = ad.build(kind, seg, precision=prec)
    assert rep.nbytes_sparse < rep.nbytes_per_texel * seg.n_texels + seg.n_texels / 8


@pytest.mark.parametrize("kind", ad.kinds())
def test_an_all_empty_map_costs_one_bit_per_texel(kind):
    seg = ad.Segments.from_arrays(np.zeros(11, np.int64), [], [], optical_depth=[], dtype="float32")
    rep = ad.build(kind, seg)
    assert rep.nbytes_sparse == 10 / 8
    assert rep.nbytes_sparse_per_texel == 1 / 8
