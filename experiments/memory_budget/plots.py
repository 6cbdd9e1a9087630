"""Figures of the ``memory_budget`` experiment: error against total bytes per scene in the
sparse layout, the headline's (geometric mean over configurations, min-max band), and the
adaptive allocation's node count per texel."""
from __future__ import annotations

import numpy as np

METHODS = ("avsm", "adaptive", "adaptive_uniform", "adaptive_count", "dsm", "optimal")
#: Curves drawn: (method, interpolation); the exp rows (AVSM's preset) dashed in the method's
#: colour, markers filled.
CURVES = tuple((m, "exp" if m in ("avsm", "adaptive") and e else None) for e in (False, True) for m in METHODS
               if not e or m in ("avsm", "adaptive"))


def plot_curves(res, rows, scenes):
    """``error_vs_bytes.png``: RMSE at in-volume receivers (top) and uniform-in-depth RMS
    (bottom) against the map's total bytes in the sparse layout (``bytes_sparse`` x texels:
    the layout the savings count), one column per scene; fixed and adaptive AVSM with the
    exp interpolation (AVSM's preset) dashed beside their linear curves."""
    import matplotlib
    matplotlib.use("Agg")
    from .. import _plotstyle as plotstyle
    with plotstyle.context():
        fig, axes = plotstyle.grid(2, len(scenes), panel=(3.0, 2.3), sharey="row")
        for j, scene in enumerate(scenes):
            for i, (key, ylab) in enumerate((("rmse", "RMSE, in-volume receivers"),
                                             ("depth_rms", "RMS, uniform in depth"))):
                ax = axes[i][j]
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
                if i == 0:
                    ax.set_title(scene)
                else:
                    ax.set_xlabel("total bytes of the map, sparse (KiB)")
                if j == 0:
                    ax.set_ylabel(ylab)
        plotstyle.legend_below(fig, axes[0], ncol=min(4, 3 * len(scenes)))
        res.save_figure(fig, "error_vs_bytes.png")


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
    scene, the budget of AVSM-4)."""
    if not heat:
        return
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    names = list(heat)
    fig, axes = plt.subplots(1, len(names), figsize=(3.4 * len(names), 3.2), squeeze=False)
    for ax, name in zip(axes[0], names):
        img, target = heat[name]
        im = ax.imshow(img, origin="lower", cmap="magma", interpolation="nearest")
        ax.set_title(f"{name}\n{target:g} B/texel budget", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
        fig.colorbar(im, ax=ax, fraction=0.046, label="nodes per texel")
    res.save_figure(fig, "allocation.png")
