"""Cost of gradients: the backward pass against the forward pass, per representation.

For the plume (``keep_zero`` capture) and each of exact, FOM, OSM, AVSM and DSM
('curve'), two computations are timed and their memory measured - ``representation``:
build + lookup at the scene's receivers + loss, differentiated w.r.t. the segments'
optical depths; ``pipeline``: the same from the density grid (capture included,
differentiated w.r.t. the voxels) - in five modes:

* ``forward``         primal only (no AD graph);
* ``forward_ad``      primal with gradients enabled (records the AD graph);
* ``reverse``         ``dr.backward`` after ``forward_ad`` (all voxels at once);
* ``forward_mode``    one directional derivative (``dr.forward_to``) after ``forward_ad``;
* ``reverse_cheap``   reverse mode through ``build(kind, seg, reverse='checkpoint')``
                      (exact: sum-loop recomputation, its default;
                      AVSM: checkpointing), forward + backward.

Memory: ``heap_mb`` = peak of Dr.Jit's allocator above the live arrays before the
step (``dr.detail.malloc_watermark``), ``rss_mb`` = peak resident set above the
start of the step (kernel stacks included, but pages touched by an earlier step are
not counted again).  The reverse pass through a symbolic loop also keeps a
per-lane trajectory of ``max segments per texel x loop-state words`` in kernel-local
memory (the CPU worker's stack; per-thread local memory on a GPU), reported
analytically as ``trajectory_words_per_lane`` and, for every lane at once (what a GPU
with all lanes resident would hold), ``trajectory_mb_all_lanes``.  A sweep over the
march step grows the segments per texel.  ``stack_limit`` rows run AVSM's reverse
pass on synthetic texels of many segments in a subprocess: the plain kernel's
trajectory overflows the stack (segfault) where the checkpointed one does not.

Timings are medians after one warm-up (JIT compile excluded), on a shared machine.
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import time

import numpy as np
from tqdm import tqdm

from ._common import Meter as _Meter
from ._headline import num, wrap
from ._plotstyle import style
from ._study import Study

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    "The guide's gradient results: cost of the backward pass against the forward pass per "
    "representation, and the inverse problem (a plume's density recovered from its shadows)."
)


MODES = ["forward", "forward_ad", "reverse", "forward_mode", "reverse_cheap"]

#: Parameters of the full and the quick run (``kinds``: every differentiable kind, filled in).
FULL = dict(size=16, density_scale=20.0, resolution=128, step_fractions=[0.5, 0.25, 0.125, 0.0625], repeats=3,
            kinds=None, stack_cases=[(8, 1000), (8, 4000), (32, 500), (32, 2000)])
QUICK = dict(FULL, size=12, resolution=64, step_fractions=[0.5, 0.125], repeats=2, stack_cases=[(8, 4000)])

_STACK_SCRIPT = r"""
import sys, time
import avsm_dr as ad, numpy as np, drjit as dr
from avsm_dr import backend
F = backend.types().Float
mode, N, M, T = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
off = np.concatenate([[0], np.cumsum(np.full(T, M))])
rng = np.random.default_rng(0)
z0 = np.sort(rng.uniform(0, 1, (T, M)), axis=1).ravel()
tau = F(rng.uniform(0, 3.0 / M, off[-1]).astype(np.float32)); dr.enable_grad(tau)
seg = ad.Segments.from_arrays(off, z0, z0 + 1e-3, optical_depth=tau)
t0 = time.perf_counter()
try:
    rep = ad.build("avsm", seg, nodes=N, reverse="trajectory" if mode == "plain" else "checkpoint")
except ValueError as exc:          # trajectory beyond the budget: refused, not a segfault
    print("REFUSED", exc); sys.exit(3)
dr.backward(dr.sum(rep.eval(np.arange(T), np.full(T, 0.7))))
dr.eval(dr.grad(tau)); dr.sync_thread()
print("OK", time.perf_counter() - t0)
"""


def differentiable_kinds() -> list[tuple[str, dict]]:
    """(kind, params) for every registered kind that is not an offline reference and has a
    differentiable configuration (``ad.representations.differentiable_configuration``)."""
    from avsm_dr import describe, kinds
    from avsm_dr.representations import differentiable_configuration
    out = []
    for kind in kinds():
        p = None if describe(kind)["offline"] else differentiable_configuration(kind)
        if p is not None:
            out.append((kind, p))
    return out


def _stack_limit(n_nodes: int, segments: int, mode: str, texels: int = 64) -> dict:
    """AVSM reverse pass on ``texels`` texels of ``segments`` segments in a subprocess."""
    from avsm_dr.representations._loops import safe_chunk
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _STACK_SCRIPT, mode, str(n_nodes), str(segments), str(texels)],
                          capture_output=True, text=True, timeout=600)
    ok = proc.returncode == 0 and "OK" in proc.stdout
    return {"table": "stack_limit", "kind": "avsm", "mode": f"reverse_{mode}", "nodes": n_nodes,
            "max_count": segments, "lanes": texels, "returncode": proc.returncode,
            "outcome": "ok" if ok else ("refused" if proc.returncode == 3 else
                                        "segfault" if proc.returncode in (-11, 139) else "error"),
            "seconds": time.perf_counter() - t0,
            "trajectory_words_per_lane": (segments if mode == "plain" else
                                          min(segments, safe_chunk(2 * n_nodes + 5))) * (2 * n_nodes + 5)}


def _resolve(params: dict, quick: bool) -> dict:
    """``kinds=None``: every differentiable online kind; a list restricts the run to those."""
    if params.get("kinds") is not None:
        return dict(params)
    return dict(params, kinds=[k for k, _ in differentiable_kinds()])


def _compute(res, params: dict) -> dict:
    """The forward and backward timings and memory, per kind and step, and the stack limits."""
    import drjit as dr
    from avsm_dr import backend, builtin_scenes as scene_lib, reconstruction as inv
    from avsm_dr import build
    unknown = set(params["kinds"]) - {k for k, _ in differentiable_kinds()}
    if unknown:
        raise ValueError(f"kinds: {sorted(unknown)} are not differentiable online kinds")
    KINDS = [(k, p) for k, p in differentiable_kinds() if k in params["kinds"]]
    from avsm_dr.capture import capture
    from avsm_dr.segments import Segments
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = backend.types()
    scene = scene_lib.plume(size=params["size"], density_scale=params["density_scale"])
    dens = np.asarray(scene.density, np.float32)
    voxel = float(np.min((scene.bbox[1] - scene.bbox[0]) / np.array(dens.shape[::-1])))
    pts = scene.receivers
    w = np.random.default_rng(0).normal(size=pts.shape[0])
    direction = np.random.default_rng(1).normal(size=dens.shape).astype(np.float32)
    rows = []

    def pipeline(x, kind, p, step, reverse="trajectory"):
        if not dr.is_tensor_v(x) and reverse == "checkpoint":
            reverse = "trajectory"
        sh = inv.shadow(scene, x, pts, kind=kind, params=p, resolution=params["resolution"], step=step,
                        reverse=reverse)
        loss = dr.sum(sh.T * t.Float(w))
        dr.eval(loss)
        return loss, sh

    def representation(seg, tau, kind, p, reverse="trajectory"):
        s = Segments(seg.offsets, seg.z0, seg.z1, tau, seg.dtype, seg.sorted_by_depth)
        rep = build(kind, s, reverse=reverse, **p)
        loss = dr.sum(rep.eval(tex, depth) * t.Float(w))
        dr.eval(loss)
        return loss, None

    probe = Segments.from_arrays([0, 1], [0.2], [0.4], optical_depth=[0.5])
    # the cheap reverse path differs from the plain one where a loop is stored or recomputed
    cheap_kinds = {k for k, p in KINDS if k == "exact" or build(k, probe, **p).loop_state_words > 0}

    def measure(make_leaf, forward, kind):
        """Median seconds and peak memory of the five modes; ``make_leaf(grad)`` -> input,
        ``forward(x, reverse)`` -> (loss, keep-alive)."""
        times = {m: [] for m in MODES}
        mem = {m: (0.0, 0.0) for m in MODES}
        for rep_i in range(params["repeats"] + 1):             # first round: warm-up (JIT)
            meas = {}
            x = make_leaf(False)
            with _Meter() as m:
                loss, keep = forward(x, "trajectory")
            meas["forward"] = m
            del loss, keep, x
            x = make_leaf(True)
            with _Meter() as m:
                loss, keep = forward(x, "trajectory")
            meas["forward_ad"] = m
            with _Meter() as m:
                dr.backward(loss)
                g = dr.grad(x)
                dr.eval(g)
            meas["reverse"] = m
            del loss, keep, g, x
            x = make_leaf(True)
            loss, keep = forward(x, "trajectory")
            with _Meter() as m:
                dr.set_grad(x, tangent(x))
                dr.forward_to(loss)
                dl = dr.grad(loss)
                dr.eval(dl)
            meas["forward_mode"] = m
            del loss, keep, x
            if kind in cheap_kinds:
                x = make_leaf(True)
                with _Meter() as m:
                    loss, keep = forward(x, "checkpoint")
                    dr.backward(loss)
                    g = dr.grad(x)
                    dr.eval(g)
                meas["reverse_cheap"] = m
                del loss, keep, g, x
            if rep_i == 0:
                continue
            for k, m in meas.items():
                times[k].append(m.seconds)
                mem[k] = (max(mem[k][0], m.heap_mb), max(mem[k][1], m.rss_mb))
        return times, mem

    def tangent(x):
        if dr.is_tensor_v(x):
            return t.TensorXf(direction)
        return t.Float(np.random.default_rng(2).normal(size=dr.width(x)).astype(np.float32))

    jobs = [(f, kind, p) for f in params["step_fractions"] for kind, p in KINDS]
    for frac, kind, p in tqdm(jobs, desc="backward_cost", unit="config"):
        step = frac * voxel
        cap = capture(scene, resolution=params["resolution"], step=step, density=dens, keep_zero=True, order="depth")
        seg = cap.segments
        tex, depth = cap.lookup(pts)
        info = dict(segments=seg.n_segments, max_count=seg.max_count, texels=seg.n_texels,
                    lanes=int(np.count_nonzero(seg.counts)),
                    mean_count=float(seg.n_segments / max(1, np.count_nonzero(seg.counts))))
        tau_host = np.asarray(dr.detach(seg.optical_depth).numpy())

        def tau_leaf(grad):
            tau = t.Float(tau_host)
            if grad:
                dr.enable_grad(tau)
            return tau

        def dens_leaf(grad):
            return inv.density_tensor(dens) if grad else dens

        words = build(kind, seg, **p).loop_state_words * info["max_count"]   # 0: sum loop, recomputed
        # loop lanes: receivers for exact's lookup loop, non-empty texels for AVSM's build
        # loop, DSM nodes for its gradient loop
        lanes = {"exact": pts.shape[0], "avsm": info["lanes"]}.get(kind, 0)
        if kind == "dsm":
            lanes = int(build("dsm", seg, **p).node_counts.sum())
        info["loop_lanes"] = lanes
        for table, leaf, fwd in (("representation", tau_leaf, lambda x, r: representation(seg, x, kind, p, r)),
                                 ("pipeline", dens_leaf, lambda x, r: pipeline(x, kind, p, step, r))):
            times, mem = measure(leaf, fwd, kind)
            for mode in MODES:
                if not times[mode]:
                    continue
                rows.append(dict(table=table, kind=kind, step_fraction=frac, mode=mode, **info,
                                 seconds=statistics.median(times[mode]), heap_mb=mem[mode][0],
                                 rss_mb=mem[mode][1],
                                 trajectory_words_per_lane=words if mode == "reverse" else 0,
                                 trajectory_mb_all_lanes=4e-6 * words * lanes if mode == "reverse" else 0.0))

    for n_nodes, segs in tqdm(params["stack_cases"], desc="stack limit", unit="case"):
        for mode in ("plain", "checkpointed"):
            rows.append(_stack_limit(n_nodes, segs, mode))

    # ---- figures: reverse / forward time ratio and memory vs segments per texel
    pipe = [r for r in rows if r["table"] == "representation"]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for kind, _ in KINDS:
        rs = [r for r in pipe if r["kind"] == kind]
        fw = {r["step_fraction"]: r for r in rs if r["mode"] == "forward_ad"}
        rv = {r["step_fraction"]: r for r in rs if r["mode"] == "reverse"}
        xs = sorted(rv, key=lambda f: rv[f]["max_count"])
        mc = [rv[f]["max_count"] for f in xs]
        axes[0].plot(mc, [rv[f]["seconds"] / fw[f]["seconds"] for f in xs], **style(kind), label=kind)
        axes[1].plot(mc, [rv[f]["heap_mb"] for f in xs], **style(kind), label=kind)
        if kind in ("exact", "avsm", "dsm"):
            axes[2].plot(mc, [max(rv[f]["trajectory_mb_all_lanes"], 1e-3) for f in xs], **style(kind), label=kind)
    axes[0].set(xlabel="max segments per texel", ylabel="reverse time / forward (AD) time",
                title="build + lookup: backward vs forward time")
    axes[1].set(xlabel="max segments per texel", ylabel="MB", title="reverse pass: Dr.Jit heap peak")
    axes[2].set(xlabel="max segments per texel", ylabel="MB (log)", yscale="log",
                title="loop trajectory, all lanes resident")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    res.save_figure(fig, "backward_cost.png")

    summary = {}
    finest = min(params["step_fractions"])
    for table in ("representation", "pipeline"):
        for kind, _ in KINDS:
            rs = {r["mode"]: r for r in rows if r["table"] == table and r["kind"] == kind
                  and r["step_fraction"] == finest}
            if "reverse" not in rs:
                continue
            s = {"max_count": rs["reverse"]["max_count"], "segments": rs["reverse"]["segments"],
                 "forward_s": rs["forward"]["seconds"], "forward_ad_s": rs["forward_ad"]["seconds"],
                 "reverse_s": rs["reverse"]["seconds"], "forward_mode_s": rs["forward_mode"]["seconds"],
                 "reverse_over_forward_ad": rs["reverse"]["seconds"] / rs["forward_ad"]["seconds"],
                 "forward_ad_heap_mb": rs["forward_ad"]["heap_mb"], "reverse_heap_mb": rs["reverse"]["heap_mb"],
                 "trajectory_mb_all_lanes": rs["reverse"]["trajectory_mb_all_lanes"]}
            if "reverse_cheap" in rs:
                s["reverse_cheap_total_s"] = rs["reverse_cheap"]["seconds"]
                s["reverse_cheap_heap_mb"] = rs["reverse_cheap"]["heap_mb"]
            summary[f"{table}/{kind}"] = s
    summary["stack_limit"] = [{k: r[k] for k in ("mode", "nodes", "max_count", "outcome")}
                              for r in rows if r["table"] == "stack_limit"]
    return dict(rows=rows, summary=summary)

def _headline(s: dict) -> list[str]:
    """Per table: the reverse pass's time over the forward AD pass's, per kind (finest step),
    and what happened past the worker stack's limit."""
    out = []
    for table in ("representation", "pipeline"):
        items = [f"{k.split('/', 1)[1]} {num(v['reverse_over_forward_ad'])}x" for k, v in s.items()
                 if k.startswith(table + "/")]
        out += wrap(f"{table}: reverse / forward-AD time: ", items)
    if s.get("stack_limit"):
        out += wrap("past the stack limit: ", [f"{r['mode']} N={r['nodes']} at {r['max_count']} segments "
                                               f"{r['outcome']}" for r in s["stack_limit"]])
    return out


STUDY = Study("backward_cost", "Cost of gradients: the backward pass against the forward pass, per representation",
              REPRODUCES, FULL, QUICK, _compute, resolve=_resolve, headline=_headline)
run = STUDY.run
