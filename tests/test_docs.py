"""The docs' generated parts: README's kinds table is current, every public object has a docstring,
and the build-time generator writes a page per kind from the registry and the committed data; every
```python block of a user page runs (or is marked as an excerpt of a file that exists).
(The Sphinx build itself runs in CI: README's test command, warnings as errors.)"""
import importlib.util
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import avsm_dr as ad

ROOT = Path(__file__).resolve().parents[1]


def _ext():
    spec = importlib.util.spec_from_file_location("avsm_docs", ROOT / "docs" / "_ext" / "avsm_docs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_readme_kinds_table_current():
    assert _ext().update_kinds_tables(check=True) == [], "run python docs/_ext/avsm_docs.py"


def test_every_public_object_has_a_docstring():
    assert _ext().missing_docstrings() == []


def test_generated_pages(tmp_path):
    mod = _ext()
    kinds = mod.generate(tmp_path)
    assert set(kinds) == {k for k in ad.kinds() if ad.REGISTRY[k].__module__.startswith("avsm_dr.")}
    for kind in kinds:
        page = (tmp_path / "representations" / f"{kind}.md").read_text()
        d = ad.describe(kind)
        assert page.startswith(f"# `{kind}`: {d['summary']}")
        assert all(f"| `{name}` |" in page for name in d["params"]), kind       # the parameter table
        assert f".. automodule:: {ad.REGISTRY[kind].__module__}" in page
    # measured figures come from docs/data: the reference kinds were measured
    avsm = (tmp_path / "representations" / "avsm.md").read_text()
    assert "| plume |" in avsm and "avsm_error.png" in avsm
    assert (tmp_path / "representations" / "avsm_error.png").stat().st_size > 1000
    table = (tmp_path / "fragments" / "kinds_table.md").read_text()
    assert all(f"| `{k}` |" in table for k in kinds)
    api = (tmp_path / "api.md").read_text()                        # the index, one page per module
    assert "(api/avsm_dr.segments.md)" in api and "avsm_dr.__main__" not in api
    assert ".. automodule:: avsm_dr.segments" in (tmp_path / "api" / "avsm_dr.segments.md").read_text()
    assert "automodule" not in api and not (tmp_path / "api" / "avsm_dr.__main__.md").exists()
    pages = sorted(p.stem for p in (tmp_path / "api").glob("*.md"))
    assert pages == sorted(m.__name__ for m in mod.public_modules())
    recipes = (tmp_path / "recipes.md").read_text()
    assert all(f"`{sh.name}`" in recipes for sh in (ROOT / "experiments").glob("*.sh"))
    notebooks = sorted(p.stem for p in (tmp_path / "notebooks").glob("*.ipynb"))
    assert notebooks == sorted(p.stem for p in (ROOT / "notebooks").glob("[0-9][0-9]_*.py"))


def test_kind_without_measurements(tmp_path):
    """A newly registered kind gets a page before anyone has measured it."""
    page = _ext().kind_page("exact", sweep=[], settings=[], bench=[])
    assert "No measurement of `exact`" in page and "No throughput of `exact`" in page


def test_plain_docstrings_become_valid_rst():
    """The autodoc hook escapes |x| outside literals and adds the blank lines RST needs."""
    publish_doctree = pytest.importorskip("docutils.core").publish_doctree     # with the docs extra
    from docutils.nodes import system_message
    lines = ["Error ``|a - b|`` and |e| of ``resolution``^2 maps:", "* one", "  continued", "Next paragraph:",
             "    indented after a paragraph", "back"]
    fixed = _ext().plain_docstring_to_rst(lines)
    assert fixed[0] == "Error ``|a - b|`` and \\|e\\| of ``resolution``\\ ^2 maps:"
    doc = publish_doctree("\n".join(fixed), settings_overrides={"halt_level": 5, "warning_stream": False})
    messages = [m.astext() for m in doc.findall() if isinstance(m, system_message) and m["level"] >= 2]
    assert messages == []
    doc = publish_doctree("\n".join(lines), settings_overrides={"halt_level": 5, "warning_stream": False})
    assert [m for m in doc.findall() if isinstance(m, system_message) and m["level"] >= 2], "the raw text warns"


# ===================================================================== code blocks of the user pages
#: A block preceded by this comment (blank lines between allowed) is an excerpt of FILE (a path
#: from the repository root), which must exist; every other ```python block must run by itself.
EXCERPT = re.compile(r"<!--\s*excerpt:\s*see\s+(\S+)\s*-->")
#: A block preceded by this comment runs after the block above it on the same page (its names).
CONTINUES = re.compile(r"<!--\s*continues the block above\s*-->")
FENCE = re.compile(r"^([ \t]*)```(?:python|py|python3)[ \t]*\n(.*?)^\1```[ \t]*$", re.S | re.M)


def _user_pages():
    """(page, text): docs/*.md, docs/research/*.md and README.md's Quick start section."""
    pages = sorted((ROOT / "docs").glob("*.md")) + sorted((ROOT / "docs" / "research").glob("*.md"))
    out = [(str(p.relative_to(ROOT)), p.read_text()) for p in pages]
    readme = (ROOT / "README.md").read_text()
    quick = re.search(r"^## Quick start\n(.*?)(?=^## |\Z)", readme, re.S | re.M)
    assert quick, "README.md has no '## Quick start' section"
    return out + [("README.md#quick-start", quick.group(1))]


def code_blocks():
    """(id, code, excerpt_of) of every ```python block of the user pages, in page order."""
    blocks = []
    for page, text in _user_pages():
        previous = None
        for m in FENCE.finditer(text):
            before = text[:m.start()].rstrip().rsplit("\n", 1)[-1]
            ex = EXCERPT.search(before)
            line = text[:m.start()].count("\n") + 1
            code = textwrap.dedent(m.group(2))
            if CONTINUES.search(before):
                assert previous is not None, f"{page}:{line} continues a block, but none is above it"
                code = previous + "\n" + code
            blocks.append((f"{page}:{line}", code, ex.group(1) if ex else None))
            previous = code
    return blocks


def test_code_blocks_are_found():
    """The extraction sees the blocks (a changed fence syntax would silently test nothing)."""
    ids = [b[0] for b in code_blocks()]
    fences = sum(len(re.findall(r"^[ \t]*```(?:python|py|python3)[ \t]*$", t, re.M)) for _, t in _user_pages())
    assert len(ids) == fences, "a ```python fence the extraction does not see"
    assert any(i.startswith("docs/mitsuba.md") for i in ids) and any(i.startswith("docs/gradients.md") for i in ids)
    assert any(i.startswith("README.md#quick-start") for i in ids)
    assert EXCERPT.search("<!-- excerpt: see tests/toy_kind.py -->").group(1) == "tests/toy_kind.py"
    # a continued block runs with the one above it (the Mitsuba page's gradient needs its scene)
    mitsuba = [code for i, code, _ in code_blocks() if i.startswith("docs/mitsuba.md")]
    assert len(mitsuba) == 2 and mitsuba[1].startswith(mitsuba[0])


@pytest.mark.parametrize("block_id, code, excerpt", code_blocks(), ids=[b[0] for b in code_blocks()])
def test_docs_code_block_runs(block_id, code, excerpt, tmp_path):
    """A user page's code runs as written, in a fresh interpreter (its own Mitsuba variant and
    JIT state) in an empty folder; an excerpt names a file that exists."""
    if excerpt is not None:
        assert (ROOT / excerpt).is_file(), f"{block_id}: excerpt of {excerpt!r}, which does not exist"
        return
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
               MPLBACKEND="Agg")
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, f"{block_id} failed:\n{r.stderr[-3000:]}"


# ===================================================================== the built HTML
#: The built site (``python -m sphinx -W -b html docs docs/_build/html``), or AVSM_DOCS_HTML.
HTML = Path(os.environ.get("AVSM_DOCS_HTML", ROOT / "docs" / "_build" / "html"))


def _quote_blocks(markdown: str) -> int:
    """Number of Markdown block quotes (runs of lines starting with '>') outside code fences."""
    n, fenced, inside = 0, False, False
    for line in markdown.splitlines():
        if line.lstrip().startswith(("```", "~~~")):
            fenced = not fenced
        quote = not fenced and line.lstrip().startswith(">")
        n += quote and not inside
        inside = quote
    return n


def html_defects(root: Path) -> list[str]:
    """Rendering defects of a built site: block quotes a page's Markdown source does not write
    (docstring indentation that RST turns into a quote), and table cells whose text outside
    code holds a backtick (a '|' inside a code span splits the cell)."""
    from html.parser import HTMLParser

    class Page(HTMLParser):
        def __init__(self):
            super().__init__()
            self.quotes, self.cell, self.code, self.text, self.broken = 0, 0, 0, "", []

        def handle_starttag(self, tag, attrs):
            self.quotes += tag == "blockquote"
            self.code += tag == "code"
            if tag in ("td", "th"):
                self.cell, self.text = self.cell + 1, ""

        def handle_endtag(self, tag):
            self.code -= tag == "code" and self.code > 0
            if tag in ("td", "th") and self.cell:
                self.cell -= 1
                if "`" in self.text:
                    self.broken.append(self.text.strip()[:60])

        def handle_data(self, data):
            if self.cell and not self.code:
                self.text += data

    out = []
    for path in sorted(root.rglob("*.html")):
        rel = path.relative_to(root)
        if rel.parts[0] in ("_static", "_sources", "genindex.html", "search.html", "py-modindex.html"):
            continue
        page = Page()
        page.feed(path.read_text(errors="replace"))
        sources = [root / "_sources" / rel.with_suffix(s) for s in (".md.txt", ".ipynb.txt", ".rst.txt")]
        src = next((p.read_text(errors="replace") for p in sources if p.exists()), "")
        if page.quotes > _quote_blocks(src):
            out.append(f"{rel}: {page.quotes - _quote_blocks(src)} stray block quote(s)")
        out += [f"{rel}: broken table cell {t!r}" for t in page.broken]
    return out


def test_html_checker_finds_defects(tmp_path):
    """The checker itself, on a tiny site: a docstring-made quote and a split code cell."""
    (tmp_path / "_sources").mkdir()
    (tmp_path / "_sources" / "a.md.txt").write_text("# A\n\n> a real quote\n\n```\n> not a quote\n```\n")
    (tmp_path / "a.html").write_text("<blockquote><div>quote</div></blockquote>"
                                     "<table><tr><td><code>a</code></td><td><code>x</code> `</td></tr></table>")
    (tmp_path / "b.html").write_text("<dd><blockquote><div>T(d) = exp(-tau)</div></blockquote></dd>")
    assert html_defects(tmp_path) == ["a.html: broken table cell '`'", "b.html: 1 stray block quote(s)"]


#: Largest built page (bytes): the API reference is split per module, so no page holds it all.
MAX_PAGE_BYTES = 600_000


def test_built_html_has_no_stray_quotes_or_broken_cells():
    """The built site (when present: the README's test command builds it first, see ``HTML``)
    has no broken table cell and no stray block quote (docstrings are NumPy style through
    napoleon, displays in ``::`` literal blocks), and no page is too large."""
    if not (HTML / "index.html").exists():
        pytest.skip(f"no built site at {HTML} (python -m sphinx -W -b html docs docs/_build/html)")
    assert html_defects(HTML) == []
    assert (HTML / "_generated" / "api" / "avsm_dr.segments.html").exists(), "the API reference is one page per module"
    sizes = {str(p.relative_to(HTML)): p.stat().st_size for p in HTML.rglob("*.html")}
    big = {p: n for p, n in sizes.items() if n > MAX_PAGE_BYTES}
    assert not big, f"pages above {MAX_PAGE_BYTES} bytes: {big}"


def test_numbers_on_pages_come_from_the_committed_data():
    """The ``{claim}``, ``{measured}`` and ``{runtime}`` roles read docs/data: a claim gives its
    estimate and interval (receiver RMSE or depth L2), an unknown claim or setting fails the
    build instead of printing a stale number; the claims table lists every claim with its
    order, preset and both metrics."""
    ext = _ext()
    rows = [dict(name="c1", scene="plume", statement="A | B", order="depth", at_preset="False", estimate="0.1812",
                 low="0.17", high="0.193", depth_l2_estimate="0.5", depth_l2_low="0.4", depth_l2_high="0.61",
                 n_configs="10", indicative="False", metric_dependent="False", verdict="holds pooled")]
    claims = {r["name"]: r for r in rows}
    assert ext.claim_text("c1", claims) == "0.18 [0.17, 0.19]"
    assert ext.claim_text("c1:depth_l2", claims) == "0.50 [0.40, 0.61]"
    # bounds that print alike at 2 digits get more (up to 6); trailing zeros stay
    assert ext.interval_text(0.99997, 0.99991, 0.999998) == "1.000 [0.9999, 1.000]"
    assert ext.interval_text(1.1, 1.04, 1.2) == "1.1 [1.0, 1.2]"
    assert ext.interval_text(10.15, 7.8, 13.6) == "10 [7.8, 14]"
    assert ext.interval_text(1.0, 1.0, 1.0) == "1.00000 [1.00000, 1.00000]"
    assert ext.claim_text("c1:configs", claims) == "10" and ext.claim_text("c1:verdict", claims) == "holds pooled"
    for bad in ("c2", "c1:nonsense"):
        with pytest.raises(KeyError):
            ext.claim_text(bad, claims)
    table = ext.claims_table(rows)
    assert "| A / B (`c1`) | plume | depth | no | 0.18 [0.17, 0.19] | 0.50 [0.40, 0.61] | 10 | holds pooled |" in table
    settings = [dict(scene="plume", setting="avsm-8", rmse="0.01234", bytes_per_texel="136.0")]
    assert ext.measured_text("plume:avsm-8:rmse", settings) == "0.012"
    assert ext.measured_text("plume:avsm-8:bytes_per_texel", settings) == "136"      # not 1.4e+02
    with pytest.raises(KeyError):
        ext.measured_text("plume:avsm-9:rmse", settings)
    committed = {r["name"] for r in ext.read_rows("error_claims.csv")}
    pages = "".join(p.read_text() for p in [*(ROOT / "docs").glob("*.md"),
                                            *(ROOT / "docs" / "representations" / "notes").glob("*.md")])
    quoted = set(re.findall(r"\{claim\}`([^`:]+)", pages))
    assert quoted <= committed, sorted(quoted - committed)


def test_main_job_time_is_the_committed_runs():
    """The README's time for the main job is the committed full run's (``run_seconds`` of
    docs/data/error_curves_meta.json, rounded as the ``{runtime}`` role rounds it), and the docs
    quote it only through that role: one source for the number."""
    minutes = _ext().runtime_text("error_curves")
    readme = (ROOT / "README.md").read_text()
    stated = re.findall(r"about (\d+ min) on 2 cores after setup", readme)
    assert stated == [minutes], (stated, minutes)
    pages = "".join(p.read_text() for p in (ROOT / "docs").glob("*.md"))
    assert not re.findall(r"about \d+ min on 2 cores", pages)


def test_user_pages_have_no_internal_references():
    """User text (pages, notebooks, the API's docstrings and the studies' ``--help``) and the tests'
    docstrings never point at the project's tracker ("issue" or "stop" and a number): a reader has
    no access to it, so the text says what it means instead."""
    pages = [ROOT / "README.md", *(ROOT / "docs").rglob("*.md"), *(ROOT / "notebooks").glob("*.py"),
             *(ROOT / "avsm_dr").rglob("*.py"), *(ROOT / "experiments").rglob("*.py"),   # docstrings, --help
             *(ROOT / "tests").rglob("*.py"), *(ROOT / "scripts").glob("*.py")]
    pages = [p for p in pages if "_build" not in p.parts and "_generated" not in p.parts]
    hits = [f"{p.relative_to(ROOT)}:{i}" for p in pages for i, line in enumerate(p.read_text().splitlines(), 1)
            if re.search(r"\b(issue|stop) \d+\b", line, re.IGNORECASE)]
    assert not hits, hits


def _resolve(dotted: str):
    """The object a dotted name ``pkg.mod.attr.attr`` names: the longest importable module prefix,
    then attribute lookups; AttributeError/ImportError when nothing matches."""
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for p in parts[i:]:
            obj = getattr(obj, p)
        return obj
    raise ImportError(dotted)


def test_migration_page_new_names_exist():
    """Every dotted ``avsm_dr.``/``experiments.`` name in the "new" column of docs/migration.md,
    and every function of its keyword-argument table, resolves today (the page says where things
    went; a later move must update it)."""
    text = (ROOT / "docs" / "migration.md").read_text()
    moved, signatures = text.split("## Removed keyword arguments")
    rows = [line.split(" | ") for line in moved.splitlines() if line.startswith(("| `", "| ("))]
    current = [cells[1] for cells in rows]                          # the "new" column
    current += [line.split(" | ")[0] for line in signatures.splitlines() if line.startswith("| `")]  # functions
    dotted = r"`((?:avsm_dr|experiments)(?:\.\w+)+)`"
    names = {n for cell in current for n in re.findall(dotted, cell)}
    for cell in (cells[1] for cells in rows):                      # `module` (`a`, `b`, ...): module.a, ...
        for module, members in re.findall(dotted + r" \(([^)]*)\)", cell):
            names |= {f"{module}.{m}" for m in re.findall(r"`(\w+)`", members)}
    assert len(names) > 50, "the table layout changed: the check would test nothing"
    missing = []
    for n in sorted(names):
        try:
            _resolve(n)
        except (ImportError, AttributeError):
            missing.append(n)
    assert not missing, missing


def _settings_rows():
    """error_settings.csv rows of two kinds on one scene: presets, and a non-preset FOM that is better."""
    def row(method, setting, configs, b, dense, rmse, l2, total):
        return dict(scene="plume", method=method, setting=setting, configs=str(configs), bytes=str(b),
                    bytes_per_texel=str(dense), rmse=str(rmse), depth_l2=str(l2), total_rmse=str(total),
                    mean_error="0.001", leak_fraction="0.05", p99_error="0.1")
    return [row("avsm", "avsm-8", 10, 30.1, 64, 0.02, 0.03, 0.025),
            row("fom", "fom-4/depth_range=texel", 10, 15.4, 44, 0.04, 0.02, 0.02),
            row("fom", "fom-4", 10, 17.2, 36, 0.001, 0.001, 0.001),           # not the preset: left out
            row("avsm", "avsm-2", 1, 7.6, 16, 0.2, 0.3, 0.25)]                 # base configuration only


def _table_header(md: str, first: str) -> str:
    return next(line for line in md.splitlines() if line.startswith(f"| {first} |"))


def test_measured_tables_show_sparse_bytes_and_both_metrics(tmp_path):
    """Every generated measured table (each kind's page, the choosing page's budget table) has a
    sparse bytes column beside the dense one and both metrics (receiver RMSE, depth-uniform L2),
    and says which settings and configurations it uses; the kind pages and the budget table use
    the kinds' presets measured in every configuration, not their headline settings."""
    ext = _ext()
    ext.generate(tmp_path)
    for page in (tmp_path / "representations").glob("*.md"):
        if "| scene |" in page.read_text():
            head = _table_header(page.read_text(), "scene")
            assert "sparse bytes" in head and "dense bytes" in head and "depth L2" in head, page.name
            assert "receiver RMSE" in head and "signed mean" in head and "leak share" in head, page.name
            assert "configuration" in page.read_text().split("## Measured error")[1].split("| scene |")[0]
    settings = _settings_rows()
    meta = {"params": {"configs": [[0, "dir_a"], [0, "spot"]] + [[s, "dir_b"] for s in range(8)]}}
    table = ext.choosing_table(settings, meta)
    head = _table_header(table, "scene")
    assert "sparse" in head and "depth L2" in head and "receiver RMSE" in head
    assert "`avsm-8`" in table and "`fom-4/depth_range=texel`" in table and "`fom-4`" not in table
    assert "`avsm-2`" not in table and "s0-dir_a" in table.splitlines()[0] and "all 10 configurations" in table
    # budget in sparse bytes: at <= 32 B AVSM-8 (30.1 sparse, 64 dense) fits and has the lowest RMSE
    assert "| plume | <= 32 | `avsm-8` | 30.1 / 64 | 0.02 / 0.03 | depth L2: `fom-4/depth_range=texel` 0.02; " \
           "vs truth: `fom-4/depth_range=texel` 0.02 |" in table
    assert "| plume | <= 16 | `fom-4/depth_range=texel` | 15.4 / 44 | 0.04 / 0.02 | - |" in table
    assert "| plume | <= 8 | none fits |" in table
    page = ext.kind_page("fom", sweep=[], settings=settings, bench=[])
    assert "| plume | 15.4 | 44 | 0.04 | 0.02 | 0.02 | 0.001 | 0.05 | 2 / 1 of 2 |" in page
    assert "`fom-4/depth_range=texel`" in page.split("| scene |")[0]


def test_claims_without_depth_l2_say_why():
    ext = _ext()
    rows = [dict(name="c1", scene="plume", statement="A", order="-", at_preset="True", estimate="0.5", low="0.4",
                 high="0.6", depth_l2_estimate="", depth_l2_low="", depth_l2_high="",
                 depth_l2_note=ext.L2_NOTES["compare"], n_configs="10", verdict="holds pooled")]
    assert "| n/a (a difference of errors) |" in ext.claims_table(rows)
    assert ext._l2_note({"compare": "difference"}) == ext.L2_NOTES["compare"]
    assert ext._l2_note({"a": {"study": "global_range"}, "b": {"study": "global_range"}}) == ext.L2_NOTES["study"]
    assert ext._l2_note({"metrics": {"depth_l2": {"estimate": 1.0}}}) == ""


def test_reduce_data_keeps_sparse_bytes_depth_l2_and_presets(tmp_path):
    """``reduce_data`` on a tiny run: the sweep keeps the presets' rows of the base configuration,
    the settings' medians include sparse bytes and depth L2; a run without those columns is refused."""
    import csv
    import json
    ext = _ext()
    ec = tmp_path / "run" / "error_curves"
    ec.mkdir(parents=True)
    common = dict(scene="plume", receivers="in_volume", study="main", opaque="inline", order="-", method="fom",
                  param="4", curve="False", base="False", total_rmse="0.05", mean_error="0", leak_fraction="0",
                  p99_error="0.1", bytes_per_texel="44")
    rows = [dict(common, config="s0-dir_a", base="True", setting="fom-4/depth_range=texel", bytes="20",
                 rmse="0.01", depth_l2="0.02"),
            dict(common, config="s0-dir_a", base="True", setting="fom-4", curve="True", bytes="18", rmse="0.03",
                 depth_l2="0.04", bytes_per_texel="36"),
            dict(common, config="s1-dir_b", setting="fom-4/depth_range=texel", bytes="22", rmse="0.03",
                 depth_l2="0.06")]
    with open(ec / "data.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    claims = {"c": {"statement": "s", "scene": "plume", "estimate": 0.5, "compare": "difference",
                    "a": {"study": "main"}, "b": {"study": "main"}}}
    (ec / "findings.json").write_text(json.dumps({"claims": claims, "run_seconds": 1.0}))
    (ec / "meta.json").write_text(json.dumps({"params": {"configs": [[0, "dir_a"], [1, "dir_b"]]}}))
    ext.reduce_data(tmp_path / "run", tmp_path / "out")
    read = {n: list(csv.DictReader(open(tmp_path / "out" / n))) for n in ("error_sweep.csv", "error_settings.csv",
                                                                        "error_claims.csv")}
    sweep = {r["setting"]: r for r in read["error_sweep.csv"]}
    assert sweep["fom-4/depth_range=texel"]["preset"] == "True" and sweep["fom-4"]["preset"] == "False"
    assert sweep["fom-4"]["curve"] == "True" and sweep["fom-4"]["bytes"] == "18"
    preset = next(r for r in read["error_settings.csv"] if r["setting"] == "fom-4/depth_range=texel")
    assert (preset["configs"], preset["bytes"], preset["rmse"], preset["depth_l2"]) == ("2", "21", "0.02", "0.04")
    assert read["error_claims.csv"][0]["depth_l2_note"] == ext.L2_NOTES["compare"]
    for r in rows:
        del r["depth_l2"]
    with open(ec / "data.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    with pytest.raises(ValueError, match="depth_l2"):
        ext.reduce_data(tmp_path / "run", tmp_path / "out2")


def test_committed_data_has_sparse_bytes_and_depth_l2():
    """docs/data is reduced from a run with sparse bytes and the depth-uniform L2 (else the tables
    above show '-'): regenerate with ``python docs/_ext/avsm_docs.py data DIR``."""
    ext = _ext()
    settings, sweep = ext.read_rows("error_settings.csv"), ext.read_rows("error_sweep.csv")
    assert settings and {"bytes", "depth_l2"} <= set(settings[0]), "regenerate docs/data"
    assert sweep and "preset" in sweep[0] and {"bytes", "depth_l2"} <= set(sweep[0])
    assert "depth_l2_note" in ext.read_rows("error_claims.csv")[0]
