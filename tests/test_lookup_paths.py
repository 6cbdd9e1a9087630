"""Lookup fast paths: node-list kinds read a texel's nodes with one
packet gather from a row-per-texel copy, and point lookups of plain NumPy input are
checked by their extremes on the host and run as one launch.  Both must give the values
of the general paths bit for bit (and the same ValueError where those raise)."""
from __future__ import annotations

import numpy as np
import pytest

import avsm_dr as ad
import drjit as dr
from avsm_dr import _device_checks as DC
from avsm_dr.representations.avsm import NodeList
from experiments.bench.synthetic import random_map


def _general(rep, tex, depth, monkeypatch):
    """T (or the ValueError text) of the general paths: per-array gathers, checked lookup."""
    with monkeypatch.context() as m:
        m.setattr(NodeList, "_node_rows", lambda self: None)
        m.setattr(DC, "host_point_lookup", lambda *a: None)
        return _lookup(rep, tex, depth)


def _lookup(rep, tex, depth):
    try:
        return np.asarray(rep.eval(tex, depth))
    except ValueError as exc:
        return str(exc)


def _same(a, b) -> bool:
    if isinstance(a, str) or isinstance(b, str):
        return a == b
    return a.dtype == b.dtype and np.array_equal(a.view(np.uint8), b.view(np.uint8))


def _receivers(rng, rep, k=3000):
    """Random texels; depths around the range and exactly at / next to stored node depths."""
    d, _ = rep.nodes_numpy()
    tex = rng.integers(0, rep.n_texels, k)
    at = d[tex, rng.integers(0, d.shape[1], k)].astype(np.float32)
    sel = rng.integers(0, 4, k)
    depth = np.select([sel == 0, sel == 1, sel == 2],
                      [at, np.nextafter(at, np.float32(np.inf)), np.nextafter(at, np.float32(-np.inf))],
                      rng.uniform(-0.2, 1.2, k))
    return tex, depth.astype(np.float64)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("kind, params", [("avsm", {"nodes": 2}), ("avsm", {"nodes": 5}), ("avsm", {"nodes": 8}),
                                          ("avsm", {"nodes": 8, "interpolation": "exp"}),
                                          ("avsm", {"nodes": 4, "precision": "unorm8"}), ("greedy", {"nodes": 6})])
def test_node_rows_give_the_per_array_lookup(backend, rng, monkeypatch, dtype, kind, params):
    """Same floats from another layout, same arithmetic: equal bit for bit (also empty texels)."""
    seg = random_map(150, 0, 25, seed=4, dtype=dtype, empty_fraction=0.2, mean_tau=0.3)
    rep = ad.build(kind, seg, **params)
    tex, depth = _receivers(rng, rep)
    fast = _lookup(rep, tex, depth)
    assert rep._node_rows() is not None
    assert _same(fast, _general(rep, tex, depth, monkeypatch))


def test_node_rows_follow_the_node_lists(backend, rng):
    """The row copy is rebuilt when ``depths`` / ``values`` are replaced or scattered into."""
    rep = ad.build("avsm", random_map(64, 1, 20, seed=2), nodes=4)
    tex, depth = _receivers(rng, rep)
    before = np.asarray(rep.eval(tex, depth))
    d0 = rep.nodes_numpy()[0][tex, 0]
    front = depth.astype(np.float32) < d0                       # T = 1 in front of the first node
    rep.values = [v * 0.5 for v in rep.values]                  # a new list: halved T (exact) behind
    np.testing.assert_array_equal(np.asarray(rep.eval(tex, depth)), np.where(front, 1.0, before * 0.5))
    Float, UInt32 = rep.Float, ad.backend.types().UInt32
    for v in rep.values:                                        # in place: same list, same objects
        dr.scatter(v, Float(0.0), dr.arange(UInt32, rep.n_texels))
    np.testing.assert_array_equal(np.asarray(rep.eval(tex, depth)), np.where(front, 1.0, 0.0))


def test_node_rows_are_not_used_with_gradients(backend, rng):
    """Node lists carrying gradients are gathered as they are (the AD graph of the build;
    gradients themselves: tests/test_representations.py)."""
    seg = random_map(32, 1, 10, seed=3)
    tau = seg.optical_depth
    dr.enable_grad(tau)
    rep = ad.build("avsm", ad.Segments(seg.offsets, seg.z0, seg.z1, tau, seg.dtype), nodes=4)
    assert rep._node_rows() is None
    tex, depth = _receivers(rng, rep, 200)
    assert dr.grad_enabled(rep.eval(tex, depth))


def test_numpy_point_lookup_equals_the_checked_path(backend, rng, monkeypatch):
    """Every index / depth dtype, broadcasting, and depths the extremes refuse (zero,
    subnormal, the smallest normal number, mixed signs, NaN, overflow, bad texels): same T,
    or the same ValueError, as the checked path; the fast path declines what it must."""
    rep = ad.build("avsm", random_map(100, 0, 20, seed=6), nodes=4)
    tex, depth = _receivers(rng, rep, 500)
    pos = np.abs(depth) + 1e-3
    tiny = float(np.finfo(np.float32).tiny)
    one = rng.integers(0, 6, tex.size) == 0
    taken = [(tex, pos), (tex.astype(np.int32), pos), (tex.astype(np.uint32), pos.astype(np.float32)),
             (tex.astype(np.uint64), -pos), (tex[:1], pos), (tex, pos[:1]), (tex, np.where(one, tiny * 1.0001, pos)),
             (tex[::2], pos[1::2])]
    declined = [(tex, np.where(one, 0.0, pos)), (tex, np.where(one, 1e-40, pos)), (tex, np.where(one, tiny, pos)),
                (tex, depth), (tex, np.where(one, np.nan, pos)), (tex, np.where(one, 1e39, pos)),
                (np.where(one, rep.n_texels, tex), pos), (np.where(one, -1, tex), pos), (tex.astype(np.int16), pos),
                (tex.astype(np.float64), pos), (tex, pos[:7]), (tex, pos.astype(">f8"))]
    for i, (t, d) in enumerate(taken + declined):
        fast = DC.host_point_lookup(rep._eval_texels, t, d, rep.n_texels, "float32", rep.Float)
        assert (fast is not None) == (i < len(taken)), i
        assert _same(_lookup(rep, t, d), _general(rep, t, d, monkeypatch)), i


def test_numpy_point_lookup_is_one_launch(backend, rng):
    """A plain NumPy point lookup runs one kernel: no device flag, reduction or readback."""
    rep = ad.build("avsm", random_map(100, 0, 20, seed=6), nodes=8)
    tex, depth = rng.integers(0, rep.n_texels, 5000), rng.uniform(0.01, 1.0, 5000)
    rep.eval(tex, depth)
    dr.kernel_history_clear()
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.eval(rep.eval(tex, depth))
        kinds = [k["type"] for k in dr.kernel_history()]
    assert kinds == [dr.KernelType.JIT]


def _split_reference(coords, width, height, shift, margin):
    """NumPy reference of the filters' coordinate split: float64 ``x = c - shift`` (subnormals as
    0), texel ``floor(x)`` clamped to [-margin - 1, size + margin], offset ``x - floor(x)``."""
    out = []
    for c, size in ((0, width), (1, height)):
        x = coords[:, c] - shift
        x = np.where(np.abs(x) < np.finfo(np.float64).tiny, 0.0, x)
        f = np.floor(x)
        out.append((np.clip(f, -margin - 1, size + margin).astype(np.int64), x - f))
    return out[0][0], out[1][0], out[0][1], out[1][1]


@pytest.mark.parametrize("shift, margin", [(0.0, 0), (0.5, 1), (0.0, 3)])
def test_filter_taps_split_on_the_device_equal_the_numpy_split(shift, margin):
    """The point, bilinear, box and gaussian lookups split coordinates on the device: the same
    float64 floor and subtraction as a NumPy reference, so the same texels and offsets bit for bit,
    on coordinates inside, on the edges of and far outside the map, and subnormal ones."""
    from avsm_dr.filtering import split_on_device
    rng = np.random.default_rng(7)
    w, h = 37, 21
    coords = np.concatenate([rng.uniform(-3, 40, (4000, 2)), rng.uniform(-1e12, 1e12, (64, 2)),
                             [[0, 0], [w, h], [w - 1e-9, h - 1e-9], [0.5, 0.5], [-0.5, -0.5], [2.0 ** 31, -2.0 ** 31]],
                             np.nextafter(np.arange(8.0)[:, None].repeat(2, 1), -1)])
    want = _split_reference(coords, w, h, shift, margin)
    got = split_on_device(coords, w, h, shift, margin=margin)
    for a, b in zip(want, got):
        np.testing.assert_array_equal(np.asarray(b).astype(a.dtype), a)
