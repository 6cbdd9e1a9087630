"""Figures of ``error_curves`` (read from its rows; medians over configurations)."""
from __future__ import annotations

import numpy as np

from .. import describe, kinds
from ._error_labels import _with_size, label


def _f(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return float("nan")


def _main(r, rset="in_volume") -> bool:
    return r.get("study") == "main" and r.get("opaque") == "inline" and r.get("receivers") == rset


def _headline(kind) -> str:
    d = describe(kind)
    return label(kind, _with_size(kind, d["headline"].get(d["size"]) if d["size"] else None))


def _median(rows, cond, col) -> float:
    v = [_f(r.get(col)) for r in rows if cond(r)]
    v = [x for x in v if x == x]
    return float(np.median(v)) if v else float("nan")


def plot_all(res, rows, names):
    """error_vs_memory.png, error_vs_count.png, decomposition.png, signed_errors.png."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker
    methods = [k for k in kinds() if k != "exact"]
    colors = {k: f"C{i % 10}" for i, k in enumerate(methods)}
    for xkey, fname, xlabel in (("bytes_per_texel", "error_vs_memory.png", "bytes per texel"),
                                ("param", "error_vs_count.png", "nodes / harmonics / slices")):
        fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.6), squeeze=False)
        for ax, name in zip(axes[0], names):
            base = [r for r in rows if r["scene"] == name and r.get("base") and _main(r)]
            for kind, c in colors.items():
                d = describe(kind)
                if xkey == "param" and d["params"].get(d["size"] or "", {}).get("type") != "int":
                    continue
                for texel in (False, True):
                    if texel:
                        rs = [r for r in base if r["method"] == kind and r["setting"].count("/") == 1
                              and r["setting"].endswith("/depth_range=texel")]
                    else:
                        rs = [r for r in base if r["method"] == kind and r.get("curve")]
                    if not rs:
                        continue
                    x = [_f(r[xkey]) for r in rs]
                    if any(v != v for v in x):
                        continue
                    order = np.argsort(x)
                    y = [max(_f(rs[i]["rmse"]), 1e-7) for i in order]
                    ax.loglog(np.array(x)[order], y, "o-" if not texel else "s--", color=c, ms=3,
                              alpha=1.0 if not texel else 0.6, label=f"{kind}" + (" (texel range)" if texel else ""))
            floor = [r for r in base if r["method"] == "exact"]
            if floor:
                ax.axhline(_f(floor[0]["total_rmse"]), color="k", lw=1, ls=":", label="exact map vs truth")
            ax.set_title(name)
            ax.set_xlabel(xlabel)
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        axes[0][0].set_ylabel("compression RMSE (vs exact curve)")
        handles, labels = axes[0][0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="upper center", ncol=6, fontsize=7, bbox_to_anchor=(0.5, -0.02))
        res.save_figure(fig, fname)

    # ---- stacked decomposition, medians over configurations
    variants = ["exact"] + [_headline(k) for k in methods]
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.8), squeeze=False)
    for ax, name in zip(axes[0], names):
        x = np.arange(len(variants))
        parts = {"compression": [], "capture": [], "spatial": []}
        total, ref = [], []
        for v in variants:
            cond = lambda r, v=v: r["scene"] == name and r.get("setting") == v and _main(r)  # noqa: E731
            parts["compression"].append(_median(rows, cond, "rmse"))
            parts["capture"].append(_median(rows, cond, "capture_rms"))
            parts["spatial"].append(_median(rows, cond, "spatial_rms"))
            total.append(_median(rows, cond, "total_rmse"))
            ref.append(_median(rows, cond, "reference_se_rms"))
        bottom = np.zeros(len(variants))
        for (k, vals), c in zip(parts.items(), ("C0", "C1", "C2")):
            vals = np.nan_to_num(np.array(vals))
            ax.bar(x, vals, bottom=bottom, color=c, label=f"{k} (RMS)")
            bottom += vals
        ax.plot(x, total, "k_", ms=14, mew=2, label="total RMSE vs truth")
        if any(v == v for v in ref):
            ax.axhline(np.nanmax(ref), color="r", ls=":", lw=1, label="Mitsuba std. error (RMS)")
        ax.set_xticks(x)
        ax.set_xticklabels(variants, rotation=60, fontsize=7, ha="right")
        ax.set_title(name)
    axes[0][0].set_ylabel("transmittance error, in-volume receivers")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=5, fontsize=7, bbox_to_anchor=(0.5, -0.02))
    res.save_figure(fig, "decomposition.png")

    # ---- signed errors: shares leaking (up) / over-darkening (down) by > 0.02
    vs = sorted({r["setting"] for r in rows if r["method"] == "moments"}) + [_headline(k) for k in methods
                                                                           if k != "moments"]
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.6), squeeze=False)
    for ax, name in zip(axes[0], names):
        x = np.arange(len(vs))
        leak = [_median(rows, lambda r, v=v: r["scene"] == name and r.get("setting") == v and _main(r),
                        "leak_fraction") for v in vs]
        dark = [_median(rows, lambda r, v=v: r["scene"] == name and r.get("setting") == v and _main(r),
                        "dark_fraction") for v in vs]
        ax.bar(x, np.nan_to_num(leak), color="C3", label="leaking > 0.02")
        ax.bar(x, -np.nan_to_num(dark), color="C0", label="over-darkening > 0.02")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xticks(x)
        ax.set_xticklabels(vs, rotation=60, fontsize=6, ha="right")
        ax.set_title(name)
    axes[0][0].set_ylabel("share of in-volume receivers (vs exact)")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=2, fontsize=7, bbox_to_anchor=(0.5, -0.02))
    res.save_figure(fig, "signed_errors.png")
