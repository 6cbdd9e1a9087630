"""Performance suite (issue 7): throughput of capture, build and lookup for every
representation and setting, peers measured in the same run, the machine's limit,
scaling, skipping and memory.

    python -m avsm_dr bench [--quick] [--out DIR] [--force]

Writes into ``results/bench/`` (or ``--out``):

* ``data.csv`` / ``throughput.png`` - build (segment insertions/s) and lookup (receivers/s)
  of every setting on synthetic maps (256^2 and 1024^2 texels with about 10, 100 and 1000
  segments per texel; quick: 64^2 / 32^2), next to the peers on the same map: the
  vectorised NumPy AVSM (:mod:`avsm_dr.peers.numpy_avsm`, on a subset of texels, rates
  per insertion) and the Numba ``parallel=True`` AVSM and FOM
  (:mod:`avsm_dr.peers.numba_avsm`, :mod:`avsm_dr.peers.numba_fom`; skipped with a note
  when Numba is absent).  Numba peers run in float64 on host arrays (the copy is not
  timed), our kernels in float32.
* ``scenes.csv`` - capture, build and lookup on the built-in scenes (``ad.scenes``).
* ``peers.csv`` / ``peers.png`` - ratios against each peer, and Mitsuba ratio tracking at
  equal error: the spp at which its noise (RMSE against a deterministic fine ray march of
  the same medium, ``noise^2 = v / spp`` fitted) equals a representation's compression
  error (RMSE against our exact curve), and the time that takes against ours (capture +
  build + lookup).  RMSE against our exact curve is also given: it has a floor, the
  shadow map's own discretisation (exact vs ray march), that no spp removes.
* ``machine.json`` - the machine's limit for AVSM insertion: vector operations per
  insertion counted in the kernel's LLVM IR (``dr.kernel_history()``), the best vector
  operation rate this CPU reaches in a Dr.Jit loop of the same kind of operations
  (compare / select / multiply, measured in CPU time) and the nominal one (clock x
  issue width), times SIMD lanes, per core; our measured insertions per CPU-second as a
  fraction of it.
* ``scaling.csv`` / ``scaling.png`` - build and lookup time against texels, segments per
  texel and N (stored floats per texel), with fitted log-log slopes.
* ``skipping.csv`` / ``skipping.png`` - each kind of skipped work as a measured saving:
  empty texels (compacted lanes vs all texels as lanes), lanes grouped by segment count,
  texels with room (no compression work), segments behind an opaque point (sorted AVSM and
  exact lookups stop), capture rays stopping below the transmittance epsilon, and capture
  of a map that is mostly empty.  Ablations run :func:`avsm_variant`, the same kernel
  with one skip switched off (it computes the same nodes, ``tests/test_peers.py``).
* ``memory.csv`` / ``memory.png`` - peak memory of build and lookup per representation
  against ``nbytes_per_texel x texels``: process RSS growth (Linux ``VmHWM`` reset through
  ``/proc/self/clear_refs``, after ``dr.flush_malloc_cache()``, with glibc told to mmap
  allocations >= 64 KiB; includes Dr.Jit's host buffers, NumPy and temporaries) and the growth
  of Dr.Jit's allocator watermark (its buffers of any size); peak = the larger.

Timing: median of ``repeats`` calls after one warm-up call; peers that are compared run
interleaved (ours, peer, ours, peer, ...) so load from other processes hits both alike.
Wall time and process CPU time (all threads, ``time.process_time``) are both recorded;
the first call (JIT compile included) is reported separately with the compile seconds
from ``dr.kernel_history()`` (codegen + LLVM; 0 when Dr.Jit's on-disk cache served it).
"""
from __future__ import annotations

import gc
import json
import math
import os
import re
import statistics
import time
from collections import Counter

import drjit as dr
import numpy as np
from tqdm import tqdm

from .. import _arrays as A
from .. import backend, build, kinds
from ..peers import numba_avsm, numba_fom, numpy_avsm
from ..representations import avsm as _avsm
from ..segments import OPAQUE_OPTICAL_DEPTH, Segments
from ..synthetic import random_map
from ._common import Results, sync

#: (kind, parameters) of every setting benchmarked on the synthetic maps.
SETTINGS = [
    ("avsm", {"nodes": 4}), ("avsm", {"nodes": 8}), ("avsm", {"nodes": 16}),
    ("avsm", {"nodes": 8, "sort": True}), ("avsm", {"nodes": 8, "interpolation": "exp"}),
    ("exact", {}), ("osm", {"slices": 32}), ("fom", {"harmonics": 8}),
    ("fom", {"harmonics": 8, "depth_range": "texel"}), ("dsm", {"tolerance": 0.01}),
    ("moments", {}), ("basis", {"basis": "legendre", "n": 8}),
]
#: Settings run on the built-in scenes, in the memory table and the scaling plots.
SCENE_SETTINGS = [("avsm", {"nodes": 8}), ("exact", {}), ("osm", {"slices": 32}),
                  ("fom", {"harmonics": 8}), ("dsm", {"tolerance": 0.01}), ("moments", {})]
#: Settings whose build holds O(segments) host memory or sorts on the host (DSM needs about
#: 360 bytes per segment, sort=True a host lexsort): skipped, with a note, on larger maps.
HEAVY = ("dsm", "sort")
HEAVY_MAX_SEGMENTS = 8_000_000
#: Vector instructions one core issues per cycle, nominal, for 512-bit registers on a core
#: with four 256-bit FP pipes (AMD Zen 4 runs a 512-bit op as two 256-bit halves).
NOMINAL_VECTOR_OPS_PER_CYCLE = 2.0


def _params(quick: bool) -> dict:
    if quick:
        return dict(maps=[(64, 10), (64, 100), (32, 1000)], lookups=200_000, numpy_segments=500_000,
                    repeats=3, big_repeats=1, scene_resolution=64, scene_repeats=3,
                    mitsuba_spp=[4, 16, 64], mitsuba_cap=2048,
                    mitsuba_reps=[("avsm", {"nodes": 4}), ("avsm", {"nodes": 8}), ("fom", {"harmonics": 4})],
                    scale_texels=[16, 32, 64, 128], scale_counts=[10, 30, 100, 300, 1000], scale_side=32,
                    scale_nodes=[2, 4, 8, 16, 32], scale_repeats=2, skip_side=64, memory_side=64,
                    dense_plume=48, skip_resolution=128, peak_iters=2000)
    return dict(maps=[(256, 10), (256, 100), (256, 1000), (1024, 10), (1024, 100)], lookups=1_000_000,
                numpy_segments=8_000_000, repeats=5, big_repeats=1, scene_resolution=256, scene_repeats=5,
                mitsuba_spp=[16, 64, 256], mitsuba_cap=16384,
                mitsuba_reps=[("avsm", {"nodes": 4}), ("avsm", {"nodes": 8}), ("avsm", {"nodes": 16}),
                              ("fom", {"harmonics": 4}), ("fom", {"harmonics": 8}), ("osm", {"slices": 32})],
                scale_texels=[32, 64, 128, 256, 512], scale_counts=[10, 30, 100, 300, 1000], scale_side=128,
                scale_nodes=[2, 4, 8, 16, 32, 64], scale_repeats=3, skip_side=256, memory_side=256,
                dense_plume=48, skip_resolution=256, peak_iters=8000)


# =============================================================================== timing
def _jit_kernels(hist):
    return [k for k in hist if k["type"] == dr.KernelType.JIT]


def measure(fns: dict, repeats: int = 3, warmup: int = 1) -> dict:
    """Time each callable in ``fns`` (name -> fn): a first call (JIT compile included),
    ``warmup - 1`` more, then ``repeats`` rounds run interleaved across ``fns``.

    Returns name -> dict(wall_s, cpu_s, kernel_s (Dr.Jit kernel execution, median),
    first_s, jit_s (codegen + backend of the first call), compiled, from_disk, kernels
    (JIT launches per call), out (last result))."""
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    res = {}
    for name, fn in fns.items():
        dr.kernel_history()
        c0, t0 = time.process_time(), time.perf_counter()
        out = fn()
        sync(out)
        first, first_cpu = time.perf_counter() - t0, time.process_time() - c0
        jit = _jit_kernels(dr.kernel_history())
        res[name] = dict(first_s=first, first_cpu_s=first_cpu, out=out, wall=[], cpu=[], kern=[], kernels=0,
                         jit_s=sum(k.get("codegen_time", 0) + k.get("backend_time", 0) for k in jit) / 1e3,
                         compiled=sum(1 for k in jit if not k.get("cache_hit")),
                         from_disk=sum(1 for k in jit if k.get("cache_disk")))
        for _ in range(max(warmup - 1, 0)):
            sync(fn())
    for _ in range(repeats):
        for name, fn in fns.items():
            dr.kernel_history()
            c0, t0 = time.process_time(), time.perf_counter()
            out = fn()
            sync(out)
            w, c = time.perf_counter() - t0, time.process_time() - c0
            jit = _jit_kernels(dr.kernel_history())
            r = res[name]
            r["wall"].append(w)
            r["cpu"].append(c)
            r["kern"].append(sum(k.get("execution_time", 0) for k in jit) / 1e3)
            r["kernels"] = len(jit)
            r["out"] = out
    for r in res.values():
        r["wall_s"] = statistics.median(r.pop("wall")) if repeats else r["first_s"]
        r["cpu_s"] = statistics.median(r.pop("cpu")) if repeats else r["first_cpu_s"]
        r["kernel_s"] = statistics.median(r.pop("kern")) if repeats else float("nan")
    return res


def _one(fn, repeats=3, warmup=1) -> dict:
    return measure({"x": fn}, repeats, warmup)["x"]


# ====================================================================== synthetic maps
def counts_map(side: int, mean: int, seed: int = 1) -> Segments:
    """side^2 texels with uniform-random counts in [mean/2, 3 mean/2] of smoke-like segments."""
    lo, hi = max(1, mean // 2), max(1, (3 * mean) // 2)
    return random_map(side * side, lo, hi, seed=seed)


def _label(kind, p) -> str:
    return kind + "".join(f"-{k}={v}" for k, v in p.items())


def _lookups(T: int, K: int, seed: int = 2):
    rng = np.random.default_rng(seed)
    return rng.integers(0, T, K), rng.uniform(0, 1, K)


def _heavy(kind, p) -> bool:
    return kind in HEAVY or any(k in HEAVY and v for k, v in p.items())


def throughput(P, notes, progress) -> list[dict]:
    """data.csv rows: every setting of :data:`SETTINGS` on every synthetic map of
    ``P['maps']``, with the Numba peer of the setting interleaved where there is one, and
    the NumPy peer on the maps with about 100 segments per texel."""
    rows = []
    todo = [(k, p) for k, p in SETTINGS if k in kinds()]
    for side, mean in P["maps"]:
        seg = counts_map(side, mean)
        S, T = seg.n_segments, seg.n_texels
        reps = P["repeats"] if S < 20_000_000 else P["big_repeats"]
        tex, depth = _lookups(T, P["lookups"])
        name = f"{side}^2 x {mean}"
        base = dict(map=name, texels=T, segments=S, mean_count=S / T, repeats=reps)
        host = seg.numpy() if numba_avsm.available() else None
        for kind, p in todo:
            progress.set_postfix_str(f"{name} {_label(kind, p)}")
            if _heavy(kind, p) and S > HEAVY_MAX_SEGMENTS:
                notes.append(f"{_label(kind, p)} skipped on {name} ({S} segments > {HEAVY_MAX_SEGMENTS}: "
                             "host memory / host sort)")
                progress.update()
                continue
            s_in = seg.sorted() if p.get("sort") else seg     # host sort once, outside the timing
            fns = {"drjit": (lambda k=kind, p=p, s=s_in: build(k, s, **p))}
            peer = _numba_build(kind, p, host, seg) if host is not None else None
            if peer is not None:
                fns["numba"] = peer[0]
            mb = measure(fns, reps)
            rep = mb["drjit"]["out"]
            fl = {"drjit": (lambda r=rep: r.eval(tex, depth))}
            if peer is not None:
                fl["numba"] = peer[1](mb["numba"]["out"], tex, depth)
            ml = measure(fl, reps)
            for impl in fns:
                b, lk = mb[impl], ml[impl]
                row = dict(base, method=kind, param=next(iter(p.values()), ""), setting=_label(kind, p),
                           impl=impl, build_s=b["wall_s"], build_cpu_s=b["cpu_s"], build_kernel_s=b["kernel_s"],
                           first_call_s=b["first_s"], jit_s=b["jit_s"] + lk["jit_s"],
                           kernels_compiled=b["compiled"] + lk["compiled"], kernels_per_build=b["kernels"],
                           insertions_per_s=S / b["wall_s"] if kind != "exact" else float("nan"),
                           insertions_per_cpu_s=S / b["cpu_s"] if kind != "exact" else float("nan"),
                           lookup_s=lk["wall_s"], lookup_cpu_s=lk["cpu_s"], lookup_first_s=lk["first_s"],
                           lookups_per_s=tex.size / lk["wall_s"], lookups_per_cpu_s=tex.size / lk["cpu_s"],
                           nbytes_per_texel=rep.nbytes_per_texel if impl == "drjit" else
                           (rep.nbytes_per_texel * 2))  # numba peers store float64
                if impl == "numba":
                    comp = (numba_avsm if kind == "avsm" else numba_fom).compile_seconds()
                    row["jit_s"] = sum(comp.values())
                rows.append(row)
            if peer is not None:
                ours_row, nb_row = rows[-2], rows[-1]
                ours_row["speedup_vs_numba"] = nb_row["build_s"] / ours_row["build_s"]
                ours_row["cpu_speedup_vs_numba"] = nb_row["build_cpu_s"] / ours_row["build_cpu_s"]
                ours_row["lookup_speedup_vs_numba"] = nb_row["lookup_s"] / ours_row["lookup_s"]
            progress.update()
        # NumPy peer: a subset of texels (it is ~1000x slower), rates per insertion / lookup
        if mean == 100 or (side, mean) == P["maps"][0]:      # NumPy: ~1 M insertions/s
            rows += _numpy_peer(P, seg, base, rows)
    return rows


def _numba_build(kind, p, host, seg):
    """(build fn, lookup-fn factory) of the Numba peer of a setting, or None."""
    if kind == "avsm" and set(p) <= {"nodes", "sort"} and not p.get("sort"):
        far = seg.bounds()[1]
        return ((lambda: numba_avsm.build(host["offsets"], host["z0"], host["z1"], host["optical_depth"],
                                          p["nodes"], far)),
                lambda out, tex, depth: (lambda: numba_avsm.lookup(out[0], out[1], tex, depth)))
    if kind == "fom" and set(p) == {"harmonics"}:
        near, far = seg.bounds()
        return ((lambda: numba_fom.build(host["offsets"], host["z0"], host["z1"], host["optical_depth"],
                                         p["harmonics"], near, far)),
                lambda out, tex, depth: (lambda: numba_fom.lookup(out, near, far, tex, depth)))
    return None


def _numpy_peer(P, seg, base, rows) -> list[dict]:
    """The NumPy peer on the whole map (or its first texels up to ``numpy_segments``
    segments), interleaved with our kernel on the same segments."""
    n_tex = int(np.searchsorted(seg.offsets, P["numpy_segments"], side="right")) - 1
    sub = seg if n_tex >= seg.n_texels else seg.select_texels(np.arange(max(n_tex, 1)))
    h = sub.numpy()
    out = []
    tex, depth = _lookups(sub.n_texels, min(P["lookups"], 200_000), seed=3)
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


# =========================================================================== scenes
def scenes(P, progress) -> tuple[list[dict], dict]:
    """Capture, build and lookup on every built-in scene; returns (rows, captures)."""
    from .. import capture as _capture, scenes as scene_lib
    rows, caps = [], {}
    for name in scene_lib.SCENES:
        sc = scene_lib.get(name)
        res = P["scene_resolution"]
        m = _one(lambda: _capture(sc, resolution=res), P["scene_repeats"])
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
            progress.set_postfix_str(f"{name} {_label(kind, p)}")
            mb = _one(lambda: build(kind, seg, **p), P["scene_repeats"])
            rep = mb["out"]
            ml = _one(lambda: rep.eval(tex, depth), P["scene_repeats"])
            T = np.asarray(ml["out"], np.float64)
            if kind == "exact":
                exact = T
            err = float(np.sqrt(np.mean((T - exact) ** 2))) if exact is not None else float("nan")
            for stage, mm, n in (("build", mb, seg.n_segments), ("lookup", ml, tex.size)):
                rows.append(dict(scene=name, stage=stage, setting=_label(kind, p), texels=seg.n_texels,
                                 segments=seg.n_segments, receivers=tex.size, seconds=mm["wall_s"],
                                 cpu_s=mm["cpu_s"], first_call_s=mm["first_s"], jit_s=mm["jit_s"],
                                 rate_per_s=n / mm["wall_s"], rmse_vs_exact=err,
                                 nbytes_per_texel=rep.nbytes_per_texel))
        progress.update()
    return rows, caps


# =============================================================== Mitsuba at equal error
def mitsuba_equal_error(P, caps) -> list[dict]:
    """Ratio-tracking spp and time at which its noise equals each representation's error."""
    from .. import capture as _capture, groundtruth as gt
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
        m = _one(lambda: gt.transmittance(sc, pts, spp=spp, seed=spp), repeats=3)
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
    t_cap = _one(lambda: _capture(sc, resolution=res), 3)["wall_s"]
    for kind, p in P["mitsuba_reps"]:
        mb = _one(lambda: build(kind, cap.segments, **p), 3)
        rep = mb["out"]
        ml = _one(lambda: rep.eval(tex, depth), 3)
        err = float(np.sqrt(np.mean((np.asarray(ml["out"], np.float64) - exact) ** 2)))
        spp = max(1, int(math.ceil(v / max(err, 1e-12) ** 2)))
        if spp <= P["mitsuba_cap"]:
            m = _one(lambda: gt.transmittance(sc, pts, spp=spp, seed=7), repeats=1)
            t_rt, measured = m["wall_s"], True
            nz = float(np.sqrt(np.mean((m["out"][0] - truth) ** 2)))
        else:
            t_rt, measured, nz = float(np.polyval(tfit, spp)), False, float(np.sqrt(v / spp))
        ours = t_cap + mb["wall_s"] + ml["wall_s"]
        # ratio tracking costs per receiver, ours mostly per map: receivers where both cost the same
        per_rt, per_ours = t_rt / len(pts), ml["wall_s"] / len(pts)
        even = (t_cap + mb["wall_s"]) / (per_rt - per_ours) if per_rt > per_ours else float("inf")
        rows.append(dict(peer="mitsuba", setting=_label(kind, p), rep_rmse_vs_exact=err, spp=spp,
                         seconds=t_rt, time_measured=measured, rmse_vs_raymarch=nz, capture_floor=floor,
                         ours_capture_s=t_cap, ours_build_s=mb["wall_s"], ours_lookup_s=ml["wall_s"],
                         ours_total_s=ours, ratio=t_rt / ours, receivers=len(pts), noise_v=v,
                         break_even_receivers=even))
    return rows


# ========================================================================= machine limit
_SKIP_OPS = {"phi", "insertelement", "shufflevector", "getelementptr", "bitcast", "br"}


def loop_ops(ir: str, label: str) -> tuple[Counter, int]:
    """Vector operations in one pass of the symbolic loop ``label`` (condition + body) of
    an LLVM kernel's IR, by opcode (calls by intrinsic), and the vector width.  Broadcasts,
    phis and address arithmetic are not counted (hoisted / folded by LLVM)."""
    lines = ir.splitlines()
    start = next(i for i, s in enumerate(lines) if s.strip() == f"; Symbolic loop: {label}")
    prefix = lines[start - 1].strip().rstrip(":").rsplit("_", 1)[0]
    ops, width = Counter(), 0
    for s in lines[start + 1:]:
        s = s.strip()
        if s == f"br label %{prefix}_cond":
            break
        m = re.match(r"(?:%\S+ = )?(\w+)", s)
        if not m or "<" not in s or m.group(1) in _SKIP_OPS or s.endswith(":"):
            continue
        op = m.group(1)
        if op == "call":
            c = re.search(r"@llvm\.([a-z.]+?)\.v\d", s)
            op = c.group(1) if c else "call"
        w = re.search(r"<(\d+) x", s)
        width = max(width, int(w.group(1))) if w else width
        ops[op] += 1
    return ops, width


def _cpuinfo() -> dict:
    info = {"model": "", "mhz": float("nan"), "flags": []}
    try:
        text = open("/proc/cpuinfo").read()
        mhz = [float(x) for x in re.findall(r"cpu MHz\s*:\s*([\d.]+)", text)]
        info["mhz"] = float(np.mean(mhz)) if mhz else float("nan")
        m = re.search(r"model name\s*:\s*(.*)", text)
        info["model"] = m.group(1).strip() if m else ""
        f = re.search(r"flags\s*:\s*(.*)", text)
        info["flags"] = f.group(1).split() if f else []
    except OSError:
        pass
    return info


def _peak_vector_rate(iters: int) -> dict:
    """Best vector-op rate (ops per CPU-second) of a register-only Dr.Jit loop of 12
    independent compare + multiply/subtract + select chains (the AVSM kernel's mix)."""
    t = backend.types()
    Float, UInt32 = t.Float, t.UInt32
    lanes = 1 << 14

    def run():
        x = [dr.full(Float, 0.5 + 0.01 * k, lanes) + dr.arange(Float, lanes) * 1e-9 for k in range(12)]
        dr.eval(x)
        it = dr.zeros(UInt32, lanes)

        def body(it, x):
            return it + 1, [dr.select(v < 0.7, v * 1.001, v - 0.0001) for v in x]
        it, x = dr.while_loop((it, x), lambda it, x: it < iters, body, label="bench_peak")
        return x
    sync(run())                                          # compile
    cpu, wall = [], []
    for _ in range(7):                                    # peak: the fastest of 7 runs
        c0, t0 = time.process_time(), time.perf_counter()
        sync(run())
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - t0)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    run_ir = None
    sync(run())
    for k in _jit_kernels(dr.kernel_history()):
        if "ir" in k and "bench_peak" in k["ir"].getvalue():
            run_ir = k["ir"].getvalue()
    ops, width = loop_ops(run_ir, "bench_peak")
    n_ops = sum(ops.values())
    packets = lanes // width
    return dict(ops_per_iteration=n_ops, width=width, ops=dict(ops),
                vector_ops_per_cpu_s=packets * iters * n_ops / min(cpu),
                vector_ops_per_wall_s=packets * iters * n_ops / min(wall))


def machine_limit(P, data_rows) -> dict:
    """The best achievable AVSM insertion rate on this CPU and our fraction of it."""
    if backend.get_backend() != "llvm":
        return {"note": "machine limit is estimated for the LLVM (CPU) backend only"}
    cpu = _cpuinfo()
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    peak = _peak_vector_rate(P["peak_iters"])
    out = dict(cpu=cpu["model"], mhz=cpu["mhz"], cores=cores,
               avx512="avx512f" in cpu["flags"], avx2="avx2" in cpu["flags"],
               peak_microbench=peak, nominal_vector_ops_per_cycle=NOMINAL_VECTOR_OPS_PER_CYCLE, avsm={})
    seg = counts_map(16, 40)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    for nodes in (4, 8, 16):
        dr.kernel_history()
        build("avsm", seg, nodes=nodes)
        ir = next(k["ir"].getvalue() for k in _jit_kernels(dr.kernel_history())
                  if "ir" in k and "avsm_compress" in k["ir"].getvalue())
        comp, width = loop_ops(ir, "avsm_compress")
        ins, _ = loop_ops(ir, "avsm_insert")
        n_comp = sum(comp.values())
        nominal_core = cpu["mhz"] * 1e6 * NOMINAL_VECTOR_OPS_PER_CYCLE * width / n_comp
        measured_core = peak["vector_ops_per_cpu_s"] * width / n_comp
        lim_core = max(measured_core, nominal_core) if np.isfinite(nominal_core) else measured_core
        row = dict(ops_per_insertion_packet=n_comp, insert_only_ops=sum(ins.values()), lanes=width,
                   ops_by_kind=dict(comp.most_common()),
                   limit_per_core_s=lim_core, limit_machine_per_s=lim_core * cores,
                   microbench_limit_per_core_s=measured_core,
                   nominal_limit_per_core_s=nominal_core, nominal_limit_machine_per_s=nominal_core * cores)
        ours = [r for r in data_rows if r.get("impl") == "drjit" and r.get("setting") == f"avsm-nodes={nodes}"]
        if ours:
            best = max(ours, key=lambda r: r["mean_count"])          # the compress loop dominates
            row.update(measured_map=best["map"], measured_per_cpu_s=best["insertions_per_cpu_s"],
                       measured_per_s=best["insertions_per_s"],
                       fraction_of_limit=best["insertions_per_cpu_s"] / lim_core,
                       fraction_of_nominal=best["insertions_per_cpu_s"] / nominal_core)
        out["avsm"][nodes] = row
    out["gpu"] = "not measured: no GPU in this run (run with --backend cuda on a GPU machine)"
    return out


# ============================================================================== scaling
def scaling(P, progress) -> list[dict]:
    """Build and lookup (100k receivers) time against texels (100 segments each), segments
    per texel and N (AVSM nodes, FOM harmonics, OSM slices; x = stored floats per texel)."""
    rows = []
    K = 100_000
    meth = [(k, p) for k, p in [("avsm", {"nodes": 8}), ("fom", {"harmonics": 8}), ("osm", {"slices": 32}),
                                ("exact", {}), ("dsm", {"tolerance": 0.01})] if k in kinds()]

    def run(axis, x, seg, kind, p):
        if _heavy(kind, p) and seg.n_segments > HEAVY_MAX_SEGMENTS:
            return
        tex, depth = _lookups(seg.n_texels, K)
        mb = _one(lambda: build(kind, seg, **p), P["scale_repeats"])
        rep = mb["out"]
        ml = _one(lambda: rep.eval(tex, depth), P["scale_repeats"])
        rows.append(dict(axis=axis, x=x, setting=_label(kind, p), method=kind, texels=seg.n_texels,
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


# ============================================================================= skipping
def avsm_variant(seg: Segments, nodes: int, compact: bool = True, group: bool = True, split: bool = True,
                 as_numpy: bool = True):
    """The AVSM kernel of :mod:`avsm_dr.representations.avsm` (unsorted insertion, nodes
    cleared to the global far) with its work skipping switched off piece by piece, for
    ablations; the result is the same either way.

    compact: lanes only for non-empty texels (else every texel is a lane);
    group: lanes ordered by segment count, longest first (else texel order);
    split: a first loop inserts while the texel has room and a second one compresses
    (else one loop computes both and selects, i.e. compression work in every step).
    Returns (T, N) depths and values as NumPy arrays (``as_numpy``) or Dr.Jit lists.
    """
    t = backend.types()
    Float, UInt32 = seg.Float, t.UInt32
    N, T, far = int(nodes), seg.n_texels, seg.bounds()[1]
    counts = seg.counts
    lanes_np = np.nonzero(counts > 0)[0] if compact else np.arange(T)
    if group:
        lanes_np = lanes_np[np.argsort(-counts[lanes_np], kind="stable")]
    depths = [dr.full(Float, far, T) for _ in range(N)]
    values = [dr.full(Float, 1.0, T) for _ in range(N)]
    if lanes_np.size and seg.n_segments:
        lanes = A.to_uint32(lanes_np)
        L = lanes_np.size
        offsets = seg.offsets_dr()
        i = dr.gather(UInt32, offsets, lanes)
        end = dr.gather(UInt32, offsets, lanes + 1)
        d = [dr.full(Float, far, L) for _ in range(N)]
        tt = [dr.full(Float, 1.0, L) for _ in range(N)]
        used = dr.zeros(UInt32, L)

        def fetch(i):
            return (dr.gather(Float, seg.z0, i), dr.gather(Float, seg.z1, i),
                    dr.exp(-dr.gather(Float, seg.optical_depth, i)))

        def step(i, used, d, tt, room_known):
            a, b, ts = fetch(i)
            skip = _avsm.curve_value(d, tt, a) == 0
            nd, nt = _avsm.insert_segment(d, tt, used, a, b, ts)
            if room_known == "room":
                new_d, new_t, grow = nd[:N], nt[:N], True
            else:
                cd, ct = _avsm.remove_smallest(*_avsm.remove_smallest(nd, nt))
                if room_known == "full":
                    new_d, new_t, grow = cd, ct, False
                else:
                    room = used + 2 <= N
                    new_d = [dr.select(room, nd[k], cd[k]) for k in range(N)]
                    new_t = [dr.select(room, nt[k], ct[k]) for k in range(N)]
                    grow = room
            d = [dr.select(skip, d[k], new_d[k]) for k in range(N)]
            tt = [dr.select(skip, tt[k], new_t[k]) for k in range(N)]
            if grow is not False:
                used = dr.select(skip | ~(used + 2 <= N), used, used + 2)
            return i + 1, used, d, tt

        if split:
            i, used, d, tt = dr.while_loop(
                (i, used, d, tt), lambda i, used, d, tt: (i < end) & (used + 2 <= N),
                lambda i, used, d, tt: step(i, used, d, tt, "room"), max_iterations=seg.max_count,
                label="avsm_variant_insert")
            frozen = used
            i, d, tt = dr.while_loop(
                (i, d, tt), lambda i, d, tt: i < end,
                lambda i, d, tt: (lambda r: (r[0], r[2], r[3]))(step(i, frozen, d, tt, "full")),
                max_iterations=seg.max_count, label="avsm_variant_compress")
        else:
            i, used, d, tt = dr.while_loop(
                (i, used, d, tt), lambda i, used, d, tt: i < end,
                lambda i, used, d, tt: step(i, used, d, tt, "either"), max_iterations=seg.max_count,
                label="avsm_variant_one_loop")
        for k in range(N):
            dr.scatter(depths[k], d[k], lanes)
            dr.scatter(values[k], tt[k], lanes)
    dr.eval(depths, values)
    dr.sync_thread()
    if not as_numpy:
        return depths, values
    return (np.stack([np.asarray(x.numpy()) for x in depths], axis=1),
            np.stack([np.asarray(x.numpy()) for x in values], axis=1))


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
    from .. import capture as _capture, scenes as scene_lib
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
    m = measure({"dense": lambda: avsm_variant(dense, 8, as_numpy=False),
                 "sparse": lambda: avsm_variant(sparse, 8, as_numpy=False),
                 "sparse_all": lambda: avsm_variant(sparse, 8, compact=False, group=False, as_numpy=False),
                 "build": lambda: build("avsm", sparse, nodes=8)}, reps)
    S = dense.n_segments
    add("empty texels (AVSM-8)", f"{dense.n_texels} texels, none empty (reference)", None, m["dense"],
        segments=S, texels=dense.n_texels)
    add("empty texels (AVSM-8)", f"{sparse.n_texels} texels, 15/16 empty: compacted lanes", True, m["sparse"],
        segments=S, texels=sparse.n_texels, lanes=m["build"]["out"].stats["lanes"])
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
    m = measure({"grouped": lambda: avsm_variant(mixed, 8, as_numpy=False),
                 "texel_order": lambda: avsm_variant(mixed, 8, group=False, as_numpy=False)}, reps)
    add("lanes grouped by segment count (AVSM-8, 10% of texels 1000 segments, 90% 10)",
        "lanes sorted by count", True, m["grouped"], segments=n, texels=T)
    add("lanes grouped by segment count (AVSM-8, 10% of texels 1000 segments, 90% 10)",
        "lanes in texel order", False, m["texel_order"], segments=n, texels=T)
    saving("lanes grouped by segment count (AVSM-8, 10% of texels 1000 segments, 90% 10)")
    progress.update()

    # 3. texels with room: 4-8 segments per texel, N = 16 (no compression ever needed)
    few = random_map(side * side * 4, 4, 8, seed=6)
    m = measure({"split": lambda: avsm_variant(few, 16, as_numpy=False),
                 "one": lambda: avsm_variant(few, 16, split=False, as_numpy=False),
                 "build": lambda: build("avsm", few, nodes=16)}, reps)
    case = "texels with fewer nodes than N (AVSM-16, 4-8 segments per texel; see kernel_s)"
    add(case, "insert-only loop while there is room", True, m["split"], segments=few.n_segments,
        texels=few.n_texels, compressed=m["build"]["out"].stats["compressed"])
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
    tex, _ = _lookups(opaque.n_texels, 100_000)
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
    m = measure({"eps": lambda: _capture(sc, resolution=res, epsilon=1e-4),
                 "no_eps": lambda: _capture(sc, resolution=res, epsilon=1e-30)}, reps)
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
    cap0 = _capture(sc, resolution=res)
    from ..capture import GridVolume
    lo, hi = (np.asarray(b, np.float64) for b in GridVolume.prepare(sc.density, sc.bbox).occupied)
    c, h = (lo + hi) / 2, (hi - lo) / 2
    # the map is fitted to 4x the content's extent (16x the area), at 4x the resolution
    r4 = min(4 * res, 1024)
    m = measure({"tight": lambda: _capture(sc, resolution=res),
                 "wide": lambda: _capture(sc, resolution=r4, bounds=(c - 4 * h, c + 4 * h))}, reps)
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


# =============================================================================== memory
def _status_kb() -> dict:
    out = {}
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(("VmRSS:", "VmHWM:")):
                    key, val = line.split(":")
                    out[key] = int(val.split()[0])
    except OSError:
        pass
    return out


def _malloc_returns_memory():
    """glibc: serve allocations >= 64 KiB by mmap and trim freed memory, so that RSS
    growth reflects what a call allocates (the default adaptive threshold recycles freed
    blocks from the heap, which is already resident).  No-op elsewhere."""
    try:
        import ctypes
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 1 << 16)      # M_MMAP_THRESHOLD
        libc.mallopt(-1, 1 << 16)      # M_TRIM_THRESHOLD
        return True
    except (OSError, AttributeError):
        return False


def peak_memory(fn) -> dict:
    """Peak memory while ``fn`` runs, after freeing Dr.Jit's allocation cache:
    dict(rss = process RSS growth (bytes, Linux VmHWM; NaN elsewhere), jit = growth of
    Dr.Jit's allocator watermark (its buffers, all sizes), out = fn's result).
    (No tracemalloc: on CPython < 3.12.9 stopping it while Dr.Jit / Numba threads allocate
    crashes the process, which this benchmark hit.)"""
    gc.collect()
    dr.sync_thread()
    dr.flush_malloc_cache()
    jb = dr.JitBackend.CUDA if backend.get_backend() == "cuda" else dr.JitBackend.LLVM
    dr.detail.malloc_clear_statistics()
    w0 = dr.detail.malloc_watermark(jb)
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")                             # reset VmHWM to the current RSS
        base = _status_kb().get("VmRSS")
    except OSError:
        base = None
    out = fn()
    sync(out)
    hwm = _status_kb().get("VmHWM")
    rss = (hwm - base) * 1024 if base is not None and hwm is not None else float("nan")
    return dict(rss=float(rss), jit=float(dr.detail.malloc_watermark(jb) - w0), out=out)


def memory(P, progress) -> list[dict]:
    """Peak memory of build and lookup per setting against nbytes_per_texel x texels."""
    seg = counts_map(P["memory_side"], 100)
    dr.eval(seg.z0, seg.z1, seg.optical_depth)
    tex, depth = _lookups(seg.n_texels, P["lookups"])
    rows = []
    _malloc_returns_memory()
    seg_bytes = seg.n_segments * 3 * 4 + (seg.n_texels + 1) * 8
    for kind, p in [(k, p) for k, p in SCENE_SETTINGS + [("avsm", {"nodes": 16}), ("fom", {"harmonics": 16})]
                    if k in kinds()]:
        build(kind, seg, **p).eval(tex[:10], depth[:10])     # compile outside the measurement
        mb = peak_memory(lambda: build(kind, seg, **p))
        rep = mb["out"]
        ml = peak_memory(lambda: rep.eval(tex, depth))
        formula = rep.nbytes_per_texel * seg.n_texels
        rows.append(dict(setting=_label(kind, p), texels=seg.n_texels, segments=seg.n_segments,
                         nbytes_per_texel=rep.nbytes_per_texel, formula_bytes=formula, segments_bytes=seg_bytes,
                         build_peak_rss=mb["rss"], build_peak_jit=mb["jit"],
                         build_peak=max(mb["rss"], mb["jit"]),
                         build_peak_over_formula=max(mb["rss"], mb["jit"]) / formula if formula else float("nan"),
                         lookup_receivers=tex.size, lookup_peak_rss=ml["rss"], lookup_peak_jit=ml["jit"],
                         lookup_peak=max(ml["rss"], ml["jit"]),
                         lookup_io_bytes=tex.size * 3 * 4))
        del rep, mb, ml
        progress.update()
    return rows


# ================================================================================ plots
def _plots(res, data, peers, scal, skip, mem):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # throughput: one group of bars per map
    maps = list(dict.fromkeys(r["map"] for r in data))
    fig, axes = plt.subplots(2, 1, figsize=(13, 8))
    settings = list(dict.fromkeys(r["setting"] for r in data if r["impl"] == "drjit"))
    w = 0.8 / len(maps)
    for j, mp in enumerate(maps):
        for ax, key in ((axes[0], "insertions_per_s"), (axes[1], "lookups_per_s")):
            vals = []
            for s in settings:
                r = [x for x in data if x["map"] == mp and x["setting"] == s and x["impl"] == "drjit"]
                vals.append(r[0][key] / 1e6 if r and np.isfinite(r[0][key]) else 0)
            ax.bar(np.arange(len(settings)) + j * w, vals, w, label=f"Dr.Jit {mp}")
    for ax, ylabel in ((axes[0], "M segment insertions / s"), (axes[1], "M lookups / s")):
        ax.set_xticks(np.arange(len(settings)) + 0.4 - w / 2, settings, rotation=35, ha="right", fontsize=7)
        ax.set_yscale("log")
        ax.set_ylabel(ylabel)
    for impl, marker in (("numba", "x"), ("numpy", "v")):
        for r in data:
            if r["impl"] == impl and r["setting"] in settings:
                x = settings.index(r["setting"]) + maps.index(r["map"]) * w
                axes[0].plot(x, r["insertions_per_s"] / 1e6, marker, color="k")
                axes[1].plot(x, r["lookups_per_s"] / 1e6, marker, color="k")
    axes[0].plot([], [], "x", color="k", label="Numba peer")
    axes[0].plot([], [], "v", color="k", label="NumPy peer (subset)")
    axes[0].legend(fontsize=7, ncol=4)
    fig.suptitle("Throughput (median after warm-up; wall clock, 2 shared cores)")
    res.save_figure(fig, "throughput.png")

    # peers
    fig, ax = plt.subplots(1, 2, figsize=(12, 4))
    labels, ratios, colors = [], [], []
    for r in peers:
        if r.get("peer") in ("numpy", "numba") and np.isfinite(r.get("build_ratio", np.nan)):
            labels.append(f"{r['setting']} vs {r['peer']}\n{r['map']}")
            ratios.append(r["build_ratio"])
            colors.append("C3" if r["peer"] == "numpy" else "C1")
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

    # scaling
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for ax, axis, xl in ((axes[0], "texels", "texels"), (axes[1], "segments_per_texel", "segments per texel"),
                         (axes[2], "N", "floats per texel (AVSM 2N, FOM 2n+1, OSM slices)")):
        for j, s in enumerate(dict.fromkeys(r["setting"] for r in scal if r["axis"] == axis)):
            rs = [r for r in scal if r["axis"] == axis and r["setting"] == s]
            if axis == "N":
                s = s.split("-")[0]
                rs = [r for r in scal if r["axis"] == "N" and r["method"] == s]
                if s in [l.get_label().split(" ")[0] for l in ax.get_lines()]:
                    continue
            x = [r["floats_per_texel"] if axis == "N" else r["x"] for r in rs]
            ax.loglog(x, [r["build_s"] for r in rs], "o-", color=f"C{j}", label=f"{s} build")
            ax.loglog(x, [r["lookup_s"] for r in rs], "s--", color=f"C{j}", label=f"{s} lookup (100k)")
        ax.set_xlabel(xl)
        ax.set_ylabel("seconds")
        ax.legend(fontsize=6)
    res.save_figure(fig, "scaling.png")

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

    # memory
    if mem:
        fig, ax = plt.subplots(figsize=(11, 4))
        x = np.arange(len(mem))
        for k, (key, lab) in enumerate((("formula_bytes", "bytes_per_texel x texels"),
                                        ("build_peak", "build peak"),
                                        ("build_peak_jit", "build: Dr.Jit allocator"),
                                        ("lookup_peak", "lookup peak"))):
            ax.bar(x + 0.2 * k, [max(r[key], 1) / 1e6 for r in mem], 0.2, label=lab)
        ax.set_xticks(x + 0.3, [r["setting"] for r in mem], rotation=30, ha="right", fontsize=7)
        ax.set_yscale("log")
        ax.set_ylabel("MB")
        ax.legend(fontsize=7)
        ax.set_title(f"{mem[0]['texels']} texels, {mem[0]['segments']} segments "
                     f"({mem[0]['segments_bytes'] / 1e6:.0f} MB of segments)")
        res.save_figure(fig, "memory.png")


# ================================================================================== run
def _peer_rows(data) -> list[dict]:
    out = []
    for r in data:
        if r["impl"] != "drjit":
            continue
        for peer in ("numba", "numpy"):
            key = "speedup_vs_" + peer + ("_same_subset" if peer == "numpy" else "")
            if key in r:
                out.append(dict(peer=peer, map=r["map"], setting=r["setting"], build_ratio=r[key],
                                lookup_ratio=r.get("lookup_" + key, float("nan")),
                                cpu_build_ratio=r.get("cpu_speedup_vs_numba", float("nan"))
                                if peer == "numba" else float("nan")))
    return out


def run(quick: bool = False, out=None, force: bool = False) -> dict:
    """Run the experiment; write CSV, figures and meta.json into ``out``
    (default ``results/<name>/``); ``quick`` = small sizes, ``force`` = recompute."""
    P = _params(quick)
    res = Results("bench", out, quick, {k: v for k, v in P.items()})
    if res.exists() and not force:
        return {"csv": str(res.dir / "data.csv"), "out": str(res.dir), "cached": True}
    notes = []
    if not numba_avsm.available():
        notes.append("numba not installed: Numba peers skipped (pip install 'avsm_dr[bench]')")
    t_start = time.perf_counter()
    n_steps = (len(P["maps"]) * len([s for s in SETTINGS if s[0] in kinds()]) + 5 + len(P["scale_texels"])
               + len(P["scale_counts"]) + len(P["scale_nodes"]) + 5 + len(SCENE_SETTINGS) + 2)
    tqdm.monitor_interval = 0                         # no monitor thread in timed code
    with tqdm(total=n_steps, desc="bench", unit="step") as progress:
        data = throughput(P, notes, progress)
        scene_rows, caps = scenes(P, progress)
        peers = _peer_rows(data)
        try:
            peers += mitsuba_equal_error(P, caps)
        except Exception as exc:                      # Mitsuba missing or failing: say so
            notes.append(f"Mitsuba comparison skipped: {type(exc).__name__}: {exc}")
        machine = machine_limit(P, data)
        scal = scaling(P, progress)
        skip = skipping(P, progress)
        mem = memory(P, progress)
    csv = res.write_csv(data)
    res.write_csv(scene_rows, "scenes.csv")
    res.write_csv(peers, "peers.csv")
    res.write_csv(scal, "scaling.csv")
    res.write_csv(skip, "skipping.csv")
    res.write_csv(mem, "memory.csv")
    (res.dir / "machine.json").write_text(json.dumps(machine, indent=2, default=str))
    _plots(res, data, peers, scal, skip, mem)

    def pick(setting, impl="drjit", key="insertions_per_s", mp=None):
        rs = [r for r in data if r["setting"] == setting and r["impl"] == impl and (mp is None or r["map"] == mp)]
        return max((r.get(key, float("nan")) for r in rs), default=float("nan"))
    mid = [m for m in dict.fromkeys(r["map"] for r in data) if m.endswith("x 100")]
    mid = mid[0] if mid else None
    summary = {
        "avsm8_insertions_per_s": pick("avsm-nodes=8", mp=mid),
        "avsm8_insertions_per_cpu_s": pick("avsm-nodes=8", key="insertions_per_cpu_s", mp=mid),
        "avsm8_lookups_per_s": pick("avsm-nodes=8", key="lookups_per_s", mp=mid),
        "avsm8_speedup_vs_numpy": pick("avsm-nodes=8", key="speedup_vs_numpy_same_subset", mp=mid),
        "avsm8_speedup_vs_numba": pick("avsm-nodes=8", key="speedup_vs_numba", mp=mid),
        "fom8_speedup_vs_numba": pick("fom-harmonics=8", key="speedup_vs_numba", mp=mid),
        "machine_fraction_avsm8": machine.get("avsm", {}).get(8, {}).get("fraction_of_limit"),
        "machine_limit_avsm8_per_core_s": machine.get("avsm", {}).get(8, {}).get("limit_per_core_s"),
        "mitsuba_time_ratio": {r["setting"]: r["ratio"] for r in peers
                               if r.get("peer") == "mitsuba" and "ratio" in r},
        "scaling_slopes": slopes(scal),
        "skipping_time_without_over_with": {f"{r['case']} | {r['variant']}": r["time_vs_skipping"]
                                            for r in skip if r["skipping"] is False},
        "seconds": time.perf_counter() - t_start,
        "notes": notes,
    }
    res.write_meta(summary)
    _print(data, peers, machine, skip, mem, summary)
    return {"csv": str(csv), "out": str(res.dir), "summary": summary}


def _print(data, peers, machine, skip, mem, summary):
    """The main numbers on stdout."""
    for r in data:
        extra = ""
        if r["impl"] == "drjit":
            for key, lab in (("speedup_vs_numpy_same_subset", "NumPy"), ("speedup_vs_numba", "Numba")):
                if key in r:
                    extra += f"  x{r[key]:.1f} vs {lab}"
        print(f"{r['map']:>12s} {r['impl']:6s} {r['setting']:32s} {r['insertions_per_s'] / 1e6:9.2f} M ins/s "
              f"({r.get('insertions_per_cpu_s', float('nan')) / 1e6:8.2f} per CPU-s) "
              f"{r['lookups_per_s'] / 1e6:8.2f} M lookups/s{extra}")
    for r in peers:
        if r.get("peer") == "mitsuba" and "ratio" in r:
            print(f"mitsuba {r['setting']:18s} rmse {r['rep_rmse_vs_exact']:.4f} -> spp {r['spp']:6d}: "
                  f"{r['seconds']:.3f} s vs ours {r['ours_total_s']:.4f} s (x{r['ratio']:.1f}; "
                  f"equal cost at {r['break_even_receivers']:.0f} receivers)")
    for n, r in machine.get("avsm", {}).items():
        print(f"machine AVSM-{n}: {r['ops_per_insertion_packet']} vector ops / {r['lanes']} insertions; limit "
              f"{r['limit_per_core_s'] / 1e6:.0f} M/core-s (nominal {r['nominal_limit_per_core_s'] / 1e6:.0f}); "
              f"ours {r.get('measured_per_cpu_s', float('nan')) / 1e6:.1f} M/CPU-s = "
              f"{100 * r.get('fraction_of_limit', float('nan')):.0f} %")
    for r in skip:
        print(f"skip {r['case'][:60]:60s} | {r['variant'][:48]:48s} {r['seconds'] * 1e3:9.2f} ms "
              f"(x{r.get('time_vs_skipping', float('nan')):.2f}; CPU x{r.get('cpu_vs_skipping', float('nan')):.2f}; "
              f"kernels x{r.get('kernel_vs_skipping', float('nan')):.2f})")
    for r in mem:
        print(f"memory {r['setting']:24s} formula {r['formula_bytes'] / 1e6:8.2f} MB | build peak "
              f"{r['build_peak'] / 1e6:8.2f} MB (RSS {r['build_peak_rss'] / 1e6:.2f}, Dr.Jit "
              f"{r['build_peak_jit'] / 1e6:.2f}) | lookup peak "
              f"{r['lookup_peak'] / 1e6:8.2f} MB")
    print(f"bench: {summary['seconds']:.0f} s; notes: {summary['notes']}")
