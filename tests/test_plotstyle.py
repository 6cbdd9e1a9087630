"""The figure style: one fixed, distinct look per kind, PNG + PDF output, small multiples."""
import subprocess
import sys

import pytest

import avsm_dr as ad
from experiments import _plotstyle as plotstyle


def _builtin():
    return [k for k in ad.kinds() if ad.REGISTRY[k].__module__.startswith("avsm_dr.")]


def test_every_builtin_kind_has_a_fixed_distinct_style():
    kinds = _builtin()
    assert set(kinds) == set(plotstyle.BUILTIN), "give a new built-in kind a row in plotstyle.BUILTIN"
    pairs = [(plotstyle.style(k)["color"], plotstyle.style(k)["marker"]) for k in kinds]
    assert len(set(pairs)) == len(pairs)
    # every built-in kind has a colour of its own (figures that draw all kinds, e.g. the time-error fronts)
    assert len({c for c, _ in pairs}) == len(pairs)
    # the pair the issue found shared (avsm and osm one blue line) differs in colour, marker and line
    a, o = plotstyle.style("avsm"), plotstyle.style("osm")
    assert a["color"] != o["color"] and a["marker"] != o["marker"] and a["linestyle"] != o["linestyle"]
    # within a family (one small-multiples panel) colours differ too
    for fam, members in plotstyle.families(kinds).items():
        colours = [plotstyle.style(k)["color"] for k in members]
        assert len(set(colours)) == len(colours), fam
    assert all(c in plotstyle.PALETTE.values() for c, _ in pairs)


def test_user_kinds_get_unused_deterministic_styles():
    taken = {(plotstyle.style(k)["color"], plotstyle.style(k)["marker"]) for k in _builtin()}
    s = plotstyle.style("my_kind_not_registered")
    assert (s["color"], s["marker"]) not in taken
    assert s == plotstyle.style("my_kind_not_registered")
    assert plotstyle.family("my_kind_not_registered") == plotstyle.USER_FAMILY
    # the same in a fresh process (no dependence on hash seeds or import order)
    code = "import experiments._plotstyle as p; print(p.style('my_kind_not_registered'))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == str(s)
    with pytest.raises(ValueError, match="kind"):
        plotstyle.style("")


def test_savefig_writes_png_and_pdf(tmp_path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    with plotstyle.context():
        fig, axes = plotstyle.grid(2, 3)
        assert axes.shape == (2, 3)
        for kind in ("avsm", "osm"):
            axes[0][0].plot([1, 2], [1, 0.5], **plotstyle.style(kind), label=kind)
        assert plotstyle.legend_below(fig).get_texts()[1].get_text() == "osm"
        png, pdf = plotstyle.savefig(fig, tmp_path / "sub" / "fig.png")
        again = plotstyle.savefig(fig, tmp_path / "again")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and pdf.read_bytes()[:5] == b"%PDF-"
    assert (png.name, pdf.name) == ("fig.png", "fig.pdf")
    # fixed metadata: the same figure gives the same bytes (results record checksums)
    assert again[1].read_bytes() == pdf.read_bytes() and again[0].read_bytes() == png.read_bytes()
    plt.close(fig)
    with pytest.raises(ValueError, match="path"):
        plotstyle.savefig(fig, tmp_path / "fig.jpg")
    with pytest.raises(ValueError, match="n_cols"):
        plotstyle.grid(1, 0)


@pytest.mark.parametrize("lo, hi", [(1.5e-3, 7e-2), (8e-4, 6e-2), (1e-3, 1.2e-1), (3e-3, 8e-3), (1e-7, 1e-1)])
def test_log_ticks_label_a_few_values_without_overlap(lo, hi):
    """The ordering figure's depth-L2 axis (under two decades) had matplotlib's minor labels
    (2, 3, 4, 6 x 10^k) printed on top of each other: log_ticks labels a few values, none of
    them overlapping, at least two inside the range, minor ticks unlabelled."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    with plotstyle.context():
        fig, axes = plotstyle.grid(1, 1, panel=(3.0, 2.6))
        ax = axes[0][0]
        ax.semilogy([4, 8, 16], [hi, (lo * hi) ** 0.5, lo])
        plotstyle.log_ticks(ax)
        fig.canvas.draw()
        ymin, ymax = ax.get_ylim()
        major = [t for t in ax.yaxis.get_major_ticks() if ymin <= t.get_loc() <= ymax and t.label1.get_text()]
        assert 2 <= len(major) <= 8, [t.label1.get_text() for t in major]
        assert not [t.label1.get_text() for t in ax.yaxis.get_minor_ticks() if t.label1.get_text()]
        boxes = sorted((t.label1.get_window_extent() for t in major), key=lambda b: b.y0)
        assert all(a.y1 <= b.y0 for a, b in zip(boxes, boxes[1:])), [(b.y0, b.y1) for b in boxes]
        with pytest.raises(ValueError, match="axis"):
            plotstyle.log_ticks(ax, "z")
    plt.close(fig)


def test_panel_shape_fills_rows_evenly():
    from experiments._plotstyle import panel_shape
    assert panel_shape(7, 4) == (2, 4) and panel_shape(5, 4) == (2, 3) and panel_shape(3, 4) == (1, 3)
    assert all(r * c >= n and c <= k and (r - 1) * c < n for k in (3, 4, 5) for n in range(1, 30)
               for r, c in [panel_shape(n, k)])
