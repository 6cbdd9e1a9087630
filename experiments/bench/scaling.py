"""Scaling: build and lookup time against texels, segments per texel and N, with fitted
log-log slopes (``scaling.csv``, ``scaling.png``)."""
from __future__ import annotations

import numpy as np

from avsm_dr import build, kinds
from . import memory_guard
from .settings import counts_map, heavy, label, lookups, max_segments, one, pyplot


def scaling(P, progress, notes) -> list[dict]:
    """Build and lookup (100k receivers) time against texels (100 segments each), segments
    per texel and N (AVSM nodes, FOM harmonics, OSM slices; x = stored floats per texel);
    settings that would not fit in memory are skipped with a note (:mod:`.memory_guard`)."""
    rows = []
    K = 100_000
    meth = [(k, p) for k, p in [("avsm", {"nodes": 8}), ("fom", {"harmonics": 8}), ("osm", {"slices": 32}),
                                ("exact", {}), ("dsm", {"tolerance": 0.01})] if k in kinds()]

    def run(axis, x, seg, kind, p):
        if heavy(kind, p) and seg.n_segments > max_segments(kind):
            return
        if memory_guard.too_big(kind, p, seg, f"scaling {axis}={x:g}", notes):
            return
        tex, depth = lookups(seg.n_texels, K)
        mb = one(lambda: build(kind, seg, **p), P["scale_repeats"])
        rep = mb["out"]
        ml = one(lambda: rep.eval(tex, depth), P["scale_repeats"])
        rows.append(dict(axis=axis, x=x, setting=label(kind, p), method=kind, texels=seg.n_texels,
                         segments=seg.n_segments, floats_per_texel=rep.nbytes_per_texel / 4,
                         build_s=mb["wall_s"], build_cpu_s=mb["cpu_s"], lookup_s=ml["wall_s"],
                         lookup_cpu_s=ml["cpu_s"], lookups=K))
    for side in P["scale_texels"]:
        seg = counts_map(side, 100)
        for kind, p in meth:
            run("texels", side * side, seg, kind, p)
        progress.update()
    for mean in P["scale_counts"]:
        seg = counts_map(P["scale_side"], mean)
        for kind, p in meth:
            run("segments_per_texel", seg.n_segments / seg.n_texels, seg, kind, p)
        progress.update()
    seg = counts_map(P["scale_side"], 100)
    for n in P["scale_nodes"]:
        run("N", n, seg, "avsm", {"nodes": n})
        if "fom" in kinds():
            run("N", n, seg, "fom", {"harmonics": max(1, n // 2)})
        if "osm" in kinds():
            run("N", n, seg, "osm", {"slices": 2 * n})
        progress.update()
    return rows


def slopes(rows) -> dict:
    """Log-log slopes of build and lookup time per axis and method, fitted to the three
    largest sizes (small sizes are dominated by fixed per-call costs)."""
    out = {}
    for axis in ("texels", "segments_per_texel"):
        for setting in sorted({r["setting"] for r in rows if r["axis"] == axis}):
            rs = sorted([r for r in rows if r["axis"] == axis and r["setting"] == setting],
                        key=lambda r: r["x"])[-3:]
            x = np.log([r["x"] for r in rs])
            for what in ("build_s", "lookup_s"):
                y = np.array([r[what] for r in rs])
                if np.all(y > 0) and len(rs) > 1:
                    out[f"{axis}:{setting}:{what}"] = float(np.polyfit(x, np.log(y), 1)[0])
    for method in ("avsm", "fom", "osm"):
        rs = sorted([r for r in rows if r["axis"] == "N" and r["method"] == method],
                    key=lambda r: r["floats_per_texel"])[-3:]
        if len(rs) > 1:
            x = np.log([r["floats_per_texel"] for r in rs])
            for what in ("build_s", "lookup_s"):
                out[f"N:{method}:{what}"] = float(np.polyfit(x, np.log([r[what] for r in rs]), 1)[0])
    return out


def plot(res, scal):
    """``scaling.png``: build and lookup time against texels, segments per texel and N."""
    plt = pyplot()
    # scaling
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for ax, axis, xl in ((axes[0], "texels", "texels"), (axes[1], "segments_per_texel", "segments per texel"),
                         (axes[2], "N", "floats per texel (AVSM 2N, FOM 2n+1, OSM slices)")):
        for j, s in enumerate(dict.fromkeys(r["setting"] for r in scal if r["axis"] == axis)):
            rs = [r for r in scal if r["axis"] == axis and r["setting"] == s]
            if axis == "N":
                s = s.split("-")[0]
                rs = [r for r in scal if r["axis"] == "N" and r["method"] == s]
                if s in [ln.get_label().split(" ")[0] for ln in ax.get_lines()]:
                    continue
            x = [r["floats_per_texel"] if axis == "N" else r["x"] for r in rs]
            ax.loglog(x, [r["build_s"] for r in rs], "o-", color=f"C{j}", label=f"{s} build")
            ax.loglog(x, [r["lookup_s"] for r in rs], "s--", color=f"C{j}", label=f"{s} lookup (100k)")
        ax.set_xlabel(xl)
        ax.set_ylabel("seconds")
        ax.legend(fontsize=6)
    res.save_figure(fig, "scaling.png")
