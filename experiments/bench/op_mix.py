"""A kernel's own operation mix, measured: a register-only Dr.Jit loop that executes the kernel's
mix of vector operations (its LLVM IR histogram, :func:`.machine.kernel_ops`: selects, float and
integer compares, mask logic, arithmetic in its proportions), once per iteration, dealt out to
8-32 short independent chains.

Does the nominal limit (pipes x clock, :mod:`.machine`) hold for a kernel's mix, or do its
operations crowd a few pipes?  On the AVX2 Zen 4 of 4 Dec 2026 AVSM-8's mix runs at 8.3 G
eight-lane operations per CPU-second, 80 % of the nominal 10.4 G: the nominal limit is near, and
it stays the limit (the larger of the two).  The chains must be short: Dr.Jit emits each chain
whole, so the CPU's window holds only the next few; when every chain ran the whole mix (~150
dependent operations each) the same loop reached 3.2-4.0 G at any chain count, and a loop of
additions alone 1.55 G.  What the loop leaves out is what else makes a kernel slower: long
dependence chains, register spills, gathers, lane divergence.

Each chain holds one float ``x`` per lane; a step computes ``t = op(x)`` (one arithmetic operation
of the mix), refreshes the mask from ``x`` (a float compare, an integer compare of its bits, or a
mask operation on the previous mask) at the mix's rate, and keeps ``x = select(mask, t, x_prev)``
(the value before ``x``; selects beyond the arithmetic cycle through the chain's masks).  Selects
must stay blends in the machine code, as the kernel's do (AVSM-8: 238 blends for 269 IR selects):
``select(mask, x - c, x)`` compiles to ``x - (mask & c)``, and a first version kept 84 blends of 133
selects (llvmlite + llvm-mca on its IR); this one keeps 115, at the same rate (8.3 G).
Values stay near [1, 4] (no zero, subnormal or special values: they start near 1.5; factors and
offsets are near 1 and 0; ``floor`` runs as ``ceil``, at least 1; ``minimum`` caps at 4).
Operations the loop does not reproduce (gathers, conversions, reductions; 1-2 % of AVSM's) and
those too rare to get one step in ~300 are reported as ``uncovered``.  :func:`mix_rate` keeps the
best rate over chain counts (more independent work, more registers)."""
from __future__ import annotations

import time
from collections import Counter

import drjit as dr

from avsm_dr import backend
from avsm_dr.evaluation.timing import sync

#: One-operation arithmetic steps ``t = f(x)`` by LLVM opcode (as :func:`.machine.loop_ops` names them).
_ARITH = {
    "fsub": lambda x, U: x - 1e-7, "fadd": lambda x, U: x + 1e-7, "fmul": lambda x, U: x * 1.0000001,
    "fdiv": lambda x, U: x / dr.opaque(type(x), 1.0000001),       # a literal divisor: a multiplication
    "fabs": lambda x, U: dr.abs(x), "floor": lambda x, U: dr.ceil(x),      # one rounding instruction; >= 1
    "minimum": lambda x, U: dr.minimum(x, 4.0), "maximum": lambda x, U: dr.maximum(x, 0.25),
    "fma": lambda x, U: dr.fma(x, 1.0000001, 1e-7),
    "add": lambda x, U: dr.reinterpret_array(type(x), dr.reinterpret_array(U, x) + 1),       # one ulp
}
#: Mask refreshes by opcode: compares of x, or logic on the previous mask.
_MASK = {"fcmp": lambda x, m, U: x < 1.6, "icmp": lambda x, m, U: dr.reinterpret_array(U, x) < 0x3FCCCCCD,
         "and": lambda x, m, U: m & (x > 1.2), "or": lambda x, m, U: m | (x > 3.0),
         "xor": lambda x, m, U: m ^ (x > 2.5)}
#: Chain counts tried; the limit is the best (more chains, more independent work and registers:
#: AVSM-8's mix peaks at 16-24 chains on AVX2, float mixes at 32).
CHAINS = (8, 16, 24, 32)


def plan_steps(ops: dict, size: int = 300) -> tuple[list, list, int, float]:
    """The step sequence of one iteration for the histogram ``ops`` (opcode -> count), scaled to
    about ``size`` operations: ``(arith, masks, selects, uncovered)`` with ``arith`` the arithmetic
    opcodes in round-robin order, ``masks`` the mask opcodes, ``selects`` the number of selects,
    ``uncovered`` the share of ``ops`` the loop does not reproduce."""
    total = sum(ops.values())
    if total <= 0:
        raise ValueError(f"ops: expected a non-empty histogram of operation counts, got {ops!r}")
    known = {k: v for k, v in ops.items() if k in _ARITH or k in _MASK or k == "select"}
    scale = size / max(sum(known.values()), 1)
    n = {k: round(v * scale) for k, v in known.items() if round(v * scale) > 0}     # rarer ones: dropped
    arith = _round_robin(Counter({k: v for k, v in n.items() if k in _ARITH})) or ["fsub"]
    masks = _round_robin(Counter({k: v for k, v in n.items() if k in _MASK}))
    first = next((i for i, k in enumerate(masks) if k in ("fcmp", "icmp")), None)   # the first: a compare
    masks = ["fcmp"] + masks if first is None else [masks[first]] + masks[:first] + masks[first + 1:]
    return arith, masks, n.get("select", 0), 1.0 - sum(known[k] for k in n) / total


def _round_robin(n: Counter) -> list:
    """The opcodes of ``n`` (opcode -> count) in turn, most frequent first in each round."""
    out = []
    while n:
        for k in sorted(n, key=lambda k: (-n[k], k)):
            out.append(k)
            n[k] -= 1
        n = +n
    return out


def _chain(v, arith, masks, selects: int, UInt32):
    """One chain's share of an iteration: ``arith`` steps ``t = op(v)``, ``masks`` refreshed
    between them (a compare first), ``v = select(mask, t, v_prev)`` on the first ``selects`` steps."""
    first = masks[0] if masks and masks[0] in ("fcmp", "icmp") else "fcmp"
    m, rest = _MASK[first](v, None, UInt32), masks[1:] if masks and masks[0] == first else masks
    every = max(1, len(arith) // max(len(rest), 1))
    prev, seen = None, [m]
    for i, op in enumerate(arith):                    # masks spread over the steps, selects from the second on
        t = _ARITH[op](v, UInt32)
        # between t and the value before v: select(m, v - c, v) would compile to v - (m & c), no blend
        prev, v = v, (dr.select(m, t, prev) if prev is not None and i <= selects else t)
        if i % every == 0 and i // every < len(rest):   # of the new value: not the first compare again (merged)
            m = _MASK[rest[i // every]](v, m, UInt32)
            seen.append(m)
    for k in range(selects - max(len(arith) - 1, 0)):  # beyond the arithmetic: older values, the masks in turn
        prev, v = v, dr.select(seen[k % len(seen)], v, prev if prev is not None else -v)
    return v


def _loop(Float, UInt32, steps, chains: int, iters: int, lanes: int):
    """The mix once per iteration, dealt out to ``chains`` independent chains (each a short
    sequence: Dr.Jit emits a chain whole, and the CPU's window must hold several at once).  Each
    chain's loop-state update is one of the mix's selects (Dr.Jit's masked loop), as in the kernel."""
    arith, masks, selects, _ = steps
    selects = max(selects - chains, 0)
    x = [dr.full(Float, 1.5 + 0.01 * k, lanes) + dr.arange(Float, lanes) * 1e-7 for k in range(chains)]
    dr.eval(x)

    def body(it, x):
        return it + 1, [_chain(x[c], arith[c::chains], masks[c::chains], selects // chains + (c < selects % chains),
                               UInt32) for c in range(chains)]
    return dr.while_loop((dr.zeros(UInt32, lanes), x), lambda it, x: it < iters, body, label="op_mix")[1]


def mix_rate(ops: dict, iters: int, chains_tried=CHAINS, lanes: int = 1 << 14, repeats: int = 5) -> dict:
    """The loop for histogram ``ops`` at the current vector width (the kernels'): its best rate over
    ``chains_tried`` in vector operations per CPU-second (the loop's IR operations, counted as
    :func:`.machine.loop_ops` counts the kernel's), with the best's histogram, chains and width,
    and the rate by chain count."""
    from .machine import loop_ops, traced_ir
    t = backend.types()
    Float, UInt32 = dr.detached_t(t.Float), dr.detached_t(t.UInt32)
    steps = plan_steps(ops)
    best, rates = None, {}
    for chains in chains_tried:
        sync(_loop(Float, UInt32, steps, chains, iters, lanes))                 # compile
        ir = traced_ir(lambda: sync(_loop(Float, UInt32, steps, chains, iters, lanes)), "op_mix")
        counted, width = loop_ops(ir, "op_mix")
        cpu = []
        for _ in range(repeats):
            c0 = time.process_time()
            sync(_loop(Float, UInt32, steps, chains, iters, lanes))
            cpu.append(time.process_time() - c0)
        n_ops = sum(counted.values())
        rate = rates[f"{width} lanes, {chains} chains"] = (lanes // width) * iters * n_ops / min(cpu)
        if best is None or rate > best["vector_ops_per_cpu_s"]:
            best = dict(vector_ops_per_cpu_s=rate, chains=chains, width=width, ops_per_iteration=n_ops,
                        ops=dict(counted.most_common()))
    return dict(best, uncovered=steps[3], rate_by=rates)
