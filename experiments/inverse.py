"""Inverse problem: recover a smoke plume's density grid from its shadows.

Setup (see :mod:`avsm_dr.reconstruction`): the built-in ``plume`` (small grid, density scale 20
so that shadows are not saturated), three directional training lights 120 degrees
apart in azimuth at 20 degrees elevation, and per light a shadow image of
``image x image`` receivers on a plane behind the volume plus a lattice of probe
receivers inside the box (where the representations differ: behind the volume every
method here returns exp(-total optical depth) exactly).  Targets are the ground
truth's deterministic float64 ray march (independent of the capture code).

The unknown grid starts empty (and, in the full run, also uniform) and is fitted
with Adam (projection onto sigma >= 0) through capture -> FOM / AVSM (and the exact
curve as the ideal model) -> transmittance.  Reported: loss curves, the density
error against the known grid per iteration, and for a held-out light (azimuth 120,
elevation 35 degrees) the recovered grid's shadows - our model's and Mitsuba
ratio tracking on the recovered grid - against ratio tracking on the true grid.
"""

from __future__ import annotations

import time

import numpy as np
from tqdm import tqdm

from avsm_dr.receivers import lattice

from ._headline import num
from ._study import Study

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    "The guide's gradient results: cost of the backward pass against the forward pass per "
    "representation, and the inverse problem (a plume's density recovered from its shadows)."
)


MODELS = [("exact", {}), ("fom", {"harmonics": 4}), ("avsm", {"nodes": 8})]
TRAIN = [(180.0, 20.0), (300.0, 20.0), (60.0, 20.0)]      # (azimuth, elevation) degrees
HELD_OUT = (120.0, 35.0)

#: Parameters of the full and the quick run.
FULL = dict(size=12, density_scale=20.0, resolution=96, image=32, probes=[6, 9, 6], iterations=200, lr=0.5,
            smooth=0.0, filter="bilinear", inits=["empty", "uniform"], uniform_value=1.0, train=TRAIN,
            held_out=HELD_OUT, spp=512, models=[m[0] for m in MODELS], target="raymarch")
QUICK = dict(FULL, size=8, resolution=64, image=20, probes=[4, 6, 4], iterations=40, inits=["empty"], spp=64)


def _order(kind: str) -> str:
    """The insertion order the model's build sees: ``avsm_dr.reconstruction`` captures front to
    back ('depth') for the kinds whose build depends on it; '-' otherwise."""
    from .error_curves.labels import order_dependent
    return "depth" if order_dependent(kind) else "-"


def _rmse(a, b) -> float:
    return float(np.sqrt(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2)))


def _compute(res, params: dict) -> dict:
    """Each model fitted to the training shadows; loss curves, recovered density, held-out view."""
    from avsm_dr import builtin_scenes as scene_lib
    from avsm_dr import groundtruth as gt
    from avsm_dr import reconstruction as inv
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scene = scene_lib.plume(size=params["size"], density_scale=params["density_scale"])
    truth = np.asarray(scene.density, np.float64)
    probes = lattice(scene.bbox, params["probes"])
    n_img = params["image"] ** 2
    lights = [inv.light_from_angles(a, e) for a, e in TRAIN]
    receivers = [np.concatenate([inv.receiver_grid(scene.bbox, l, params["image"]), probes]) for l in lights]
    targets = [gt.transmittance(inv.with_light(scene, l), r, method="raymarch")[0]
               for l, r in zip(lights, receivers)]

    rows, recovered, summary, checks = [], {}, {}, {}
    runs = [(kind, p, init) for init in params["inits"] for kind, p in MODELS]
    total_iters = len(runs) * (params["iterations"] + 1)
    with tqdm(total=total_iters, desc="inverse", unit="it") as bar:
        for kind, p, init in runs:
            label = f"{kind}/{init}"
            t0 = time.perf_counter()
            rec = inv.recover(scene, lights, targets, receivers, kind=kind, params=p,
                              iterations=params["iterations"], lr=params["lr"], init=init,
                              init_value=params["uniform_value"], smooth=params["smooth"],
                              resolution=params["resolution"], filter=params["filter"], truth=truth,
                              callback=lambda it, r: bar.update(1))
            seconds = time.perf_counter() - t0
            recovered[label] = rec.density
            checks[label] = rec.gradient_check
            for h in rec.history:
                rows.append(dict(table="history", model=kind, init=init, order=_order(kind), **h))
            last = rec.history[-1]
            summary[label] = {"data_loss_first": rec.history[0]["data"], "data_loss_last": last["data"],
                              "density_rel_l2": last["density_rel_l2"], "density_rmse": last["density_rmse"],
                              "mass_rel": last["density_mass_rel"], "seconds": seconds,
                              "seconds_per_iteration": seconds / (params["iterations"] + 1),
                              "gradient_check_ok": rec.gradient_check["ok"]}

    # ---- held-out light: recovered grids vs the truth, Mitsuba ratio tracking
    held = inv.light_from_angles(*HELD_OUT)
    pts = np.concatenate([inv.receiver_grid(scene.bbox, held, params["image"]), probes])
    spp = params["spp"]
    T_true, se_true = gt.transmittance(inv.with_light(scene, held), pts, spp=spp, seed=1)
    held_rows, images = [], {"truth (Mitsuba RT)": T_true[:n_img]}
    for label, dens in tqdm(recovered.items(), desc="held-out", unit="grid"):
        kind = label.split("/")[0]
        p = dict(MODELS)[kind]
        T_rt, se_rt = gt.transmittance(inv.with_light(scene, held, density=dens), pts, spp=spp, seed=2)
        T_model = np.asarray(inv.shadow(scene, dens, pts, light=held, kind=kind, params=p,
                                        resolution=params["resolution"], filter=params["filter"]).T, np.float64)
        images[f"{label} (Mitsuba RT)"] = T_rt[:n_img]
        for part, sl in (("image", slice(0, n_img)), ("probes", slice(n_img, None)), ("all", slice(None))):
            r = dict(table="held_out", model=kind, init=label.split("/")[1], part=part, order=_order(kind),
                     rmse_recovered_vs_truth=_rmse(T_rt[sl], T_true[sl]),
                     rmse_model_vs_mitsuba_on_recovered=_rmse(T_model[sl], T_rt[sl]),
                     rmse_empty_vs_truth=_rmse(np.ones_like(T_true[sl]), T_true[sl]),
                     mc_stderr_mean=float(np.mean(np.hypot(se_rt[sl], se_true[sl]))))
            held_rows.append(r)
            if part == "all":
                summary[label].update({k: v for k, v in r.items() if k.startswith(("rmse", "mc"))})
    rows.extend(held_rows)

    # ---- figures
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for label in recovered:
        kind, init = label.split("/")
        h = [r for r in rows if r.get("table") == "history" and r["model"] == kind and r["init"] == init]
        ls = "-" if init == "empty" else "--"
        axes[0].semilogy([r["iteration"] for r in h], [r["data"] for r in h], ls, label=label)
        axes[1].plot([r["iteration"] for r in h], [r["density_rel_l2"] for r in h], ls, label=label)
    axes[0].set(xlabel="Adam iteration", ylabel="shadow loss (mean squared T error)", title="loss")
    axes[1].set(xlabel="Adam iteration", ylabel="||sigma - sigma*|| / ||sigma*||", title="density error vs known grid")
    for ax in axes:
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    res.save_figure(fig, "loss_curves.png")

    kz = truth.shape[0] // 2
    grids = {"truth": truth, **{k: v for k, v in recovered.items() if k.endswith("/empty")}}
    fig, axes = plt.subplots(2, len(grids), figsize=(2.6 * len(grids), 5.6), squeeze=False)
    vmax = float(truth.max())
    for c, (name, g) in enumerate(grids.items()):
        axes[0, c].imshow(g[kz], origin="lower", vmin=0, vmax=vmax, cmap="magma")
        axes[0, c].set_title(f"{name}\nslice z={kz}", fontsize=8)
        axes[1, c].imshow(np.asarray(g).sum(axis=0), origin="lower", cmap="magma")
        axes[1, c].set_title("sum along z", fontsize=8)
        for ax in axes[:, c]:
            ax.axis("off")
    res.save_figure(fig, "density_slices.png")

    n = params["image"]
    fig, axes = plt.subplots(1, len(images), figsize=(2.6 * len(images), 2.9), squeeze=False)
    for ax, (name, img) in zip(axes[0], images.items()):
        ax.imshow(np.asarray(img).reshape(n, n), vmin=0, vmax=1, cmap="gray")
        ax.set_title(name, fontsize=7)
        ax.axis("off")
    res.save_figure(fig, "held_out.png")

    summary["gradient_checks"] = checks
    summary["note"] = ("targets: float64 ray march of the true grid; held-out: Mitsuba ratio tracking "
                       f"({spp} spp) on the recovered and the true grid")
    return dict(rows=rows, summary=summary)

def _headline(s: dict) -> list[str]:
    """Per model and start: the recovered density's error, the data loss before and after,
    the held-out light's RMSE (recovered and empty grid against the truth), the gradient check."""
    out = []
    for label, d in s.items():
        if not isinstance(d, dict) or "density_rmse" not in d:
            continue
        line = (f"{label}: density RMSE {num(d['density_rmse'])} (relative L2 {num(d['density_rel_l2'])}), "
                f"data loss {num(d['data_loss_first'])} -> {num(d['data_loss_last'])} in {num(d['seconds'])} s")
        if "rmse_recovered_vs_truth" in d:
            line += (f"; held-out light RMSE {num(d['rmse_recovered_vs_truth'])} "
                     f"(empty grid {num(d['rmse_empty_vs_truth'])})")
        out.append(line)
    checks = s.get("gradient_checks", {})
    bad = [k for k, c in checks.items() if not c.get("ok")]
    if checks:
        worst = max(c.get("error", 0.0) for c in checks.values())
        out.append(f"gradient checks (reverse vs forward mode): {len(checks) - len(bad)} of {len(checks)} agree, "
                   f"largest difference {num(worst)}" + (f"; failed: {', '.join(bad)}" if bad else ""))
    return out


STUDY = Study("inverse", "Inverse problem: recover a smoke plume's density grid from its shadows", REPRODUCES,
              FULL, QUICK, _compute, headline=_headline)
run = STUDY.run
