"""One figure style for every plot of the studies (not part of the installed package).

Each kind has one colour, one marker and one line style in every figure: a fixed table for
the built-in kinds (colours from Paul Tol's "muted" scheme, distinguishable under the common
colour-vision deficiencies: P. Tol, "Colour Schemes", SRON/EPS/TN/09-002, 2021), the line
style shared by a family of kinds, the marker unique per kind (so no figure relies on colour
alone); a kind registered by a user
takes the next unused (colour, marker) pair in registry order, and a name the registry does
not know gets a pair chosen from a checksum of the name, so a figure never depends on chance.

:func:`savefig` writes a raster PNG and a vector PDF beside it; :func:`grid` and
:func:`legend_below` are the small-multiples helpers (one panel per family or scene, a legend
outside the data).  Matplotlib is imported only when a figure is made or saved.
"""
from __future__ import annotations

import math
import zlib
from pathlib import Path

from avsm_dr import REGISTRY, kinds

#: Tol's muted colours by name, black for the reference, then two of Tol's vibrant colours (so
#: that every built-in kind has a colour of its own).
PALETTE = {"rose": "#CC6677", "indigo": "#332288", "sand": "#DDCC77", "green": "#117733", "cyan": "#88CCEE",
           "wine": "#882255", "teal": "#44AA99", "olive": "#999933", "purple": "#AA4499", "black": "#000000",
           "orange": "#EE7733", "blue": "#0077BB"}

#: Families of the built-in kinds, in figure order: name -> (line style, kinds).
FAMILIES = {
    "AVSM (streaming nodes)": ("-", ("avsm", "avsm_adaptive", "avsm_march")),
    "node lists (error-bounded / offline)": ("--", ("dsm", "greedy", "optimal")),
    "linear bases": ("-.", ("fom", "osm", "basis")),
    "moments / homogeneous": (":", ("moments", "beer")),
    "reference": ((0, (1, 1)), ("exact",)),
}

#: The fixed style of each built-in kind: kind -> (colour name, marker).  Colours and markers
#: differ between all kinds, so a figure that draws every kind needs no colours of its own.
BUILTIN = {
    "avsm": ("rose", "o"), "avsm_adaptive": ("purple", "D"), "avsm_march": ("cyan", "v"),
    "dsm": ("wine", "s"), "greedy": ("teal", "^"), "optimal": ("green", "P"),
    "fom": ("indigo", "<"), "osm": ("orange", ">"), "basis": ("sand", "p"),
    "moments": ("olive", "*"), "beer": ("blue", "h"),
    "exact": ("black", "x"),
}
#: Line style of kinds outside :data:`FAMILIES` (a user's own kinds).
USER_LINESTYLE = (0, (5, 1, 1, 1, 1, 1))
USER_FAMILY = "other kinds"

#: Matplotlib settings of every figure (used by :func:`context`).
RC = {"font.size": 8, "axes.titlesize": 9, "axes.labelsize": 8, "legend.fontsize": 7,
      "xtick.labelsize": 7, "ytick.labelsize": 7, "lines.linewidth": 1.3, "lines.markersize": 4,
      "axes.spines.top": False, "axes.spines.right": False, "axes.grid": True,
      "grid.alpha": 0.3, "grid.linewidth": 0.5, "legend.frameon": False}

_MARKERS = ("o", "D", "v", "s", "^", "P", "<", ">", "p", "*", "h", "X", "d", "H", "8", "x")


def _spare_pairs() -> list[tuple[str, str]]:
    used = set(BUILTIN.values())
    colours = [c for c in PALETTE if c != "black"]
    return [(c, m) for m in _MARKERS for c in colours if (c, m) not in used]


def family(kind: str) -> str:
    """Family name of ``kind`` (a key of :data:`FAMILIES`, or :data:`USER_FAMILY`)."""
    for name, (_, members) in FAMILIES.items():
        if kind in members:
            return name
    return USER_FAMILY


def families(kinds_: list[str]) -> dict[str, list[str]]:
    """``kinds_`` grouped by :func:`family`, families in :data:`FAMILIES` order (user kinds
    last), kinds in the order given: the panels of a small-multiples figure."""
    order = list(FAMILIES) + [USER_FAMILY]
    out: dict[str, list[str]] = {}
    for f in order:
        members = [k for k in kinds_ if family(k) == f]
        if members:
            out[f] = members
    return out


def style(kind: str) -> dict:
    """Plot keywords of ``kind``: ``color`` (hex), ``marker``, ``linestyle``, the same in every
    figure.  Built-in kinds: :data:`BUILTIN`; a registered user kind: the n-th unused
    (colour, marker) pair, n its position among the non-built-in kinds in registry order;
    any other name: a pair chosen by the CRC-32 of the name."""
    if not isinstance(kind, str) or not kind:
        raise ValueError(f"kind: expected a non-empty string, got {kind!r}")
    if kind in BUILTIN:
        colour, marker = BUILTIN[kind]
        return {"color": PALETTE[colour], "marker": marker,
                "linestyle": FAMILIES[family(kind)][0]}
    spare = _spare_pairs()
    user = [k for k in kinds() if k not in BUILTIN]
    i = user.index(kind) if kind in REGISTRY and kind in user else zlib.crc32(kind.encode())
    colour, marker = spare[i % len(spare)]
    return {"color": PALETTE[colour], "marker": marker, "linestyle": USER_LINESTYLE}


def variant_style(kind: str) -> dict:
    """:func:`style` of a variant of ``kind`` drawn beside its main curve (e.g. a per-texel
    depth range): the same colour and marker, hollow, thinner and lighter."""
    s = style(kind)
    return dict(s, markerfacecolor="none", linewidth=0.9, alpha=0.75)


def context():
    """``matplotlib.rc_context`` with :data:`RC`: ``with plotstyle.context(): ...`` makes the
    figures of a block in the common style without changing global settings."""
    import matplotlib
    return matplotlib.rc_context(RC)


def panel_shape(n: int, columns: int = 5) -> tuple[int, int]:
    """(rows, columns) of ``n`` small-multiple panels: at most ``columns`` a row, rows filled
    evenly (7 panels at most 4 a row: 2 x 4, not 4 + 3 of unequal widths)."""
    rows = math.ceil(n / columns)
    return rows, math.ceil(n / rows)


def grid(n_rows: int, n_cols: int, *, panel: tuple[float, float] = (2.6, 2.1), sharex=True, sharey=True,
         **kw):
    """Small multiples: ``(fig, axes)`` with ``axes`` always 2-D (``n_rows x n_cols``), each panel
    ``panel`` inches (width, height), axes shared by default so that panels compare at a glance."""
    for name, v in (("n_rows", n_rows), ("n_cols", n_cols)):
        if not isinstance(v, int) or v < 1:
            raise ValueError(f"{name}: expected a positive integer, got {v!r}")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(panel[0] * n_cols, panel[1] * n_rows), squeeze=False,
                             sharex=sharex, sharey=sharey, layout="constrained", **kw)
    return fig, axes


def legend_below(fig, axes=None, *, ncol: int | None = None, handles=None, labels=None):
    """One legend for the whole figure, centred below the panels (never over data); entries
    are gathered from ``axes`` (default: all of ``fig``'s axes), deduplicated by label, in
    first-seen order.  Returns the legend (``None`` when there is nothing to show)."""
    if handles is None:
        seen: dict[str, object] = {}
        for ax in (fig.axes if axes is None else list(getattr(axes, "flat", axes))):
            for h, lab in zip(*ax.get_legend_handles_labels()):
                if not lab.startswith("_") and lab not in seen:
                    seen[lab] = h
        labels, handles = list(seen), list(seen.values())
    if not handles:
        return None
    ncol = ncol or min(len(handles), 6)
    return fig.legend(handles, labels, loc="outside lower center", ncol=ncol)


def log_ticks(ax, axis: str = "y") -> None:
    """Labels of a log ``axis`` (``"x"`` or ``"y"``) of ``ax`` that never crowd: at 1, 2 and 5 x
    10^k where the shown range spans at most 1.2 decades, at 1 and 3 x 10^k up to 3 decades,
    else at every decade; plain numbers (``%g``), minor ticks unlabelled.  Call it after the
    data are drawn (it reads the axis limits)."""
    import numpy as np
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter
    if axis not in ("x", "y"):
        raise ValueError(f"axis: expected 'x' or 'y', got {axis!r}")
    lo, hi = sorted(ax.get_ylim() if axis == "y" else ax.get_xlim())
    span = np.log10(hi / lo) if lo > 0 else np.inf
    subs = (1.0, 2.0, 5.0) if span <= 1.2 else (1.0, 3.0) if span <= 3 else (1.0,)
    a = ax.yaxis if axis == "y" else ax.xaxis
    a.set_major_locator(LogLocator(base=10, subs=subs))
    a.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    a.set_minor_formatter(NullFormatter())


def kind_handle(kind: str, label: str | None = None, **kw):
    """A legend entry (``Line2D`` without data) in the style of ``kind``, labelled ``label``
    (default: the kind's name); ``kw`` override the style."""
    from matplotlib.lines import Line2D
    return Line2D([], [], **dict(style(kind), **kw), label=kind if label is None else label)


def legend_columns(fig, columns):
    """A figure legend below the panels with one legend column per inner list of
    ``columns`` (lists of handles, e.g. one per family, so that each column of the legend
    reads as one group); shorter columns are padded with blank entries."""
    from matplotlib.lines import Line2D
    columns = [list(c) for c in columns if c]
    if not columns:
        return None
    depth = max(len(c) for c in columns)
    flat = [h for c in columns for h in c + [Line2D([], [], linestyle="none", label=" ")] * (depth - len(c))]
    return fig.legend(flat, [h.get_label() for h in flat], loc="outside lower center", ncol=len(columns))


def render(fig, file, fmt: str) -> None:
    """Write ``fig`` to ``file`` (a path or binary file) as ``fmt`` (``"png"``, ``"pdf"``,
    ``"svg"``) with fixed metadata, so the same figure gives the same bytes."""
    if fmt not in ("png", "pdf", "svg"):
        raise ValueError(f"fmt: expected 'png', 'pdf' or 'svg', got {fmt!r}")
    meta = {"png": {"Software": None}, "pdf": {"CreationDate": None, "Producer": None, "Creator": None},
            "svg": {"Date": None, "Creator": None}}[fmt]
    import matplotlib
    kw = {"dpi": 150} if fmt == "png" else {}
    with matplotlib.rc_context({"pdf.fonttype": 42, "svg.hashsalt": "avsm_dr"}):   # TrueType: editable text
        fig.savefig(file, format=fmt, bbox_inches="tight", metadata=meta, **kw)


def savefig(fig, path) -> tuple[Path, Path]:
    """Write ``fig`` as ``path`` with suffix ``.png`` (raster, 150 dpi) and beside it with
    suffix ``.pdf`` (vector); returns ``(png_path, pdf_path)``.  A ``path`` without a suffix
    or with ``.png`` / ``.pdf`` names both; any other suffix raises ``ValueError``."""
    path = Path(path)
    if path.suffix not in ("", ".png", ".pdf"):
        raise ValueError(f"path: expected a .png or .pdf name (both are written), got {str(path)!r}")
    png, pdf = path.with_suffix(".png"), path.with_suffix(".pdf")
    png.parent.mkdir(parents=True, exist_ok=True)
    render(fig, png, "png")
    render(fig, pdf, "pdf")
    return png, pdf
