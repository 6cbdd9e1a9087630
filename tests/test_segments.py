"""Segments: CSR packing, conversions and boundary validation."""
import numpy as np
import pytest

import avsm_dr as ad
import drjit as dr
from avsm_dr import backend


def make(**over):
    args = dict(offsets=[0, 2, 3], z0=[0.1, 0.2, 0.0], z1=[0.3, 0.2, 0.5], transmittance=[0.5, 0.0, 1.0])
    args.update(over)
    return ad.Segments.from_arrays(**args)


def test_basic_properties():
    seg = make()
    assert seg.n_texels == 2 and seg.n_segments == 3 and seg.max_count == 2
    np.testing.assert_array_equal(seg.counts, [2, 1])
    # opaque transmittance 0 becomes the finite opaque optical depth, 1 becomes 0
    np.testing.assert_allclose(np.asarray(seg.optical_depth), [np.log(2), ad.OPAQUE_OPTICAL_DEPTH, 0.0], rtol=1e-6)
    assert seg.bounds() == (0.0, 0.5)
    near, far = seg.texel_bounds()
    np.testing.assert_allclose(near, [0.1, 0.0]) and np.testing.assert_allclose(far, [0.3, 0.5])


@pytest.mark.parametrize("over, name", [
    (dict(offsets=[]), "offsets"),
    (dict(offsets=[[0, 2, 3]]), "offsets"),
    (dict(offsets=[1, 2, 3]), "offsets"),
    (dict(offsets=[0, 3, 2]), "offsets"),
    (dict(offsets=[0, 2, 4]), "z0"),
    (dict(z0=[0.1, np.nan, 0.0]), "z0"),
    (dict(z1=[0.3, np.inf, 0.5]), "z1"),
    (dict(z1=[0.05, 0.2, 0.5]), "z1"),
    (dict(transmittance=[0.5, 1.5, 1.0]), "transmittance"),
    (dict(transmittance=[0.5, -0.1, 1.0]), "transmittance"),
    (dict(transmittance=[0.5, np.nan, 1.0]), "transmittance"),
    (dict(transmittance=[0.5, 1.0]), "transmittance"),
    (dict(transmittance=None, optical_depth=[1.0, -1.0, 0.0]), "optical_depth"),
    (dict(transmittance=None, optical_depth=[1.0, np.nan, 0.0]), "optical_depth"),
    (dict(optical_depth=[1.0, 1.0, 0.0]), "transmittance"),
    (dict(dtype="float16"), "dtype"),
])
def test_bad_input_names_the_argument(over, name):
    with pytest.raises(ValueError, match=name):
        make(**over)


def test_no_segments_is_valid():
    seg = ad.Segments.from_arrays([0, 0, 0], [], [], transmittance=[])
    assert seg.n_segments == 0
    T = ad.build("exact", seg).eval([0, 1], [0.5, 2.0])
    np.testing.assert_array_equal(np.asarray(T), [1.0, 1.0])


def test_sorted_keeps_gradients():
    Float = backend.types().Float
    tau = Float([0.1, 0.2, 0.3, 0.4])
    dr.enable_grad(tau)
    seg = ad.Segments.from_arrays([0, 3, 4], [0.5, 0.1, 0.3, 0.2], [0.6, 0.2, 0.4, 0.3], optical_depth=tau)
    s = seg.sorted()
    np.testing.assert_allclose(np.asarray(s.z0), [0.1, 0.3, 0.5, 0.2])
    dr.backward(dr.sum(s.optical_depth * Float([1, 2, 3, 4])))
    np.testing.assert_allclose(dr.grad(tau).numpy(), [3, 1, 2, 4])


def test_drjit_float64_input_selects_float64():
    F64 = backend.types().Float64
    seg = ad.Segments.from_arrays([0, 1], F64([0.0]), F64([1.0]), optical_depth=F64([0.5]))
    assert seg.dtype == "float64" and type(seg.z0) is F64
