"""The LLVM backend's SIMD target: which instruction set and vector width Dr.Jit compiles for,
how wide the CPU really executes those vectors, and a comparison of vector widths.

Dr.Jit 1.5 exports ``jit_llvm_set_target(cpu, features, width)`` from its core library but
binds no Python function for it; :func:`set_vector_width` calls it (through ``ctypes``) for
the kernels compiled afterwards (the width is process-global).

    python -m experiments.bench.simd [--widths 16,8,4] [--rounds 5] [--repeats 5]

compares widths in separate processes run alternately (``--child W`` is one of them):
median insertions (lookups) per CPU-second of AVSM-8 build, FOM-8 build and AVSM-8 lookup,
with the spread over rounds."""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time

#: LLVM CPU name -> (bits of the vector datapath, vector pipes): a wider register runs as
#: datapath-wide parts (AMD Zen 4: four 256-bit FP pipes, a 512-bit AVX-512 operation split
#: into two 256-bit halves).  Other CPUs: the register width and two pipes (2 operations per
#: cycle, the bench's nominal rate before the ISA was recorded).
DATAPATH = {"znver4": (256, 4)}
_REGISTER_BITS = {"avx512f": 512, "avx2": 256, "avx": 256, "neon": 128, "sse": 128}


def _core():
    """Dr.Jit's core library with its (C++-mangled) LLVM target functions typed."""
    from avsm_dr._llvm import core
    return core()


def target() -> dict:
    """The LLVM target: ``llvm_cpu`` (e.g. 'znver4'), ``isa`` (widest SIMD extension enabled:
    avx512f, avx2, avx, neon or sse), ``vector_width`` (float32 lanes per SIMD packet; Dr.Jit
    picks the register width: 16 with AVX-512, 8 with AVX2) and :func:`executed`'s figures."""
    lib = _core()
    feats = set((lib._Z24jit_llvm_target_featuresv() or b"").decode().split(","))
    isa = next((f for f in ("avx512f", "avx2", "avx", "neon") if "+" + f in feats), "sse")
    cpu = (lib._Z19jit_llvm_target_cpuv() or b"").decode()
    width = int(lib._Z21jit_llvm_vector_widthv())
    return dict(llvm_cpu=cpu, isa=isa, vector_width=width, **executed(cpu, isa, width))


def executed(cpu: str, isa: str, width: int) -> dict:
    """How a core executes packets of ``width`` float32 lanes: ``register_bits`` (32 x width),
    ``executed_bits`` and ``pipes`` (:data:`DATAPATH`), ``nominal_ops_per_cycle``: packet
    operations issued per cycle, ``pipes x min(1, executed_bits / register_bits)`` (Zen 4: 2 at
    16 lanes, 4 at 8 lanes; 32 float lanes per cycle either way)."""
    bits, pipes = DATAPATH.get(cpu, (_REGISTER_BITS.get(isa, 128), 2))
    return dict(register_bits=32 * width, executed_bits=bits, pipes=pipes,
                nominal_ops_per_cycle=pipes * min(1.0, bits / (32 * width)))


def set_vector_width(width: int) -> None:
    """Compile the LLVM kernels traced afterwards with ``width`` float32 lanes per packet (a
    power of two, 1 to 64), same CPU and features; kernels compiled before keep theirs."""
    if not isinstance(width, int) or width < 1 or width & (width - 1) or width > 64:
        raise ValueError(f"width: expected a power of two in [1, 64], got {width!r}")
    lib = _core()
    lib._Z19jit_llvm_set_targetPKcS0_j(lib._Z19jit_llvm_target_cpuv(), lib._Z24jit_llvm_target_featuresv(), width)


#: (side, mean segments per texel) of the maps of the comparison (bench --quick's densest, and ~100).
MAPS = ((32, 1000), (64, 100))


def _child(width: int, repeats: int) -> dict:
    """One process at ``width``: median per CPU-second rates, interleaved repeats after a warm-up."""
    set_vector_width(width)
    import numpy as np
    from avsm_dr import build
    from .._common import sync
    from .settings import counts_map, lookups
    out = dict(target(), width=width)
    for side, mean in MAPS:
        seg = counts_map(side, mean)
        tex, depth = lookups(seg.n_texels, 200_000)
        fns = {"avsm8_build": lambda: build("avsm", seg, nodes=8), "fom8_build": lambda: build("fom", seg, harmonics=8)}
        rep = {k: f() for k, f in fns.items()}                   # warm-up (JIT compile)
        fns["avsm8_lookup"] = lambda: rep["avsm8_build"].eval(tex, depth)
        sync(fns["avsm8_lookup"]())
        n = {"avsm8_build": seg.n_segments, "fom8_build": seg.n_segments, "avsm8_lookup": tex.size}
        rates = {k: [] for k in fns}
        for _ in range(repeats):
            for k, f in fns.items():
                c0 = time.process_time()
                sync(f())
                rates[k].append(n[k] / (time.process_time() - c0))
        out.update({f"{k}@{side}^2x{mean}": float(np.median(v)) for k, v in rates.items()})
    return out


def compare(widths=(16, 8, 4), rounds: int = 5, repeats: int = 5) -> list[dict]:
    """Rows per (width, rate): median over ``rounds`` processes run alternately (the width
    order reversed every other round, so drifting load hits each alike), min and max."""
    from tqdm import tqdm
    runs = []
    with tqdm(total=rounds * len(widths), desc="widths", unit="process") as bar:
        for r in range(rounds):
            for w in (widths if r % 2 == 0 else widths[::-1]):
                res = subprocess.run([sys.executable, "-m", "experiments.bench.simd", "--child", str(w),
                                      "--repeats", str(repeats)], capture_output=True, text=True, check=True)
                runs.append(json.loads(res.stdout.strip().splitlines()[-1]))
                bar.update()
    keys = [k for k in runs[0] if "@" in k]
    rows = []
    for k in keys:
        for w in widths:
            v = [r[k] for r in runs if r["width"] == w]
            rows.append(dict(rate=k, width=w, median=statistics.median(v), min=min(v), max=max(v), n=len(v)))
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--widths", default="16,8,4")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(_child(a.child, a.repeats)))
        return
    widths = tuple(int(w) for w in a.widths.split(","))
    rows = compare(widths, a.rounds, a.repeats)
    print(json.dumps({k: v for k, v in target().items()}))
    for r in rows:
        ref = next(x["median"] for x in rows if x["rate"] == r["rate"] and x["width"] == widths[0])
        print(f"{r['rate']:28s} width {r['width']:2d}: {r['median'] / 1e6:7.1f} M/CPU-s [{r['min'] / 1e6:.1f}-"
              f"{r['max'] / 1e6:.1f}, n={r['n']}]  {widths[0]}/{r['width']}: {ref / r['median']:.2f}")


if __name__ == "__main__":
    main()
