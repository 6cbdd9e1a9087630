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
    not_kinds = ("base", "schema", "registry", "opaque_composite", "basis_functions")
    files = {p.stem for p in (PKG / "representations").glob("*.py")
             if not p.stem.startswith("_") and p.stem not in not_kinds}
    assert files <= modules, files - modules


def test_toy_kind_joins_the_contract_tests():
    assert "toy_beer" in ad.kinds()
    ids = [case_id(c) for c in representations()]
    assert "toy_beer" in ids and "toy_beer-scale=1.0" not in ids     # defaults == example: deduplicated


def test_toy_kind_joins_a_quick_sweep(tmp_path):
    """The studies' sweeps are registry-driven (``ad.kinds()`` x ``ad.configurations``): a kind
    registered at run time is built and looked up like the built-in ones."""
    seg = ad.Segments.from_arrays([0, 1, 3], [0.2, 0.1, 0.5], [0.4, 0.3, 0.6], optical_depth=[1.0, 0.5, 2.0])
    texel, depth = np.array([0, 1, 1]), np.array([0.3, 0.2, 0.9])
    truth = np.asarray(ad.build("exact", seg).eval(texel, depth))
    rows = [(kind, float(np.sqrt(np.mean((np.asarray(ad.build(kind, seg, **p).eval(texel, depth)) - truth) ** 2))))
            for kind in ad.kinds() for p in ad.configurations(kind, True)]
    toy = [r for r in rows if r[0] == "toy_beer"]
    assert len(toy) == 1 and toy[0][1] < 0.2
    assert {r[0] for r in rows} >= set(ad.kinds())


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


#: The layers, bottom first: a module may import its own layer and those below, never above
#: (DESIGN.md: studies -> evaluation / shading / ground truth / reconstruction / integrator ->
#: representations / capture -> segments -> backend).  The longest matching prefix decides.
LAYERS = [
    ["avsm_dr._llvm", "avsm_dr.backend", "avsm_dr._arrays", "avsm_dr.validation", "avsm_dr.geometry",
     "avsm_dr.camera",
     "avsm_dr._device_checks"],
    ["avsm_dr.segments", "avsm_dr.segment_dtype", "avsm_dr.texel_sort",
     "avsm_dr.filtering", "avsm_dr.stats", "avsm_dr.metrics",
     "avsm_dr.scene", "avsm_dr.io"],
    ["avsm_dr.representations", "avsm_dr.capture", "avsm_dr.fluid"],
    ["avsm_dr.builtin_scenes", "avsm_dr.procedural"],
    ["avsm_dr.groundtruth", "avsm_dr.receivers", "avsm_dr.shading", "avsm_dr.reconstruction", "avsm_dr.mitsuba",
     "avsm_dr.area_lights", "avsm_dr.checks", "avsm_dr.evaluation"],
    ["avsm_dr"],
]


def _layer(module: str):
    best = None
    for i, prefixes in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and (best is None or len(p) > best[1]):
                best = (i, len(p))
    return None if best is None else best[0]


def _package_graph():
    graph = {}
    for path in PKG.rglob("*.py"):
        parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mod = ".".join(parts)
        graph[mod] = ({m for m in _imports(path, mod) if m != mod and _module_path(m)}, path)
    return graph


def test_imports_point_down_the_layers():
    """No module imports a layer above its own (between different top-level subpackages), and
    every module of the package has a layer."""
    graph = _package_graph()
    unassigned = sorted(m for m in graph if _layer(m) is None)
    assert not unassigned, f"give these modules a layer in LAYERS: {unassigned}"
    top = lambda m: ".".join(m.split(".")[:2])   # noqa: E731
    upward = [f"{m} -> {n}" for m, (deps, _) in sorted(graph.items()) for n in sorted(deps)
              if _layer(n) > _layer(m) and top(m) != top(n)]
    assert not upward, "imports pointing up the layers: " + "; ".join(upward)


def test_ground_truth_never_imports_capture():
    """The oracle does not lean on the code it checks: no module of ``avsm_dr.groundtruth``
    imports ``avsm_dr.capture`` (shared geometry and validation live below both)."""
    bad = [f"{m} -> {n}" for m, (deps, _) in sorted(_package_graph().items())
           if m == "avsm_dr.groundtruth" or m.startswith("avsm_dr.groundtruth.")
           for n in sorted(deps) if n == "avsm_dr.capture" or n.startswith("avsm_dr.capture.")]
    assert not bad, "; ".join(bad)


def _private_imports(root: Path, package: str):
    """``(module, imported)`` for every ``from X import _name`` in ``root`` where ``_name`` is a
    private name (not a private submodule) of another module."""
    found = []
    for path in root.rglob("*.py"):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mod = ".".join(parts)
        pkg_parts = mod.split(".") if path.name == "__init__.py" else mod.split(".")[:-1]
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ImportFrom):
                continue
            if node.level:
                base = ".".join(pkg_parts[:len(pkg_parts) - node.level + 1])
                target = f"{base}.{node.module}" if node.module else base
            else:
                target = node.module or ""
            if not target.startswith(("avsm_dr", package)):
                continue
            for a in node.names:
                sub = (root.parent / Path(*f"{target}.{a.name}".split("."))).with_suffix(".py")
                if a.name.startswith("_") and not a.name.startswith("__") and not sub.exists() \
                        and not (sub.with_suffix("") / "__init__.py").exists():
                    found.append(f"{mod} imports {target}.{a.name}")
    return found


def test_no_private_name_crosses_modules():
    """Neither the package nor the studies import another module's private names (private
    modules such as ``_loops`` are shared on purpose; their names are public within them)."""
    found = _private_imports(PKG, "avsm_dr") + _private_imports(PKG.parent / "experiments", "experiments")
    assert not found, "; ".join(found)


def test_the_package_never_imports_the_studies():
    """``avsm_dr`` works installed without the repository: no import of ``experiments``."""
    bad = [str(path.relative_to(PKG.parent)) for path in PKG.rglob("*.py")
           for node in ast.walk(ast.parse(path.read_text()))
           if isinstance(node, (ast.Import, ast.ImportFrom))
           and any((n or "").split(".")[0] == "experiments"
                   for n in ([a.name for a in node.names] if isinstance(node, ast.Import) else [node.module]))]
    assert bad == ["avsm_dr/__main__.py"], bad      # the forwarder, which says where the studies are


# ----------------------------------------------------------- one home per concept
#: isinstance checks on a concrete blocker / light / occluder type outside the module defining
#: it, allowed because they validate an argument (the ValueError names it) rather than
#: dispatch behaviour: (file, enclosing function, type) -> reason.
TYPE_CHECKS_ALLOWED = {
    ("avsm_dr/reconstruction.py", "receiver_grid", "DirectionalLight"):
        "argument check: the radiograph plane is orthogonal to a parallel light ('light: expected ...')",
    ("avsm_dr/evaluation/configuration.py", "light_variants", "DirectionalLight"):
        "argument check: the variants tilt a directional light ('scene: light_variants needs ...')",
}


def _concrete_content_types() -> dict:
    """{name: defining module} of every concrete blocker, light and area-light occluder type."""
    from avsm_dr import scene
    from avsm_dr.area_lights import area_scene
    out, todo = {}, [scene.Blocker, scene.Light, area_scene.Occluder]
    while todo:
        for sub in todo.pop().__subclasses__():
            if sub.__module__.startswith("avsm_dr."):
                out[sub.__name__] = sub.__module__
            todo.append(sub)
    out["QuadLight"] = area_scene.QuadLight.__module__
    return out


def _type_checks(path: Path, names):
    """(enclosing function, type name) of every ``isinstance`` / ``issubclass`` call and every
    ``type(x) is / == T`` comparison in ``path`` naming one of ``names``."""
    def named(node):
        if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            return [n for e in node.elts for n in named(e)]
        if isinstance(node, ast.Starred):
            return named(node.value)
        name = node.id if isinstance(node, ast.Name) else node.attr if isinstance(node, ast.Attribute) else None
        return [name] if name in names else []

    found = []

    def visit(node, func):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            func = node.name
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) \
                and node.func.id in ("isinstance", "issubclass") and len(node.args) == 2:
            found.extend((func, n) for n in named(node.args[1]))
        if isinstance(node, ast.Compare) and isinstance(node.left, ast.Call) \
                and isinstance(node.left.func, ast.Name) and node.left.func.id == "type":
            found.extend((func, n) for c in node.comparators for n in named(c))
        for child in ast.iter_child_nodes(node):
            visit(child, func)

    visit(ast.parse(path.read_text()), "<module>")
    return found


def test_content_types_carry_their_behaviour():
    """Blockers, lights and area-light occluders carry their behaviour (bounds, hits, paths,
    cameras, Mitsuba dicts) as methods: outside the module defining a concrete type no code
    dispatches on it with isinstance / type(...) is.  A new shape or light is one class in
    one file; argument checks are listed in TYPE_CHECKS_ALLOWED with a reason."""
    types = _concrete_content_types()
    assert {"OpaqueSphere", "OpaqueBox", "OpaquePlane", "DirectionalLight", "SpotLight", "PointLight",
            "Sphere", "Box"} <= set(types)
    bad, seen = [], set()
    for path in sorted(PKG.rglob("*.py")):
        rel = str(path.relative_to(PKG.parent))
        mod = ".".join(path.relative_to(PKG.parent).with_suffix("").parts)
        for func, name in _type_checks(path, types):
            if types[name] == mod:
                continue
            if (rel, func, name) in TYPE_CHECKS_ALLOWED:
                seen.add((rel, func, name))
            else:
                bad.append(f"{rel}:{func} checks isinstance(..., {name})")
    assert not bad, "dispatch on a concrete type outside its module (give the class a method): " + "; ".join(bad)
    stale = set(TYPE_CHECKS_ALLOWED) - seen
    assert not stale, f"TYPE_CHECKS_ALLOWED lists sites that no longer exist: {sorted(stale)}"


# ------------------------------------------------------------- the build template
def test_kinds_fill_the_build_template_instead_of_the_constructor():
    """One template in the base class, no metaclass: every registered kind (and the opaque
    composite) builds through ``Representation.__init__`` -> _validate -> _resolve -> _build
    -> _apply_precision; none overrides ``__init__`` (was: 12 overrides and a metaclass
    running the precision step)."""
    import abc
    import inspect

    from avsm_dr.representations.base import Representation
    from avsm_dr.representations.opaque_composite import OpaqueComposite
    assert type(Representation) is abc.ABCMeta          # abstract methods only, no custom __call__
    for kind in ad.kinds():
        cls = ad.REGISTRY[kind]
        own = [c.__name__ for c in cls.__mro__[:cls.__mro__.index(Representation)] if "__init__" in c.__dict__]
        assert not own, f"{kind}: __init__ overridden in {own}"
    src = inspect.getsource(Representation.eval).splitlines()
    assert len(src) <= 40, f"eval is {len(src)} lines (argument handling belongs in _lookup_args)"
    assert OpaqueComposite.__module__ == "avsm_dr.representations.opaque_composite"
    from avsm_dr.capture import opaque_map
    assert opaque_map.OpaqueComposite is OpaqueComposite


def test_build_template_runs_its_steps_in_order():
    """validate -> resolve -> build -> store at the precision, for a kind filling only hooks;
    the precision step sees the built buffers (AVSM, unorm16: quantised nodes)."""
    calls = []

    class Traced(ad.REGISTRY["avsm"]):
        def _validate(self, segments, params):
            calls.append("validate")
            super()._validate(segments, params)

        def _resolve(self):
            calls.append("resolve")
            super()._resolve()

        def _build(self):
            calls.append("build")
            super()._build()

        def _apply_precision(self):
            calls.append(("precision", len(self.depths)))
            super()._apply_precision()

    seg = ad.Segments.from_arrays([0, 2], [0.1, 0.5], [0.3, 0.9], optical_depth=[0.5, 1.0])
    rep = Traced(seg, nodes=4, precision="unorm16")
    assert calls == ["validate", "resolve", "build", ("precision", 4)]
    ref = ad.build("avsm", seg, nodes=4, precision="unorm16")
    assert rep.nbytes_per_texel == ref.nbytes_per_texel
    d = np.array([0.0, 0.2, 0.6, 1.0])
    np.testing.assert_array_equal(np.asarray(rep.eval(np.zeros(4, np.int64), d)),
                                  np.asarray(ref.eval(np.zeros(4, np.int64), d)))


# ------------------------------------------------------------- the package's size
#: Most lines (``find avsm_dr -name '*.py' | xargs cat | wc -l``) the installed package may hold.
#: The issue's target was 16,000 (from 23,548), reached at 15,952; lower this constant as the
#: package shrinks, never raise it (study-only code belongs in ``experiments/``, dead code nowhere).
#: Raised twice, each time with what paid for most of it: +4 for ``validation.MemoryBudgetError``;
#: +11 for the sorted AVSM's 64-bit sort words, the radix lane order, ``WorkLimitError`` and the
#: cached counts (+35), after the float64 rank sort the key passes replace was deleted (-24).
PACKAGE_LINE_BUDGET = 16386
#: Most lines of one module of the package.
MODULE_LINE_LIMIT = 600
#: Modules allowed above MODULE_LINE_LIMIT: path under the repository root -> reason.  An entry
#: whose module is gone or back under the limit fails the test (remove it).  The two modules
#: the brief listed as "being split" (representations/dsm.py, capture/grid.py) were split in
#: cab7835 and are under the limit, so the list is empty.
LARGE_MODULES_ALLOWED: dict = {}


def _package_lines() -> dict:
    """{path under the repository root: line count (newlines, as ``wc -l``)} of ``avsm_dr/**/*.py``."""
    return {str(p.relative_to(PKG.parent)): p.read_bytes().count(b"\n") for p in sorted(PKG.rglob("*.py"))}


def test_the_package_stays_within_its_line_budget():
    """The installed package stays within the issue's 16,000 lines and never grows back:
    its total is at most PACKAGE_LINE_BUDGET, and no module is above MODULE_LINE_LIMIT lines
    except those listed (with a reason) in LARGE_MODULES_ALLOWED."""
    lines = _package_lines()
    total = sum(lines.values())
    assert total <= PACKAGE_LINE_BUDGET, (
        f"avsm_dr/**/*.py holds {total} lines, above PACKAGE_LINE_BUDGET = {PACKAGE_LINE_BUDGET}: move "
        f"study-only code to experiments/ or delete dead code rather than raising the budget")
    large = {p: n for p, n in lines.items() if n > MODULE_LINE_LIMIT}
    bad = sorted(f"{p} ({n} lines)" for p, n in large.items() if p not in LARGE_MODULES_ALLOWED)
    assert not bad, f"modules above {MODULE_LINE_LIMIT} lines (split them by concept): " + "; ".join(bad)
    stale = sorted(set(LARGE_MODULES_ALLOWED) - set(large))
    assert not stale, f"LARGE_MODULES_ALLOWED lists modules that are gone or within the limit: {stale}"
