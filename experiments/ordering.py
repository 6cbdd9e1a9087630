"""Effect of insertion order on AVSM (Salvi et al. 2010, sec. 4.1): error against the exact curve and
temporal flicker (the change of T between two random insertion orders of the same
segments, as unordered GPU capture would produce frame to frame), with and without
sorting, for several node counts.

Fair-comparison columns: ``order`` ('random': the shuffled orders as inserted; 'depth': the same
shuffles sorted front to back by ``build(..., sort=True)``), ``signed_mean`` and
``leak_share`` (error > 0.02) at the scene's receivers and ``depth_l2``
(:func:`avsm_dr.evaluation.depth_l2`), each averaged over the shuffled orders (RMS for
``depth_l2``), beside ``rmse``; ``bytes`` (sparse) and ``bytes_dense``.  One configuration per
scene: no interval.  :mod:`experiments.insertion_order` measures the orders with intervals
over configurations; this study's claim is the flicker (zero when sorted).
"""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from avsm_dr import build
from avsm_dr.metrics import error_stats
from avsm_dr.segments import Segments
from ._headline import num, wrap
from ._study import Study

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    'Salvi et al., "Adaptive Volumetric Shadow Maps", EGSR 2010, section 4.1 (insertion order): '
    'AVSM error and frame-to-frame flicker under shuffled insertion, sorted against unsorted.'
)


def shuffled(seg: Segments, rng) -> Segments:
    """The same segments in a random order within every texel."""
    h = seg.numpy()
    tex = np.repeat(np.arange(seg.n_texels), seg.counts)
    perm = np.lexsort((rng.random(tex.size), tex))
    return Segments.from_arrays(h["offsets"], h["z0"][perm], h["z1"][perm], optical_depth=h["optical_depth"][perm],
                                dtype=seg.dtype)


#: Parameters of the full and the quick run.
FULL = dict(scenes=["three_columns", "hair_and_smoke", "plume"], resolution=128, orders=8, nodes=[4, 8, 12, 16])
QUICK = dict(FULL, scenes=["three_columns"], resolution=64, orders=3)


def _compute(res, params: dict) -> dict:
    """AVSM's error and frame-to-frame flicker over shuffled insertion orders, sorted or not."""
    from avsm_dr import builtin_scenes as scene_lib
    from avsm_dr import capture
    from avsm_dr.evaluation import curve_values, depth_l2
    names = params["scenes"]
    rng = np.random.default_rng(3)
    rows = []
    for name in tqdm(names, desc="ordering", unit="scene"):
        scene = getattr(scene_lib, name)()
        cap = capture(scene, resolution=params["resolution"], order="depth")
        texel, depth = cap.lookup(np.asarray(scene.receivers))
        ex_rep = build("exact", cap.segments)
        exact = np.asarray(ex_rep.eval(texel, depth))
        curve = curve_values(ex_rep, cap.segments)
        orders = [shuffled(cap.segments, rng) for _ in range(params["orders"])]
        for nodes in params["nodes"]:
            for sort in (False, True):
                reps = [build("avsm", s, nodes=nodes, sort=sort) for s in orders]
                Ts = [np.asarray(rep.eval(texel, depth)) for rep in reps]
                flicker = [np.abs(Ts[k + 1] - Ts[k]) for k in range(len(Ts) - 1)]
                errs = [error_stats(T, exact) for T in Ts]
                l2 = [depth_l2(rep, cap.segments, exact=curve) for rep in reps]
                rows.append(dict(scene=name, method="avsm", param=nodes, sorted=sort,
                                 rmse=float(np.mean([e["rmse"] for e in errs])),
                                 max_error=float(np.max([e["max_error"] for e in errs])),
                                 flicker_rms=float(np.sqrt(np.mean(np.square(flicker)))),
                                 flicker_max=float(np.max(flicker)),
                                 flicker_texels_over_1pct=float(np.mean(np.stack(flicker) > 0.01)),
                                 order="depth" if sort else "random",
                                 signed_mean=float(np.mean([e["mean_error"] for e in errs])),
                                 leak_share=float(np.mean([e["leak_fraction"] for e in errs])),
                                 depth_l2=float(np.sqrt(np.mean(np.square(l2)))),
                                 bytes=reps[0].nbytes_sparse_per_texel, bytes_dense=reps[0].nbytes_per_texel))
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for name in names:
        for sort, ls in ((False, "-"), (True, "--")):
            rs = [r for r in rows if r["scene"] == name and r["sorted"] == sort]
            lab = f"{name} {'sorted' if sort else 'unsorted'}"
            axes[0].semilogy([r["param"] for r in rs], [max(r["rmse"], 1e-7) for r in rs], "o" + ls, label=lab)
            axes[1].semilogy([r["param"] for r in rs], [max(r["flicker_rms"], 1e-7) for r in rs], "o" + ls, label=lab)
    axes[0].set_ylabel("RMSE vs exact")
    axes[1].set_ylabel("RMS change between two orders (flicker)")
    for ax in axes:
        ax.set_xlabel("AVSM nodes")
    axes[1].legend(fontsize=7)
    res.save_figure(fig, "ordering.png")
    summary = {f"{r['scene']}_N{r['param']}_{'sorted' if r['sorted'] else 'unsorted'}_flicker_rms": r["flicker_rms"]
               for r in rows}
    return dict(rows=rows, summary=summary)

def _headline(s: dict) -> list[str]:
    """Per scene: the flicker RMS of AVSM-N built unsorted, against sorted (0: no flicker)."""
    import re
    groups: dict = {}
    for key, v in s.items():
        m = re.match(r"(.+)_N(\d+)_(sorted|unsorted)_flicker_rms$", key)
        if m:
            groups.setdefault(m[1], {}).setdefault(int(m[2]), {})[m[3]] = v
    return [line for scene, per_n in groups.items() for line in wrap(
        f"{scene}, flicker RMS unsorted / sorted: ",
        [f"N={n} {num(d.get('unsorted'))} / {num(d.get('sorted'))}" for n, d in sorted(per_n.items())])]


STUDY = Study("ordering", "Effect of insertion order on AVSM: error and flicker, sorted against unsorted",
              REPRODUCES, FULL, QUICK, _compute, headline=_headline)
run = STUDY.run
