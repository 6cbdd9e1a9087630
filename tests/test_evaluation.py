"""The public evaluation harness (avsm_dr.evaluation): the docs page's example as written, the
table's columns, agreement with error_curves, compare's statistical unit, depth_l2 against a
slow NumPy reference, user-defined kinds, and Scene.from_grid's box / scale / errors."""
import contextlib
import inspect
import io
import math
import re
from pathlib import Path

import drjit as dr
import numpy as np
import pytest

import avsm_dr as ad
from avsm_dr import stats
from avsm_dr.evaluation import Configuration, Table, compare, configurations, depth_l2, evaluate

ROOT = Path(__file__).resolve().parents[1]
#: error_curves' quick receiver set.
QUICK = dict(resolution=64, n_volume=512, n_surface=256, n_decomp=128, progress=False)
COLUMNS = ["method", "kind", "params", "scene", "seed", "light", "receivers", "order", "resolution", "opaque",
           "n_receivers", "n_decomp", "rmse", "compression_rms", "capture_rms", "spatial_rms", "signed_mean",
           "leak_share", "dark_share", "p99", "p99_9", "max", "nonfinite", "depth_l2", "bytes", "bytes_dense",
           "build_s", "lookup_s", "build_first_s"]


class Beer(ad.Representation):
    """Unregistered test kind: T = exp(-tau_total) behind the texel's first entry."""

    schema = ad.representations.Schema(params=(ad.representations.Param("scale", "float", 1.0, "tau factor",
                                                                        min=0.0),))
    nbytes_per_texel = 8

    def __init__(self, segments, **params):
        super().__init__(segments, **params)
        self.a = segments.Float(segments.texel_bounds()[0])
        self.tau = dr.zeros(segments.Float, segments.n_texels)
        dr.scatter_reduce(dr.ReduceOp.Add, self.tau, segments.optical_depth * self.params["scale"],
                          segments.texel_of_segment())

    def _eval_texels(self, texel, depth):
        a, tau = dr.gather(self.Float, self.a, texel), dr.gather(self.Float, self.tau, texel)
        return dr.select(depth < a, 1.0, dr.exp(-tau))


@pytest.fixture(scope="module")
def small():
    """avsm-8 and fom-4 on the plume, two configurations, error_curves' quick receivers."""
    return evaluate({"avsm-8": ("avsm", {"nodes": 8}), "fom-4": ("fom", {"harmonics": 4})}, ["plume"],
                    configurations(seeds=1, lights=("dir_a", "spot")), **QUICK)


# ----------------------------------------------------------------------- the docs page
def test_docs_example_runs_as_written():
    """The first Python block of docs/evaluation.md, executed as it stands (<= 15 lines of code)."""
    page = (ROOT / "docs" / "evaluation.md").read_text()
    code = re.search(r"```python\n(.*?)```", page, re.S).group(1)
    assert len([ln for ln in code.splitlines() if ln.strip()]) <= 15
    out = io.StringIO()
    ns: dict = {"__name__": "docs_example"}
    with contextlib.redirect_stdout(out):
        exec(compile(code, "docs/evaluation.md", "exec"), ns)
    text = out.getvalue()
    assert "rmse(slab) / rmse(avsm-8)" in text and "over 4 configurations" in text
    table = ns["table"]
    assert len(table) == 2 * 4 and set(table.column("kind")) == {"Slab", "avsm"}
    assert "Slab" not in ad.kinds()                                  # never registered
    assert all(np.isfinite(table.column("rmse"))) and set(table.column("bytes_dense")) == {12.0, 64.0}


# ------------------------------------------------------------------------- the table
def test_table_columns_and_rows(small):
    assert small.columns == COLUMNS
    # 2 methods x 2 configurations x 2 receiver sets (the plume has a receiver plane)
    assert len(small) == 8
    assert set(small.column("receivers")) == {"in_volume", "surface"}
    r = small.where(method="avsm-8", light="spot", receivers="in_volume")[0]
    assert r["kind"] == "avsm" and r["params"] == {"nodes": 8} and r["n_receivers"] == 512
    assert r["resolution"] == 64 and r["opaque"] == "inline" and r["n_decomp"] == 128
    # bytes: the sparse layout (1/8 per texel + 64 per non-empty texel), bytes_dense: 2 N x 4
    n_texels = 64 * 64
    filled = (r["bytes"] - 1 / 8) * n_texels / 64          # non-empty texels (float64 rounding only)
    assert r["bytes_dense"] == 64.0 and abs(filled - round(filled)) < 1e-6 and 0 < filled < n_texels
    assert r["build_s"] > 0 and r["lookup_s"] > 0 and r["build_first_s"] > 0
    assert 0 < r["compression_rms"] and 0 < r["depth_l2"] < 1 and 0 <= r["leak_share"] <= 1
    assert r["p99"] <= r["p99_9"] <= r["max"]
    # the capture's insertion order is recorded: evaluate's default, front to back
    assert inspect.signature(evaluate).parameters["order"].default == "depth"
    assert set(small.column("order")) == {"depth"}


def test_table_where_csv_and_text(small, tmp_path):
    assert len(small.where(method=["avsm-8", "fom-4"], receivers=lambda s: s == "surface")) == 4
    with pytest.raises(ValueError, match="nope: no such column"):
        small.where(nope=1)
    path = small.to_csv(tmp_path / "t.csv")
    lines = path.read_text().splitlines()
    assert lines[0].split(",")[:3] == ["method", "kind", "params"] and len(lines) == 9
    assert '"{""nodes"": 8}"' in lines[1]                              # params as JSON
    text = repr(small)
    assert text.splitlines()[0].split() == ["method", "scene", "seed", "light", "receivers", "rmse", "depth_l2",
                                            "bytes"]
    assert "(8 rows x 29 columns)" in text
    assert len(Table([])) == 0


def test_numbers_agree_with_error_curves():
    """One error_curves configuration (the quick spot-light one: subset builds) and the same
    measured through evaluate: identical float64 numbers (the same code paths)."""
    from experiments import error_curves as E
    P = dict(n_volume=512, n_surface=256, resolution=64, n_decomp=128, spp=32, kinds=["avsm"])
    cell = E._cell(dict(scene="plume", seed=1, light="spot", base=False, quick=True, P=P, whole_map=[]))
    ref = {r["receivers"]: r for r in cell["rows"]             # evaluate's default order: front to back
           if r.get("setting") == "avsm-8" and r["study"] == "main" and r["order"] == "depth"}
    assert set(ref) == {"in_volume", "surface"}
    for subset in (False, True):
        tab = evaluate({"avsm-8": ("avsm", {"nodes": 8})}, ["plume"], [Configuration(1, "spot")], subset=subset,
                       **QUICK)
        for row in tab:
            e = ref[row["receivers"]]
            assert row["compression_rms"] == e["compression_rms"]
            assert (row["rmse"], row["signed_mean"], row["p99"], row["leak_share"]) == \
                (e["total_rmse"], e["total_mean_error"], e["total_p99_error"], e["total_leak_fraction"])
            assert (row["capture_rms"], row["spatial_rms"]) == (e["capture_rms"], e["spatial_rms"])


def test_separate_opaque_rows():
    tab = evaluate({"avsm-8": ("avsm", {"nodes": 8})}, ["smoke_over_table"], opaque=("inline", "separate"),
                   metrics=("receiver_rmse",), **QUICK)
    assert sorted(set(tab.column("opaque"))) == ["inline", "separate"] and len(tab) == 4
    assert all(math.isnan(v) for v in tab.column("depth_l2") + tab.column("build_s"))


def test_orders_are_captured_and_recorded():
    """order= reaches ad.capture and the order column: the receivers and truth are shared,
    sorted AVSM is the same in every order, unsorted AVSM is not; 'random' is shuffled with
    the configuration's seed; a bad order names the argument."""
    orders = ("depth", "reverse_depth", "random", "submission")
    methods = {"avsm-4": ("avsm", {"nodes": 4}), "sorted-4": ("avsm", {"nodes": 4, "sort": True})}
    tab = evaluate(methods, ["plume"], [Configuration(3, "dir_a")], receivers=("in_volume",), order=orders,
                   metrics=("receiver_rmse",), **QUICK)
    assert tab.column("order") == [o for o in orders for _ in methods]
    rows = {(r["order"], r["method"]): r for r in tab}
    assert len({rows[o, "sorted-4"]["rmse"] for o in orders}) == 1
    assert len({rows[o, "avsm-4"]["rmse"] for o in orders}) == len(orders)
    sc = ad.scenes.get("plume", seed=3)                            # 'dir_a': the scene's own light
    want = ad.capture(sc, resolution=64, order="random", order_seed=3).segments.numpy()["z0"]
    got = {s: ad.capture(sc, resolution=64, order="random", order_seed=s).segments.numpy()["z0"] for s in (0, 3)}
    assert np.array_equal(got[3], want) and not np.array_equal(got[0], want)
    import avsm_dr.evaluation.harness as H
    assert np.array_equal(H._capture(sc, 64, "random", "inline", 3)[0].segments.numpy()["z0"], want)
    with pytest.raises(ValueError, match="^order: "):
        evaluate(methods, ["plume"], order="sorted", **QUICK)


# --------------------------------------------------------------------------- compare
def _rows(values, n_receivers=100, extra=None):
    """A hand-made table: values = {(scene, seed, light): (metric a, metric b)}."""
    rows = []
    for (scene, seed, light), (va, vb) in values.items():
        for m, v in (("a", va), ("b", vb)):
            rows.append(dict(method=m, scene=scene, seed=seed, light=light, receivers="in_volume",
                             n_receivers=n_receivers, rmse=v, **(extra or {})))
    return Table(rows)


def test_compare_unit_is_the_configuration():
    rng = np.random.default_rng(3)
    vals = {(sc, s, li): (float(rng.uniform(0.5, 1)), float(rng.uniform(1, 2)))
            for sc in ("plume", "mine") for s in range(3) for li in ("dir_a",)}
    c = compare(_rows(vals), "a", "b", n_boot=500)
    assert c.n_configurations == 6 and not c.indicative
    ratios = np.array([va / vb for va, vb in vals.values()])
    assert [p["ratio"] for p in c.per_configuration] == list(ratios)
    assert c.ratio == pytest.approx(math.exp(np.mean(np.log(ratios))), rel=1e-12)
    ci = stats.bootstrap_ci(np.log(ratios), "mean", n_boot=500)
    assert (c.low, c.high) == pytest.approx((math.exp(ci["low"]), math.exp(ci["high"])), rel=1e-12)
    # receivers are not the unit: the same configurations with 100x the receivers give the same interval
    c2 = compare(_rows(vals, n_receivers=10000), "a", "b", n_boot=500)
    assert (c2.low, c2.high, c2.n_configurations) == (c.low, c.high, 6)
    # per scene: 3 configurations, indicative
    c3 = compare(_rows(vals), "a", "b", scene="mine", n_boot=500)
    assert c3.n_configurations == 3 and c3.indicative and "indicative" in str(c3)
    one = compare(_rows({("plume", 0, "dir_a"): (1.0, 2.0)}), "a", "b")
    assert one.ratio == 0.5 and math.isnan(one.low) and "no interval" in str(one)


def test_compare_refuses_ambiguous_or_unpaired_rows(small):
    vals = {("plume", 0, "dir_a"): (1.0, 2.0)}
    t = Table(list(_rows(vals, extra={"order": "depth"})) + list(_rows(vals, extra={"order": "random"})))
    with pytest.raises(ValueError, match=r"a: several rows .*order"):
        compare(t, "a", "b")
    assert compare(t, "a", "b", order="random").ratio == 0.5
    with pytest.raises(ValueError, match="b: no rows of method 'zz'"):
        compare(small, "avsm-8", "zz")
    with pytest.raises(ValueError, match="metric: no column"):
        compare(small, "avsm-8", "fom-4", metric="nope")
    with pytest.raises(ValueError, match="receivers: no rows"):
        compare(small, "avsm-8", "fom-4", receivers="uniform")
    c = compare(small, "avsm-8", "fom-4", metric="depth_l2")
    assert c.n_configurations == 2 and c.indicative and c.receivers == "in_volume"


# --------------------------------------------------------------------------- depth_l2
def _reference_depth_l2(rep, offsets, z0, z1, tau, n):
    """Slow float64 reference: a Python loop over texels, the exact curve of exact.py's formula;
    opaque segments end a texel's range at their front face and their interiors do not count."""
    sq = []
    for t in range(len(offsets) - 1):
        s, e = offsets[t], offsets[t + 1]
        if s == e:
            continue
        opaque = tau[s:e] >= ad.OPAQUE_OPTICAL_DEPTH
        a, b = z0[s:e].min(), np.where(opaque, z0[s:e], z1[s:e]).max()
        if b <= a:
            continue                                     # only opaque faces: not counted
        z = a + (np.arange(n) + 0.5) / n * (b - a)
        f = np.zeros(n)
        keep = np.ones(n, bool)
        for i in range(s, e):
            ln = z1[i] - z0[i]
            f += tau[i] * (np.clip((z - z0[i]) / ln, 0, 1) if ln > 0 else (z >= z0[i]).astype(float))
            if tau[i] >= ad.OPAQUE_OPTICAL_DEPTH:
                keep &= ~((z > z0[i]) & (z < z1[i]))
        t_rep = np.asarray(rep.eval(np.full(n, t), z), np.float64)
        sq.append(np.mean(((t_rep - np.exp(-f)) ** 2)[keep]))
    return math.sqrt(np.mean(sq))


def test_depth_l2_matches_a_numpy_reference():
    rng = np.random.default_rng(7)
    counts = rng.integers(0, 7, 40)
    counts[[3, 10]] = 0                                                   # empty texels do not count
    counts[5] = 1                                                         # one opaque slab alone
    offsets = np.concatenate([[0], np.cumsum(counts)])
    z0 = rng.uniform(0, 1, offsets[-1])
    z1 = z0 + rng.uniform(0, 0.3, z0.size) * (rng.random(z0.size) > 0.1)    # some zero-length segments
    tau = rng.uniform(0, 1.5, z0.size)
    tau[rng.random(z0.size) < 0.15] = ad.OPAQUE_OPTICAL_DEPTH             # blockers' slabs
    tau[offsets[5]], z1[offsets[5]] = ad.OPAQUE_OPTICAL_DEPTH, z0[offsets[5]] + 0.01
    seg = ad.Segments.from_arrays(offsets, z0, z1, optical_depth=tau)
    h = seg.numpy()                      # the float32-stored depths the kernels see
    rep = ad.build("avsm", seg, nodes=2)
    ref = _reference_depth_l2(rep, offsets, h["z0"], h["z1"], h["optical_depth"], 16)
    # the exact kind sums optical depth in float64 and returns float32 T: <= 6e-8 per value
    assert depth_l2(rep, seg, n_depths=16) == pytest.approx(ref, abs=1e-7)
    assert ref > 1e-3
    per = depth_l2(rep, seg, n_depths=16, per_texel=True)
    faces_only = [t for t in range(40) if counts[t] and
                  np.all(h["optical_depth"][offsets[t]:offsets[t + 1]] >= ad.OPAQUE_OPTICAL_DEPTH) and
                  np.ptp(h["z0"][offsets[t]:offsets[t + 1]]) == 0]
    assert 5 in faces_only and per.shape == (np.count_nonzero(counts) - len(faces_only),)
    assert depth_l2(ad.build("exact", seg), seg) == 0.0
    with pytest.raises(ValueError, match="n_depths"):
        depth_l2(rep, seg, n_depths=0)


# ------------------------------------------------------------------ user-defined kinds
def test_user_defined_kind_is_built_directly():
    before = dict(ad.REGISTRY)
    scene = ad.Scene.from_grid(np.pad(np.full((6, 6, 6), 2.0), 2), name="cube")
    tab = evaluate({"beer": (Beer, {"scale": 1.0}), "toy": ("toy_beer", {}), "exact": "exact"}, [scene],
                   configurations(seeds=2, lights=("dir_a", "spot")), metrics=("receiver_rmse", "depth_l2"),
                   **QUICK)
    assert ad.REGISTRY == before
    assert set(tab.column("kind")) == {"Beer", "toy_beer", "exact"} and set(tab.column("scene")) == {"cube"}
    assert set(tab.column("receivers")) == {"in_volume"}              # no receiver plane: no surface set
    ex = tab.where(method="exact")
    assert all(v == 0 for v in ex.column("compression_rms")) and all(v == 0 for v in ex.column("depth_l2"))
    assert compare(tab, "beer", "toy").n_configurations == 4
    with pytest.raises(ValueError, match=r"methods\['beer'\]: scale"):
        evaluate({"beer": (Beer, {"scale": -1.0})}, [scene], **QUICK)
    with pytest.raises(ValueError, match=r"methods\['x'\]: kind: unknown"):
        evaluate({"x": ("no_such_kind", {})}, [scene], **QUICK)
    with pytest.raises(ValueError, match=r"methods\['x'\]: expected a kind name"):
        evaluate({"x": (dict, {})}, [scene], **QUICK)
    with pytest.raises(ValueError, match="scenes: unknown built-in scene"):
        evaluate({"x": "exact"}, ["nowhere"], **QUICK)
    with pytest.raises(ValueError, match="receivers: expected one of"):
        evaluate({"x": "exact"}, [scene], receivers=("inside",), **QUICK)
    with pytest.raises(ValueError, match="receivers: scene 'cube' has none"):
        evaluate({"x": "exact"}, [scene], receivers=("surface",), **QUICK)


def test_a_method_at_its_preset():
    """("fom", "preset") is the kind at describe(kind)["preset"]: the same rows as the preset's
    parameters given explicitly, recorded in params; a user kind's PRESET too."""
    scene = ad.Scene.from_grid(np.pad(np.full((6, 6, 6), 2.0), 2), name="cube")
    kw = dict(QUICK, receivers=("in_volume",), metrics=("receiver_rmse",))
    tab = evaluate({"fom": ("fom", "preset"), "fom-texel": ("fom", {"depth_range": "texel"}),
                    "avsm": ("avsm", "preset"), "beer": (Beer, "preset")}, [scene], **kw)
    fom, explicit = tab.where(method="fom")[0], tab.where(method="fom-texel")[0]
    assert fom["params"] == ad.describe("fom")["preset"] == {"depth_range": "texel"}
    assert (fom["rmse"], fom["bytes"]) == (explicit["rmse"], explicit["bytes"])
    assert tab.where(method="avsm")[0]["params"] == {"interpolation": "linear"}
    assert tab.where(method="beer")[0]["params"] == {}                # Representation.PRESET: defaults
    with pytest.raises(ValueError, match=r"methods\['fom'\]: expected \(kind, params dict or 'preset'\)"):
        evaluate({"fom": ("fom", "best")}, [scene], **kw)


def test_configurations():
    cs = configurations(seeds=2, lights=("dir_a", "spot"))
    assert [c.label for c in cs] == ["s0-dir_a", "s0-spot", "s1-dir_a", "s1-spot"]
    light = ad.SpotLight((0, 3, 0), (0, -1, 0), fov=40)
    assert configurations(seeds=[5], lights=light)[0].light_label.startswith("spot(")
    with pytest.raises(ValueError, match="light: expected one of"):
        Configuration(0, "sun")
    with pytest.raises(ValueError, match="seeds"):
        configurations(seeds=0)
    with pytest.raises(ValueError, match="seed"):
        Configuration(-1)


def test_configuration_builds_its_scene_capture_and_receivers():
    from avsm_dr import builtin_scenes, receivers
    cfg = Configuration(1, "dir_b")
    scene = cfg.scene("plume")
    base = builtin_scenes.get("plume", seed=1)                      # regenerated with the seed
    assert np.array_equal(scene.density, base.density)
    assert not np.array_equal(scene.density, builtin_scenes.get("plume").density)
    assert np.allclose(scene.light.direction, ad.evaluation.light_variants(base)["dir_b"].direction)
    own = ad.Scene.from_grid(np.ones((4, 4, 4)))                    # a Scene object keeps its content
    lit = cfg.scene(own)
    assert lit.density is own.density and not np.allclose(lit.light.direction, own.light.direction)
    scene2, cap = cfg.capture("plume", 64, order="submission")
    ref = ad.capture(scene, resolution=64, order="submission")
    assert np.array_equal(cap.segments.z0, ref.segments.z0) and np.array_equal(scene2.density, scene.density)
    pts = cfg.in_volume_receivers(scene, 16)
    assert np.array_equal(pts, receivers.in_volume(scene, 16, 1))
    assert not np.array_equal(pts, receivers.in_volume(scene, 16, 0))


def test_moved_names_are_public():
    from avsm_dr import evaluation
    from experiments import _common
    for name in ("truth", "Probe", "Built", "SubsetBuilder", "light_variants"):
        assert callable(getattr(evaluation, name))
    for name in ("measure", "timed", "sync"):
        assert getattr(_common, name) is getattr(evaluation, name)
    assert not hasattr(evaluation, "Meter") and _common.Meter.__module__ == "experiments._common"   # studies only
    scene_parts = {"Scene", "DirectionalLight", "SpotLight", "PointLight", "Particles", "Hair", "OpaqueSphere",
                   "OpaqueBox", "OpaquePlane"}          # a scene of one's own needs no private import
    assert scene_parts | {"evaluation"} <= set(ad.__all__)
    assert all(getattr(ad, n).__module__ == "avsm_dr.scene" for n in scene_parts)


# ------------------------------------------------------------------ Scene.from_grid
def test_from_grid_box_and_scale(tmp_path):
    grid = np.random.default_rng(0).uniform(0, 1, (4, 6, 8))
    grid[:, :, :4] = 0                                                   # empty half (x < 0)
    s = ad.Scene.from_grid(grid, density_scale=2.5)
    lo, hi = s.bbox
    assert lo.tolist() == [-4, -3, -2] and hi.tolist() == [4, 3, 2]     # unit voxels, (nx, ny, nz) / 2
    np.testing.assert_array_equal(s.density, (grid * 2.5).astype(np.float32))
    assert s.density.dtype == np.float32 and s.meta["bbox_from"] == "unit voxels"
    assert s.receivers.shape == (1024, 3) and np.all(s.receivers[:, 0] >= 0)   # in occupied voxels only
    assert np.all((s.receivers >= lo) & (s.receivers <= hi))
    assert isinstance(s.light, ad.DirectionalLight) and s.light.direction.tolist() == [0, -1, 0]
    # an explicit box is used as given (no rescaling of the density)
    b = ad.Scene.from_grid(grid, bbox=((0, 0, 0), (1, 2, 3)), receivers=10, name="mine")
    assert [x.tolist() for x in b.bbox] == [[0, 0, 0], [1, 2, 3]] and b.receivers.shape == (10, 3)
    np.testing.assert_array_equal(b.density, grid.astype(np.float32))
    assert b.name == "mine"
    # files: .npy (unit voxels), .vol (its header's box unless one is given)
    np.save(tmp_path / "vol.npy", grid)
    n = ad.Scene.from_grid(tmp_path / "vol.npy")
    assert n.name == "vol" and n.bbox[1].tolist() == [4, 3, 2]
    ad.io.write_vol(tmp_path / "v.vol", grid, bbox=((-1, -1, -1), (1, 2, 3)))
    v = ad.Scene.from_grid(str(tmp_path / "v.vol"), density_scale=4.0)
    assert [x.tolist() for x in v.bbox] == [[-1, -1, -1], [1, 2, 3]] and v.meta["bbox_from"] == "vol header"
    np.testing.assert_allclose(v.density, 4 * grid.astype(np.float32), rtol=1e-6)   # float32 file
    pts = np.array([[0.5, 0.5, 0.5], [1.0, 1.0, 1.0]])
    w = ad.Scene.from_grid(str(tmp_path / "v.vol"), bbox=((0, 0, 0), (2, 2, 2)), receivers=pts)
    assert w.bbox[1].tolist() == [2, 2, 2] and np.array_equal(w.receivers, pts)
    # a scene from a grid is captured and measured like a built-in one
    cap = ad.capture(s, resolution=64, order="depth")
    assert cap.segments.n_segments > 0


@pytest.mark.parametrize("kwargs, name", [
    (dict(grid_or_path=np.ones((4, 4, 4), np.uint8)), "grid_or_path"),
    (dict(grid_or_path=np.ones((4, 4))), "grid_or_path"),
    (dict(grid_or_path=-np.ones((4, 4, 4))), "grid_or_path"),
    (dict(grid_or_path="missing.npy"), "grid_or_path"),
    (dict(grid_or_path="volume.raw"), "grid_or_path"),
    (dict(bbox=((0, 0, 0), (1, -1, 1))), "bbox"),
    (dict(bbox=(0, 1)), "bbox"),
    (dict(density_scale=0.0), "density_scale"),
    (dict(density_scale=float("nan")), "density_scale"),
    (dict(density_scale=1e39), "density_scale"),
    (dict(light="sun"), "light"),
    (dict(receivers=0), "receivers"),
    (dict(receivers=np.zeros((3, 2))), "receivers"),
    (dict(name=""), "name"),
])
def test_from_grid_errors_name_the_argument(kwargs, name):
    kwargs = dict(dict(grid_or_path=np.ones((4, 4, 4))), **kwargs)
    with pytest.raises(ValueError, match=f"^{name}:"):
        ad.Scene.from_grid(**kwargs)
