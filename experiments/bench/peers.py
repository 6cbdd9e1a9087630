"""Peers: speed ratios against the Numba, Warp and NumPy peers (from the throughput table) and
Mitsuba ratio tracking at equal error (``peers.csv``, ``peers.png``)."""
from __future__ import annotations

import math
import time

import numpy as np

from avsm_dr import build
from .settings import label, one, pyplot


def mitsuba_equal_error(P, caps) -> list[dict]:
    """Ratio-tracking spp and time at which its noise equals each representation's error."""
    from avsm_dr import capture as _capture
    from avsm_dr import groundtruth as gt
    sc, cap = caps["plume"]
    pts = np.asarray(sc.receivers, np.float64)
    tex, depth = cap.lookup(pts)
    truth, _ = gt.transmittance(sc, pts, method="raymarch")
    exact = np.asarray(build("exact", cap.segments).eval(tex, depth), np.float64)
    floor = float(np.sqrt(np.mean((exact - truth) ** 2)))
    rows = []
    first = time.perf_counter()
    gt.transmittance(sc, pts, spp=1, seed=99)          # Mitsuba variant + kernel compile
    first = time.perf_counter() - first
    runs = []
    for spp in P["mitsuba_spp"]:
        m = one(lambda: gt.transmittance(sc, pts, spp=spp, seed=spp), repeats=3)
        mean = m["out"][0]
        runs.append((spp, m["wall_s"], m["cpu_s"], float(np.sqrt(np.mean((mean - truth) ** 2))),
                     float(np.sqrt(np.mean((mean - exact) ** 2)))))
    s = np.array([r[0] for r in runs], float)
    noise = np.array([r[3] for r in runs])
    v = float(np.sum(noise ** 2 / s) / np.sum(1 / s ** 2))           # least squares: noise^2 = v / spp
    tfit = np.polyfit(s, [r[1] for r in runs], 1)                      # wall = t0 + t1 spp
    for spp, w, c, nz, ex in runs:
        rows.append(dict(peer="mitsuba", setting=f"ratio_tracking spp={spp}", spp=spp, seconds=w, cpu_s=c,
                         rmse_vs_raymarch=nz, rmse_vs_exact=ex, capture_floor=floor, first_call_s=first,
                         receivers=len(pts)))
    res = P["scene_resolution"]
    t_cap = one(lambda: _capture(sc, resolution=res, order="depth"), 3)["wall_s"]
    for kind, p in P["mitsuba_reps"]:
        mb = one(lambda: build(kind, cap.segments, **p), 3)
        rep = mb["out"]
        ml = one(lambda: rep.eval(tex, depth), 3)
        err = float(np.sqrt(np.mean((np.asarray(ml["out"], np.float64) - exact) ** 2)))
        spp = max(1, int(math.ceil(v / max(err, 1e-12) ** 2)))
        if spp <= P["mitsuba_cap"]:
            m = one(lambda: gt.transmittance(sc, pts, spp=spp, seed=7), repeats=1)
            t_rt, measured = m["wall_s"], True
            nz = float(np.sqrt(np.mean((m["out"][0] - truth) ** 2)))
        else:
            t_rt, measured, nz = float(np.polyval(tfit, spp)), False, float(np.sqrt(v / spp))
        ours = t_cap + mb["wall_s"] + ml["wall_s"]
        # ratio tracking costs per receiver, ours mostly per map: receivers where both cost the same
        per_rt, per_ours = t_rt / len(pts), ml["wall_s"] / len(pts)
        even = (t_cap + mb["wall_s"]) / (per_rt - per_ours) if per_rt > per_ours else float("inf")
        rows.append(dict(peer="mitsuba", setting=label(kind, p), rep_rmse_vs_exact=err, spp=spp,
                         seconds=t_rt, time_measured=measured, rmse_vs_raymarch=nz, capture_floor=floor,
                         ours_capture_s=t_cap, ours_build_s=mb["wall_s"], ours_lookup_s=ml["wall_s"],
                         ours_total_s=ours, ratio=t_rt / ours, receivers=len(pts), noise_v=v,
                         break_even_receivers=even))
    return rows


def peer_rows(data) -> list[dict]:
    """``peers.csv`` rows: our speed-up over the Numba, Warp and NumPy peers, from the
    throughput rows (``cpu_build_ratio``: process CPU seconds, Numba and Warp only; Warp
    runs its CPU launches on one thread)."""
    out = []
    for r in data:
        if r["impl"] != "drjit":
            continue
        for peer in ("numba", "warp", "numpy"):
            key = "speedup_vs_" + peer + ("_same_subset" if peer == "numpy" else "")
            if key in r:
                out.append(dict(peer=peer, map=r["map"], setting=r["setting"], build_ratio=r[key],
                                lookup_ratio=r.get("lookup_" + key, float("nan")),
                                cpu_build_ratio=r.get("cpu_speedup_vs_" + peer, float("nan"))))
    return out


def plot(res, peers):
    """``peers.png``: build speed-up over each peer; Mitsuba time against RMSE at equal error."""
    plt = pyplot()
    # peers
    fig, ax = plt.subplots(1, 2, figsize=(12, 4))
    labels, ratios, colors = [], [], []
    for r in peers:
        if r.get("peer") in ("numpy", "numba", "warp") and np.isfinite(r.get("build_ratio", np.nan)):
            labels.append(f"{r['setting']} vs {r['peer']}\n{r['map']}")
            ratios.append(r["build_ratio"])
            colors.append({"numpy": "C3", "numba": "C1", "warp": "C4"}[r["peer"]])
    ax[0].barh(np.arange(len(labels)), ratios, color=colors)
    ax[0].set_yticks(np.arange(len(labels)), labels, fontsize=5)
    ax[0].set_xscale("log")
    ax[0].axvline(1, color="k", lw=0.8)
    ax[0].set_xlabel("build speed-up of Dr.Jit over the peer (wall)")
    mi = [r for r in peers if r.get("peer") == "mitsuba" and "spp=" in r["setting"]]
    if mi:
        ax[1].loglog([r["rmse_vs_raymarch"] for r in mi], [r["seconds"] for r in mi], "o-", color="C2",
                     label="Mitsuba ratio tracking (noise)")
        eq = [r for r in peers if r.get("peer") == "mitsuba" and "spp=" not in r["setting"]]
        ax[1].loglog([r["rep_rmse_vs_exact"] for r in eq], [r["ours_total_s"] for r in eq], "s", color="C0",
                     label="ours: capture + build + lookup")
        ax[1].loglog([r["rmse_vs_raymarch"] for r in eq], [r["seconds"] for r in eq], "^", color="C2",
                     label="ratio tracking at equal error")
        for r in eq:
            ax[1].annotate(r["setting"], (r["rep_rmse_vs_exact"], r["ours_total_s"]), fontsize=6)
        ax[1].set_xlabel("RMSE")
        ax[1].set_ylabel("seconds (plume receivers)")
        ax[1].legend(fontsize=7)
    res.save_figure(fig, "peers.png")
