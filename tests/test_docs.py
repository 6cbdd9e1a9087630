"""The docs' generated parts: README's kinds table is current, every public object has a docstring,
and the build-time generator writes a page per kind from the registry and the committed data.
(The Sphinx build itself runs in CI: README's test command, warnings as errors.)"""
import importlib.util
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
    api = (tmp_path / "api.md").read_text()
    assert ".. automodule:: avsm_dr.segments" in api and "avsm_dr.__main__" not in api
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
