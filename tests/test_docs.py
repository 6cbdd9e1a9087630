"""The docs build (API reference from docstrings) runs and finds no undocumented public object."""
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_docs_build(tmp_path):
    spec = importlib.util.spec_from_file_location("docs_build", ROOT / "docs" / "build.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    # the generated kinds tables in README.md and the guide match the registry (no drift)
    assert mod.update_kinds_tables(check=True) == [], "run python docs/build.py"
    assert mod.main(["--out", str(tmp_path), "--results", str(tmp_path / "none")]) == 0
    api = (tmp_path / "api.md").read_text()
    assert "avsm_dr.segments" in api and "Segments" in api and "class `AVSM" in api
    assert (tmp_path / "index.md").read_text().startswith("# avsm_dr")
