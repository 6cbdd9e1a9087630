"""Figures of the ``temporal`` experiment: error and flicker per frame, flicker against mean
error (one row per kind; AVSM's insertion variants in a figure of their own), and animated
GIFs (Matplotlib's Pillow writer) of the light's T on a slice of the content."""
from __future__ import annotations

import numpy as np


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _log(ax, x: bool = False):
    """Log axes with a few plain '1e-02' labels and no minor ticks (Matplotlib's default
    log ticks and mathtext labels cost most of the figures' drawing time): at 1 and 3 per
    decade, only at 1 where the data span more than three decades (labels would overlap)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullLocator
    fmt = FuncFormatter(lambda v, _: f"{v:.0e}")
    for axis, on in ((ax.yaxis, True), (ax.xaxis, x)):
        if on:
            lo, hi = sorted(axis.get_view_interval())
            wide = lo > 0 and hi / lo > 1e3
            axis.set_major_locator(LogLocator(subs=(1.0,) if wide else (1.0, 3.0), numticks=8))
            axis.set_major_formatter(fmt)
            axis.set_minor_locator(NullLocator())


def _series(rows, setting, method, vs, key):
    """Per frame, the RMS over configurations of ``key``."""
    sel = [r for r in rows if r["setting"] == setting and r["method"] == method and r["vs"] == vs]
    frames = sorted({int(r["frame"]) for r in sel})
    y = [np.sqrt(np.mean([float(r[key]) ** 2 for r in sel if int(r["frame"]) == t])) for t in frames]
    return np.array(frames), np.array(y)


def _style(label: str) -> dict:
    """Plot keywords of a build label such as ``avsm-8 sorted``: its kind's style
    (``experiments._plotstyle``), hollow for the ``sorted`` variant."""
    import re
    from .. import _plotstyle as plotstyle
    kind = re.match(r"[A-Za-z0-9_]+", label).group(0)
    st = plotstyle.variant_style(kind) if re.search(r"(?<!un)sorted", label) else plotstyle.style(kind)
    return dict(st, markersize=3.5)


def _bar(v) -> list:
    """Errorbar extent [[estimate - low], [high - estimate]] of an interval dict (0 where it
    has no bounds: one configuration)."""
    lo, hi = v["estimate"] - v["low"], v["high"] - v["estimate"]
    return [[lo if lo == lo else 0.0], [hi if hi == hi else 0.0]]


def plot_all(res, rows, summary, series, P, gif_labels):
    """Write the figures of :func:`plot_summary` and one ``shadow_<setting>.gif`` per
    animation with slice images (first configuration)."""
    plot_summary(res, rows, summary)
    cfg0 = "s{}-{}".format(*P["configs"][0])
    for s in P["gif_settings"]:
        images = series.get((s, cfg0), {}).get("image")
        if images:
            _gif(res, s, images, gif_labels, P["image"])


def plot_summary(res, rows, summary):
    """Write ``error_flicker_per_frame.png`` (from the per-frame ``rows``, numbers or the strings
    of a ``data.csv``), ``flicker_vs_error.png`` and ``insertion_flicker.png``
    (:func:`plot_insertion`) from the findings' ``summary``."""
    from matplotlib.ticker import MaxNLocator
    from .. import _plotstyle as plotstyle
    _plt()                        # the Agg backend
    settings = list(summary["per_setting"])
    variants = {m for blk in summary.get("insertion", {}).values() for m in blk}
    labels = [m for m in summary["per_setting"][settings[0]]["exact"] if m not in variants]
    with plotstyle.context():
        fig, axes = plotstyle.grid(len(settings), 2, panel=(3.6, 1.9), sharey=False)
        for i, s in enumerate(settings):
            for m in labels:
                if m.startswith("exact"):
                    continue
                f, e = _series(rows, s, m, "exact", "error_rms")
                axes[i][0].plot(f, e, **_style(m), label=m)
                f, fl = _series(rows, s, m, "exact", "flicker_rms")
                axes[i][1].plot(f[1:], fl[1:], **_style(m), label=m)
            f, c = _series(rows, s, labels[0], "exact", "content_rms")
            axes[i][1].plot(f[1:], c[1:], ":", color="k", linewidth=1.2, label="content change (exact)")
            for ax in axes[i]:
                ax.set_yscale("log")
                _log(ax)
                ax.xaxis.set_major_locator(MaxNLocator(integer=True))
            axes[i][0].set_ylabel(f"{s}\nRMS over receivers (T)")
        axes[0][0].set_title("error vs exact curve, per frame")
        axes[0][1].set_title("flicker |e_t - e_(t-1)| (RMS), per frame")
        for ax in axes[-1]:
            ax.set_xlabel("frame")
        plotstyle.legend_below(fig, ncol=4)
        res.save_figure(fig, "error_flicker_per_frame.png")

        fig, axes = plotstyle.grid(1, len(settings), panel=(3.0, 2.8), sharex=False, sharey=False)
        for ax, s in zip(axes[0], settings):
            blk = summary["per_setting"][s]["exact"]
            lo_hi = []
            for m in labels:
                v = blk[m]
                x, y = v["error"], v["flicker"]
                if x["estimate"] <= 0:
                    continue
                st = _style(m)
                ax.errorbar(x["estimate"], y["estimate"], xerr=_bar(x), yerr=_bar(y), linestyle="none",
                            color=st["color"], marker=st["marker"], markerfacecolor=st.get("markerfacecolor"),
                            markersize=5, capsize=2, elinewidth=0.8, label=m)
                lo_hi += [x["estimate"], y["estimate"]]
            if lo_hi:
                g = np.geomspace(min(lo_hi) / 2, max(lo_hi) * 2, 10)
                ax.plot(g, np.sqrt(2) * g, "k:", linewidth=1, label="sqrt(2) x error (uncorrelated frames)")
            content = summary["headline"][s]["content_change"]
            ax.axhline(content, color="grey", linewidth=0.8, linestyle="--", label="content change (exact)")
            ax.set_xscale("log")
            ax.set_yscale("log")
            _log(ax, x=True)
            ax.set_xlabel("RMS error of T vs exact\n(mean over configurations)")
            ax.set_title(s)
        axes[0][0].set_ylabel("flicker (RMS change of the error\nbetween frames)")
        plotstyle.legend_below(fig, ncol=4)
        res.save_figure(fig, "flicker_vs_error.png")
        if variants:
            plot_insertion(res, summary, labels, sorted(variants))


#: Markers of :func:`plot_insertion` per insertion order (the label's last word).
MARKERS = {"unsorted": "o", "sorted": "s", "submission": "^"}


def plot_insertion(res, summary, labels, variants):
    """``insertion_flicker.png``: pooled flicker against error (with their intervals) of stream
    AVSM and each insertion variant, circles unsorted (a random order per frame), hollow squares
    sorted, triangles in submission order (the same draw order every frame); one colour per
    insertion; one column per animation, against the exact curve (top) and the truth (bottom);
    linear error axes (the methods' errors lie within a few x of each other).  The dashed
    line is sorted stream AVSM's flicker: the moonshot's bar."""
    from matplotlib.ticker import FuncFormatter, MaxNLocator
    from .. import _plotstyle as plotstyle
    stream = [m for m in labels if m.startswith("avsm-") and m.split(" ")[-1] in ("unsorted", "sorted")]
    names = sorted({" ".join(m.split(" ")[1:-1]) for m in variants} - {""})     # "": stream AVSM
    rank = {o: i for i, o in enumerate(MARKERS)}
    variants = sorted(variants, key=lambda m: (" ".join(m.split(" ")[1:-1]), rank.get(m.split(" ")[-1], 9)))
    colours = [c for c in plotstyle.PALETTE if c not in ("black", "rose")]
    colour = {"": plotstyle.PALETTE["rose"]} | {n: plotstyle.PALETTE[colours[i % len(colours)]]
                                                for i, n in enumerate(names)}
    settings = list(summary["per_setting"])
    fig, axes = plotstyle.grid(2, len(settings), panel=(2.6, 2.4), sharex=False, sharey=False)
    for row, vs in enumerate(("exact", "truth")):
        for ax, s in zip(axes[row], settings):
            blk = summary["per_setting"][s][vs]
            for m in stream + list(variants):
                x, y = blk[m]["error"], blk[m]["flicker"]
                name, order = " ".join(m.split(" ")[1:-1]), m.split(" ")[-1]
                ax.errorbar(x["estimate"], y["estimate"], xerr=_bar(x), yerr=_bar(y), linestyle="none",
                            color=colour[name], marker=MARKERS.get(order, "o"),
                            markerfacecolor="none" if order == "sorted" else colour[name], markersize=4.5,
                            capsize=2, elinewidth=0.8, label=f"{name or 'stream'} {order}")
            bar = [m for m in stream if m.split(" ")[-1] == "sorted"]
            if bar:
                ax.axhline(blk[bar[0]]["flicker"]["estimate"], color="grey", linewidth=0.8, linestyle="--",
                           label="sorted stream AVSM's flicker")
            ax.set_yscale("log")
            _log(ax)
            ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.3g}"))   # narrow ranges: 1 digit repeats
            ax.xaxis.set_major_locator(MaxNLocator(nbins=4))
            ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.3g}"))
            ax.set_title(f"{s}, vs {vs}")
            ax.set_xlabel(f"RMS error vs {vs}\n(mean over configurations)")
            _note_shared_error(ax, [blk[m]["error"] for m in stream + list(variants)])
        axes[row][0].set_ylabel("flicker (RMS change of\nthe error between frames)")
    handles = {lab: h for h, lab in zip(*axes[0][0].get_legend_handles_labels())}
    columns = [[h for lab, h in handles.items() if lab.rsplit(" ", 1)[0] == (n or "stream")] for n in [""] + names]
    plotstyle.legend_columns(fig, columns + [[h for lab, h in handles.items() if lab.startswith("sorted stream")]])
    res.save_figure(fig, "insertion_flicker.png")


def _note_shared_error(ax, errors) -> None:
    """Say so in the panel when the methods' errors differ by less than their typical interval
    half-width: an error common to all of them (e.g. the capture's against the truth) hides
    what the insertions change, and the points only look like one."""
    est = [e["estimate"] for e in errors]
    halves = np.array([(e["high"] - e["low"]) / 2 for e in errors], float)
    if not np.isfinite(halves).any():         # no interval (a quick run's single configuration)
        return
    half = np.nanmedian(halves)
    if len(est) > 1 and max(est) - min(est) < half:
        ax.text(0.03, 0.97, f"all within {max(est) - min(est):.1e} of each other:\nan error common to every"
                f" method\n(mean {np.mean(est):.3g}) hides the differences", transform=ax.transAxes,
                va="top", ha="left", fontsize=6, bbox=dict(facecolor="white", edgecolor="none", alpha=0.85))


def _rgb(x, cmap, lo, hi):
    """(n, n) values -> (n, n, 3) uint8 through a Matplotlib colormap on [lo, hi], rows flipped
    (row 0 at the bottom, as the slice's vertical axis)."""
    import matplotlib
    c = matplotlib.colormaps[cmap](np.clip((x - lo) / (hi - lo), 0.0, 1.0))[..., :3]
    return (255 * c[::-1]).astype(np.uint8)


def _gif(res, setting, images, labels, n):
    """Animated GIF (Pillow writer): top row the exact shadow and each method's on the box's
    mid-depth slice (light mostly from the left);
    bottom row the exact shadow's change since the last frame, then each method's signed
    error vs exact (blue-red, symmetric range in the title).  One image per frame (panels
    side by side on a mosaic), so a frame costs one draw."""
    from matplotlib.animation import FuncAnimation, PillowWriter
    plt = _plt()
    cols = ["exact"] + [m for m in labels if m in images[0]]
    F = len(images)
    grid = {m: np.stack([im[m] for im in images]).reshape(F, n, n) for m in cols}
    err = {m: grid[m] - grid["exact"] for m in cols}
    err["exact"] = np.concatenate([np.zeros((1, n, n)), np.diff(grid["exact"], axis=0)])
    vmax = {m: max(1e-6, float(np.max(np.abs(err[m])))) for m in cols}
    vmax.update({m: max([1e-6] + [vmax[c] for c in cols[1:]]) for m in cols[1:]})      # one scale for the methods
    g = max(1, n // 16)
    gap = np.full((n, g, 3), 96, np.uint8)

    def mosaic(t):
        top = [_rgb(grid[m][t], "gray", 0.0, 1.0) for m in cols]
        bot = [_rgb(err[m][t], "RdBu", -vmax[m], vmax[m]) for m in cols]
        row = lambda panels: np.concatenate(sum(([p, gap] for p in panels), [])[:-1], axis=1)  # noqa: E731
        return np.concatenate([row(top), np.full((g, row(top).shape[1], 3), 96, np.uint8), row(bot)], axis=0)

    first = mosaic(0)
    fig = plt.figure(figsize=(1.6 * len(cols), 3.6), facecolor=(0.85, 0.85, 0.85))
    ax = fig.add_axes([0.0, 0.0, 1.0, 0.8])
    ax.set_axis_off()
    im = ax.imshow(first, interpolation="nearest")
    fig.text(0.01, 0.97, f"{setting}:  " + " | ".join(cols), fontsize=6, va="top")
    fig.text(0.01, 0.89, f"top: T on the slice z = 0 (white 1, black 0); bottom, blue-red: exact change since the last "
             f"frame (+-{vmax['exact']:.2g}), then error vs exact (+-{vmax[cols[-1]]:.2g})", fontsize=5, va="top")
    stamp = fig.text(0.99, 0.97, "frame 0", fontsize=6, va="top", ha="right")

    def update(t):
        im.set_data(mosaic(t))
        stamp.set_text(f"frame {t}")
        return [im, stamp]

    anim = FuncAnimation(fig, update, frames=F, blit=False)
    path = res.write_file(f"shadow_{setting}.gif", lambda tmp: anim.save(tmp, writer=PillowWriter(fps=8), dpi=100))
    plt.close(fig)
    res.figures.append(str(path))
