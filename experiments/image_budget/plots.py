"""Figures of the ``image_budget`` study: the budget map (resolution x bytes per texel, each cell
coloured by its best kind), compression FLIP against bytes per kind, and frame 0's images."""
from __future__ import annotations

import numpy as np

#: Compression FLIPs below this are drawn at it on the log axis (exact agreement gives 0).
FLIP_FLOOR = 1e-4


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _text_colour(hex_colour: str) -> str:
    """Black or white, whichever reads on ``hex_colour`` (relative luminance)."""
    r, g, b = (int(hex_colour[i:i + 2], 16) / 255 for i in (1, 3, 5))
    return "white" if 0.2126 * r + 0.7152 * g + 0.0722 * b < 0.45 else "black"


def budget_map(res, cells, P):
    """``budget_map.png``: one panel per animation; rows = shadow-map resolutions, columns =
    budgets; a cell names its best kind and shows it in the kind's colour
    (:mod:`experiments._plotstyle`): filled where compression is invisible, framed (white
    inside) where even the best kind within the budget is visible; the threshold cell is
    outlined in black."""
    from matplotlib.patches import Patch, Rectangle
    from .. import _plotstyle as plotstyle
    _plt()
    settings, resolutions, budgets = P["settings"], P["resolutions"], P["budgets"]
    with plotstyle.context():
        fig, axes = plotstyle.grid(1, len(settings), panel=(max(0.95 * len(budgets) + 0.9, 4.2),
                                                            max(0.62 * len(resolutions) + 0.9, 2.3)),
                                   sharex=False, sharey=False)
        shown = []
        for j, setting in enumerate(settings):
            ax = axes[0][j]
            for c in (c for c in cells if c["setting"] == setting):
                x, y = budgets.index(c["budget"]), resolutions.index(c["resolution"])
                if not c["best_kind"]:
                    ax.add_patch(Rectangle((x - 0.5, y - 0.5), 1, 1, facecolor="white", edgecolor="0.7", lw=0.5))
                    ax.text(x, y, "none fits", ha="center", va="center", fontsize=6, color="0.4")
                    continue
                colour = plotstyle.style(c["best_kind"])["color"]
                if c["best_kind"] not in shown:
                    shown.append(c["best_kind"])
                if c["invisible"]:
                    ax.add_patch(Rectangle((x - 0.5, y - 0.5), 1, 1, facecolor=colour, edgecolor="white", lw=1.0))
                else:                        # visible: the kind's colour as a frame, white inside
                    ax.add_patch(Rectangle((x - 0.44, y - 0.44), 0.88, 0.88, facecolor="white", edgecolor=colour,
                                           lw=3.0))
                if c["threshold"]:
                    ax.add_patch(Rectangle((x - 0.46, y - 0.46), 0.92, 0.92, facecolor="none", edgecolor="black",
                                           lw=2.0))
                tc = _text_colour(colour) if c["invisible"] else "black"
                ratio = c["best_flip_compression"] / c["noise_flip"] if c["noise_flip"] > 0 else float("nan")
                ax.text(x, y + 0.13, c["best_label"], ha="center", va="center", fontsize=6.5, color=tc)
                ax.text(x, y - 0.2, f"{ratio:.2g}x noise", ha="center", va="center", fontsize=5.5, color=tc)
            ax.set_xlim(-0.5, len(budgets) - 0.5)
            ax.set_ylim(-0.5, len(resolutions) - 0.5)
            ax.set_xticks(range(len(budgets)), [f"{b:g}" for b in budgets])
            ax.set_yticks(range(len(resolutions)), [f"{r}$^2$" for r in resolutions])
            ax.grid(False)
            ax.set_xlabel("budget (bytes per texel)")
            if j == 0:
                ax.set_ylabel("map (texels)")
            ax.set_title(f"{setting}: best kind per budget")
        kinds_ = [Patch(facecolor=plotstyle.style(k)["color"], label=k) for k in shown]
        marks = [Patch(facecolor="0.45", label="filled: compression invisible (FLIP to exact < reference noise)"),
                 Patch(facecolor="white", edgecolor="0.45", lw=2.0,
                       label="framed: visible; the least visible kind within the budget"),
                 Patch(facecolor="none", edgecolor="black", lw=2.0, label="black outline: threshold (invisible from "
                                                                         "here on)")]
        plotstyle.legend_columns(fig, [kinds_[i:i + 3] for i in range(0, len(kinds_), 3)] + [marks])
        fig.suptitle("Cheapest kind whose compression is invisible, else the least visible\n"
                     "cell text: its size (the most common over configurations); its compression FLIP / the "
                     "reference-noise FLIP", fontsize=7.5)
        res.save_figure(fig, "budget_map.png")


def _distinct(rows, setting, resolution):
    """{kind: [(mean bytes, mean compression FLIP, label)]} over configurations and frames, one
    entry per size label."""
    acc = {}
    for r in rows:
        if r["setting"] == setting and r["resolution"] == resolution:          # a label's rows agree at every budget
            acc.setdefault((r["kind"], r["label"]), {})[(r["config"], r["frame"])] = (r["bytes_per_texel"],
                                                                                      r["flip_compression"])
    out = {}
    for (kind, lab), by_frame in acc.items():
        v = np.array(list(by_frame.values()))
        out.setdefault(kind, []).append((float(v[:, 0].mean()), float(v[:, 1].mean()), lab))
    return {k: sorted(v) for k, v in out.items()}


def flip_vs_bytes(res, rows, P):
    """``flip_vs_bytes.png``: rows = animations, columns = resolutions; compression FLIP (mean
    over configurations and frames) against stored bytes per texel, one line per kind in its
    fixed style (:mod:`experiments._plotstyle`), with the reference's and the renders' noise
    FLIP as horizontal lines and ``exact``'s bytes as a vertical one; the legend below the
    panels, one column per family of kinds."""
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullLocator
    from .. import _plotstyle as plotstyle
    _plt()
    settings, resolutions = P["settings"], P["resolutions"]
    drawn = []
    marks = [dict(color="black", ls="--", lw=0.9), dict(color="0.5", ls=":", lw=0.9),
             dict(color="black", ls=(0, (1, 1)), lw=0.8)]           # reference noise, render noise, exact
    lines = [Line2D([], [], **kw, label=lab) for kw, lab in zip(marks, (
        "reference noise (FLIP of its halves)", "render noise (exact, two seeds)", "exact's bytes"))]
    with plotstyle.context():
        fig, axes = plotstyle.grid(len(settings), len(resolutions), panel=(2.7, 2.2))
        for i, setting in enumerate(settings):
            for j, resolution in enumerate(resolutions):
                ax = axes[i][j]
                d = _distinct(rows, setting, resolution)
                for kind in P["kinds"]:
                    if kind == "exact" or kind not in d:
                        continue
                    x = [p[0] for p in d[kind]]
                    y = [max(p[1], FLIP_FLOOR) for p in d[kind]]
                    ax.plot(x, y, **plotstyle.style(kind), label=kind)
                    if kind not in drawn:
                        drawn.append(kind)
                sel = [r for r in rows if r["setting"] == setting and r["resolution"] == resolution
                       and r["kind"] == "exact" and r["budget"] == P["budgets"][0]]
                ax.axhline(np.mean([r["flip_reference_noise"] for r in sel]), **marks[0])
                ax.axhline(np.mean([r["flip_render_noise"] for r in sel]), **marks[1])
                if "exact" in d:
                    ax.axvline(d["exact"][0][0], **marks[2])
                ax.set_xscale("log", base=2)
                ax.set_yscale("log")
                ax.set_title(f"{setting}, {resolution}$^2$ map")
                if i == len(settings) - 1:
                    ax.set_xlabel("stored bytes per texel")
        lo, hi = axes[0][0].get_xlim()
        ticks = [2.0 ** e for e in range(int(np.ceil(np.log2(lo))), int(np.floor(np.log2(hi))) + 1)]
        for ax in axes.flat:             # shared axes: plain numbers at the powers of two
            ax.xaxis.set_major_locator(FixedLocator(ticks))
            ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            ax.xaxis.set_minor_locator(NullLocator())
            plotstyle.log_ticks(ax, "y")
        for row in axes:                 # on the panels (a figure-wide label runs into a one-panel legend)
            row[0].set_ylabel("compression FLIP to exact")
        columns = [[plotstyle.kind_handle(k) for k in members]
                   for members in plotstyle.families(drawn).values()] + [lines]
        plotstyle.legend_columns(fig, columns)
        res.save_figure(fig, "flip_vs_bytes.png")


def _shown(label: str, imgs: dict) -> str:
    """``label`` if frame 0 (the first configuration's) has its image, else the same kind's
    setting that configuration rendered (sizes within a budget differ between configurations:
    ``label`` is the most common one), else ``'exact'``."""
    if label in imgs:
        return label
    kind = label.split("-")[0]
    return next((k for k in imgs if k.split("-")[0] == kind), "exact")


def frame_images(res, found, frames0, whites, P):
    """``frames.png``: frame 0 of each animation in the first configuration at the finest
    resolution: the reference, exact, the threshold's size (or the least visible at the largest
    budget) and the best at the smallest budget, tonemapped as measured, with each one's
    compression FLIP."""
    from . import render as R
    _plt()
    from .. import _plotstyle as plotstyle
    finest = str(P["resolutions"][-1])
    with plotstyle.context():
        fig, axes = plotstyle.grid(len(P["settings"]), 5, panel=(1.55, 1.75), sharex=True, sharey=True)
        for i, setting in enumerate(P["settings"]):
            imgs = frames0[setting]["images"]
            ref, s = frames0[setting]["reference"], whites[setting]
            cells = [c for c in found["map"] if c["setting"] == setting and str(c["resolution"]) == finest]
            thr = found["thresholds"][setting][finest]
            low = cells[0]["best_label"] or "exact"
            high = thr["label"] if thr["reached"] else (cells[-1]["best_label"] or "exact")
            high, low = _shown(high, imgs), _shown(low, imgs)
            panels = [("reference", ref), ("exact", imgs["exact"]), (high, imgs[high]), (low, imgs[low])]
            for j, (name, img) in enumerate(panels):
                ax = axes[i][j]
                ax.imshow(R.tonemap(img, s), interpolation="nearest")
                note = "" if j < 2 else f"\nFLIP to exact {R.flip(imgs['exact'], img, s):.3f}"
                tag = " (threshold)" if j == 2 and thr["reached"] else ""
                ax.set_title(f"{name}{tag}{note}", fontsize=6.5)
            diff = (imgs[low] - imgs["exact"]) / s
            lim = max(float(np.abs(diff).max()), 1e-6)
            im = axes[i][4].imshow(diff, cmap="RdBu_r", vmin=-lim, vmax=lim, interpolation="nearest")
            axes[i][4].set_title(f"({low} - exact) / S", fontsize=6.5)
            fig.colorbar(im, ax=axes[i][4], shrink=0.7)
            axes[i][0].set_ylabel(setting)
            for ax in axes[i]:
                ax.set_xticks([])
                ax.set_yticks([])
                ax.grid(False)
                for spine in ax.spines.values():
                    spine.set_visible(False)
        fig.suptitle(f"Frame 0 of the first configuration, {finest}$^2$ map: the reference, exact, and two budgets' "
                     "best kinds", fontsize=7.5)
        res.save_figure(fig, "frames.png")


def plot_all(res, rows, found, cells, frames0, whites, P):
    """Write the three figures."""
    budget_map(res, cells, P)
    flip_vs_bytes(res, rows, P)
    frame_images(res, found, frames0, whites, P)
