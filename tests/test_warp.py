"""The learnable depth warp (avsm_dr/warp.py) against the float64 NumPy reference
(tests/reference/warp_ref.py): warp values, warped segments, invariance of the exact
curve, identity warp = no warp for the linear kinds, gradients w.r.t. the warp's logits."""
from __future__ import annotations

import numpy as np
import pytest

import avsm_dr as ad
import drjit as dr
from avsm_dr.checks import check_gradients
from experiments.learned_warp.depth_warp import DepthWarp, log_values

from cases import random_segments, to_segments
from reference import warp_ref

LINEAR = [("fom", {"harmonics": 3}), ("osm", {"slices": 8}), ("moments", {})]


def _case(seed=0, texels=24, depth_range=(0.2, 1.4)):
    rng = np.random.default_rng(seed)
    c = random_segments(rng, texels=texels, max_count=8, opaque_fraction=0.0, depth_range=depth_range)
    c["optical_depth"] = c["tau"]
    return c


def _receivers(case, rng, per=12, pad=0.1):
    T = len(case["offsets"]) - 1
    tex = np.repeat(np.arange(T), per)
    lo, hi = case["z0"].min(), case["z1"].max()
    return tex, rng.uniform(lo - pad, hi + pad, tex.size)


def test_warp_values_match_reference(backend):
    """w(z) inside, at and beyond [near, far] equals the float64 reference to 1e-13
    (same formula, other order of float64 operations); knots go 0 .. 1 increasing."""
    rng = np.random.default_rng(1)
    theta = rng.normal(size=11)
    w = DepthWarp(0.3, 1.7, theta=theta, dtype="float64")
    z = np.r_[rng.uniform(0.0, 2.0, 200), 0.3 + np.arange(12) * 1.4 / 11]
    np.testing.assert_allclose(np.asarray(w(z)), warp_ref.warp(z, 0.3, 1.7, theta), rtol=0, atol=1e-13)
    v = w.knot_values()
    assert v[0] == 0 and abs(v[-1] - 1) < 1e-15 and np.all(np.diff(v) > 0)
    ident = DepthWarp(0.3, 1.7, knots=7, dtype="float64")
    np.testing.assert_allclose(np.asarray(ident(z)), (z - 0.3) / 1.4, rtol=0, atol=1e-14)


def test_warped_segments_match_reference(backend):
    """Pieces, their warped depths and optical depths equal the reference's (1e-13); the
    total optical depth per texel is preserved (float64 sums: 1e-12 relative)."""
    c = _case(2)
    near, far = c["z0"].min(), c["z1"].max()
    theta = np.random.default_rng(3).normal(size=9)
    seg = to_segments(c, "float64")
    ws = DepthWarp.for_segments(seg, theta=theta).segments(seg)
    ref = warp_ref.warp_segments(c, near, far, theta)
    got = ws.numpy()
    np.testing.assert_array_equal(got["offsets"], ref["offsets"])
    for k in ("z0", "z1", "optical_depth"):
        np.testing.assert_allclose(got[k], ref[k], rtol=1e-13, atol=1e-13, err_msg=k)
    assert ws.n_segments > seg.n_segments                        # knots were crossed
    tex_w = np.repeat(np.arange(ws.n_texels), ws.counts)
    tex_s = np.repeat(np.arange(seg.n_texels), seg.counts)
    np.testing.assert_allclose(np.bincount(tex_w, got["optical_depth"], seg.n_texels),
                               np.bincount(tex_s, c["optical_depth"], seg.n_texels), rtol=1e-12)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_exact_curve_is_invariant_under_any_warp(backend, dtype):
    """T_exact of the warped segments at w(z) equals T_exact at z for random warps, also
    outside [near, far] (the warp is strictly increasing everywhere).  Tolerance: float64
    1e-12.  float32: warped depths (~1) are rounded to ~eps = 6e-8 absolute, a depth error
    of eps h / d_min in z where the warp is flattest (slope d_min / h), so T may move by
    |dT/dz| times a few of those (|dT/dz| from the reference), plus 2e-6 for T itself."""
    c = _case(4)
    rng = np.random.default_rng(5)
    seg = to_segments(c, dtype)
    tex, z = _receivers(c, rng)
    want = warp_ref.exact(c, tex, z)
    T0 = np.asarray(ad.build("exact", seg).eval(tex, z), np.float64)
    np.testing.assert_allclose(T0, want, rtol=0, atol=1e-12 if dtype == "float64" else 2e-6)
    dz = 1e-7
    slope = np.abs(warp_ref.exact(c, tex, z + dz) - warp_ref.exact(c, tex, z - dz)) / (2 * dz)
    for knots in (1, 5, 16):
        theta = rng.normal(scale=1.5, size=knots)
        w = DepthWarp.for_segments(seg, theta=theta)
        Tw = np.asarray(ad.build("exact", w.segments(seg)).eval(tex, w(z)), np.float64)
        if dtype == "float64":
            tol = 1e-12
        else:
            d_min = np.diff(warp_ref.knot_values(theta)).min()
            tol = 2e-6 + 4 * 6e-8 * (w.h / d_min) * slope
        assert np.all(np.abs(Tw - want) <= tol), np.max(np.abs(Tw - want) / tol)


@pytest.mark.parametrize("kind,params", LINEAR, ids=[k for k, _ in LINEAR])
def test_identity_warp_reproduces_the_unwarped_kind(backend, kind, params):
    """The identity warp on [near, far] = the global bounds, built with near=0, far=1,
    gives the unwarped kind's T to float64 rounding: 1e-10 (the linear coefficients are
    sums over split pieces instead of whole segments; the moments' Hankel solve amplifies
    the rounding, hence 1e-7 there)."""
    c = _case(6)
    seg = to_segments(c, "float64")
    tex, z = _receivers(c, np.random.default_rng(7))
    w = DepthWarp.for_segments(seg, knots=8)
    T0 = np.asarray(ad.build(kind, seg, **params).eval(tex, z))
    Tw = np.asarray(ad.build(kind, w.segments(seg), near=0.0, far=1.0, **params).eval(tex, w(z)))
    np.testing.assert_allclose(Tw, T0, rtol=0, atol=1e-7 if kind == "moments" else 1e-10)


def test_a_warp_changes_the_linear_kinds():
    """A non-identity warp changes OSM's T (resolution moved), so the tests above could fail."""
    c = _case(6)
    seg = to_segments(c, "float64")
    tex, z = _receivers(c, np.random.default_rng(7))
    w = DepthWarp.for_segments(seg, theta=DepthWarp.logits_for(log_values(8, 50.0)))
    T0 = np.asarray(ad.build("osm", seg, slices=8).eval(tex, z))
    Tw = np.asarray(ad.build("osm", w.segments(seg), slices=8, near=0.0, far=1.0).eval(tex, w(z)))
    assert np.abs(Tw - T0).max() > 1e-3


@pytest.mark.parametrize("kind,params", LINEAR, ids=[k for k, _ in LINEAR])
def test_gradient_wrt_warp_logits(backend, kind, params):
    """d(sum of squared T errors)/d theta in reverse mode matches central differences of
    the same float64 loss (eps 1e-6: truncation ~1e-12, cancellation ~1e-10 relative) and
    forward mode; the structure of the pieces does not depend on theta, so the loss is
    smooth in theta except where a receiver crosses an OSM slice boundary (then |g - fd|
    would be O(1); not met at this seed)."""
    c = _case(8, texels=10)
    seg = to_segments(c, "float64")
    tex, z = _receivers(c, np.random.default_rng(9), per=6, pad=0.0)
    target = warp_ref.exact(c, tex, z)
    Float = ad.backend.types().Float64
    theta0 = np.random.default_rng(10).normal(scale=0.3, size=6)

    def loss(theta):
        w = DepthWarp.for_segments(seg, theta=theta)
        T = ad.build(kind, w.segments(seg), near=0.0, far=1.0, **params).eval(tex, w(z))
        return dr.sum(dr.square(T - Float(target)))

    res = check_gradients(loss, Float(theta0), fd=6, eps=1e-6, fd_rtol=1e-5, fd_atol=1e-8, rtol=1e-8)
    assert res.ok, str(res)
    assert np.abs(res.gradient).max() > 1e-4                    # the warp does matter


def test_logits_for_round_trip():
    """logits_for(values) gives a warp with those knot values (float64: 1e-15)."""
    v = log_values(10, 30.0)
    w = DepthWarp(0.0, 1.0, theta=DepthWarp.logits_for(v), dtype="float64")
    np.testing.assert_allclose(w.knot_values(), v, rtol=0, atol=1e-15)


@pytest.mark.parametrize("call,name", [
    (lambda: DepthWarp(1.0, 1.0, knots=4), "far"),
    (lambda: DepthWarp(float("nan"), 1.0, knots=4), "near"),
    (lambda: DepthWarp(0.0, 1.0), "theta"),
    (lambda: DepthWarp(0.0, 1.0, knots=0), "knots"),
    (lambda: DepthWarp(0.0, 1.0, theta=[0.0, np.inf]), "theta"),
    (lambda: DepthWarp(0.0, 1.0, theta=np.zeros((2, 2))), "theta"),
    (lambda: DepthWarp(0.0, 1.0, theta=[0.0, 1.0], knots=3), "knots"),
    (lambda: DepthWarp(0.0, 1.0, knots=2, dtype="float16"), "dtype"),
    (lambda: DepthWarp(0.0, 1.0, knots=2)(np.zeros((2, 2))), "z"),
    (lambda: DepthWarp(0.0, 1.0, knots=2)([np.nan]), "z"),
    (lambda: DepthWarp(0.0, 1.0, knots=2).segments("x"), "seg"),
    (lambda: DepthWarp.for_segments(None, knots=2), "seg"),
    (lambda: DepthWarp.logits_for([0.0, 0.5, 0.4, 1.0]), "values"),
    (lambda: log_values(4, 1.0), "ratio"),
])
def test_bad_input_names_the_argument(call, name):
    with pytest.raises(ValueError, match=f"^{name}:"):
        call()


def test_dtype_mismatch_is_refused():
    seg = to_segments(_case(0), "float64")
    with pytest.raises(ValueError, match="^seg:"):
        DepthWarp(0.0, 1.0, knots=2).segments(seg)
