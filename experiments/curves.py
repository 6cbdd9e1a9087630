"""Transmittance along single texels: the exact curve (hundreds of segments) next to
AVSM-4/8/12/16, FOM-16, OSM-32 and DSM, as in Salvi et al. 2010, "Adaptive
Volumetric Shadow Maps", figs. 6-7.

Texels chosen: the one with the most segments in ``hair_and_smoke`` (hair steps in
smoke, fig. 6) and in ``three_columns`` (three smoke columns, fig. 7).

Each row records the insertion ``order`` of its representation ('depth': the capture is front
to back, for the kinds whose build depends on the order; '-' otherwise).  The figure is the
claim: single curves, no receivers, no interval; the summary gives each representation's
largest ``|T - T_exact|`` along the texel.
"""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from avsm_dr import build, kinds
from ._headline import num, wrap
from ._study import Study
from .error_curves import march_step
from .error_curves.labels import order_dependent

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    'Salvi et al., "Adaptive Volumetric Shadow Maps", EGSR 2010, figures 6-7: transmittance '
    'along single texels (hair in smoke; three smoke columns), exact curve against AVSM-4..16, '
    'FOM-16, OSM-32 and DSM.'
)


METHODS = [("avsm", {"nodes": 4}), ("avsm", {"nodes": 8}), ("avsm", {"nodes": 12}), ("avsm", {"nodes": 16}),
           ("fom", {"harmonics": 16}), ("osm", {"slices": 32}), ("dsm", {"tolerance": 0.01})]


#: Parameters of the full and the quick run.
FULL = dict(scenes=["hair_and_smoke", "three_columns"], resolution=256, samples=2000, step_fraction=0.125)
QUICK = dict(FULL, resolution=64, samples=400)


def _compute(res, params: dict) -> dict:
    """The curves of the texel with the most segments, per scene and representation."""
    from avsm_dr import builtin_scenes as scene_lib, capture
    names = params["scenes"]
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = []
    fig, axes = plt.subplots(1, len(names), figsize=(6.5 * len(names), 4.2), squeeze=False)
    summary = {}
    for ax, name in tqdm(list(zip(axes[0], names)), desc="curves", unit="scene"):
        scene = getattr(scene_lib, name)()
        seg = capture(scene, resolution=params["resolution"],
                      step=march_step(scene, params["step_fraction"]), order="depth").segments
        texel = int(np.argmax(seg.counts))
        h = seg.numpy()
        s = slice(h["offsets"][texel], h["offsets"][texel + 1])
        lo, hi = float(h["z0"][s].min()), float(h["z1"][s].max())
        x = np.linspace(lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo), params["samples"])
        tex = np.full(x.size, texel)
        exact = np.asarray(build("exact", seg).eval(tex, x))
        ax.plot(x, exact, "k", lw=2.2, label=f"exact ({seg.counts[texel]} segments)")
        for d, t in zip(x, exact):
            rows.append(dict(scene=name, texel=texel, method="exact", param="", order="-", depth=d, transmittance=t))
        summary[name] = {"texel": texel, "segments": int(seg.counts[texel])}
        for kind, p in METHODS:
            if kind not in kinds():
                continue
            rep = build(kind, seg, **p)
            T = np.asarray(rep.eval(tex, x))
            label = f"{kind}-{next(iter(p.values()))}"
            ax.plot(x, T, lw=1.1, label=label)
            summary[name][label + "_max_error"] = float(np.max(np.abs(T - exact)))
            for d, t in zip(x, T):
                rows.append(dict(scene=name, texel=texel, method=kind, param=next(iter(p.values())),
                                 order="depth" if order_dependent(kind) else "-", depth=d, transmittance=t))
        ax.set_title(f"{name}, texel {texel}")
        ax.set_xlabel("light-space depth")
        ax.set_ylabel("transmittance")
        ax.set_ylim(-0.05, 1.05)
        ax.legend(fontsize=7)
    res.save_figure(fig, "curves.png")
    return dict(rows=rows, summary=summary)

def _headline(s: dict) -> list[str]:
    """Per scene: the texel drawn and each representation's largest |T - T_exact| along it."""
    out = []
    for scene, d in s.items():
        errs = [f"{k[:-len('_max_error')]} {num(v)}" for k, v in d.items() if k.endswith("_max_error")]
        out += wrap(f"{scene} texel {d['texel']} ({d['segments']} segments), max |T - exact|: ", errs)
    return out


STUDY = Study("curves", "Transmittance along single texels: every representation against the exact curve",
              REPRODUCES, FULL, QUICK, _compute, headline=_headline)
run = STUDY.run
