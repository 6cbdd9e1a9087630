"""Figures of the ``memory_budget`` experiment: error against total bytes per scene in the
sparse layout, the headline's (geometric mean over configurations, min-max band), one figure
per metric, and the adaptive allocation's node count per texel; small multiples of at most
:data:`COLUMNS` scenes a row."""
from __future__ import annotations

import numpy as np

METHODS = ("avsm", "adaptive", "adaptive_uniform", "adaptive_count", "dsm", "optimal")
#: Curves drawn: (method, interpolation); the exp rows (AVSM's preset) dashed in the method's
#: colour, markers filled.
CURVES = tuple((m, "exp" if m in ("avsm", "adaptive") and e else None) for e in (False, True) for m in METHODS
               if not e or m in ("avsm", "adaptive"))
#: Scene panels per row of a figure.
COLUMNS = 5
#: The error figures: (file, row key, y label).
METRICS = (("error_vs_bytes.png", "rmse", "RMSE, in-volume receivers"),
           ("error_vs_bytes_depth.png", "depth_rms", "RMS, uniform in depth"))


def _title(scene: str) -> str:
    """The scene's name and its content types (``SCENES.entry(name).content``)."""
    from avsm_dr.builtin_scenes import SCENES
    content = SCENES.entry(scene).content if scene in SCENES else ()
    return f"{scene}\n({', '.join(content)})" if content else scene


def plot_curves(res, rows, scenes):
    """``error_vs_bytes.png`` (RMSE at in-volume receivers) and ``error_vs_bytes_depth.png``
    (uniform-in-depth RMS) against the map's total bytes in the sparse layout (``bytes_sparse``
    x texels: the layout the savings count), one panel per scene, axes shared; fixed and
    adaptive AVSM with the exp interpolation (AVSM's preset variant) dashed beside their linear
    curves."""
    import matplotlib
    matplotlib.use("Agg")
    from .. import _plotstyle as plotstyle
    n_rows, n_cols = plotstyle.panel_shape(len(scenes), COLUMNS)   # at most COLUMNS a row
    for filename, key, ylab in METRICS:
        with plotstyle.context():
            fig, axes = plotstyle.grid(n_rows, n_cols, panel=(2.7, 2.3))
            for j, ax in enumerate(axes.flat):
                if j >= len(scenes):
                    ax.set_visible(False)
                    continue
                scene = scenes[j]
                for m, interp in CURVES:
                    rs = [r for r in rows if r["scene"] == scene and r["method"] == m
                          and (r.get("interpolation") == "exp") == (interp == "exp")]
                    ns = sorted({r["nodes"] for r in rs})
                    if not ns:
                        continue
                    xb = [np.mean([r["bytes_sparse"] * r["texels"] for r in rs if r["nodes"] == n]) / 1024
                          for n in ns]
                    ys = [np.array([max(r[key], 1e-7) for r in rs if r["nodes"] == n]) for n in ns]
                    gm = [float(np.exp(np.mean(np.log(y)))) for y in ys]
                    st = _style(m)
                    if interp == "exp":
                        st = dict(st, linestyle="--", markerfacecolor=st["color"])
                    ax.plot(xb, gm, **st, label=m if interp is None else f"{m} (exp)")
                    ax.fill_between(xb, [y.min() for y in ys], [y.max() for y in ys], color=st["color"],
                                    alpha=0.12, linewidth=0)
                ax.set_xscale("log")
                ax.set_yscale("log")
                ax.set_title(_title(scene))
                if j % n_cols == 0:
                    ax.set_ylabel(ylab)
                if j + n_cols >= len(scenes):           # the lowest panel of its column
                    ax.set_xlabel("map bytes, sparse (KiB)")
                    ax.xaxis.set_tick_params(labelbottom=True)
            for ax in axes.flat:
                if ax.get_visible():
                    plotstyle.log_ticks(ax, "x")
            plotstyle.legend_below(fig, axes, ncol=4 if n_cols > 2 else 2)
            res.save_figure(fig, filename)


def _style(method: str) -> dict:
    """The kind's style (``experiments._plotstyle``); the adaptive allocation's two baselines in its
    colour, hollow (uniform budget) and hollow dotted (count-proportional)."""
    from .. import _plotstyle as plotstyle
    if method == "adaptive_uniform":
        return plotstyle.variant_style("avsm_adaptive")
    if method == "adaptive_count":
        return dict(plotstyle.variant_style("avsm_adaptive"), linestyle=":")
    return plotstyle.style("avsm_adaptive" if method == "adaptive" else method)


def plot_heat(res, heat):
    """``allocation.png``: nodes per texel of adaptive AVSM (first configuration of each
    scene, the budget of AVSM-4), one colour scale for every scene."""
    if not heat:
        return
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.colors import Normalize
    from .. import _plotstyle as plotstyle
    names = list(heat)
    n_rows, n_cols = plotstyle.panel_shape(len(names), COLUMNS)
    norm = Normalize(0, max(float(np.max(heat[n][0])) for n in names))
    targets = {heat[n][1] for n in names}
    with plotstyle.context():
        fig, axes = plotstyle.grid(n_rows, n_cols, panel=(2.3, 2.5))
        im = None
        for j, ax in enumerate(axes.flat):
            ax.set_xticks([])
            ax.set_yticks([])
            if j >= len(names):
                ax.set_visible(False)
                continue
            img, target = heat[names[j]]
            im = ax.imshow(img, origin="lower", cmap="magma", norm=norm, interpolation="nearest")
            ax.set_title(names[j] if len(targets) == 1 else f"{names[j]}\n{target:g} B/texel budget")
        fig.colorbar(im, ax=axes, shrink=0.8, label="nodes per texel")
        if len(targets) == 1:
            fig.suptitle(f"Adaptive AVSM, {targets.pop():g} B/texel budget:\nnodes per texel "
                         f"(first configuration{' of each scene' if len(names) > 1 else ''})")
        res.save_figure(fig, "allocation.png")
