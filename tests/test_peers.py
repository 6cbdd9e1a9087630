"""Benchmark peers run the same algorithms as our kernels.

The Numba peers (Numba: in the ``test`` and ``bench`` extras) are checked against the
Dr.Jit kernels in float64; these tests need Numba (absent, they fail rather than skip),
and one proves that the modules import without it.  Tolerances:
* AVSM node depths bit-identical (depths are only copied, never computed); node values
  and lookups to 1e-13 (products of <= ~1200 factors each rounded to 1.1e-16; Dr.Jit may
  contract a multiply-add where Numba does not).
* FOM coefficients to 1e-13 x 2 sum(tau) of the texel (|a'_k| <= 2 sum tau; different
  sin/cos: Dr.Jit's polynomial per harmonic vs libm + angle-addition recurrence, a few
  ulp each); transmittance to 1e-10 (exp of an optical depth wrong by <= 1e-13 x 2e4
  for opaque texels, where T is 0 anyway).
The Warp peers (warp-lang, also in both extras; absent, these tests fail too) run the
Numba peers' float64 expressions in the same order: AVSM node depths equal to Numba's and
the kernel's, values and lookups to the same 1e-13 (Warp's Clang may contract a
multiply-add where Numba's LLVM does not); FOM coefficients within the bound above of
the kernel's, lookups to 1e-10 as above.
"""
import csv
import json

import numpy as np
import pytest

import avsm_dr as ad
from experiments.bench.peer_kernels import numba_avsm, numba_fom, numpy_avsm, warp_avsm, warp_fom
from cases import random_segments, to_segments


def adversarial(rng, texels=120):
    """Random overlapping, zero-length and opaque segments, empty texels, and one texel
    with 1200 segments."""
    case = random_segments(rng, texels=texels, max_count=30)
    n_big = 1200
    z0 = rng.uniform(0, 0.9, n_big)
    big = dict(z0=z0, z1=z0 + rng.uniform(0, 0.1, n_big), tau=rng.exponential(0.01, n_big))
    counts = np.diff(case["offsets"])
    offsets = np.concatenate([[0], np.cumsum(np.append(counts, n_big))]).astype(np.int64)
    return to_segments(dict(offsets=offsets, **{k: np.concatenate([case[k], big[k]])
                                                for k in ("z0", "z1", "tau")}), "float64")


def test_peers_import_without_numba(monkeypatch):
    """Importing needs no Numba; calling without it raises an ImportError naming the extra."""
    for mod in (numba_avsm, numba_fom):
        monkeypatch.setattr(mod, "numba", None)
        monkeypatch.setattr(mod, "_KERNELS", {})
        assert not mod.available()
    with pytest.raises(ImportError, match="bench"):
        numba_avsm.build([0, 1], [0.1], [0.2], [0.5], 4, 1.0)
    with pytest.raises(ImportError, match="bench"):
        numba_fom.build([0, 1], [0.1], [0.2], [0.5], 2, 0.0, 1.0)


def test_warp_peers_import_without_warp(monkeypatch):
    """Importing needs no Warp; calling without it raises an ImportError naming the extra."""
    for mod in (warp_avsm, warp_fom):
        monkeypatch.setattr(mod, "wp", None)
        monkeypatch.setattr(mod, "_KERNELS", {})
        assert not mod.available()
    with pytest.raises(ImportError, match="bench"):
        warp_avsm.build([0, 1], [0.1], [0.2], [0.5], 4, 1.0)
    with pytest.raises(ImportError, match="bench"):
        warp_fom.build([0, 1], [0.1], [0.2], [0.5], 2, 0.0, 1.0)


def test_warp_peers_refuse_bad_arguments():
    with pytest.raises(ValueError, match="nodes"):
        warp_avsm.build([0, 1], [0.1], [0.2], [0.5], 1, 1.0)
    with pytest.raises(ValueError, match="harmonics"):
        warp_fom.build([0, 1], [0.1], [0.2], [0.5], 0, 0.0, 1.0)
    with pytest.raises(ValueError, match="texel"):          # Warp's loop counters are 32-bit
        warp_avsm.lookup(np.ones((1, 2)), np.ones((1, 2)), [2 ** 31], [0.5])


@pytest.mark.parametrize("nodes", [2, 3, 8])
@pytest.mark.parametrize("sort", [False, True])
def test_warp_avsm_matches_kernel_and_numba(rng, nodes, sort):
    seg = adversarial(rng)
    rep = ad.build("avsm", seg, nodes=nodes, sort=sort)
    h = (seg.sorted() if sort else seg).numpy()
    args = (h["offsets"], h["z0"], h["z1"], h["optical_depth"], nodes, rep.params["far"])
    D, V, used, stats = warp_avsm.build(*args, sort=sort)
    Dn, Vn, used_n, stats_n = numba_avsm.build(*args, sort=sort)
    Dk, Vk = rep.nodes_numpy()
    np.testing.assert_array_equal(D, Dk)
    np.testing.assert_array_equal(D, Dn)
    np.testing.assert_allclose(V, Vk, rtol=0, atol=1e-13)
    np.testing.assert_allclose(V, Vn, rtol=0, atol=1e-13)
    np.testing.assert_array_equal(used, rep.used)
    assert stats == stats_n == {"skipped": rep.stats["skipped"], "compressed": rep.stats["compressed"]}
    assert stats["compressed"] > 0 and stats["skipped"] > 0       # both paths exercised
    tex = rng.integers(0, seg.n_texels, 3000)
    depth = np.concatenate([rng.uniform(-0.2, 1.2, 2000), D[tex[2000:], rng.integers(0, nodes, 1000)]])
    got = warp_avsm.lookup(D, V, tex, depth)
    np.testing.assert_allclose(got, numba_avsm.lookup(Dn, Vn, tex, depth), rtol=0, atol=1e-13)
    np.testing.assert_allclose(got, np.asarray(rep.eval(tex, depth)), rtol=0, atol=1e-13)


@pytest.mark.parametrize("harmonics", [1, 8])
@pytest.mark.parametrize("margin", [None, 0.3])
def test_warp_fom_matches_kernel_and_numba(rng, harmonics, margin):
    seg = adversarial(rng)
    lo, hi = seg.bounds()
    kw = {} if margin is None else dict(near=lo - margin, far=hi + margin)
    rep = ad.build("fom", seg, harmonics=harmonics, **kw)
    h = seg.numpy()
    args = (h["offsets"], h["z0"], h["z1"], h["optical_depth"], harmonics, rep.near, rep.far)
    C, Cn = warp_fom.build(*args), numba_fom.build(*args)
    Ck = np.stack([np.asarray(c) for c in rep.coefficients], axis=1)
    scale = 2 * np.add.reduceat(np.append(h["optical_depth"], 0), h["offsets"][:-1])
    scale[np.diff(h["offsets"]) == 0] = 0
    for ref in (Ck, Cn):
        assert np.all(np.abs(C - ref) <= 1e-13 * scale[:, None] + 1e-15)
    tex = rng.integers(0, seg.n_texels, 3000)
    depth = rng.uniform(-0.2, 1.2, 3000)
    got = warp_fom.lookup(C, rep.near, rep.far, tex, depth)
    np.testing.assert_allclose(got, numba_fom.lookup(Cn, rep.near, rep.far, tex, depth), rtol=0, atol=1e-10)
    np.testing.assert_allclose(got, np.asarray(rep.eval(tex, depth)), rtol=0, atol=1e-10)


@pytest.mark.parametrize("nodes", [2, 3, 8])
@pytest.mark.parametrize("sort", [False, True])
def test_numba_avsm_matches_kernel(rng, nodes, sort):
    seg = adversarial(rng)
    rep = ad.build("avsm", seg, nodes=nodes, sort=sort)
    h = (seg.sorted() if sort else seg).numpy()
    D, V, used, stats = numba_avsm.build(h["offsets"], h["z0"], h["z1"], h["optical_depth"], nodes,
                                         rep.params["far"], sort=sort)
    Dk, Vk = rep.nodes_numpy()
    np.testing.assert_array_equal(D, Dk)
    np.testing.assert_allclose(V, Vk, rtol=0, atol=1e-13)
    np.testing.assert_array_equal(used, rep.used)
    assert stats == {"skipped": rep.stats["skipped"], "compressed": rep.stats["compressed"]}
    assert stats["compressed"] > 0 and stats["skipped"] > 0       # both paths exercised
    tex = rng.integers(0, seg.n_texels, 3000)
    depth = np.concatenate([rng.uniform(-0.2, 1.2, 2000), D[tex[2000:], rng.integers(0, nodes, 1000)]])
    np.testing.assert_allclose(numba_avsm.lookup(D, V, tex, depth), np.asarray(rep.eval(tex, depth)),
                               rtol=0, atol=1e-13)


def test_numba_avsm_matches_numpy_peer(rng):
    """Both peers of the benchmark compute the same nodes (unsorted insertion)."""
    h = adversarial(rng, texels=60).numpy()
    far = float(h["z1"].max())
    D, V, _, _ = numba_avsm.build(h["offsets"], h["z0"], h["z1"], h["optical_depth"], 6, far)
    Dn, Vn = numpy_avsm.build(h["offsets"], h["z0"], h["z1"], h["optical_depth"], 6, far)
    np.testing.assert_array_equal(D, Dn)
    np.testing.assert_allclose(V, Vn, rtol=0, atol=1e-13)


@pytest.mark.parametrize("harmonics", [1, 4, 8])
@pytest.mark.parametrize("margin", [None, 0.3])
def test_numba_fom_matches_kernel(rng, harmonics, margin):
    """Global range from the segments, and an explicit range wider than the content (a range
    that cuts the content is refused: tests/test_depth_range.py)."""
    seg = adversarial(rng)
    lo, hi = seg.bounds()
    kw = {} if margin is None else dict(near=lo - margin, far=hi + margin)
    rep = ad.build("fom", seg, harmonics=harmonics, **kw)
    h = seg.numpy()
    C = numba_fom.build(h["offsets"], h["z0"], h["z1"], h["optical_depth"], harmonics, rep.near, rep.far)
    Ck = np.stack([np.asarray(c) for c in rep.coefficients], axis=1)
    scale = 2 * np.add.reduceat(np.append(h["optical_depth"], 0), h["offsets"][:-1])
    scale[np.diff(h["offsets"]) == 0] = 0
    assert np.all(np.abs(C - Ck) <= 1e-13 * scale[:, None] + 1e-15)
    tex = rng.integers(0, seg.n_texels, 3000)
    depth = rng.uniform(-0.2, 1.2, 3000)
    np.testing.assert_allclose(numba_fom.lookup(C, rep.near, rep.far, tex, depth),
                               np.asarray(rep.eval(tex, depth)), rtol=0, atol=1e-10)


@pytest.mark.parametrize("sort", [False, True])
def test_avsm_ablations_compute_the_same_nodes(rng, sort):
    """The benchmark's ablations (AVSM's private ``_compact`` / ``_group`` / ``_split``
    switches: work skipping switched off piece by piece) give exactly the nodes, node
    counts and counters of the default kernel, so their timings compare like with like."""
    seg = to_segments(random_segments(rng, texels=200, max_count=12, empty_fraction=0.5), "float32")
    rep = ad.build("avsm", seg, nodes=4, sort=sort)
    Dk, Vk = rep.nodes_numpy()
    assert rep.stats["compressed"] > 0 and rep.stats["lanes"] < seg.n_texels    # both skips exercised
    for flags in [dict(_compact=False), dict(_group=False), dict(_split=False),
                  dict(_compact=False, _group=False, _split=False)]:
        abl = ad.build("avsm", seg, nodes=4, sort=sort, **flags)
        D, V = abl.nodes_numpy()
        np.testing.assert_array_equal(D, Dk)
        np.testing.assert_array_equal(V, Vk)
        np.testing.assert_array_equal(abl.used, rep.used)
        assert {k: abl.stats[k] for k in ("skipped", "compressed")} == \
            {k: rep.stats[k] for k in ("skipped", "compressed")}
        assert abl.params == rep.params                   # private switches stay out of params
    assert ad.build("avsm", seg, nodes=4, _compact=False).stats["lanes"] == seg.n_texels
    with pytest.raises(ValueError, match="_split"):
        ad.build("avsm", seg, _split=1)


@pytest.mark.slow
def test_bench_quick_writes_its_tables(tmp_path):
    """``python -m experiments bench --quick`` end to end (about a minute on 2 shared cores)."""
    from experiments import bench
    out = bench.run(quick=True, out=tmp_path, force=True)
    for name in ("data.csv", "peers.csv", "scaling.csv", "skipping.csv", "memory.csv", "scenes.csv",
                 "meta.json", "throughput.png", "scaling.png", "machine.csv"):
        assert (tmp_path / name).exists(), name
    assert out["summary"]["avsm8_insertions_per_cpu_s"] > 0
    kinds = json.loads((tmp_path / "machine.json").read_text())["kinds"]
    assert {k for k in ad.kinds()} <= {name.split("-")[0] for name in kinds}
    assert kinds["avsm-nodes=8"]["fraction_of_limit"] > 0
    machine_rows = list(csv.DictReader(open(tmp_path / "machine.csv")))
    assert any(r["setting"] == "avsm-nodes=8" and float(r["fraction_of_limit"]) > 0 for r in machine_rows)


def test_kernel_ops_reads_the_per_segment_loop_or_the_whole_kernel():
    """``machine.kernel_ops`` (the per-kind operation counts of ``machine.json``): for AVSM the
    loop with the most operations is its compress loop (the count the AVSM limit uses); FOM's
    and moments' projections loop over each texel's segments (``fom_project``,
    ``basis_project``); for a kernel without a loop (a plain elementwise one) every vector
    operation of the kernel is counted."""
    import drjit as dr
    from avsm_dr.evaluation.timing import jit_kernels
    from experiments.bench import machine
    from experiments.bench.settings import counts_map
    seg = counts_map(8, 10)
    irs = {}
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        for kind, p in (("avsm", {"nodes": 4}), ("fom", {"harmonics": 4}), ("moments", {})):
            dr.kernel_history()
            ad.build(kind, seg, **p)
            irs[kind] = [k["ir"].getvalue() for k in jit_kernels(dr.kernel_history()) if "ir" in k]
        dr.kernel_history()
        x = seg.z0 * 1.5 + seg.z1
        dr.eval(dr.exp(-x * seg.optical_depth) * dr.sin(x) + dr.sqrt(x * x + 1) / (x + 2))
        irs["plain"] = [k["ir"].getvalue() for k in jit_kernels(dr.kernel_history()) if "ir" in k]
    ir = next(s for s in irs["avsm"] if "avsm_compress" in s)
    ops, width, loop = machine.kernel_ops(ir)
    assert loop == "avsm_compress" and width >= 4
    assert ops == machine.loop_ops(ir, "avsm_compress")[0]
    assert "fom_project" in [machine.kernel_ops(s)[2] for s in irs["fom"]]
    assert "basis_project" in [machine.kernel_ops(s)[2] for s in irs["moments"]]
    counted = [machine.kernel_ops(s) for s in irs["plain"]]
    assert all(lab == "" for _, _, lab in counted) and max(sum(o.values()) for o, _, _ in counted) > 10


def test_memory_table_has_every_kind():
    """The bench's memory table holds every registered kind (offline ones only on maps they run on)."""
    from experiments.bench import memory
    assert {k for k, _ in memory.memory_settings(10_000)} == set(ad.kinds())
    assert {k for k, _ in memory.memory_settings(6_553_600)} == {k for k in ad.kinds() if not ad.describe(k)["offline"]}
    assert ("avsm", {"nodes": 8, "sort": True}) in memory.memory_settings(6_553_600)
