"""One :class:`~avsm_dr.Segments` reused across ``dr.backward`` calls.

``dr.backward`` frees the graph edges it traverses; a Segments array derived from the caller's
grad-enabled leaf (a clamp, a cast, ``-ln`` of a transmittance, a sorted gather) used to be such
an interior node, so a second build from the same Segments got all-zero gradients.  Every
differentiable configuration of the registry runs two build + backward rounds on one Segments
and is compared against a fresh Segments and against central differences of one element.

Tolerances: float64 throughout.  Reused vs fresh: the same arithmetic, but reverse-mode
scatter-adds may sum in another order, rtol 1e-12.  Central differences (eps = 1e-6, depths and
layouts as in test_representations._fd_check): truncation O(eps^2) plus cancellation
~1e-16 / eps, 1e-6 absolute.
"""
import re
from pathlib import Path

import numpy as np
import pytest

import avsm_dr as ad
import drjit as dr
from avsm_dr import backend
from cases import case_id, random_segments, representations

PROBE = ad.Segments.from_arrays([0, 1], [0.2], [0.4], optical_depth=[0.5])
DIFFERENTIABLE = [c for c in representations() if ad.build(c[0], PROBE, **c[1]).differentiable]
#: how the reused Segments is made from the leaf (the leaf is tau, or exp(-tau) for transmittance)
SOURCES = ("optical_depth", "transmittance", "clamped", "sorted", "selected")
TEXELS = 12


def _data():
    rng = np.random.default_rng(21)
    data = random_segments(rng, texels=TEXELS, max_count=10, opaque_fraction=0.0, zero_fraction=0.0)
    tex = np.repeat(np.arange(TEXELS), 6)
    return data, tex, rng.uniform(0, 1, tex.size), rng.normal(size=tex.size)


DATA, TEX, DEPTH, W = _data()


def _segments(leaf, source):
    """Segments from the leaf: kept itself (optical_depth), or derived from it."""
    off, z0, z1 = DATA["offsets"], DATA["z0"], DATA["z1"]
    if source == "transmittance":
        return ad.Segments.from_arrays(off, z0, z1, transmittance=leaf)
    if source == "clamped":             # one value above OPAQUE_OPTICAL_DEPTH: a clamped copy,
        return ad.Segments.from_arrays(np.r_[off, off[-1] + 1], np.r_[z0, 2.0], np.r_[z1, 2.5],
                                       optical_depth=leaf)      # (an extra texel behind all)
    seg = ad.Segments.from_arrays(off, z0, z1, optical_depth=leaf)
    if source == "sorted":
        # reversed texel order within the CSR: sorted() gathers (a permutation), then sorts
        rev = seg.select_texels(np.arange(TEXELS)[::-1])
        return rev.sorted()
    if source == "selected":
        return seg.select_texels(np.r_[np.arange(TEXELS), 3])
    return seg


def _leaf_values(source, tau):
    if source == "transmittance":
        return np.exp(-tau)
    if source == "clamped":
        return np.r_[tau, 2.0 * ad.OPAQUE_OPTICAL_DEPTH]
    return tau


def _loss(kind, params, seg):
    return dr.sum(ad.build(kind, seg, **params).eval(TEX, DEPTH) * backend.types().Float64(W))


def _rounds(kind, params, source, rounds=2):
    """Gradients w.r.t. the leaf of ``rounds`` build + backward rounds on one Segments."""
    F64 = backend.types().Float64
    leaf = F64(_leaf_values(source, DATA["tau"]))
    dr.enable_grad(leaf)
    seg = _segments(leaf, source)
    out = []
    for _ in range(rounds):
        dr.backward(_loss(kind, params, seg))
        out.append(dr.grad(leaf).numpy().copy())
        dr.clear_grad(leaf)
    return out


def _check_rounds(kind, params, source):
    """Two rounds on one Segments equal one round on a fresh one; returns the second."""
    first, second = _rounds(kind, params, source)
    fresh = _rounds(kind, params, source, rounds=1)[0]
    assert np.abs(fresh).max() > 0.05, source
    np.testing.assert_allclose(first, fresh, rtol=1e-12, atol=1e-15, err_msg=source)
    np.testing.assert_allclose(second, fresh, rtol=1e-12, atol=1e-15, err_msg=source)
    return second


@pytest.mark.parametrize("case", DIFFERENTIABLE, ids=case_id)
def test_reused_segments_keep_gradients(case):
    """Every differentiable configuration, the caller's optical depth as the leaf."""
    kind, params = case
    F64 = backend.types().Float64
    second = _check_rounds(kind, params, "optical_depth")
    if kind == "dsm":
        return      # node depths move with tau: FD crosses layouts (test_dsm checks fixed depths)
    # the reused Segments' second-round gradient against central differences of one element
    j = int(np.argmax(np.abs(second)))
    eps = 1e-6
    vals = _leaf_values("optical_depth", DATA["tau"])

    def f(x):
        return _loss(kind, params, _segments(F64(x), "optical_depth"))[0]
    tp, tm = vals.copy(), vals.copy()
    tp[j] += eps
    tm[j] -= eps
    fd = (f(tp) - f(tm)) / (2 * eps)
    assert abs(second[j] - fd) < 1e-6, (j, second[j], fd)


@pytest.mark.parametrize("source", SOURCES[1:])
@pytest.mark.parametrize("case", [("exact", {}), ("avsm", {"nodes": 4, "sort": True}), ("fom", {})], ids=case_id)
def test_derived_segments_keep_gradients(case, source):
    """Arrays Segments derives from the leaf (-ln of a transmittance, a clamp, the gathers of
    sorted() and select_texels()) are re-derived on reads: a lazy kind (exact reads the
    segments at lookup, in a loop body), a loop kind reading through depth_view, a linear one."""
    _check_rounds(*case, source)


def test_caller_array_is_kept_itself():
    """An input of the storage type that needs no change is stored as the caller's array."""
    t = backend.types()
    tau, z0, z1 = t.Float([0.5, 0.7]), t.Float([0.1, 0.35]), t.Float([0.3, 0.5])
    dr.enable_grad(tau, z0, z1)
    seg = ad.Segments.from_arrays([0, 2], z0, z1, optical_depth=tau)
    assert seg.optical_depth is tau and seg.z0 is z0 and seg.z1 is z1
    # a float64 leaf stored as float32 is a cast: derived, but still linked to the leaf
    t64 = t.Float64([0.5, 0.7])
    dr.enable_grad(t64)
    seg = ad.Segments.from_arrays([0, 2], [0.1, 0.35], [0.3, 0.5], optical_depth=t64, dtype="float32")
    grads = []
    for _ in range(2):
        dr.backward(dr.sum(ad.build("fom", seg).eval([0, 0], [0.32, 0.48])))
        grads.append(dr.grad(t64).numpy().copy())
        dr.clear_grad(t64)
    assert np.all(grads[0] != 0) and np.array_equal(grads[0], grads[1])


def test_assigned_array_replaces_the_link():
    """Assigning a field (as tests do) drops its recipe: the assigned array is read back."""
    t = backend.types()
    leaf = t.Float([0.5, 0.5])
    dr.enable_grad(leaf)
    seg = ad.Segments.from_arrays([0, 2], [0.1, 0.35], [0.3, 0.5], transmittance=leaf)
    new = t.Float([1.0, 2.0])
    seg.optical_depth = new
    assert seg.optical_depth is new and not dr.grad_enabled(seg.optical_depth)


@pytest.mark.parametrize("case", DIFFERENTIABLE, ids=case_id)
def test_segments_cache_holds_no_graph(case):
    """What builds cache on a Segments (offsets, texel map, sort plan, curve points, ...)
    carries no AD graph a backward could consume."""
    kind, params = case
    leaf = backend.types().Float64(DATA["tau"])
    dr.enable_grad(leaf)
    seg = _segments(leaf, "optical_depth").sorted()
    dr.backward(_loss(kind, params, seg))

    def walk(x):
        if isinstance(x, dict):
            return [v for y in x.values() for v in walk(y)]
        if isinstance(x, (list, tuple)):
            return [v for y in x for v in walk(y)]
        return [x] if dr.is_array_v(x) and dr.grad_enabled(x) else []
    assert walk(seg._cache) == []


def test_gradients_page_example_runs():
    """docs/gradients.md: the example of reusing a Segments across backwards."""
    page = (Path(__file__).resolve().parents[1] / "docs" / "gradients.md").read_text()
    section = page.split("## What `dr.backward` consumes", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    exec(compile(code, "docs/gradients.md", "exec"), {})
