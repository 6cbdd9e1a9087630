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


@pytest.mark.parametrize("n", [1_000_000, 4_000_000])
def test_long_sums_stay_accurate(n):
    """n equal segments of total optical depth 3 on one ray: the optical depth is summed
    in float64 whatever the storage (in float32 the sum drifted by -2.3 % at n = 1e6 and
    +8 % at 4e6).  Reference: exp(-float64 sum of the stored float32 terms); 1e-5
    relative is the float32 rounding of the returned T plus the terms' rounding."""
    z0 = np.arange(n) / n
    seg = ad.Segments.from_arrays([0, n], z0, z0 + 1.0 / n, optical_depth=np.full(n, 3.0 / n))
    ref = np.exp(-np.sum(seg.numpy()["optical_depth"]))
    got = np.asarray(ad.build("exact", seg).eval([0, 0], [2.0, 0.5]), np.float64)
    np.testing.assert_allclose(got[0], ref, rtol=1e-5)
    np.testing.assert_allclose(got[1], np.exp(-1.5), rtol=1e-5)


def test_float32_gradients_with_float64_sum(rng):
    """Reverse and forward mode through the mixed-precision sum loop (float32 terms,
    float64 accumulator): dT/dtau_i = -T f_i, compared with the float64 reference's
    analytic value (rtol 1e-5: float32 T and f)."""
    import drjit as dr
    from avsm_dr import backend
    Float = backend.types().Float
    case = random_segments(rng, texels=6, max_count=12, opaque_fraction=0.0)
    t = Float(case["tau"].astype(np.float32))
    dr.enable_grad(t)
    seg = ad.Segments.from_arrays(case["offsets"], case["z0"], case["z1"], optical_depth=t)
    h = seg.numpy()
    tex = np.repeat(np.arange(6), 5)
    depth = rng.uniform(0, 1, tex.size)
    T = ad.build("exact", seg).eval(tex, depth)
    dr.backward(dr.sum(T))
    g = dr.grad(t).numpy()
    ref = np.zeros(h["optical_depth"].size)
    for tx, d in zip(tex, depth):
        s = slice(h["offsets"][tx], h["offsets"][tx + 1])
        Tk = exact_ref.transmittance(h["z0"][s], h["z1"][s], h["optical_depth"][s], d)
        for i in range(s.start, s.stop):
            a, b = h["z0"][i], h["z1"][i]
            f = 1.0 if d >= b else (0.0 if d <= a else (d - a) / (b - a))
            ref[i] -= Tk * f
    np.testing.assert_allclose(g, ref, rtol=1e-5, atol=1e-7)
    assert np.abs(ref).max() > 0.1
