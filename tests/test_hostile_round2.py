"""Hostile round 2: what a second round of hostile inputs found at the public
boundary (messages, refusals, crashes), one regression test each (crash cases in a subprocess)."""
from __future__ import annotations

import re
import subprocess
import sys
import textwrap

import avsm_dr as ad
import drjit as dr
import numpy as np
import pytest


def _seg():
    return ad.Segments.from_arrays([0, 1], [0.2], [0.4], optical_depth=[0.5])


# ----------------------------------------------------------------- messages: unknown names
@pytest.mark.parametrize("kind", ad.kinds())
def test_unknown_parameter_lists_public_and_base_parameters(kind):
    """The message lists the kind's public parameters and the base ones every kind takes
    (``precision``, ``reverse``, ``chunk``), never the private ablation switches."""
    with pytest.raises(ValueError, match=rf"^zzz_unknown: unknown parameter of '{kind}'; known: ") as err:
        ad.build(kind, _seg(), zzz_unknown=1)
    known = eval(re.search(r"known: (\[.*?\])", str(err.value)).group(1))
    public = [n for n in ad.describe(kind)["params"]]
    assert known == public + ["precision", "reverse", "chunk"]
    assert not any(n.startswith("_") for n in known)


def test_misspelt_parameter_and_kind_suggest_the_name():
    with pytest.raises(ValueError, match=r"^nodez: unknown parameter of 'avsm'; known: \[.*\]; "
                                         r"did you mean 'nodes'\?$"):
        ad.build("avsm", _seg(), nodez=8)
    with pytest.raises(ValueError, match=r"did you mean 'harmonics'\?$"):
        ad.build("fom", _seg(), harmonic=3)
    with pytest.raises(ValueError, match=r"^kind: unknown representation 'avms'; known: \[.*\]; "
                                         r"did you mean 'avsm'\?$"):
        ad.build("avms", _seg())
    with pytest.raises(ValueError, match=r"^kind: unknown representation 'osn'.*did you mean 'osm'\?$"):
        ad.describe("osn")
    # nothing close: no suggestion; a private switch is still accepted, never suggested
    with pytest.raises(ValueError) as err:
        ad.build("avsm", _seg(), qqqqqq=1)
    assert "did you mean" not in str(err.value)
    with pytest.raises(ValueError) as err:
        ad.build("avsm", _seg(), compact=False)
    assert "_compact" not in str(err.value)
    ad.build("avsm", _seg(), _compact=False)


def test_allows_accepts_base_parameters():
    assert ad.allows("avsm", {"nodes": 8, "reverse": "checkpoint", "chunk": 16, "precision": "float16"})
    assert not ad.allows("avsm", {"nodez": 8})


# ----------------------------------------------------------------- helpers
def run_python(code: str, timeout: float = 180) -> str:
    """Run ``code`` in a fresh interpreter (a crash fails this test, not the run)."""
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                         timeout=timeout)
    assert out.returncode == 0, f"exit {out.returncode}: {out.stderr[-2000:]}"
    return out.stdout


def _three():
    return ad.Segments.from_arrays([0, 2, 3, 3], [0.1, 0.5, 0.2], [0.3, 0.7, 0.6],
                                   optical_depth=[0.5, 1.0, 2.0])


# ----------------------------------------------------------------- crashes: Dr.Jit tensors
def test_tensor_arguments_are_not_corrupted():
    """Dr.Jit 1.5: ``Float(TensorXf(...))`` corrupts the tensor (a segfault at its next read).
    A 1-D tensor as ``depth`` (or as a segment array) used to crash the process after the
    lookup; now it is read through its flat storage and stays intact."""
    out = run_python("""
        import numpy as np
        import avsm_dr as ad
        import drjit as dr
        t = ad.backend.types()
        seg = ad.Segments.from_arrays([0, 2, 3, 3], [0.1, 0.5, 0.2], [0.3, 0.7, 0.6],
                                      optical_depth=[0.5, 1.0, 2.0])
        depth = dr.llvm.ad.TensorXf(np.array([0.4, 0.4], np.float32))
        texel = dr.llvm.ad.TensorXu(np.array([1, 0], np.uint32))
        for kind in ad.kinds():
            T = np.asarray(ad.build(kind, seg).eval(np.array([1, 0]), depth))
            T2 = np.asarray(ad.build(kind, seg).eval(texel, np.array([0.4, 0.4])))
            assert np.array_equal(T, T2), kind
        z0 = dr.llvm.ad.TensorXf(np.array([0.1, 0.5, 0.2], np.float32))
        ad.Segments.from_arrays([0, 2, 3, 3], z0, [0.3, 0.7, 0.6], optical_depth=[0.5, 1.0, 2.0])
        print(depth.numpy().tolist(), texel.numpy().tolist(), z0.numpy().tolist())
    """)
    assert out.strip().startswith("[0.4")


# ----------------------------------------------------------------- refused: non-numeric arrays
@pytest.mark.parametrize("bad", ["bool", "complex", "str", "object", "dr-Bool"])
@pytest.mark.parametrize("field", ["z0", "z1", "optical_depth", "transmittance", "offsets"])
def test_segments_refuse_non_numeric_arrays(field, bad):
    """NumPy ``astype`` turned True into 1, dropped imaginary parts and parsed '0.5': a
    boolean, complex, string or object array (or a Dr.Jit Bool) was accepted silently."""
    base = {"offsets": [0, 2, 3, 3], "z0": [0.1, 0.5, 0.2], "z1": [0.3, 0.7, 0.6],
            "optical_depth": [0.5, 1.0, 0.2], "transmittance": [0.5, 0.4, 0.2]}
    good = np.asarray(base[field], np.float64)
    value = {"bool": (good > 0.25), "complex": good + 0j, "str": good.astype(str),
             "object": good.astype(object), "dr-Bool": ad.backend.types().Bool(good > 0.25)}[bad]
    kw = dict(base, **{field: value})
    if field == "transmittance":
        kw.pop("optical_depth")
    else:
        kw.pop("transmittance")
    with pytest.raises(ValueError, match=rf"^{field}: expected a numeric \(integer or float\) array"):
        ad.Segments.from_arrays(kw.pop("offsets"), kw.pop("z0"), kw.pop("z1"), **kw)


@pytest.mark.parametrize("kind", ad.kinds())
def test_eval_refuses_non_numeric_and_nested_depths(kind):
    """Depths: bool / complex / str arrays and Dr.Jit Bool were read as numbers; a Dr.Jit
    Array3f or 2-D tensor raised a TypeError of Dr.Jit; the texel as a Dr.Jit Bool was read
    as indices 0 / 1."""
    t = ad.backend.types()
    rep = ad.build(kind, _three())
    tex = np.array([1, 0])
    for depth in (np.array([True, False]), np.array([0.4 + 1j, 0.4]), np.array(["0.4", "0.4"]),
                  t.Bool([True, False])):
        with pytest.raises(ValueError, match=r"^depth: expected a numeric \(integer or float\) array"):
            rep.eval(tex, depth)
    for depth in (dr.llvm.ad.Array3f([0.4, 0.4, 0.4]), dr.llvm.ad.TensorXf(np.ones((1, 2), np.float32))):
        with pytest.raises(ValueError, match=r"^depth: expected shape \(K,\)"):
            rep.eval(tex, depth)
    with pytest.raises(ValueError, match=r"^texel: expected a numeric \(integer or float\) array"):
        rep.eval(t.Bool([True, False]), np.array([0.4, 0.4]))
    # numeric Dr.Jit and NumPy types still read as before
    ref = np.asarray(rep.eval(tex, np.array([0.4, 0.4])))
    for depth in (t.Float64([0.4, 0.4]), [0.4, 0.4], np.array([0.4, 0.4], np.float32)):
        np.testing.assert_array_equal(np.asarray(rep.eval(tex, depth)), ref)


# ----------------------------------------------------------------- silent NaN: gaussian filter
@pytest.mark.parametrize("kind", ["exact", "avsm", "fom"])
def test_gaussian_filter_with_a_tiny_radius_is_the_point_filter(kind):
    """radius 1e-30: 1 / (2 sigma^2) overflowed float32 and inf * 0 made every weight NaN;
    the docstring's limit is the point filter (texel centres: no ties)."""
    seg = ad.Segments.from_arrays(np.arange(21), np.linspace(0.0, 0.5, 20), np.linspace(0.3, 0.8, 20),
                                  optical_depth=np.linspace(0.2, 2.0, 20))
    rep = ad.build(kind, seg)
    xy = np.array([[0.5, 0.5], [2.3, 1.6], [4.9, 3.9], [1.7, 2.2]])
    point = np.asarray(rep.eval(xy, np.full(4, 0.6), filter="point", width=5, height=4))
    for radius in (1e-30, 1e-20, 1e-12):
        got = np.asarray(rep.eval(xy, np.full(4, 0.6), filter="gaussian", width=5, height=4, radius=radius))
        np.testing.assert_array_equal(got, point)


# ----------------------------------------------------------------- silently wrong: depth scales
def _random_map(seed=5, n_tex=64, kmax=10):
    rng = np.random.default_rng(seed)
    c = rng.integers(0, kmax + 1, n_tex)
    off = np.concatenate([[0], np.cumsum(c)])
    n = int(off[-1])
    z0 = rng.random(n)
    z1 = z0 + 0.3 * rng.random(n)
    tau = rng.exponential(0.5, n)
    tex = np.repeat(np.arange(n_tex), 8)
    depth = rng.random(tex.size) * 1.6 - 0.2
    return off, z0, z1, tau, tex, depth


@pytest.mark.parametrize("kind", ["fom", "osm", "basis", "moments"])
@pytest.mark.parametrize("scale, offset", [(1e-100, 0.0), (1e-150, 0.0), (1.0, 1e7), (1.0, 1e9)])
def test_linear_kinds_in_float64_keep_any_depth_scale(kind, scale, offset):
    """One float32 span floor (1e-6 relative + 1e-30) for both dtypes widened float64
    content at depth 1e7 with span 1 (error 0.55) and any range below 1e-30 (T = 1
    everywhere) far beyond its length; float64 resolves both.  T is affine invariant in
    depth: within float64 rounding of the depths (1e9 x 2^-53 / span ~ 1e-7 relative)."""
    off, z0, z1, tau, tex, depth = _random_map()
    a = ad.build(kind, ad.Segments.from_arrays(off, z0, z1, optical_depth=tau, dtype="float64"))
    b = ad.build(kind, ad.Segments.from_arrays(off, z0 * scale + offset, z1 * scale + offset,
                                               optical_depth=tau, dtype="float64"))
    Ta = np.asarray(a.eval(tex, depth))
    Tb = np.asarray(b.eval(tex, depth * scale + offset))
    np.testing.assert_allclose(Tb, Ta, rtol=0, atol=1e-5)


@pytest.mark.parametrize("kind", [k for k in ad.kinds() if ad.describe(k)["precisions"]])
def test_precision_refuses_float64_depths_below_float32(kind):
    """float64 segments at depth scale 1e-150 with any precision code: depths and ranges
    flushed to 0 in float32 (T = 0.0044 where the exact T is 1); now refused, naming
    ``precision``.  At 1e-30 (normal in float32) the codes work as at scale 1."""
    off, z0, z1, tau, tex, depth = _random_map()
    seg = ad.Segments.from_arrays(off, z0 * 1e-150, z1 * 1e-150, optical_depth=tau, dtype="float64")
    kinds_in_u = {"fom", "osm", "basis", "moments"}          # depths normalised by a float64 range
    for p in ad.describe(kind)["precisions"]:
        if kind in kinds_in_u:
            ad.build(kind, seg, precision=p)
        else:
            with pytest.raises(ValueError, match=r"^precision: .* below float32's smallest normal number"):
                ad.build(kind, seg, precision=p)
    seg30 = ad.Segments.from_arrays(off, z0 * 1e-30, z1 * 1e-30, optical_depth=tau, dtype="float64")
    seg1 = ad.Segments.from_arrays(off, z0, z1, optical_depth=tau, dtype="float64")
    T30 = np.asarray(ad.build(kind, seg30, precision="unorm16").eval(tex, depth * 1e-30))
    T1 = np.asarray(ad.build(kind, seg1, precision="unorm16").eval(tex, depth))
    np.testing.assert_allclose(T30, T1, rtol=0, atol=1e-5)    # same codes: float rounding only


def test_beer_extent_below_float32_is_refused():
    """beer's extent (depth units, stored as a coefficient): front 0, extent 1e-150 decoded
    to a float32 subnormal scale."""
    seg = ad.Segments.from_arrays([0, 1], [0.0], [1e-150], optical_depth=[1.0], dtype="float64")
    with pytest.raises(ValueError, match=r"^precision: 'beer' stores extent values"):
        ad.build("beer", seg, precision="float16")


# ----------------------------------------------------------------- Scene.from_grid
def test_from_grid_npy_lying_or_malformed_header(tmp_path):
    """A header announcing 3.6 TiB was allocated before reading (MemoryError); a malformed
    one raised tokenize.TokenError; an object array is refused, never unpickled."""
    np.save(tmp_path / "g.npy", np.ones((8, 8, 8), np.float32))
    raw = (tmp_path / "g.npy").read_bytes()
    head = raw[:128].decode("latin1")
    lying = head.replace("(8, 8, 8)", "(9999, 9999, 9999)").rstrip("\n").rstrip(" ")
    lying = lying + " " * (127 - len(lying)) + "\n"
    (tmp_path / "lying.npy").write_bytes(lying.encode("latin1") + raw[128:])
    (tmp_path / "broken.npy").write_bytes(raw.replace(b"(8, 8, 8)", b"(9999999,"))
    (tmp_path / "short.npy").write_bytes(raw[:200])
    for name, msg in (("lying", "header announces more data"), ("short", "truncated"),
                      ("broken", "not a readable .npy file")):
        with pytest.raises(ValueError, match=rf"^grid_or_path: .*{name}\.npy.*{msg}"):
            ad.Scene.from_grid(str(tmp_path / f"{name}.npy"))
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match=r"^grid_or_path: .*Python objects"):
        ad.Scene.from_grid(str(tmp_path / "obj.npy"))
    np.save(tmp_path / "f.npy", np.asfortranarray(np.ones((4, 5, 6), np.float32)))
    assert ad.Scene.from_grid(str(tmp_path / "f.npy")).density.shape == (4, 5, 6)


def test_from_grid_receiver_count_is_bounded():
    with pytest.raises(ValueError, match=r"^receivers: 1000000000 points needs .* receivers <= \d+ fits"):
        ad.Scene.from_grid(np.ones((2, 2, 2), np.float32), receivers=10**9)
    from avsm_dr import receivers as R
    sc = ad.Scene.from_grid(np.ones((2, 2, 2), np.float32), receivers=4)
    with pytest.raises(ValueError, match=r"^n: 1000000000000 points needs"):
        R.in_volume(sc, 10**12)


# ----------------------------------------------------------------- avsm_dr.evaluation
def test_evaluate_refuses_bad_sizes_before_any_capture():
    ev = ad.evaluation
    sc = ad.Scene.from_grid(np.ones((4, 4, 4), np.float32), receivers=8, name="g")
    with pytest.raises(ValueError, match=r"^configurations: expected a list"):
        ev.evaluate({"a": "avsm"}, [sc], 3, progress=False)              # was TypeError
    with pytest.raises(ValueError, match=r"^resolution: expected an integer"):
        ev.evaluate({"a": "avsm"}, [sc], resolution=64.0, progress=False)   # was TypeError
    with pytest.raises(ValueError, match=r"^n_volume: 1000000000000 receivers needs"):
        ev.evaluate({"a": "avsm"}, [sc], n_volume=10**12, progress=False)   # was MemoryError
    with pytest.raises(ValueError, match=r"^seeds: 1000000000 configurations needs"):
        ev.configurations(seeds=10**9)                                   # was MemoryError


def _table(values, scene="s"):
    return ad.evaluation.Table([dict(method=m, rmse=v, scene=scene, seed=s, light="l", receivers="in_volume")
                                for m, v in values for s in range(2)])


def test_compare_and_table_messages():
    ev = ad.evaluation
    with pytest.raises(ValueError, match=r"^metric: 'rmse' is not numeric"):
        ev.compare(_table([("a", True), ("b", 0.2)]), "a", "b")          # True was read as 1.0
    with pytest.raises(ValueError, match=r"^table: the configuration columns"):
        ev.compare(_table([("a", 0.1), ("b", 0.2)], scene=["s"]), "a", "b")   # was TypeError
    with pytest.raises(ValueError, match=r"^seed: expected an integer"):
        ev.compare(_table([("a", 0.1), ("b", 0.2)]), "a", "b", seed="x")      # was TypeError
    with pytest.raises(ValueError, match=r"^rows: expected an iterable of dicts"):
        ev.Table(None)                                                   # was TypeError
    c = ev.compare(_table([("a", 0.1), ("b", 0.2)]), "a", "b")
    assert c.ratio == pytest.approx(0.5) and c.n_configurations == 2
    # a filter that leaves no row is named (was "method: no such column; columns: []")
    with pytest.raises(ValueError, match=r"^scene: no rows with scene=\['nope'\]; values: \['s'\]"):
        ev.compare(_table([("a", 0.1), ("b", 0.2)]), "a", "b", scene="nope")
    with pytest.raises(ValueError, match=r"^resolution: no rows with resolution=999; values: \['64'\]"):
        ev.compare(ev.Table([dict(r, resolution=64) for r in _table([("a", 0.1), ("b", 0.2)])]), "a", "b",
                   resolution=999)
    # far apart metrics: the ratio in log space (1e-300 / 1e300 made NaN logs, "x: contains NaN")
    c = ev.compare(ev.Table([dict(method=m, rmse=v, scene="s", seed=s, light="l", receivers="in_volume")
                             for m, v in (("a", 1e-300), ("b", 1e300)) for s in range(5)]), "a", "b")
    assert c.ratio == 0.0 and c.n_configurations == 5
    c = ev.compare(ev.Table([dict(method=m, rmse=v, scene="s", seed=s, light="l", receivers="in_volume")
                             for m, v in (("a", 1e-150), ("b", 1e150)) for s in range(5)]), "a", "b")
    assert c.ratio == pytest.approx(1e-300, rel=1e-12)


def test_depth_l2_validates_its_arguments():
    ev = ad.evaluation
    seg = _three()
    rep = ad.build("avsm", seg)
    with pytest.raises(ValueError, match=r"^exact: contains 128 NaN"):
        ev.depth_l2(rep, seg, exact=np.full((2, 64), np.nan))            # was a NaN result
    with pytest.raises(ValueError, match=r"^texels: expected a 1-D array of texel indices in \[0, 3\)"):
        ev.depth_l2(rep, seg, texels=[-1, 99])                           # was NaN
    with pytest.raises(ValueError, match=r"^texels:"):
        ev.depth_l2(rep, seg, texels=[0.5])                              # was texel 0
    with pytest.raises(ValueError, match=r"^rep: expected a representation"):
        ev.depth_l2(42, seg)                                             # was AttributeError
    with pytest.raises(ValueError, match=r"^rep: built on 1 texels, the segments have 3"):
        ev.depth_l2(ad.build("avsm", ad.Segments.from_arrays([0, 1], [0.0], [1.0], optical_depth=[1.0])), seg)
    with pytest.raises(ValueError, match=r"^segments: expected avsm_dr.Segments"):
        ev.depth_l2(rep, "seg")
    with pytest.raises(ValueError, match=r"^n_depths: 10000000000 depths on 2 texels needs"):
        ev.depth_l2(rep, seg, n_depths=10**10)                           # was MemoryError
    exact = ev.curve_values(ad.build("exact", seg), seg)
    assert ev.depth_l2(rep, seg, exact=exact.tolist()) == pytest.approx(ev.depth_l2(rep, seg))

    class Short(ad.REGISTRY["exact"]):
        def _eval_texels(self, texel, depth):
            return dr.zeros(type(depth), 3)

    with pytest.raises(ValueError, match=r"^rep: eval returned 3 values for 128 receivers"):
        ev.depth_l2(Short(seg), seg)
