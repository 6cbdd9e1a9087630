"""The notebooks (jupytext ``py:percent`` sources in notebooks/) run top to bottom at small sizes,
so they cannot drift from the API; the docs build runs them too (CI: at the small sizes, before
the tests), and a test reads that build's executed copy instead of running a notebook twice when
the copy is newer than everything the notebook runs."""
from pathlib import Path

import pytest

jupytext = pytest.importorskip("jupytext")
nbclient = pytest.importorskip("nbclient")

#: matplotlib's backend in a Jupyter kernel (figures as image/png outputs; Agg would drop them).
INLINE = "module://matplotlib_inline.backend_inline"
ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("[0-9][0-9]_*.py"))
#: Where the docs build (myst-nb, ``nb_execution_mode = "force"``) writes the notebooks it executed.
BUILT = ROOT / "docs" / "_build" / "jupyter_execute" / "_generated" / "notebooks"


def built_copy(path: Path):
    """The docs build's executed copy of the notebook ``path`` when it was written after every
    file it runs was last changed (its source, the package, the studies, docs/data): the build
    ran this code and raises on a cell's error.  None otherwise (no build, or a stale one)."""
    built = BUILT / f"{path.stem}.ipynb"
    if not built.exists():
        return None
    return built if built.stat().st_mtime > newest_input(path) else None


def newest_input(path: Path) -> float:
    """The latest modification time of what the notebook ``path`` runs: its source, the package,
    the studies and docs/data."""
    inputs = [path, *(ROOT / "avsm_dr").rglob("*.py"), *(ROOT / "experiments").rglob("*.py"),
              *(ROOT / "docs" / "data").iterdir()]
    return max(p.stat().st_mtime for p in inputs)


def test_notebooks_found():
    assert len(NOTEBOOKS) >= 5, NOTEBOOKS


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_runs(path, tmp_path, monkeypatch):
    monkeypatch.setenv("AVSM_DR_NOTEBOOK_SMALL", "1")      # the notebooks' small sizes
    monkeypatch.setenv("AVSM_DR_RESULTS", str(tmp_path))    # no results/: 03 reads docs/data
    monkeypatch.setenv("MPLBACKEND", INLINE)                # figures become outputs, as in the docs
    nb = jupytext.read(path, fmt="py:percent")
    assert nb.cells[0].cell_type == "markdown" and nb.cells[0].source.startswith("# "), "title cell first"
    built = built_copy(path)
    if built is not None:                                   # the docs build ran it: read its outputs
        import nbformat
        ran = nbformat.read(built, as_version=4)
        assert [c.source for c in ran.cells if c.cell_type == "code"] == \
            [c.source for c in nb.cells if c.cell_type == "code"], f"{built} is not this notebook"
        nb = ran
    else:
        client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                                         resources={"metadata": {"path": str(tmp_path)}})
        client.execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.output_type == "error"]
    # the notebook shows something: printed text, and figures wherever it draws
    assert any(o.output_type == "stream" for o in outputs)
    if "plt.show()" in path.read_text():
        assert any("image/png" in o.get("data", {}) for o in outputs), "no figure rendered"


def test_a_stale_docs_build_is_not_read(tmp_path, monkeypatch):
    """A built copy newer than every input is read; one older than an input (a notebook or a
    module changed after the build) is run again, not trusted."""
    import os
    monkeypatch.setitem(globals(), "BUILT", tmp_path)
    src = NOTEBOOKS[0]
    copy = tmp_path / f"{src.stem}.ipynb"
    copy.write_text("{}")
    newest = newest_input(src)      # every input: a study edited after the package counts too
    os.utime(copy, (newest + 3600, newest + 3600))
    assert built_copy(src) == copy
    os.utime(copy, (newest - 1, newest - 1))
    assert built_copy(src) is None


def test_your_volume_reads_a_vol_file(tmp_path, monkeypatch):
    """05 loads a user's .vol grid (not only the built-in plume): a small random grid."""
    import numpy as np

    from avsm_dr import io
    rng = np.random.default_rng(0)
    io.write_vol(tmp_path / "mine.vol", rng.random((6, 8, 6)).astype(np.float32))
    monkeypatch.setenv("AVSM_DR_NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("AVSM_DR_VOLUME", str(tmp_path / "mine.vol"))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = jupytext.read(NOTEBOOKS[0].parent / "05_your_volume.py", fmt="py:percent")
    nb.cells = nb.cells[:next(i for i, c in enumerate(nb.cells) if c.source.startswith("## Capture"))]
    nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(tmp_path)}}).execute()
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []))
    assert "mine: grid (6, 8, 6)" in text
