"""Performance suite: throughput of capture, build and lookup for every
representation and setting, peers measured in the same run, the machine's limit,
scaling, skipping and memory.

    python -m experiments bench [--quick] [--out DIR] [--force]

Writes into ``results/bench/`` (or ``<--out>/bench/``); one module per table:

* ``data.csv`` / ``throughput.png`` - build (segment insertions/s) and lookup (receivers/s)
  of every setting on synthetic maps (256^2 and 1024^2 texels with about 10, 100 and 1000
  segments per texel; quick: 64^2 / 32^2), next to the peers on the same map: the
  vectorised NumPy AVSM (:mod:`experiments.bench.peer_kernels.numpy_avsm`, on a subset of texels, rates
  per insertion) and the Numba ``parallel=True`` AVSM and FOM
  (:mod:`.peer_kernels.numba_avsm`, :mod:`.peer_kernels.numba_fom`; skipped with a note
  when Numba is absent), and the same two in NVIDIA Warp on its ``cpu`` device
  (:mod:`.peer_kernels.warp_avsm`, :mod:`.peer_kernels.warp_fom`; skipped with a note when
  warp-lang is absent; Warp runs a CPU launch on one thread, so its wall ratio carries the
  idle cores and ``cpu_build_ratio`` compares like with like; its module compile, or load
  from ``~/.cache/warp``, is the row's ``jit_s``, outside the medians).  Numba and Warp
  peers run in float64 on host arrays (the copy is not timed), our kernels in float32.
* ``scenes.csv`` - capture, build and lookup on the built-in scenes (``ad.scenes``).
* ``peers.csv`` / ``peers.png`` - ratios against each peer, and Mitsuba ratio tracking at
  equal error: the spp at which its noise (RMSE against a deterministic fine ray march of
  the same medium, ``noise^2 = v / spp`` fitted) equals a representation's compression
  error (RMSE against our exact curve), and the time that takes against ours (capture +
  build + lookup).  RMSE against our exact curve is also given: it has a floor, the
  shadow map's own discretisation (exact vs ray march), that no spp removes.
* ``machine.json`` - the machine's limit for AVSM insertion: vector operations per
  insertion counted in the kernel's LLVM IR (``dr.kernel_history()``) against the larger of
  the nominal rate (clock x issue width at the vector width the CPU executes: AMD Zen 4 runs a
  512-bit operation as two 256-bit halves: :mod:`experiments.bench.simd`) and the best rate of a
  register-only Dr.Jit loop of the kernel's own operation mix (:mod:`experiments.bench.op_mix`:
  once per iteration in 8-32 short independent chains, measured in CPU time at the kernel's
  width), times SIMD lanes, per core; a generic compare / select / multiply loop beside it; our
  measured insertions per CPU-second as a fraction of it; the LLVM target (ISA, lanes per
  packet, executed bits);
  ``machine.csv`` has the same figures for every setting (also columns of ``data.csv``), with
  the fraction from the median and from the fastest repeat and the build's kernel-time share;
  AVSM's rows add ``model_fraction``, the ceiling of that fraction by llvm-mca's model of this
  CPU for the compress loop's machine code (:mod:`experiments.bench.mca`; empty without llvm-mca).
* ``scaling.csv`` / ``scaling.png`` - build and lookup time against texels, segments per
  texel and N (stored floats per texel), with fitted log-log slopes.
* ``skipping.csv`` / ``skipping.png`` - each kind of skipped work as a measured saving:
  empty texels (compacted lanes vs all texels as lanes), lanes grouped by segment count,
  texels with room (no compression work), segments behind an opaque point (sorted AVSM and
  exact lookups stop), capture rays stopping below the transmittance epsilon, and capture
  of a map that is mostly empty.  Ablations run the shipped AVSM kernel with one skip
  switched off (its private ``_compact`` / ``_group`` / ``_split`` arguments; the nodes are
  the same, ``tests/test_peers.py``).
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

import time

from tqdm import tqdm

from .peer_kernels import numba_avsm, warp_avsm
from .._headline import num
from .._study import Study
from . import memory, peers, report, scaling, skipping, throughput
from .machine import machine_limit
from .settings import SCENE_SETTINGS, SETTINGS, settings

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    "The guide's Performance section: throughput, peers (NumPy, Numba, Warp, Mitsuba at equal error), "
    "the machine's limit, scaling, skipped work and memory; capture cost against the bounding "
    'box; the whole frame (capture -> build -> lookups) per stage on the built-in scenes.'
)

#: Sizes of every table: full, and quick (about a minute on 2 cores).
FULL = dict(maps=[(256, 10), (256, 100), (256, 1000), (1024, 10), (1024, 100)], lookups=1_000_000,
            numpy_segments=8_000_000, repeats=5, big_repeats=1, scene_resolution=256, scene_repeats=5,
            mitsuba_spp=[16, 64, 256], mitsuba_cap=16384,
            mitsuba_reps=[("avsm", {"nodes": 4}), ("avsm", {"nodes": 8}), ("avsm", {"nodes": 16}),
                          ("fom", {"harmonics": 4}), ("fom", {"harmonics": 8}), ("osm", {"slices": 32})],
            scale_texels=[32, 64, 128, 256, 512], scale_counts=[10, 30, 100, 300, 1000], scale_side=128,
            scale_nodes=[2, 4, 8, 16, 32, 64], scale_repeats=3, skip_side=256, memory_side=256,
            dense_plume=48, skip_resolution=256, peak_iters=8000)
QUICK = dict(maps=[(64, 10), (64, 100), (32, 1000)], lookups=200_000, numpy_segments=500_000,
             repeats=3, big_repeats=1, scene_resolution=64, scene_repeats=3,
             mitsuba_spp=[4, 16, 64], mitsuba_cap=2048,
             mitsuba_reps=[("avsm", {"nodes": 4}), ("avsm", {"nodes": 8}), ("fom", {"harmonics": 4})],
             scale_texels=[16, 32, 64, 128], scale_counts=[10, 30, 100, 300, 1000], scale_side=32,
             scale_nodes=[2, 4, 8, 16, 32], scale_repeats=2, skip_side=64, memory_side=64,
             dense_plume=48, skip_resolution=128, peak_iters=2000)


def _compute(res, P: dict) -> dict:
    """Every table of the suite, ``machine.json`` and the figures."""
    notes = []
    if not numba_avsm.available():
        notes.append("numba not installed: Numba peers skipped (pip install 'avsm_dr[bench]')")
    if not warp_avsm.available():
        notes.append("warp-lang not installed: Warp peers skipped (pip install 'avsm_dr[bench]')")
    t_start = time.perf_counter()
    n_steps = (len(P["maps"]) * len(settings(SETTINGS)) + 5 + len(P["scale_texels"])
               + len(P["scale_counts"]) + len(P["scale_nodes"]) + 5 + len(SCENE_SETTINGS)
               + len(settings(memory.MEMORY_SETTINGS)))
    tqdm.monitor_interval = 0                         # no monitor thread in timed code
    with tqdm(total=n_steps, desc="bench", unit="step") as progress:
        data = throughput.throughput(P, notes, progress)
        scene_rows, caps = throughput.scenes(P, progress)
        peer = peers.peer_rows(data)
        try:
            peer += peers.mitsuba_equal_error(P, caps)
        except Exception as exc:                      # Mitsuba missing or failing: say so
            notes.append(f"Mitsuba comparison skipped: {type(exc).__name__}: {exc}")
        machine = machine_limit(P, data)
        report.annotate(data, machine)                # machine figures as columns of our rows
        scal = scaling.scaling(P, progress, notes)
        skip = skipping.skipping(P, progress)
        mem = memory.memory(P, progress, notes)
    res.write_json("machine.json", machine, indent=2, default=str)
    throughput.plot(res, data)
    peers.plot(res, peer)
    scaling.plot(res, scal)
    skipping.plot(res, skip)
    memory.plot(res, mem)
    summary = report.summary(data, peer, machine, scal, skip, notes, time.perf_counter() - t_start)
    report.print_report(data, peer, machine, skip, mem, summary)
    tables = {"scenes.csv": scene_rows, "peers.csv": peer, "scaling.csv": scal, "skipping.csv": skip,
              "memory.csv": mem, "machine.csv": report.machine_rows(data, machine)}
    return dict(rows=data, tables=tables, summary=summary)

def _headline(s: dict) -> list[str]:
    """AVSM-8's rates on the ~100 segments per texel map, its speed-ups over the peers and its
    share of the machine's limit; the run's time."""
    return [f"AVSM-8: {num(s['avsm8_insertions_per_s'])} insertions/s ({num(s['avsm8_insertions_per_cpu_s'])} per "
            f"CPU-second), {num(s['avsm8_lookups_per_s'])} lookups/s",
            f"AVSM-8 speed-up over NumPy {num(s['avsm8_speedup_vs_numpy'])}x, Numba "
            f"{num(s['avsm8_speedup_vs_numba'])}x, Warp {num(s['avsm8_speedup_vs_warp'])}x; FOM-8 over Numba "
            f"{num(s['fom8_speedup_vs_numba'])}x, Warp {num(s['fom8_speedup_vs_warp'])}x",
            f"AVSM-8 at {num(s['machine_fraction_avsm8'])} of the machine's limit (best map "
            f"{num(s['machine_fraction_avsm8_best'])}; the pipeline model's ceiling "
            f"{num(s.get('machine_model_fraction_avsm8'))})",
            f"run time {num(s['seconds'])} s; {len(s.get('notes') or [])} settings skipped (notes in meta.json)"]


STUDY = Study("bench", "Performance suite: throughput of capture, build and lookup for every representation",
              REPRODUCES, FULL, QUICK, _compute,
              writes=("data.csv (throughput)", "scenes.csv", "peers.csv", "scaling.csv", "skipping.csv",
                      "memory.csv", "machine.csv", "machine.json"), headline=_headline)
run = STUDY.run
