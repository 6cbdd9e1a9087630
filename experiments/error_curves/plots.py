"""Figures of ``error_curves`` (read from its rows; medians over configurations)."""
from __future__ import annotations

import numpy as np

from avsm_dr import describe, kinds

from .. import _plotstyle as plotstyle
from .labels import with_size, label


def _f(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return float("nan")


def _main(r, rset="in_volume") -> bool:
    """Rows of the main study, opaque inline, at ``rset``, in the depth order (or order-independent)."""
    return (r.get("study") == "main" and r.get("opaque") == "inline" and r.get("receivers") == rset
            and r.get("order", "-") in ("depth", "-"))


def _headline(kind) -> str:
    d = describe(kind)
    return label(kind, with_size(kind, d["headline"].get(d["size"]) if d["size"] else None))


def _median(rows, cond, col) -> float:
    v = [_f(r.get(col)) for r in rows if cond(r)]
    v = [x for x in v if x == x]
    return float(np.median(v)) if v else float("nan")


def _series(base, kind, xkey, texel):
    """(x, y) of one curve of ``kind`` in the base configuration, sorted by x (None if absent)."""
    if texel:
        rs = [r for r in base if r["method"] == kind and r["setting"].count("/") == 1
              and r["setting"].endswith("/depth_range=texel")]
    else:
        rs = [r for r in base if r["method"] == kind and r.get("curve")]
    x = [_f(r[xkey]) for r in rs]
    if not rs or any(v != v for v in x):
        return None
    order = np.argsort(x)
    return np.array(x)[order], np.array([max(_f(rs[i]["rmse"]), 1e-7) for i in order])


def _curve_figure(res, rows, names, methods, xkey, fname, xlabel):
    """Small multiples: one row per scene, one column per family of kinds; solid markers at
    the scene's global depth range, hollow ones with a per-texel range (``depth_range='texel'``).
    ``xlabel`` None: each column's kinds' size parameters."""
    import matplotlib.ticker
    from matplotlib.lines import Line2D
    if xkey == "param":
        methods = [k for k in methods
                   if describe(k)["params"].get(describe(k)["size"] or "", {}).get("type") == "int"]
    fams = plotstyle.families(methods)
    fig, axes = plotstyle.grid(len(names), len(fams), panel=(2.5, 1.95))
    has_texel = False
    for i, name in enumerate(names):
        base = [r for r in rows if r["scene"] == name and r.get("base") and _main(r)]
        floor = [r for r in base if r["method"] == "exact"]
        for j, (fam, members) in enumerate(fams.items()):
            ax = axes[i][j]
            for kind in members:
                for texel in (False, True):
                    xy = _series(base, kind, xkey, texel)
                    if xy is None:
                        continue
                    st = plotstyle.variant_style(kind) if texel else plotstyle.style(kind)
                    ax.plot(*xy, **st, markersize=3.5)
                    has_texel |= texel
            if floor:
                ax.axhline(_f(floor[0]["total_rmse"]), **_FLOOR)
            ax.set_xscale("log", base=2)
            ax.set_yscale("log")
            ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            if i == 0:
                ax.set_title(fam)
            if i == len(names) - 1:
                ax.set_xlabel(xlabel if xlabel else
                              " / ".join(dict.fromkeys(describe(k)["size"] for k in members)) + " (count)")
            if j == 0:
                ax.set_ylabel(f"{name}\nRMSE of T vs exact map")
    extra = [Line2D([], [], **_FLOOR, label="exact map vs truth (total RMSE)")]
    if has_texel:
        extra.append(Line2D([], [], color="0.4", marker="o", markerfacecolor="none", linewidth=0.9,
                            label="hollow: per-texel depth range"))
    plotstyle.legend_columns(fig, [[plotstyle.kind_handle(k) for k in members] for members in fams.values()]
                             + [extra])
    res.save_figure(fig, fname)


#: The floor every compressed map sits on: the exact map's own error against ground truth.
_FLOOR = dict(color="k", linewidth=0.8, linestyle=":")


def plot_all(res, rows, names):
    """error_vs_memory, error_vs_count, decomposition, signed_errors (PNG + PDF each)."""
    import matplotlib
    matplotlib.use("Agg")
    methods = [k for k in kinds() if k != "exact"]
    with plotstyle.context():
        _curve_figure(res, rows, names, methods, "bytes", "error_vs_memory.png",
                      "memory (bytes per texel, sparse layout)")
        _curve_figure(res, rows, names, methods, "param", "error_vs_count.png", None)
        _decomposition(res, rows, names, methods)
        _signed(res, rows, names, methods)


def _decomposition(res, rows, names, methods):
    """Stacked error terms per build (medians over configurations), one panel per scene,
    builds as horizontal bars so that their names read without rotation."""
    variants = ["exact"] + [_headline(k) for k in methods]
    fig, axes = plotstyle.grid(1, len(names), panel=(2.9, 0.2 * len(variants) + 0.9), sharex=False)
    y = np.arange(len(variants))
    colours = {"compression": plotstyle.PALETTE["indigo"], "capture": plotstyle.PALETTE["rose"],
               "spatial": plotstyle.PALETTE["teal"]}
    for ax, name in zip(axes[0], names):
        parts = {k: [] for k in colours}
        total, ref = [], []
        for v in variants:
            cond = lambda r, v=v: r["scene"] == name and r.get("setting") == v and _main(r)  # noqa: E731
            parts["compression"].append(_median(rows, cond, "rmse"))
            parts["capture"].append(_median(rows, cond, "capture_rms"))
            parts["spatial"].append(_median(rows, cond, "spatial_rms"))
            total.append(_median(rows, cond, "total_rmse"))
            ref.append(_median(rows, cond, "reference_se_rms"))
        left = np.zeros(len(variants))
        for k, vals in parts.items():
            vals = np.nan_to_num(np.array(vals))
            ax.barh(y, vals, left=left, color=colours[k], height=0.7, label=f"{k} term (RMS)")
            left += vals
        ax.plot(total, y, "|", color="k", markersize=9, markeredgewidth=1.6, label="total RMSE vs truth")
        if any(v == v for v in ref):
            ax.axvline(np.nanmax(ref), color="0.35", linestyle="--", linewidth=1,
                       label="Mitsuba std. error (RMS)")
        ax.set_yticks(y, variants)
        ax.invert_yaxis()
        ax.grid(axis="y", visible=False)
        ax.set_title(name)
        ax.set_xlabel("error of T, in-volume receivers")
    plotstyle.legend_below(fig, axes[0], ncol=5)
    res.save_figure(fig, "decomposition.png")


def _signed(res, rows, names, methods):
    """Shares of receivers leaking light (T too high) or over-darkened (T too low) by more
    than 0.02 against the exact map, per build, one panel per scene."""
    vs = sorted({r["setting"] for r in rows if r["method"] == "moments"}) + [_headline(k) for k in methods
                                                                           if k != "moments"]
    fig, axes = plotstyle.grid(1, len(names), panel=(2.6, 0.16 * len(vs) + 0.9))
    y = np.arange(len(vs))
    for ax, name in zip(axes[0], names):
        cond = lambda r, v: r["scene"] == name and r.get("setting") == v and _main(r)  # noqa: E731
        leak = [_median(rows, lambda r, v=v: cond(r, v), "leak_fraction") for v in vs]
        dark = [_median(rows, lambda r, v=v: cond(r, v), "dark_fraction") for v in vs]
        ax.barh(y, np.nan_to_num(leak), height=0.7, color=plotstyle.PALETTE["rose"],
                label="leaking: T - T_exact > 0.02")
        ax.barh(y, -np.nan_to_num(dark), height=0.7, color=plotstyle.PALETTE["indigo"],
                label="over-darkening: T_exact - T > 0.02")
        ax.axvline(0, color="k", linewidth=0.5)
        ax.set_xlim(-1.05, 1.05)
        ax.set_xticks([-1, -0.5, 0, 0.5, 1], ["1", "0.5", "0", "0.5", "1"])
        ax.set_yticks(y, vs, fontsize=6)
        ax.invert_yaxis()
        ax.grid(axis="y", visible=False)
        ax.set_title(name)
        ax.set_xlabel("share of in-volume receivers\n(left: too dark, right: too light)")
    plotstyle.legend_below(fig, axes[0], ncol=2)
    res.save_figure(fig, "signed_errors.png")
