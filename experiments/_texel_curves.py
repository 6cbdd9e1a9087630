"""One texel's transmittance curves: the exact curve, ``optimal``, and AVSM in two insertion
orders, plus the product of AVSM's linear segment ramps ``prod_s R_s(x)`` (Salvi et al. 2010,
sec. 3.1: what uncompressed AVSM would store if every node took its exact product) and each
method's depth-uniform L2 on that texel (:func:`avsm_dr.evaluation.depth_l2`).

Written to explain gaussian_blobs' front-to-back floor (docs/research/insertion_order.md): each
blob is 4 nested uniform spheres, so a texel's segments contain one another; inserted outer
first (``depth`` order), an inner segment's entry node takes its value by linear interpolation
on the partial list, between nodes where the product of the ramps already curves; inserted
inner first (``reverse_depth``), every new node lies outside the nodes before it and every
value is the exact product.  Run: ``python -m experiments._texel_curves [--scene S] [--nodes N]
[--out PATH]`` (default: gaussian_blobs, configuration s0-dir_a, 64^2, N = 16, the texel where
depth order's L2 exceeds reverse_depth's most).
"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from avsm_dr import build, builtin_scenes, capture
from avsm_dr.evaluation import Configuration, curve_values, depth_grid, depth_l2


def ramp_product(z0, z1, tau, x):
    """``prod_s R_s(x)`` of the segments (AVSM's ramp of sec. 3.1: 1 in front, linear inside, exp(-tau) behind)."""
    f = np.clip((x[:, None] - z0) / np.where(z1 > z0, z1 - z0, 1.0), 0.0, 1.0)
    f = np.where(x[:, None] >= z1, 1.0, f)
    return np.prod(1.0 + (np.exp(-tau) - 1.0) * f, axis=1)


def texel_curves(scene: str = "gaussian_blobs", nodes: int = 16, seed: int = 0, light: str = "dir_a",
                 resolution: int = 64, texel: int | None = None) -> dict:
    """The curves of one texel (``texel`` None: where ``depth`` order's L2 exceeds ``reverse_depth``'s most)."""
    cfg = Configuration(seed, light)
    sc0 = builtin_scenes.get(scene, seed=seed)
    seg = capture(dataclasses.replace(sc0, light=cfg.light_for(sc0)), resolution=resolution).segments
    segs = {o: seg.in_order(o) for o in ("depth", "reverse_depth")}
    base = segs["depth"]
    ex = curve_values(build("exact", base), base, 64)
    reps = {"optimal": (build("optimal", base, nodes=nodes), base)}
    reps.update({f"avsm ({o})": (build("avsm", s, nodes=nodes), s) for o, s in segs.items()})
    l2 = {k: depth_l2(r, s, exact=ex, per_texel=True) for k, (r, s) in reps.items()}
    tex = depth_grid(base)[0]
    row = int(np.argmax(l2["avsm (depth)"] - l2["avsm (reverse_depth)"])) if texel is None else \
        int(np.searchsorted(tex, texel))
    t = int(tex[row])
    h = base.numpy()
    s = slice(h["offsets"][t], h["offsets"][t + 1])
    z0, z1, tau = (np.asarray(h[k][s], np.float64) for k in ("z0", "z1", "optical_depth"))
    x = np.linspace(z0.min() - 0.02 * np.ptp(z1), z1.max() + 0.02 * np.ptp(z1), 800)
    tx = np.full(x.size, t, np.uint32)
    curves = {"exact": np.asarray(build("exact", base).eval(tx, x), np.float64)}
    curves.update({k: np.asarray(r.eval(tx, x), np.float64) for k, (r, _) in reps.items()})
    curves["prod R_s (ramp model)"] = ramp_product(z0, z1, tau, x)
    return dict(scene=scene, config=cfg.label, nodes=nodes, texel=t, segments=int(z0.size), x=x, curves=curves,
                l2={k: float(v[row]) for k, v in l2.items()},
                l2_map={k: float(np.sqrt(np.mean(v ** 2))) for k, v in l2.items()})


def plot(res: dict, path: str):
    """The curves of :func:`texel_curves` in one panel, each method's texel L2 in its label."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from . import _plotstyle as plotstyle
    styles = {"exact": dict(color="k", lw=2.2), "prod R_s (ramp model)": dict(color="0.55", ls=":", lw=1.6),
              "optimal": dict(color=plotstyle.PALETTE["green"], ls="--"),
              "avsm (depth)": dict(color=plotstyle.PALETTE["rose"]),
              "avsm (reverse_depth)": dict(color=plotstyle.PALETTE["indigo"], ls="-.")}
    with plotstyle.context():
        fig, ax = plt.subplots(figsize=(6.4, 3.6))
        for k, y in res["curves"].items():
            lab = k if k not in res["l2"] else f"{k}: texel L2 {res['l2'][k]:.4f}"
            ax.plot(res["x"], y, label=lab, **styles[k])
        ax.set_xlabel("depth from the light")
        ax.set_ylabel("transmittance T")
        ax.set_title(f"{res['scene']} {res['config']}, texel {res['texel']} ({res['segments']} segments), "
                     f"N = {res['nodes']}")
        ax.legend(loc="upper right")
        plotstyle.savefig(fig, path)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="gaussian_blobs")
    p.add_argument("--nodes", type=int, default=16)
    p.add_argument("--texel", type=int, default=None)
    p.add_argument("--out", default="docs/research/insertion_order/texel_curves.png")
    a = p.parse_args(argv)
    res = texel_curves(a.scene, a.nodes, texel=a.texel)
    plot(res, a.out)
    print(f"texel {res['texel']} ({res['segments']} segments): texel L2",
          {k: round(v, 5) for k, v in res["l2"].items()}, "map RMS", {k: round(v, 5) for k, v in res["l2_map"].items()})


if __name__ == "__main__":
    main()
