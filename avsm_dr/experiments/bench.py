"""Throughput benchmark: build (segment insertions/s) and lookup (receivers/s) of every
representation on a synthetic map with 50-300 segments per texel, next to the
vectorised NumPy peer (:mod:`avsm_dr.peers.numpy_avsm`) measured in the same run.

Times are medians of repeats after a warm-up call; the first call (JIT compile
included) is reported separately as ``first_call_s``.
"""
from __future__ import annotations

import numpy as np
from tqdm import tqdm

from .. import build, kinds
from ..peers import numpy_avsm
from ..synthetic import random_map
from ._common import Results, timed

SETTINGS = [
    ("avsm", {"nodes": 4}), ("avsm", {"nodes": 8}), ("avsm", {"nodes": 16}),
    ("exact", {}), ("osm", {"slices": 32}), ("fom", {"harmonics": 8}), ("dsm", {"tolerance": 0.01}),
]


def run(quick: bool = False, out=None, force: bool = False) -> dict:
    """Run the experiment; write CSV, figures and meta.json into ``out``
    (default ``results/<name>/``); ``quick`` = small sizes, ``force`` = recompute."""
    side = 64 if quick else 256
    params = dict(side=side, min_count=50, max_count=300, lookups=200_000 if quick else 1_000_000,
                  numpy_texels=256 if quick else 2048, repeats=3 if quick else 5)
    res = Results("bench", out, quick, params)
    if res.exists() and not force:
        return {"csv": str(res.dir / "data.csv"), "out": str(res.dir), "cached": True}

    seg = random_map(side * side, params["min_count"], params["max_count"], seed=1)
    S = seg.n_segments
    rng = np.random.default_rng(2)
    tex = rng.integers(0, seg.n_texels, params["lookups"])
    depth = rng.uniform(0, 1, params["lookups"])
    rows = []

    # NumPy peer on a subset of texels (rates are per insertion / per lookup)
    sub = seg.select_texels(np.arange(params["numpy_texels"]))
    h = sub.numpy()
    np_rates = {}
    for nodes in (4, 8, 16):
        t_np, _, (D, V) = timed(lambda: numpy_avsm.build(h["offsets"], h["z0"], h["z1"], h["optical_depth"],
                                                          nodes, float(h["z1"].max())), repeats=1, warmup=0)
        lk = rng.integers(0, sub.n_texels, 100_000)
        t_lk, _, _ = timed(lambda: numpy_avsm.lookup(D, V, lk, rng.uniform(0, 1, lk.size)), repeats=1, warmup=0)
        np_rates[nodes] = (sub.n_segments / t_np, lk.size / t_lk)
        rows.append(dict(method="avsm", param=nodes, impl="numpy", texels=sub.n_texels, segments=sub.n_segments,
                         build_s=t_np, first_call_s=t_np, insertions_per_s=sub.n_segments / t_np,
                         lookups_per_s=lk.size / t_lk, speedup_vs_numpy=1.0))

    todo = [(k, p) for k, p in SETTINGS if k in kinds()]
    for kind, p in tqdm(todo, desc="bench", unit="setting"):
        t_build, first, rep = timed(lambda: build(kind, seg, **p), repeats=params["repeats"])
        t_look, first_look, _ = timed(lambda: rep.eval(tex, depth), repeats=params["repeats"])
        param = next(iter(p.values()), "")
        # 'exact' stores the segments as they are: it has no build work to rate
        row = dict(method=kind, param=param, impl="drjit", texels=seg.n_texels, segments=S, build_s=t_build,
                   first_call_s=first, insertions_per_s=S / t_build if kind != "exact" else float("nan"),
                   lookups_per_s=tex.size / t_look,
                   nbytes_per_texel=rep.nbytes_per_texel)
        if kind == "avsm":
            row["speedup_vs_numpy"] = row["insertions_per_s"] / np_rates[param][0]
            row["lookup_speedup_vs_numpy"] = row["lookups_per_s"] / np_rates[param][1]
        rows.append(row)
    csv = res.write_csv(rows)

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(1, 2, figsize=(11, 3.8))
    ours = [r for r in rows if r["impl"] == "drjit"]
    labels = [f"{r['method']}-{r['param']}" if r["param"] != "" else r["method"] for r in ours]
    ax[0].bar(labels, [r["insertions_per_s"] / 1e6 for r in ours], color="C0", label="Dr.Jit")
    peer = [r for r in rows if r["impl"] == "numpy"]
    ax[0].bar([f"avsm-{r['param']} numpy" for r in peer], [r["insertions_per_s"] / 1e6 for r in peer], color="C3", label="NumPy")
    ax[0].set_yscale("log"); ax[0].set_ylabel("M segments / s (build)"); ax[0].tick_params(axis="x", rotation=60)
    ax[0].legend()
    ax[1].bar(labels, [r["lookups_per_s"] / 1e6 for r in ours], color="C0")
    ax[1].bar([f"avsm-{r['param']} numpy" for r in peer], [r["lookups_per_s"] / 1e6 for r in peer], color="C3")
    ax[1].set_yscale("log"); ax[1].set_ylabel("M lookups / s"); ax[1].tick_params(axis="x", rotation=60)
    fig.suptitle(f"{seg.n_texels} texels, {S} segments ({params['min_count']}-{params['max_count']} per texel)")
    res.save_figure(fig, "throughput.png")
    summary = {f"avsm{r['param']}_speedup_vs_numpy": r["speedup_vs_numpy"] for r in ours if r["method"] == "avsm"}
    res.write_meta(summary)
    for r in rows:
        print(f"{r['impl']:6s} {r['method']:5s} {str(r['param']):>5s}: {r['insertions_per_s']/1e6:9.2f} M ins/s "
              f"{r['lookups_per_s']/1e6:8.2f} M lookups/s" +
              (f"  x{r['speedup_vs_numpy']:.0f} vs NumPy" if r.get("speedup_vs_numpy") and r["impl"] == "drjit" else ""))
    return {"csv": str(csv), "out": str(res.dir), "summary": summary}
