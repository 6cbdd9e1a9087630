"""Redrawing a study's figures from a table (experiments._replot): typed rows, the study's own
plot, errors that name the argument, and the ordering page's figure drawn from its committed data."""
import csv
from pathlib import Path

import numpy as np
import pytest

from experiments import _replot

ROOT = Path(__file__).resolve().parents[1]


def _ordering_table(path):
    """A small data.csv of ``ordering``: two scenes, two configurations, N = 4 and 8."""
    rows = []
    for si, scene in enumerate(("three_columns", "plume")):
        for ci, config in enumerate(("s0-dir_a", "s1-spot")):
            for n in (4, 8):
                for sort in (False, True):
                    e = (1 + si + ci) * 0.1 / n
                    rows.append(dict(scene=scene, config=config, param=n, sorted=sort, rmse=e, depth_l2=e / 2,
                                     flicker_rms=0.0 if sort else e / 3, flicker_depth_l2=0.0 if sort else e / 4))
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return rows


def test_typed_reads_back_what_a_study_wrote():
    rows = _replot.typed([{"a": "True", "b": "8", "c": "0.25", "d": "s0-dir_a", "e": "", "f": "1e-07"}])
    assert rows == [{"a": True, "b": 8, "c": 0.25, "d": "s0-dir_a", "e": "", "f": 1e-07}]
    assert type(rows[0]["b"]) is int and type(rows[0]["a"]) is bool


def test_replot_draws_the_studys_figure_from_a_table(tmp_path):
    _ordering_table(tmp_path / "t.csv")
    files = _replot.replot("ordering", tmp_path / "t.csv", tmp_path / "out")
    assert files == [tmp_path / "out" / "ordering.png"]
    assert files[0].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    again = _replot.replot("ordering", tmp_path / "t.csv", tmp_path / "again", pdf=True)
    assert [p.name for p in again] == ["ordering.png", "ordering.pdf"]
    assert again[0].read_bytes() == files[0].read_bytes()          # fixed metadata: same rows, same bytes


def test_replot_reads_a_gzipped_table(tmp_path):
    """A committed run's ``data.csv.gz`` draws the same figure as the plain table."""
    import gzip
    _ordering_table(tmp_path / "t.csv")
    (tmp_path / "t.csv.gz").write_bytes(gzip.compress((tmp_path / "t.csv").read_bytes()))
    assert _replot.read_table(tmp_path / "t.csv.gz") == _replot.read_table(tmp_path / "t.csv")
    (plain,) = _replot.replot("ordering", tmp_path / "t.csv", tmp_path / "plain")
    (packed,) = _replot.replot("ordering", tmp_path / "t.csv.gz", tmp_path / "packed")
    assert packed.read_bytes() == plain.read_bytes()
    (tmp_path / "bad.csv.gz").write_bytes(b"not gzip")
    with pytest.raises(ValueError, match="table"):
        _replot.replot("ordering", tmp_path / "bad.csv.gz", tmp_path / "out")


def test_replot_errors_name_the_argument(tmp_path):
    _ordering_table(tmp_path / "t.csv")
    with pytest.raises(ValueError, match="study"):
        _replot.replot("no_such_study", tmp_path / "t.csv", tmp_path / "out")
    with pytest.raises(ValueError, match="study: .*redraw"):
        _replot.replot("stress", tmp_path / "t.csv", tmp_path / "out")
    with pytest.raises(ValueError, match="table"):
        _replot.replot("ordering", tmp_path / "missing.csv", tmp_path / "out")
    (tmp_path / "empty.csv").write_text("scene,config\n")
    with pytest.raises(ValueError, match="table"):
        _replot.replot("ordering", tmp_path / "empty.csv", tmp_path / "out")


def test_ordering_page_figure_is_drawn_from_its_committed_table(tmp_path):
    """docs/research/ordering/ordering.png is what the committed configs.csv draws with this
    revision's plot code (redraw with ``python -m experiments._replot ordering
    docs/research/ordering/configs.csv --out docs/research/ordering`` when the plot changes)."""
    here = ROOT / "docs" / "research" / "ordering"
    from matplotlib.image import imread
    (png,) = _replot.replot("ordering", here / "configs.csv", tmp_path)
    drawn, committed = imread(png), imread(here / "ordering.png")
    assert drawn.shape == committed.shape
    # pixels, not bytes: another FreeType build may move anti-aliasing by a level or two, while a
    # stale figure (a colour, a tick, a moved point) changes thousands of pixels by far more
    changed = np.abs(drawn - committed).max(axis=-1) > 0.25
    assert changed.mean() < 1e-3, f"{changed.sum()} pixels differ: redraw the figure (command above)"
