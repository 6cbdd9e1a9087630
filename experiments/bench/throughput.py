"""Throughput tables: build (segment insertions/s) and lookup (receivers/s) of every
setting on synthetic maps, with the Numba, Warp and NumPy peers run interleaved on the same
map (``data.csv``, ``throughput.png``), and capture / build / lookup on the built-in scenes
(``scenes.csv``).

Our builds also record their fastest repeat in process CPU time (``build_cpu_best_s``,
``insertions_per_cpu_s_best``): the machine table compares it with the best vector-op
rate of the CPU (the microbenchmark's fastest of 7 runs, or the nominal rate), like for
like, where the median also carries the load of other processes on a shared machine."""
from __future__ import annotations

import time

import numpy as np

from avsm_dr import build, kinds
from . import memory_guard
from .peer_kernels import numba_avsm, numba_fom, numpy_avsm, warp_avsm, warp_fom
from .._common import measure, sync
from .settings import (
    max_segments,
    SCENE_SETTINGS,
    SETTINGS,
    counts_map,
    heavy,
    label,
    lookups,
    one,
    pyplot,
    settings,
)


def _cpu_logged(fn, log: list):
    """``fn`` that also appends the process CPU seconds of each call, its kernels waited
    for (:func:`~experiments._common.sync`), to ``log``."""
    def run():
        c0 = time.process_time()
        out = fn()
        sync(out)
        log.append(time.process_time() - c0)
        return out
    return run


def throughput(P, notes, progress) -> list[dict]:
    """data.csv rows: every setting of :data:`SETTINGS` on every synthetic map of
    ``P['maps']``, with the Numba and Warp peers of the setting interleaved where there are
    some, and the NumPy peer on the maps with about 100 segments per texel."""
    rows = []
    todo = settings(SETTINGS)
    for side, mean in P["maps"]:
        seg = counts_map(side, mean)
        S, T = seg.n_segments, seg.n_texels
        reps = P["repeats"] if S < 20_000_000 else P["big_repeats"]
        tex, depth = lookups(T, P["lookups"])
        name = f"{side}^2 x {mean}"
        base = dict(map=name, texels=T, segments=S, mean_count=S / T, repeats=reps)
        host = seg.numpy() if numba_avsm.available() or warp_avsm.available() else None
        for kind, p in todo:
            progress.set_postfix_str(f"{name} {label(kind, p)}")
            if heavy(kind, p) and S > max_segments(kind):
                notes.append(f"{label(kind, p)} skipped on {name} ({S} segments > {max_segments(kind)}: "
                             "host memory / host sort / offline build)")
                progress.update()
                continue
            if memory_guard.too_big(kind, p, seg, name, notes):     # its build would not fit in memory
                progress.update()
                continue
            s_in = seg.sorted() if p.get("sort") else seg     # sorted once, outside the timing
            cpu_log = []
            fns = {"drjit": _cpu_logged(lambda k=kind, p=p, s=s_in: build(k, s, **p), cpu_log)}
            peer = {}
            for impl, mods in (("numba", (numba_avsm, numba_fom)), ("warp", (warp_avsm, warp_fom))):
                pr = _peer_build(kind, p, host, seg, *mods) if host is not None and mods[0].available() else None
                if pr is not None:
                    peer[impl] = pr
                    fns[impl] = pr[0]
            mb = measure(fns, reps)
            rep = mb["drjit"]["out"]
            fl = {"drjit": (lambda r=rep: r.eval(tex, depth))}
            for impl, pr in peer.items():
                fl[impl] = pr[1](mb[impl]["out"], tex, depth)
            ml = measure(fl, reps)
            for impl in fns:
                b, lk = mb[impl], ml[impl]
                row = dict(base, method=kind, param=next(iter(p.values()), ""), setting=label(kind, p),
                           impl=impl, build_s=b["wall_s"], build_cpu_s=b["cpu_s"], build_kernel_s=b["kernel_s"],
                           first_call_s=b["first_s"], jit_s=b["jit_s"] + lk["jit_s"],
                           kernels_compiled=b["compiled"] + lk["compiled"], kernels_per_build=b["kernels"],
                           insertions_per_s=S / b["wall_s"] if kind != "exact" else float("nan"),
                           insertions_per_cpu_s=S / b["cpu_s"] if kind != "exact" else float("nan"),
                           lookup_s=lk["wall_s"], lookup_cpu_s=lk["cpu_s"], lookup_first_s=lk["first_s"],
                           lookups_per_s=tex.size / lk["wall_s"], lookups_per_cpu_s=tex.size / lk["cpu_s"],
                           nbytes_per_texel=rep.nbytes_per_texel if impl == "drjit" else
                           (rep.nbytes_per_texel * 2))  # numba / warp peers store float64
                if impl == "drjit" and len(cpu_log) > 1 and kind != "exact":
                    row["build_cpu_best_s"] = min(cpu_log[1:])          # [0]: the first call (JIT)
                    row["insertions_per_cpu_s_best"] = S / row["build_cpu_best_s"]
                if impl in peer:    # compile (Warp: module load, or its disk cache) of the first call
                    mods = {"numba": (numba_avsm, numba_fom), "warp": (warp_avsm, warp_fom)}[impl]
                    row["jit_s"] = sum(mods[kind != "avsm"].compile_seconds().values())
                rows.append(row)
            ours_row = rows[-len(fns)]
            for impl, pr_row in zip(fns, rows[-len(fns):]):
                if impl in peer:
                    ours_row["speedup_vs_" + impl] = pr_row["build_s"] / ours_row["build_s"]
                    ours_row["cpu_speedup_vs_" + impl] = pr_row["build_cpu_s"] / ours_row["build_cpu_s"]
                    ours_row["lookup_speedup_vs_" + impl] = pr_row["lookup_s"] / ours_row["lookup_s"]
            progress.update()
        # NumPy peer: a subset of texels (it is ~1000x slower), rates per insertion / lookup
        if mean == 100 or (side, mean) == P["maps"][0]:      # NumPy: ~1 M insertions/s
            rows += _numpy_peer(P, seg, base, rows)
    return rows


def _peer_build(kind, p, host, seg, avsm_peer=numba_avsm, fom_peer=numba_fom):
    """(build fn, lookup-fn factory) of a peer of a setting (Numba's modules, or Warp's:
    same arguments), or None."""
    if kind == "avsm" and set(p) <= {"nodes", "sort"} and not p.get("sort"):
        far = seg.bounds()[1]
        return ((lambda: avsm_peer.build(host["offsets"], host["z0"], host["z1"], host["optical_depth"],
                                         p["nodes"], far)),
                lambda out, tex, depth: (lambda: avsm_peer.lookup(out[0], out[1], tex, depth)))
    if kind == "fom" and set(p) == {"harmonics"}:
        near, far = seg.bounds()
        return ((lambda: fom_peer.build(host["offsets"], host["z0"], host["z1"], host["optical_depth"],
                                        p["harmonics"], near, far)),
                lambda out, tex, depth: (lambda: fom_peer.lookup(out, near, far, tex, depth)))
    return None


def _numpy_peer(P, seg, base, rows) -> list[dict]:
    """The NumPy peer on the whole map (or its first texels up to ``numpy_segments``
    segments), interleaved with our kernel on the same segments."""
    n_tex = int(np.searchsorted(seg.offsets, P["numpy_segments"], side="right")) - 1
    sub = seg if n_tex >= seg.n_texels else seg.select_texels(np.arange(max(n_tex, 1)))
    h = sub.numpy()
    out = []
    tex, depth = lookups(sub.n_texels, min(P["lookups"], 200_000), seed=3)
    for nodes in (4, 8, 16):
        far = float(h["z1"].max())
        fns = {"numpy": lambda: numpy_avsm.build(h["offsets"], h["z0"], h["z1"], h["optical_depth"], nodes, far),
               "drjit": lambda: build("avsm", sub, nodes=nodes, far=far)}
        m = measure({"numpy": fns["numpy"]}, repeats=0)   # NumPy needs no warm-up: one call
        m.update(measure({"drjit": fns["drjit"]}, repeats=3))
        D, V = m["numpy"]["out"]
        rep = m["drjit"]["out"]
        ml = measure({"numpy": lambda: numpy_avsm.lookup(D, V, tex, depth)}, repeats=0)
        ml.update(measure({"drjit": lambda: rep.eval(tex, depth)}, repeats=3))
        S = sub.n_segments
        row = dict(base, texels=sub.n_texels, segments=S, method="avsm", param=nodes, setting=f"avsm-nodes={nodes}",
                   impl="numpy", build_s=m["numpy"]["wall_s"], build_cpu_s=m["numpy"]["cpu_s"],
                   first_call_s=m["numpy"]["first_s"], insertions_per_s=S / m["numpy"]["wall_s"],
                   insertions_per_cpu_s=S / m["numpy"]["cpu_s"], lookup_s=ml["numpy"]["wall_s"],
                   lookups_per_s=tex.size / ml["numpy"]["wall_s"], speedup_vs_numpy=1.0, repeats=1)
        # same subset, same run, interleaved: the ratio; the full-map row gets it too
        ratio = m["numpy"]["wall_s"] / m["drjit"]["wall_s"]
        lratio = ml["numpy"]["wall_s"] / ml["drjit"]["wall_s"]
        row["drjit_on_subset_speedup"] = ratio
        out.append(row)
        for r in rows:
            if r["map"] == base["map"] and r["impl"] == "drjit" and r["setting"] == f"avsm-nodes={nodes}":
                r["speedup_vs_numpy"] = r["insertions_per_s"] / row["insertions_per_s"]
                r["lookup_speedup_vs_numpy"] = r["lookups_per_s"] / row["lookups_per_s"]
                r["speedup_vs_numpy_same_subset"] = ratio
                r["lookup_speedup_vs_numpy_same_subset"] = lratio
    return out


def scenes(P, progress) -> tuple[list[dict], dict]:
    """Capture, build and lookup on every built-in scene; returns (rows, captures)."""
    from avsm_dr import capture as _capture
    from avsm_dr import builtin_scenes as scene_lib
    rows, caps = [], {}
    for name in scene_lib.SCENES:
        sc = scene_lib.get(name)
        res = P["scene_resolution"]
        m = one(lambda: _capture(sc, resolution=res, order="depth"), P["scene_repeats"])
        cap = m["out"]
        seg = cap.segments
        caps[name] = (sc, cap)
        tex, depth = cap.lookup(np.asarray(sc.receivers))
        rows.append(dict(scene=name, stage="capture", setting="", texels=seg.n_texels, segments=seg.n_segments,
                         receivers=tex.size, seconds=m["wall_s"], cpu_s=m["cpu_s"], first_call_s=m["first_s"],
                         jit_s=m["jit_s"], rate_per_s=seg.n_segments / m["wall_s"]))
        exact = None
        for kind, p in sorted(SCENE_SETTINGS, key=lambda s: s[0] != "exact"):   # exact first
            if kind not in kinds():
                continue
            progress.set_postfix_str(f"{name} {label(kind, p)}")
            mb = one(lambda: build(kind, seg, **p), P["scene_repeats"])
            rep = mb["out"]
            ml = one(lambda: rep.eval(tex, depth), P["scene_repeats"])
            T = np.asarray(ml["out"], np.float64)
            if kind == "exact":
                exact = T
            err = float(np.sqrt(np.mean((T - exact) ** 2))) if exact is not None else float("nan")
            for stage, mm, n in (("build", mb, seg.n_segments), ("lookup", ml, tex.size)):
                rows.append(dict(scene=name, stage=stage, setting=label(kind, p), texels=seg.n_texels,
                                 segments=seg.n_segments, receivers=tex.size, seconds=mm["wall_s"],
                                 cpu_s=mm["cpu_s"], first_call_s=mm["first_s"], jit_s=mm["jit_s"],
                                 rate_per_s=n / mm["wall_s"], rmse_vs_exact=err,
                                 nbytes_per_texel=rep.nbytes_per_texel))
        progress.update()
    return rows, caps


def plot(res, data):
    """``throughput.png``: build and lookup rates per setting and map, peers marked."""
    plt = pyplot()
    # throughput: one group of bars per map
    maps = list(dict.fromkeys(r["map"] for r in data))
    fig, axes = plt.subplots(2, 1, figsize=(13, 8))
    names = list(dict.fromkeys(r["setting"] for r in data if r["impl"] == "drjit"))
    w = 0.8 / len(maps)
    for j, mp in enumerate(maps):
        for ax, key in ((axes[0], "insertions_per_s"), (axes[1], "lookups_per_s")):
            vals = []
            for s in names:
                r = [x for x in data if x["map"] == mp and x["setting"] == s and x["impl"] == "drjit"]
                vals.append(r[0][key] / 1e6 if r and np.isfinite(r[0][key]) else 0)
            ax.bar(np.arange(len(names)) + j * w, vals, w, label=f"Dr.Jit {mp}")
    for ax, ylabel in ((axes[0], "M segment insertions / s"), (axes[1], "M lookups / s")):
        ax.set_xticks(np.arange(len(names)) + 0.4 - w / 2, names, rotation=35, ha="right", fontsize=7)
        ax.set_yscale("log")
        ax.set_ylabel(ylabel)
    for impl, marker in (("numba", "x"), ("warp", "+"), ("numpy", "v")):
        for r in data:
            if r["impl"] == impl and r["setting"] in names:
                x = names.index(r["setting"]) + maps.index(r["map"]) * w
                axes[0].plot(x, r["insertions_per_s"] / 1e6, marker, color="k")
                axes[1].plot(x, r["lookups_per_s"] / 1e6, marker, color="k")
    axes[0].plot([], [], "x", color="k", label="Numba peer")
    axes[0].plot([], [], "+", color="k", label="Warp peer (1 thread)")
    axes[0].plot([], [], "v", color="k", label="NumPy peer (subset)")
    axes[0].legend(fontsize=7, ncol=4)
    fig.suptitle("Throughput (median after warm-up; wall clock, 2 shared cores)")
    res.save_figure(fig, "throughput.png")
