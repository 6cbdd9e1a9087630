"""The exact (uncompressed) curve against an independent float64 NumPy reference."""
import numpy as np
import pytest

import avsm_dr as ad
from cases import random_segments, to_segments
from reference import exact_ref


@pytest.mark.parametrize("dtype, rtol", [("float64", 1e-12), ("float32", 2e-5)])
def test_exact_matches_reference(rng, dtype, rtol):
    # float32: exp of an optical-depth sum of <= 20 terms, each rounded to 2^-24 relative
    case = random_segments(rng, texels=80, max_count=20)
    seg = to_segments(case, dtype)
    h = seg.numpy()   # the values the kernel sees (float32-rounded for float32)
    tex = rng.integers(0, 80, 2000)
    depth = rng.uniform(-0.1, 1.1, tex.size)
    # include the exact endpoint depths: steps are right-continuous
    ends = np.concatenate([h["z0"], h["z1"]])
    texe = np.concatenate([np.repeat(np.arange(80), np.diff(case["offsets"]))] * 2)
    tex, depth = np.concatenate([tex, texe]), np.concatenate([depth, ends])
    got = np.asarray(ad.build("exact", seg).eval(tex, depth), dtype=np.float64)
    ref = exact_ref.evaluate(h["offsets"], h["z0"], h["z1"], h["optical_depth"], tex, depth)
    np.testing.assert_allclose(got, ref, rtol=rtol, atol=1e-30)


def test_many_segments_and_opaque_early_exit(rng):
    n = 3000
    z0 = np.sort(rng.uniform(0, 1, n))
    z1 = z0 + 1e-3
    tau = np.full(n, 1e-3)
    tau[n // 2] = ad.OPAQUE_OPTICAL_DEPTH
    seg = ad.Segments.from_arrays([0, n], z0, z1, optical_depth=tau, dtype="float64")
    d = np.array([z0[10], z1[n // 2] + 1e-9, 2.0])
    got = np.asarray(ad.build("exact", seg).eval([0, 0, 0], d))
    ref = exact_ref.evaluate([0, n], z0, z1, tau, [0, 0, 0], d)
    np.testing.assert_allclose(got, ref, rtol=1e-10)
    assert got[1] == 0.0 and got[2] == 0.0
