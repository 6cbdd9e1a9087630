"""Skipped work as measured savings (``skipping.csv``, ``skipping.png``): empty texels,
lanes grouped by segment count, texels with room, segments behind an opaque point,
capture rays below the transmittance epsilon and mostly empty maps.  Ablations switch
one skip off in the shipped AVSM kernel (its private ``_compact``, ``_group`` and
``_split`` arguments; same nodes either way, ``tests/test_peers.py``)."""
from __future__ import annotations

import numpy as np

from avsm_dr import build
from avsm_dr.segments import OPAQUE_OPTICAL_DEPTH, Segments
from .synthetic import random_map
from .._common import measure
from .settings import counts_map, lookups, pyplot


def _spread(seg: Segments, factor: int) -> Segments:
    """The same segments with ``factor - 1`` empty texels after each texel."""
    counts = np.zeros(seg.n_texels * factor, np.int64)
    counts[::factor] = seg.counts
    offsets = np.concatenate([[0], np.cumsum(counts)])
    return Segments(offsets, seg.z0, seg.z1, seg.optical_depth, seg.dtype, seg.sorted_by_depth)


def _with_front_blocker(side: int, tau_front: float, seed: int = 5) -> Segments:
    """Texels with a blocker segment in [0.02, 0.04] (optical depth tau_front) in front of
    100-300 smoke segments in [0.05, 1], sorted by depth."""
    rng = np.random.default_rng(seed)
    T = side * side
    counts = rng.integers(100, 301, T)
    offsets = np.concatenate([[0], np.cumsum(counts + 1)])
    n = int(offsets[-1])
    z0 = rng.uniform(0.05, 1.0, n)
    z1 = np.minimum(z0 + rng.exponential(0.01, n), 1.0)
    tau = rng.exponential(0.02, n)
    first = offsets[:-1]
    z0[first], z1[first], tau[first] = 0.02, 0.04, tau_front
    return Segments.from_arrays(offsets, z0, z1, optical_depth=tau).sorted()


def skipping(P, progress) -> list[dict]:
    """Each kind of skipped work as a measured saving (rows of one case share ``case``;
    ``time_vs_skipping`` = time / time with skipping, also for CPU and kernel time)."""
    from avsm_dr import capture as _capture
    from avsm_dr import builtin_scenes as scene_lib
    rows = []
    side = P["skip_side"]
    reps = P["repeats"]

    def add(case, variant, skipping_on, m, **extra):
        rows.append(dict(case=case, variant=variant, skipping=skipping_on, seconds=m["wall_s"],
                         cpu_s=m["cpu_s"], kernel_s=m.get("kernel_s", float("nan")), **extra))

    def saving(case):
        rs = [r for r in rows if r["case"] == case]
        on = [r for r in rs if r["skipping"]][0]
        for r in rs:
            r["time_vs_skipping"] = r["seconds"] / on["seconds"]
            r["cpu_vs_skipping"] = r["cpu_s"] / on["cpu_s"] if on["cpu_s"] > 0 else float("nan")
            r["kernel_vs_skipping"] = r["kernel_s"] / on["kernel_s"] if on["kernel_s"] > 0 else float("nan")

    # 1. empty texels: the same segments in a map 16x larger (15 of 16 texels empty)
    dense = counts_map(side, 100)
    sparse = _spread(dense, 16)
    m = measure({"dense": lambda: build("avsm", dense, nodes=8),
                 "sparse": lambda: build("avsm", sparse, nodes=8),
                 "sparse_all": lambda: build("avsm", sparse, nodes=8, _compact=False, _group=False)}, reps)
    S = dense.n_segments
    add("empty texels (AVSM-8)", f"{dense.n_texels} texels, none empty (reference)", None, m["dense"],
        segments=S, texels=dense.n_texels)
    add("empty texels (AVSM-8)", f"{sparse.n_texels} texels, 15/16 empty: compacted lanes", True, m["sparse"],
        segments=S, texels=sparse.n_texels, lanes=m["sparse"]["out"].stats["lanes"])
    add("empty texels (AVSM-8)", "15/16 empty: every texel a lane (no compaction)", False, m["sparse_all"],
        segments=S, texels=sparse.n_texels, lanes=sparse.n_texels)
    saving("empty texels (AVSM-8)")
    progress.update()

    # 2. lanes grouped by segment count: 90 % texels with 10 segments, 10 % with 1000
    rng = np.random.default_rng(4)
    T = side * side
    counts = np.where(rng.random(T) < 0.1, 1000, 10)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    n = int(offsets[-1])
    z0 = rng.uniform(0, 1, n)
    mixed = Segments.from_arrays(offsets, z0, np.minimum(z0 + rng.exponential(0.01, n), 1.0),
                                 optical_depth=rng.exponential(0.02, n))
    m = measure({"grouped": lambda: build("avsm", mixed, nodes=8),
                 "texel_order": lambda: build("avsm", mixed, nodes=8, _group=False)}, reps)
    add("lanes grouped by segment count (AVSM-8, 10% of texels 1000 segments, 90% 10)",
        "lanes sorted by count", True, m["grouped"], segments=n, texels=T)
    add("lanes grouped by segment count (AVSM-8, 10% of texels 1000 segments, 90% 10)",
        "lanes in texel order", False, m["texel_order"], segments=n, texels=T)
    saving("lanes grouped by segment count (AVSM-8, 10% of texels 1000 segments, 90% 10)")
    progress.update()

    # 3. texels with room: 4-8 segments per texel, N = 16 (no compression ever needed)
    few = random_map(side * side * 4, 4, 8, seed=6)
    m = measure({"split": lambda: build("avsm", few, nodes=16),
                 "one": lambda: build("avsm", few, nodes=16, _split=False)}, reps)
    case = "texels with fewer nodes than N (AVSM-16, 4-8 segments per texel; see kernel_s)"
    add(case, "insert-only loop while there is room", True, m["split"], segments=few.n_segments,
        texels=few.n_texels, compressed=m["split"]["out"].stats["compressed"])
    add(case, "compression computed in every step (one loop)", False, m["one"], segments=few.n_segments,
        texels=few.n_texels)
    saving(case)
    progress.update()

    # 4. segments behind an opaque point: sorted AVSM stops, exact lookups stop
    opaque = _with_front_blocker(side, OPAQUE_OPTICAL_DEPTH)
    thin = _with_front_blocker(side, 3.0)            # same geometry, the blocker lets 5 % through
    m = measure({"opaque": lambda: build("avsm", opaque, nodes=8, sort=True),
                 "thin": lambda: build("avsm", thin, nodes=8, sort=True)}, reps)
    case = "segments behind an opaque point (AVSM-8, sorted insertion)"
    add(case, "blocker opaque: rest of the texel skipped", True, m["opaque"], segments=opaque.n_segments,
        texels=opaque.n_texels, skipped_segments=m["opaque"]["out"].stats["skipped"])
    add(case, "blocker with T = 0.05: every segment inserted", False, m["thin"], segments=thin.n_segments,
        texels=thin.n_texels, skipped_segments=m["thin"]["out"].stats["skipped"])
    saving(case)
    m = measure({"opaque": lambda: build("avsm", opaque, nodes=8),
                 "thin": lambda: build("avsm", thin, nodes=8)}, reps)
    case = "segments behind an opaque point (AVSM-8, unsorted: skip is a select, no time saved)"
    add(case, "blocker opaque", True, m["opaque"], segments=opaque.n_segments,
        skipped_segments=m["opaque"]["out"].stats["skipped"])
    add(case, "blocker with T = 0.05", False, m["thin"], segments=thin.n_segments,
        skipped_segments=m["thin"]["out"].stats["skipped"])
    saving(case)
    ex_o, ex_t = build("exact", opaque), build("exact", thin)
    tex, _ = lookups(opaque.n_texels, 100_000)
    depth = np.ones(tex.size)
    m = measure({"opaque": lambda: ex_o.eval(tex, depth), "thin": lambda: ex_t.eval(tex, depth)}, reps)
    case = "exact lookups behind an opaque point (100k receivers at depth 1)"
    add(case, "blocker opaque: loop stops", True, m["opaque"], segments=opaque.n_segments)
    add(case, "blocker with T = 0.05: whole texel summed", False, m["thin"], segments=thin.n_segments)
    saving(case)
    progress.update()

    # 5. capture: rays stop once T < epsilon (dense plume)
    sc = scene_lib.plume(size=P["dense_plume"], density_scale=600.0)
    res = P["skip_resolution"]
    m = measure({"eps": lambda: _capture(sc, resolution=res, epsilon=1e-4, order="depth"),
                 "no_eps": lambda: _capture(sc, resolution=res, epsilon=1e-30, order="depth")}, reps)
    case = "capture rays below transmittance epsilon (plume x10 density)"
    caps = {}
    for key, label, on in (("eps", "epsilon = 1e-4 (default)", True), ("no_eps", "epsilon = 1e-30", False)):
        cap = caps[key] = m[key]["out"]
        add(case, label, on, m[key], segments=cap.segments.n_segments, texels=cap.segments.n_texels,
            march_iterations=cap.stats.get("grid", {}).get("iterations"))
    saving(case)
    m = measure({k: (lambda c=c: build("avsm", c.segments, nodes=8)) for k, c in caps.items()}, reps)
    case = "AVSM-8 build on those captures (segments below epsilon not emitted)"
    add(case, "epsilon = 1e-4 (default)", True, m["eps"], segments=caps["eps"].segments.n_segments)
    add(case, "epsilon = 1e-30", False, m["no_eps"], segments=caps["no_eps"].segments.n_segments)
    saving(case)
    # 6. capture of a mostly empty map: 4x the bounds at 4x the resolution (same texel size)
    sc = scene_lib.plume(size=P["dense_plume"])
    cap0 = _capture(sc, resolution=res, order="depth")
    from avsm_dr.capture import GridVolume
    lo, hi = (np.asarray(b, np.float64) for b in GridVolume.prepare(sc.density, sc.bbox).occupied)
    c, h = (lo + hi) / 2, (hi - lo) / 2
    # the map is fitted to 4x the content's extent (16x the area), at 4x the resolution
    r4 = min(4 * res, 1024)
    m = measure({"tight": lambda: _capture(sc, resolution=res, order="depth"),
                 "wide": lambda: _capture(sc, resolution=r4, bounds=(c - 4 * h, c + 4 * h), order="depth")}, reps)
    big = m["wide"]["out"]
    case = "capture of a mostly empty map (plume; 4x wider map at 4x resolution)"
    add(case, f"tight map {res}^2", True, m["tight"], segments=cap0.segments.n_segments,
        texels=cap0.segments.n_texels, empty_texels=int(np.sum(cap0.segments.counts == 0)))
    add(case, f"wide map {r4}^2", False, m["wide"], segments=big.segments.n_segments,
        texels=big.segments.n_texels, empty_texels=int(np.sum(big.segments.counts == 0)))
    saving(case)
    rows[-1]["skipping"] = None                       # both skip; the ratio is the cost of empty texels
    progress.update()
    return rows


def plot(res, skip):
    """``skipping.png``: time with and without each kind of skipping."""
    plt = pyplot()
    # skipping
    cases = list(dict.fromkeys(r["case"] for r in skip))
    fig, ax = plt.subplots(figsize=(11, 0.6 * len(skip) + 1))
    y = 0
    ticks, tl = [], []
    for i, c in enumerate(cases):
        for r in [r for r in skip if r["case"] == c]:
            ax.barh(y, r["seconds"] * 1e3, color="C0" if r["skipping"] else ("C3" if r["skipping"] is False else "C7"))
            ticks.append(y)
            tl.append(f"{c[:45]}: {r['variant'][:45]}")
            y += 1
        y += 0.6
    ax.set_yticks(ticks, tl, fontsize=6)
    ax.set_xscale("log")
    ax.set_xlabel("ms (median wall; blue: with skipping, red: without)")
    ax.invert_yaxis()
    res.save_figure(fig, "skipping.png")
