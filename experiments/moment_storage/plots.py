"""Figure of :mod:`experiments.moment_storage`: RMSE ratio of every storage variant
to float32 (tuned alpha) per scene, pooled estimate with its 95 % interval, bytes per texel
in the variant labels."""
from __future__ import annotations

#: (opaque mode, alpha choice) -> (marker, colour, filled)
STYLE = {("inline", "default"): ("o", "C0", True), ("inline", "tuned"): ("o", "C1", True),
         ("separate", "default"): ("s", "C0", False), ("separate", "tuned"): ("s", "C1", False)}


def plot_ratios(res, summary: dict, labs: list[str], tags: tuple[str, ...], reference: str) -> None:
    """``storage_ratio.png``: one panel per scene, x = variant ``labs`` (with its bytes per
    texel), y = RMSE / ``reference``'s (linear, per panel), one series per alpha choice in
    ``tags``, error bars = the claim's 95 % interval."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    claims, nbytes = summary["claims"], summary["bytes_per_texel"]
    scenes = list(claims)
    fig, axes = plt.subplots(1, len(scenes), figsize=(5.0 * len(scenes), 3.8), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        modes = list(claims[scene])
        slots = [(m, t) for m in modes for t in tags]
        width = 0.7 / len(slots)
        for j, (mode, tag) in enumerate(slots):
            xs, ys, lo, hi = [], [], [], []
            for i, lab in enumerate(labs):
                key = f"{lab}/{tag} vs {reference}"
                c = claims[scene][mode].get(key)
                if c is None:                      # float32 tuned is the reference itself
                    continue
                xs.append(i - 0.35 + (j + 0.5) * width)
                ys.append(c["estimate"])
                lo.append(max(c["estimate"] - c["low"], 0.0))
                hi.append(max(c["high"] - c["estimate"], 0.0))
            marker, colour, filled = STYLE.get((mode, tag), ("^", "C2", True))
            ax.errorbar(xs, ys, yerr=[lo, hi], fmt=marker, color=colour, mfc=colour if filled else "white",
                        ms=5, capsize=2, lw=1, label=f"{mode}, {tag} alpha")
        ax.axhline(1.0, color="0.5", lw=0.8, ls="--")
        ax.set_xticks(range(len(labs)))
        ax.set_xticklabels(["\n".join(lab.split("/") + [f"{nbytes.get(lab, float('nan')):g} B"]) for lab in labs],
                           fontsize=7)
        ax.ticklabel_format(axis="y", useOffset=False)         # own scale per scene: ratios span 1.0003 .. 3
        ax.set_title(scene, fontsize=9)
        ax.grid(True, axis="y", which="both", alpha=0.3)
    axes[0][0].set_ylabel(f"RMSE / {reference}'s (tuned alpha, same capture)", fontsize=8)
    axes[0][-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    fig.suptitle("4 power moments: 16-bit storage vs float32 (pooled over seeds x lights, 95 % interval)",
                 fontsize=9)
    fig.tight_layout()
    res.save_figure(fig, "storage_ratio.png")
