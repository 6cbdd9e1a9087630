"""Figures of the ``learned_warp`` experiment: warp curves, both metrics per configuration
against no warp and against the kind at its preset, training loss."""
from __future__ import annotations

import numpy as np


def plot(res, rows, loss_rows, warp_rows) -> None:
    """warps.png, error_per_scene.png, loss.png into ``res`` (a Results)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from .. import _plotstyle as plotstyle
    kinds = list(dict.fromkeys(r["kind"] for r in rows))

    # ---- learned warp curves
    fig, axes = plt.subplots(1, len(kinds), figsize=(3.8 * len(kinds), 3.6), squeeze=False)
    for ax, kind in zip(axes[0], kinds):
        ax.plot([0, 1], [0, 1], "k:", lw=0.8, label="identity")
        for method, style in (("log", dict(color="0.45", linestyle="--")),      # the learned warp in the kind's colour
                              ("learned", dict(color=plotstyle.style(kind)["color"], marker="o", linestyle="-"))):
            w = [r for r in warp_rows if r["kind"] == kind and r["method"] == method]
            lab = method if method == "learned" else f"log (r={w[0]['log_ratio']:g})"
            ax.plot([r["u"] for r in w], [r["w"] for r in w], ms=3, label=lab, **style)
        ax.set_title(kind)
        ax.set_xlabel("normalised depth u")
        ax.set_aspect("equal")
        ax.legend(fontsize=8)                 # per panel: the log ratio is chosen per kind
    axes[0][0].set_ylabel("warped depth w(u)")
    res.save_figure(fig, "warps.png")

    # ---- per scene, both metrics: learned vs no warp and vs the kind at its preset (where it has one)
    groups = list(dict.fromkeys(r["group"] for r in rows))
    bases = [b for b in ("identity", "preset") if any(r["method"] == b for r in rows)]
    panels = [(b, m) for b in bases for m in ("depth_l2", "receiver_rmse")]
    names = {"depth_l2": "depth-uniform L2", "receiver_rmse": "receiver RMSE"}
    fig, axes = plt.subplots(len(panels), len(kinds), figsize=(4.2 * len(kinds), 4.0 * len(panels)), squeeze=False)
    fig.subplots_adjust(hspace=0.55, bottom=0.8 / (4.0 * len(panels)))
    for row, (b, metric) in zip(axes, panels):
        for ax, kind in zip(row, kinds):
            if not any(r["kind"] == kind and r["method"] == b for r in rows):
                ax.set_axis_off()
                ax.text(0.5, 0.5, f"{kind}: no preset\nat equal bytes", ha="center", va="center",
                        transform=ax.transAxes, fontsize=9)
                continue
            _scatter(ax, rows, kind, b, groups, metric)
            ax.set_title(f"{kind}, {names[metric]}")
            ax.set_xlabel("without warp" if b == "identity" else "at the preset (per-texel range)")
            ax.set_ylabel("with learned warp")
    handles, labs = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labs, loc="upper center", ncol=4, fontsize=8, bbox_to_anchor=(0.5, 0.0))
    res.save_figure(fig, "error_per_scene.png")

    # ---- training loss
    fig, ax = plt.subplots(figsize=(4.8, 3.4))
    for kind in kinds:
        ls = [r for r in loss_rows if r["kind"] == kind]
        v = np.array([r["train_mse"] for r in ls])
        ax.semilogy([r["iteration"] for r in ls], v / v[0], color=plotstyle.style(kind)["color"], label=kind)
    ax.set_xlabel("Adam iteration")
    ax.set_ylabel("training MSE / MSE of the identity warp")
    ax.legend(fontsize=8)
    res.save_figure(fig, "loss.png")


def _scatter(ax, rows, kind, base_method, groups, metric="depth_l2") -> None:
    """Per configuration: ``metric`` of ``base_method`` (x) against the learned warp's (y),
    log axes, y = x dotted; spot-light configurations as hollow squares."""
    import matplotlib.ticker
    lo, hi = np.inf, 0.0
    for gi, g in enumerate(groups):
        base = [r for r in rows if r["kind"] == kind and r["group"] == g and r["method"] == base_method]
        lrn = [r for r in rows if r["kind"] == kind and r["group"] == g and r["method"] == "learned"]
        x = np.array([r[metric] for r in base])
        y = np.array([r[metric] for r in lrn])
        spot = np.array([str(r["light"]) == "spot" for r in base])
        ax.scatter(x[~spot], y[~spot], s=16, color=f"C{gi}", marker="o" if base[0]["split"] == "train" else "^",
                   label=f"{g} ({base[0]['split']})")
        if spot.any():                     # spot-light configurations: hollow squares in the group's colour
            ax.scatter(x[spot], y[spot], s=22, marker="s", facecolors="none", edgecolors=f"C{gi}", linewidths=1.0)
        lo, hi = min(lo, x.min(), y.min()), max(hi, x.max(), y.max())
    if any(str(r["light"]) == "spot" for r in rows):
        ax.scatter([], [], s=22, marker="s", facecolors="none", edgecolors="0.3", label="spot light (any group)")
    lim = (lo / 1.2, hi * 1.2)
    ax.plot(lim, lim, "k:", lw=0.8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(lim)
    ax.set_ylim(lim)
    for axis in (ax.xaxis, ax.yaxis):          # labels at 1, 2 and 5 x 10^k (more overlap on wide ranges)
        axis.set_minor_locator(matplotlib.ticker.LogLocator(base=10, subs=(2.0, 5.0)))
        axis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%.2g"))
        axis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%.2g"))
    ax.tick_params(axis="x", which="both", labelrotation=60, labelsize=7)
    ax.tick_params(axis="y", which="both", labelsize=7)


def plot_metric(res, loss_rows, sweep) -> None:
    """avsm_metric.png: beta and the surrogate's training MSE per iteration; the hard
    algorithm's training RMSE over beta (when swept)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(10.5, 3.4))
    fig.subplots_adjust(wspace=0.6)
    it = [r["iteration"] for r in loss_rows]
    axes[0].plot(it, [r["beta"] for r in loss_rows], "C0o-", ms=3, label="beta")
    axes[0].set_xlabel("Adam iteration (temperature annealed)")
    axes[0].set_ylabel("beta (weight of the depth-gap term)")
    ax2 = axes[0].twinx()
    ax2.semilogy(it, [r["surrogate_mse"] for r in loss_rows], "C1s--", ms=3, label="surrogate MSE")
    ax2.set_ylabel("surrogate training MSE")
    axes[0].legend(loc="upper left", fontsize=8)
    ax2.legend(loc="upper right", fontsize=8)
    if sweep:
        b = np.array([r["beta"] for r in sweep])
        axes[1].plot(np.maximum(b, 1e-4), [r["train_rmse"] for r in sweep], "C2o-", ms=3)
        axes[1].axvline(max(loss_rows[-1]["beta_next"], 1e-4), color="k", ls=":", lw=0.8, label="learned")
        axes[1].set_xscale("log")
        axes[1].set_xlabel("beta (0 plotted at 1e-4)")
        axes[1].set_ylabel("hard AVSM training RMSE")
        axes[1].legend(fontsize=8)
    else:
        axes[1].set_axis_off()
    res.save_figure(fig, "avsm_metric.png")
