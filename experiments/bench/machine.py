"""The machine's limit for AVSM insertion (``machine.json``): vector operations per
insertion counted in the kernel's LLVM IR, and the rate this CPU can execute them at: the larger
of the nominal rate and the best rate of a register-only loop of the kernel's own operation mix
(:mod:`.op_mix`: the mix once per iteration, dealt out to 8-32 short independent chains); beside
them a generic microbenchmark (compare, multiply, subtract, select); the same for every registered
kind (``kinds``).

The nominal rate is per packet-wide operation at the width the CPU executes
(:func:`.simd.target`): AMD Zen 4 runs a 512-bit AVX-512 operation as two 256-bit halves on
four 256-bit pipes, so 2 packet operations per cycle at 16 lanes and 4 at 8 lanes (32 float
lanes per cycle either way); elsewhere 2 per cycle at the register width.  AVSM-8's mix reaches
80 % of it on the AVX2 Zen 4 of 4 Dec 2026 (docs/performance.md)."""
from __future__ import annotations

import os
import re
import time
from collections import Counter

import drjit as dr
import numpy as np

from avsm_dr import backend, build
from avsm_dr.evaluation.timing import jit_kernels, sync
from .op_mix import mix_rate
from .settings import counts_map
from .simd import target

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
        width = _count(s, ops, width)
    return ops, width


def _count(s: str, ops: Counter, width: int) -> int:
    """Count the vector operation on IR line ``s`` (if any) into ``ops``; returns the
    widest vector width seen so far."""
    m = re.match(r"(?:%\S+ = )?(\w+)", s)
    if not m or "<" not in s or m.group(1) in _SKIP_OPS or s.endswith(":") or s.startswith(("declare", "define")):
        return width
    op = m.group(1)
    if op == "call":
        c = re.search(r"@llvm\.([a-z.]+?)\.v\d", s)
        op = c.group(1) if c else "call"
    ops[op] += 1
    w = re.search(r"<(\d+) x", s)
    return max(width, int(w.group(1))) if w else width


def kernel_ops(ir: str) -> tuple[Counter, int, str]:
    """Vector operations of one lane packet's pass through a kernel: its symbolic loop with
    the most operations (the per-segment loop of node / curve kinds: one pass per inserted
    segment), or the whole kernel when it has no loop (per-segment projections of the
    linear kinds: one lane per segment).  Returns (ops by opcode, vector width, loop label
    or '')."""
    labels = re.findall(r"; Symbolic loop: (\S+)", ir)
    best: tuple[Counter, int, str] = (Counter(), 0, "")
    for lab in labels:
        ops, width = loop_ops(ir, lab)
        if sum(ops.values()) > sum(best[0].values()):
            best = (ops, width, lab)
    if labels:
        return best
    ops, width = Counter(), 0
    for line in ir.splitlines():
        width = _count(line.strip(), ops, width)
    return ops, width, ""


#: Chain counts of the op-mix loop for the kinds other than AVSM (which tries :data:`.op_mix.CHAINS`).
KIND_CHAINS = (16, 32)


def _limits(mix: dict, n: int, width: int, peak: dict, nominal: float, cores: int) -> dict:
    """Limits per core-second of a kernel of ``n`` operations per ``width``-lane packet: the op mix's
    best (``mix_limit``), the microbenchmark's, the nominal; the limit is the larger of the mix's
    best and the nominal (and ``cores`` times it for the machine)."""
    mix_lim = mix["vector_ops_per_cpu_s"] * width / n
    lim = max(mix_lim, nominal) if np.isfinite(nominal) else mix_lim
    return dict(limit_per_core_s=lim, limit_machine_per_s=lim * cores, mix_limit_per_core_s=mix_lim,
                microbench_limit_per_core_s=peak["vector_ops_per_cpu_s"] * width / n,
                nominal_limit_per_core_s=nominal, mix_uncovered=mix["uncovered"])


def kind_limits(P, data_rows, peak: dict, cores: int, mhz: float, ops_per_cycle: float, mixes=None) -> dict:
    """Every benchmarked setting (the registry's kinds, :func:`.settings.settings`): vector
    operations per packet of insertions in its build's main kernel (:func:`kernel_ops` of
    the kernel with the most, on a 16^2 x 40 map), the insertion rate that operation count
    allows at the larger of the nominal rate (``mhz x ops_per_cycle``) and the best rate of its own
    operation mix (:func:`.op_mix.mix_rate`, :data:`KIND_CHAINS`: the limit; :func:`_limits`),
    and our measured insertions per CPU-second (``data.csv``, map with the most segments per
    texel) as a fraction of it.  ``mixes``: mix rates already measured, by histogram (reused)."""
    from .settings import SETTINGS, label, settings
    seg = counts_map(16, 40)
    out, mixes = {}, {} if mixes is None else mixes
    for kind, p in settings(SETTINGS):
        name = label(kind, p)
        try:
            dr.kernel_history()
            build(kind, seg, **p)
            kern = [k for k in jit_kernels(dr.kernel_history()) if "ir" in k]
        except Exception as exc:                            # noqa: BLE001 - say why, keep the table
            out[name] = {"note": f"{type(exc).__name__}: {exc}"}
            continue
        cands = [(kernel_ops(k["ir"].getvalue()), k.get("size", 0)) for k in kern]
        if not cands:
            out[name] = {"note": "no Dr.Jit build kernel (a host build, or no build work)"}
            continue
        looped = [c for c in cands if c[0][2]]
        if looped:          # one loop pass per inserted segment: the loop with the most ops
            (ops, width, loop), size = max(looped, key=lambda c: sum(c[0][0].values()))
            n = sum(ops.values())
        else:               # per-segment (or per segment x coefficient) kernels: all of them
            ops, width, loop, size = Counter(), max(c[0][1] for c in cands), "", sum(c[1] for c in cands)
            for (o, _, _), lanes in cands:
                for op, v in o.items():
                    ops[op] += v * lanes / max(seg.n_segments, 1)
            n = int(round(sum(ops.values())))
        row = dict(ops_per_insertion_packet=n, lanes=width, loop=loop, kernel_lanes=size,
                   ops_by_kind={k: round(v, 1) for k, v in ops.most_common(8)})
        if n and width:
            key = tuple(sorted(ops.items()))
            mix = mixes[key] = mixes.get(key) or mix_rate(ops, P["peak_iters"], KIND_CHAINS, repeats=3)
            row.update(_limits(mix, n, width, peak, mhz * 1e6 * ops_per_cycle * width / n, cores))
            lim = row["limit_per_core_s"]
            ours = [r for r in data_rows if r.get("impl") == "drjit" and r.get("setting") == name
                    and np.isfinite(r.get("insertions_per_cpu_s", float("nan")))]
            if ours:
                best = max(ours, key=lambda r: r["mean_count"])
                row.update(measured_map=best["map"], measured_per_cpu_s=best["insertions_per_cpu_s"],
                           fraction_of_limit=best["insertions_per_cpu_s"] / lim)
        out[name] = row
    return out


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
    for k in jit_kernels(dr.kernel_history()):
        if "ir" in k and "bench_peak" in k["ir"].getvalue():
            run_ir = k["ir"].getvalue()
    ops, width = loop_ops(run_ir, "bench_peak")
    n_ops = sum(ops.values())
    packets = lanes // width
    return dict(ops_per_iteration=n_ops, width=width, ops=dict(ops),
                vector_ops_per_cpu_s=packets * iters * n_ops / min(cpu),
                vector_ops_per_wall_s=packets * iters * n_ops / min(wall))


def machine_limit(P, data_rows) -> dict:
    """The best achievable AVSM insertion rate on this CPU and our fraction of it
    (LLVM backend only: the operation count is read from the kernel's LLVM IR)."""
    if backend.get_backend() != "llvm":
        return {"note": "machine limit is estimated for the LLVM (CPU) backend only"}
    flag = dr.flag(dr.JitFlag.KernelHistory)
    try:
        return _machine_limit(P, data_rows)
    finally:
        dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, flag)


def traced_ir(run, label: str) -> str:
    """The LLVM IR of the kernel with the symbolic loop ``label`` among those ``run()`` launches
    (Dr.Jit's kernel history, on for the call)."""
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        run()
        return next(k["ir"].getvalue() for k in jit_kernels(dr.kernel_history())
                    if "ir" in k and f"; Symbolic loop: {label}" in k["ir"].getvalue())


def avsm_kernel_ir(nodes: int, seg=None) -> str:
    """The LLVM IR of the AVSM build kernel (its ``avsm_compress`` loop) for ``nodes`` on ``seg``
    (default: 16^2 texels of 20-60 segments, :func:`.settings.counts_map`)."""
    return traced_ir(lambda: build("avsm", counts_map(16, 40) if seg is None else seg, nodes=nodes), "avsm_compress")


def _machine_limit(P, data_rows) -> dict:
    from . import mca                     # here: ``python -m experiments.bench.mca`` imports the package first
    cpu = _cpuinfo()
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    peak = _peak_vector_rate(P["peak_iters"])
    try:                            # ISA, lanes per packet, executed (datapath) bits, nominal ops/cycle
        simd = target()
    except (OSError, AttributeError) as exc:        # no libdrjit-core.so (macOS, Windows): as before
        simd = dict(target_note=f"LLVM target not read: {type(exc).__name__}: {exc}", nominal_ops_per_cycle=2.0)
    opc = simd["nominal_ops_per_cycle"]
    out = dict(cpu=cpu["model"], mhz=cpu["mhz"], cores=cores,
               avx512="avx512f" in cpu["flags"], avx2="avx2" in cpu["flags"], **simd,
               peak_microbench=peak, nominal_vector_ops_per_cycle=opc, avsm={})
    seg, mixes = counts_map(16, 40), {}
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    for nodes in (4, 8, 16):
        ir = avsm_kernel_ir(nodes, seg)
        comp, width = loop_ops(ir, "avsm_compress")
        ins, _ = loop_ops(ir, "avsm_insert")
        n_comp = sum(comp.values())
        nominal_core = cpu["mhz"] * 1e6 * opc * width / n_comp
        mix = mixes[tuple(sorted(comp.items()))] = mix_rate(comp, P["peak_iters"])
        row = dict(ops_per_insertion_packet=n_comp, insert_only_ops=sum(ins.values()), lanes=width,
                   ops_by_kind=dict(comp.most_common()), op_mix=mix, **_limits(mix, n_comp, width, peak, nominal_core,
                                                                               cores),
                   nominal_limit_machine_per_s=nominal_core * cores)
        row.update(mca.ceiling(ir, simd.get("llvm_cpu", ""), n_comp / opc))     # the pipeline model's ceiling
        lim_core = row["limit_per_core_s"]
        ours = [r for r in data_rows if r.get("impl") == "drjit" and r.get("setting") == f"avsm-nodes={nodes}"]
        if ours:
            best = max(ours, key=lambda r: r["mean_count"])          # the compress loop dominates
            row.update(measured_map=best["map"], measured_per_cpu_s=best["insertions_per_cpu_s"],
                       measured_per_s=best["insertions_per_s"],
                       fraction_of_limit=best["insertions_per_cpu_s"] / lim_core,
                       fraction_of_mix=best["insertions_per_cpu_s"] / row["mix_limit_per_core_s"],
                       fraction_of_nominal=best["insertions_per_cpu_s"] / nominal_core)
        out["avsm"][nodes] = row
    out["kinds"] = kind_limits(P, data_rows, peak, cores, cpu["mhz"], opc, mixes)
    out["gpu"] = "not measured: no GPU in this run (run with --backend cuda on a GPU machine)"
    return out

