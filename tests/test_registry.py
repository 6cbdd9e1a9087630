"""The self-describing registry: schemas, describe(), explicit imports, the run-time
registered toy kind (tests/toy_kind.py) joining contract tests and sweeps, and an
import graph without cycles."""
import ast
from pathlib import Path

import numpy as np
import pytest

import avsm_dr as ad
from avsm_dr.representations import Param
from cases import case_id, representations

PKG = Path(ad.__file__).resolve().parent


@pytest.mark.parametrize("kind", ad.kinds())
def test_describe_contract(kind):
    d = ad.describe(kind)
    assert set(d) >= {"params", "size", "sweep", "quick_sweep", "examples", "headline"}
    for name, p in d["params"].items():
        assert set(p) >= {"default", "type", "min", "max", "doc"}, name
        assert p["doc"], f"{kind}.{name} has no doc"
    if d["size"] is not None:
        assert d["size"] in d["params"]
        assert len(d["sweep"]) >= 2
    schema = ad.REGISTRY[kind].schema
    # every documented configuration validates (a typo in a sweep would fail here)
    for params in [d["headline"], *d["examples"], *ad.configurations(kind), *ad.configurations(kind, quick=True)]:
        schema.validate(kind, params)


def test_every_kind_module_is_registered():
    """Explicit imports: each kind module in representations/ registers a kind, so a
    misspelt or unimported module cannot silently drop out of tests and benchmarks."""
    modules = {cls.__module__.rsplit(".", 1)[-1] for cls in ad.REGISTRY.values()}
    files = {p.stem for p in (PKG / "representations").glob("*.py")
             if not p.stem.startswith("_") and p.stem not in ("base", "schema", "registry")}
    assert files <= modules, files - modules


def test_toy_kind_joins_the_contract_tests():
    assert "toy_beer" in ad.kinds()
    ids = [case_id(c) for c in representations()]
    assert "toy_beer" in ids and "toy_beer-scale=1.0" not in ids     # defaults == example: deduplicated


def test_toy_kind_joins_a_quick_sweep(tmp_path):
    from avsm_dr.experiments.error_curves import sweep_rows
    seg = ad.Segments.from_arrays([0, 1, 3], [0.2, 0.1, 0.5], [0.4, 0.3, 0.6], optical_depth=[1.0, 0.5, 2.0])
    texel, depth = np.array([0, 1, 1]), np.array([0.3, 0.2, 0.9])
    truth = np.asarray(ad.build("exact", seg).eval(texel, depth))
    rows = sweep_rows(seg, lambda rep: np.asarray(rep.eval(texel, depth)), truth, quick=True)
    toy = [r for r in rows if r["method"] == "toy_beer"]
    assert len(toy) == 1 and toy[0]["rmse"] < 0.2
    assert {r["method"] for r in rows} >= set(ad.kinds())


def test_toy_kind_is_exact_for_one_uniform_segment():
    seg = ad.Segments.from_arrays([0, 1], [0.2], [0.6], optical_depth=[1.5])
    d = np.linspace(0, 1, 21)
    got = np.asarray(ad.build("toy_beer", seg).eval(np.zeros(21, int), d))
    ref = np.asarray(ad.build("exact", seg).eval(np.zeros(21, int), d))
    np.testing.assert_allclose(got, ref, rtol=1e-6)     # float32: one exp of the same product


@pytest.mark.parametrize("value, ok", [
    (3, True), (np.int64(3), True), (True, False), ("3", False), (2.5, False), (1, False), (65, False)])
def test_int_parameter_rule(value, ok):
    p = Param("nodes", "int", 8, "n", min=2, max=64)
    if ok:
        assert p.validate(value) == 3
    else:
        with pytest.raises(ValueError, match="^nodes: expected an integer in \\[2, 64\\]"):
            p.validate(value)


@pytest.mark.parametrize("value, ok", [
    (0.01, True), (np.float32(0.5), True), (1, True), (True, False), ("0.01", False), (float("nan"), False),
    (float("inf"), False), (0.0, False), (np.array([0.5]), False), (None, False)])
def test_float_parameter_rule(value, ok):
    p = Param("tolerance", "float", 0.01, "eps", min=0.0, open_min=True)
    if ok:
        assert isinstance(p.validate(value), float)
    else:
        with pytest.raises(ValueError, match="^tolerance: expected a finite real number"):
            p.validate(value)


@pytest.mark.parametrize("kind, params, name", [
    ("avsm", {"nodes": True}, "nodes"), ("fom", {"harmonics": True}, "harmonics"),
    ("dsm", {"tolerance": True}, "tolerance"), ("dsm", {"tolerance": "0.01"}, "tolerance"),
    ("fom", {"far": "2"}, "far"), ("fom", {"far": True}, "far"), ("fom", {"near": "0.1"}, "near"),
    ("osm", {"far": np.array([2.0])}, "far"), ("avsm", {"sort": 1}, "sort"),
    ("avsm", {"interpolation": "cubic"}, "interpolation"), ("avsm", {"nodez": 8}, "nodez"),
    ("moments", {"overestimation": 1.5}, "overestimation"), ("avsm", {"reverse": "fast"}, "reverse"),
    ("avsm", {"chunk": 0}, "chunk"), ("dsm", {"tolerance": 1e-12}, "tolerance"),
])
def test_one_rule_for_every_kind(kind, params, name):
    seg = ad.Segments.from_arrays([0, 1], [0.2], [0.4], optical_depth=[0.5])
    with pytest.raises(ValueError, match=f"^{name}:"):
        ad.build(kind, seg, **params)


def _imports(path: Path, module: str):
    """Modules of the package imported anywhere in ``path`` (module level or lazily)."""
    tree = ast.parse(path.read_text())
    pkg_parts = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("avsm_dr")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(pkg_parts[:len(pkg_parts) - node.level + 1])
                target = f"{base}.{node.module}" if node.module else base
            else:
                target = node.module or ""
            if not target.startswith("avsm_dr"):
                continue
            for a in node.names:      # `from pkg import submodule` imports the submodule
                sub = f"{target}.{a.name}"
                out.add(sub if _module_path(sub) else target)
    return out


def _module_path(name: str):
    parts = name.split(".")[1:]
    if not parts:
        return PKG / "__init__.py"
    rel = Path(*parts)
    for cand in (PKG / rel.with_suffix(".py"), PKG / rel / "__init__.py"):
        if cand.is_file():
            return cand
    return None


def test_import_graph_has_no_cycle():
    """Every import statement between the package's modules (lazy ones included), as a
    graph: no cycle (e.g. the old checkpoint.py <-> representations/avsm.py)."""
    graph = {}
    for path in PKG.rglob("*.py"):
        rel = path.relative_to(PKG.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mod = ".".join(parts)
        graph[mod] = {m for m in _imports(path, mod) if m != mod and _module_path(m)}
    state, stack = {}, []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for n in sorted(graph.get(m, ())):
            if state.get(n) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(n):] + [n]))
            if n not in state:
                visit(n)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
