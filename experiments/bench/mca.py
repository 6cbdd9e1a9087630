"""AVSM's compress loop in a CPU's pipeline model: how fast its machine code can run, for each
vector width and instruction set, without the machine that has them.

The build's kernel IR (traced here at 8 and 16 lanes, :func:`.simd.set_vector_width`) is
compiled for AMD Zen 4 (``znver4``) with Dr.Jit's own target features, once as traced (AVX2 on
this host) and once with the AVX-512 family enabled (32 vector registers, mask registers: selects
become masked moves), by LLVM at ``-O3`` as Dr.Jit does (``llvmlite``, which Numba brings).
The compress loop's body (between two markers put into its IR, without the loop condition's few
operations; conditional branches fall through: every lane of a gather loads) goes to ``llvm-mca -mcpu=znver4``
(LLVM >= 17 has Zen 4's model; Debian: ``apt-get install llvm-19``), which reports cycles per
pass, the pass's resource bound and the busiest pipes.  Against the bench's nominal limit
(:mod:`.machine`: ``ops / nominal_ops_per_cycle`` cycles per pass) that gives the fraction of the
limit the code as compiled can reach on an idle core with no host work: the ceiling of
``machine.csv``'s ``fraction_of_limit`` for that setting.

    python -m experiments.bench.mca [--nodes 4,8,16] [--widths 8,16] [--isas avx2,avx512] [--json FILE]

A model, not a measurement: on the AVX2 Zen 4 of 5 Dec 2026 it gave 281 cycles per AVSM-8 pass
where the kernel measured 318 (one thread, at the 2.84 GHz of a dependent-add chain)."""
from __future__ import annotations

import argparse
import glob
import json
import re
import shutil
import subprocess

#: The AVX-512 family a Zen 4 has (what :func:`retarget` switches on for ``isa="avx512"``).
ZEN4_AVX512 = ("avx512f", "avx512vl", "avx512bw", "avx512dq", "avx512cd", "avx512ifma", "avx512vbmi",
               "avx512vbmi2", "avx512vnni", "avx512bitalg", "avx512vpopcntdq", "avx512bf16")
#: Iterations llvm-mca simulates (the steady state; the first pass's start-up is amortised).
ITERATIONS = 100


def retarget(ir: str, isa: str) -> str:
    """The kernel IR with its target features for ``isa``: ``"avx2"`` (the AVX-512 family off,
    as on an AVX2 host) or ``"avx512"`` (Zen 4's family on, 512-bit registers allowed)."""
    if isa not in ("avx2", "avx512"):
        raise ValueError(f"isa: expected 'avx2' or 'avx512', got {isa!r}")
    on, off = ("+", "-") if isa == "avx512" else ("-", "+")
    for f in ZEN4_AVX512 + ("evex512",):
        ir = re.sub(rf'([",]){re.escape(off)}{f}(?=[,"])', rf"\g<1>{on}{f}", ir)
    if isa == "avx512" and "+evex512" not in ir:
        ir = ir.replace('"target-features"="', '"target-features"="+evex512,')
    return ir


def mark_loop(ir: str, label: str) -> str:
    """``ir`` with inline-asm markers ``MCA_BEGIN`` at the top of the symbolic loop ``label``'s body
    and ``MCA_END`` before its back edge (Dr.Jit names the blocks ``<prefix>_body`` and
    ``<prefix>_end``; the condition block follows the end)."""
    lines = ir.splitlines()
    i = next((k for k, s in enumerate(lines) if s.strip() == f"; Symbolic loop: {label}"), None)
    if i is None:
        raise ValueError(f"label: no symbolic loop {label!r} in the IR")
    pfx = lines[i - 1].strip().rstrip(":").rsplit("_", 1)[0]
    begin, end = f"{pfx}_body:\n", f"{pfx}_end:\n    br label %{pfx}_cond"
    if begin not in ir or end not in ir:
        raise ValueError(f"label: loop {label!r} has no {pfx}_body / {pfx}_end blocks")
    asm = '    call void asm sideeffect "# MCA_{}", ""()\n'
    return ir.replace(begin, begin + asm.format("BEGIN"), 1).replace(end, f"{pfx}_end:\n" + asm.format("END")
                                                                     + f"    br label %{pfx}_cond", 1)


def compile_ir(ir: str) -> str:
    """x86 assembly of ``ir`` for its own target-cpu and features, optimised at -O3 and code
    generated as Dr.Jit does (llvmlite's LLVM)."""
    import llvmlite.binding as llvm
    llvm.initialize_native_target()
    llvm.initialize_native_asmprinter()
    llvm.initialize_native_asmparser()           # the markers are inline asm
    cpu, feats = re.search(r'"target-cpu"="([^"]*)" "target-features"="([^"]*)"', ir).groups()
    tm = llvm.Target.from_triple("x86_64-unknown-linux-gnu").create_target_machine(cpu=cpu, features=feats, opt=3)
    mod = llvm.parse_assembly(ir)
    mod.verify()
    pb = llvm.create_pass_builder(tm, llvm.PipelineTuningOptions(speed_level=3))
    pb.getModulePassManager().run(mod, pb)
    return tm.emit_assembly(mod)


def loop_body(asm: str) -> list[str]:
    """The instructions from ``MCA_BEGIN`` to ``MCA_END`` in execution order: unconditional jumps
    followed (LLVM may rotate the loop), conditional ones fall through; labels, directives,
    comments and jumps dropped."""
    s = asm.splitlines()
    labels = {x.split(":")[0]: k for k, x in enumerate(s) if re.match(r"^\.?L\w+:", x)}
    k = next(j for j, x in enumerate(s) if "MCA_BEGIN" in x) + 1
    out, seen = [], set()
    while "MCA_END" not in s[k]:
        if k in seen:
            raise ValueError("asm: the walk from MCA_BEGIN loops without reaching MCA_END")
        seen.add(k)
        x = s[k].split("#")[0].strip()
        m = re.match(r"jmp\s+(\.?L\w+)$", x)
        if m:
            k = labels[m.group(1)]
            continue
        if x and not x.startswith(".") and not x.endswith(":") and not re.match(r"j[a-z]+\s", x):
            out.append(x)
        k += 1
    return out


def llvm_mca(mcpu: str = "znver4") -> str | None:
    """Path of an ``llvm-mca`` whose CPU list has ``mcpu`` (PATH first, then ``/usr/lib/llvm-*``,
    newest first), or None."""
    found = [shutil.which("llvm-mca")] + sorted(glob.glob("/usr/lib/llvm-*/bin/llvm-mca"),
                                                key=lambda p: int(re.search(r"llvm-(\d+)", p).group(1)), reverse=True)
    for path in filter(None, found):
        cpus = subprocess.run([path, "-mcpu=help"], capture_output=True, text=True)
        if re.search(rf"\b{mcpu}\b", cpus.stdout + cpus.stderr):
            return path
    return None


def model(body: list[str], mca: str, mcpu: str = "znver4") -> dict:
    """llvm-mca's steady state of ``body``: ``cycles`` per pass, ``bound`` (its resource bound,
    "Block RThroughput") and ``pipes`` (resource -> cycles of pressure per pass, busiest first)."""
    run = subprocess.run([mca, f"-mcpu={mcpu}", f"-iterations={ITERATIONS}"], input="\n".join(body) + "\n",
                         capture_output=True, text=True, check=True).stdout
    lines = run.splitlines()
    names = dict(re.findall(r"^\[([\d.]+)\]\s+-\s+(\S+)", run, re.M))
    k = next(j for j, x in enumerate(lines) if x.startswith("Resource pressure per iteration"))
    cols = re.findall(r"\[([\d.]+)\]", lines[k + 1])
    vals = [0.0 if v == "-" else float(v) for v in lines[k + 2].split()]
    pipes = dict(sorted(((names[c], v) for c, v in zip(cols, vals)), key=lambda kv: -kv[1]))
    return dict(cycles=int(re.search(r"Total Cycles:\s+(\d+)", run).group(1)) / ITERATIONS,
                bound=float(re.search(r"Block RThroughput:\s+([\d.]+)", run).group(1)), pipes=pipes)


def ceiling(ir: str, mcpu: str, nominal_cycles: float, label: str = "avsm_compress") -> dict:
    """The model's ceiling for the loop ``label`` of ``ir`` as traced (this machine's ISA and width):
    ``model_cycles_per_pass`` and ``model_fraction`` (``nominal_cycles`` over them: the most of the
    bench's limit the code can reach); ``model_note`` instead where llvmlite, an llvm-mca for
    ``mcpu`` or the compilation is missing (the bench goes on without)."""
    try:
        import llvmlite.binding  # noqa: F401
    except ImportError:
        return dict(model_note="llvmlite not installed (pip install numba)")
    try:
        path = llvm_mca(mcpu) if mcpu else None
        if path is None:
            return dict(model_note=f"no llvm-mca with a {mcpu or '(unknown CPU)'} model")
        m = model(loop_body(compile_ir(mark_loop(ir, label))), path, mcpu)
    except Exception as exc:                        # a model is context: never fail the bench
        return dict(model_note=f"pipeline model failed: {type(exc).__name__}: {exc}")
    return dict(model_cycles_per_pass=m["cycles"], model_fraction=nominal_cycles / m["cycles"])


def kernel_ir(nodes: int, width: int) -> str:
    """:func:`.machine.avsm_kernel_ir` traced at ``width`` lanes; Dr.Jit's width is restored afterwards."""
    from .machine import avsm_kernel_ir
    from .simd import set_vector_width, target
    before = target()["vector_width"]
    set_vector_width(width)
    try:
        return avsm_kernel_ir(nodes)
    finally:
        set_vector_width(before)


def rows(nodes=(4, 8, 16), widths=(8, 16), isas=("avx2", "avx512"), mcpu: str = "znver4") -> list[dict]:
    """One row per (nodes, width, isa): IR operations per pass, machine instructions, stack
    accesses (spills and reloads), selects (blends and write-masked instructions), llvm-mca's
    cycles and bound, the nominal cycles of the bench's limit at that width and ISA
    (:func:`.simd.executed`) and the model's fraction of it."""
    from .machine import loop_ops
    from .simd import executed
    mca = llvm_mca(mcpu)
    if mca is None:
        raise RuntimeError(f"no llvm-mca with a {mcpu} model (LLVM >= 17; Debian: apt-get install llvm-19)")
    out = []
    for n in nodes:
        for w in widths:
            ir = kernel_ir(n, w)
            ops = sum(loop_ops(ir, "avsm_compress")[0].values())
            for isa in isas:
                body = loop_body(compile_ir(mark_loop(retarget(ir, isa), "avsm_compress")))
                m = model(body, mca, mcpu)
                nominal = ops / executed(mcpu, "avx512f" if isa == "avx512" else "avx2", w)["nominal_ops_per_cycle"]
                out.append(dict(nodes=n, lanes=w, isa=isa, ir_ops=ops, instructions=len(body),
                                stack=sum("(%rsp)" in x or "(%rbp)" in x for x in body),
                                selects=sum(bool(re.match(r"v\w*blend", x)) or "{%k" in x for x in body),
                                cycles=m["cycles"], bound=m["bound"], cycles_per_8_lanes=m["cycles"] * 8 / w,
                                nominal_cycles=nominal, model_fraction=nominal / m["cycles"],
                                busiest=", ".join(f"{k} {v:.0f}" for k, v in list(m["pipes"].items())[:4])))
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nodes", default="4,8,16")
    ap.add_argument("--widths", default="8,16")
    ap.add_argument("--isas", default="avx2,avx512")
    ap.add_argument("--mcpu", default="znver4")
    ap.add_argument("--json", help="also write the rows to this file")
    a = ap.parse_args(argv)
    r = rows(tuple(int(x) for x in a.nodes.split(",")), tuple(int(x) for x in a.widths.split(",")),
             tuple(a.isas.split(",")), mcpu=a.mcpu)
    print(f"{'setting':22s} {'IR ops':>6s} {'instr':>6s} {'stack':>6s} {'select':>6s} {'cycles':>7s} {'bound':>6s} "
          f"{'/8 lanes':>8s} {'nominal':>7s} {'model':>6s}  busiest pipes (cycles per pass)")
    for x in r:
        print(f"AVSM-{x['nodes']} {x['lanes']:2d} lanes {x['isa']:6s} {x['ir_ops']:6d} {x['instructions']:6d} "
              f"{x['stack']:6d} {x['selects']:6d} {x['cycles']:7.0f} {x['bound']:6.0f} {x['cycles_per_8_lanes']:8.0f} "
              f"{x['nominal_cycles']:7.0f} {x['model_fraction']:6.1%}  {x['busiest']}")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(r, f, indent=1)


if __name__ == "__main__":
    main()
