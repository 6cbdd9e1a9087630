"""The op-count limit measured on the kernel's own operation mix (experiments/bench/op_mix.py)."""
import re

import drjit as dr
import numpy as np
import pytest

from avsm_dr import backend
from experiments.bench import op_mix, simd

#: AVSM-8's compress loop on an AVX2 machine (machine.json of `bench --quick`, 4 Dec 2026).
AVSM8 = {"select": 269, "fsub": 91, "fmul": 60, "icmp": 56, "fcmp": 53, "add": 20, "fabs": 15, "fadd": 11,
         "minimum": 10, "fma": 9, "and": 4, "masked.gather": 3, "fdiv": 3, "floor": 2, "vector.reduce.or": 1,
         "or": 1, "xor": 1, "fneg": 1, "fptosi": 1, "shl": 1}


@pytest.mark.parametrize("chains", [4, 8, 32])
def test_the_loop_executes_the_kernels_proportions(chains):
    """The loop's own IR (counted as the kernel's is, loop-state selects included) has the
    histogram's shares of its main opcodes to within the rounding of ~300 operations per
    iteration and the loop's control, at every chain count the bench tries."""
    base = simd.target()["vector_width"]
    r = op_mix.mix_rate(AVSM8, iters=20, chains_tried=(chains,), lanes=256, repeats=1)
    assert set(r["rate_by"]) == {f"{base} lanes, {chains} chains"}
    assert r["chains"] == chains and r["width"] == base and r["vector_ops_per_cpu_s"] > 0
    got, n_got = r["ops"], r["ops_per_iteration"]
    n_want = sum(AVSM8.values())
    for op in ("select", "fsub", "fmul", "icmp", "fcmp", "add", "fabs"):
        assert got[op] / n_got == pytest.approx(AVSM8[op] / n_want, abs=0.012), op
    assert "masked.gather" not in got and r["uncovered"] == pytest.approx(9 / n_want)     # gather, ...; or, xor: rare
    assert r["vector_ops_per_cpu_s"] == max(r["rate_by"].values())


#: A float-heavy mix (Legendre-8's basis projection, top opcodes).
FLOATS = {"fmul": 211, "fsub": 65, "fadd": 33, "select": 23, "fdiv": 12, "fcmp": 5, "maximum": 4, "minimum": 4}


@pytest.mark.parametrize("ops", [AVSM8, FLOATS], ids=["avsm8", "floats"])
@pytest.mark.parametrize("chains", [3, 32])
def test_the_loop_stays_finite_and_normal(ops, chains):
    """Near [1, 4] after 8000 iterations, the full bench's count (no zero, NaN, infinity or
    subnormal: no slow paths in the rate)."""
    t = backend.types()
    F, U = dr.detached_t(t.Float), dr.detached_t(t.UInt32)
    x = np.concatenate([v.numpy() for v in op_mix._loop(F, U, op_mix.plan_steps(ops), chains, 8000, 16)])
    assert np.all(np.isfinite(x)) and x.min() >= 0.9 and x.max() <= 4.0


def test_plan_steps_rejects_an_empty_histogram_and_puts_a_compare_first():
    with pytest.raises(ValueError, match="ops"):
        op_mix.plan_steps({})
    arith, masks, selects, uncovered = op_mix.plan_steps({"and": 10, "fmul": 20, "select": 15, "fptosi": 5})
    assert masks[0] in ("fcmp", "icmp") and "and" in masks and selects == 15 * 300 // 45
    assert set(arith) == {"fmul"} and uncovered == pytest.approx(5 / 50)


def test_the_loops_selects_stay_blends_in_machine_code():
    """The loop's IR compiled for this CPU (llvmlite, which Numba brings; AVX2 only) keeps a blend
    instruction for >= 80 % of its IR selects, as the AVSM-8 kernel does (238 of 269): a select
    between ``x - c`` and ``x`` compiles to ``x - (mask & c)``, which kept the first version at 84
    of 133 (63 %) and left the pipes the kernel's blends occupy idle."""
    pytest.importorskip("llvmlite.binding")
    if simd.target()["isa"] != "avx2":
        pytest.skip("AVX2's blend instruction (AVX-512 selects become masked moves)")
    from experiments.bench.machine import loop_ops, traced_ir
    from experiments.bench.mca import compile_ir
    t = backend.types()
    ir = traced_ir(lambda: dr.eval(op_mix._loop(dr.detached_t(t.Float), dr.detached_t(t.UInt32),
                                                op_mix.plan_steps(AVSM8), 16, 3, 64)), "op_mix")
    selects = loop_ops(ir, "op_mix")[0]["select"]
    blends = len(re.findall(r"\bvblendvps\b", compile_ir(ir)))     # as Dr.Jit: -O3, then codegen
    assert selects > 100 and blends >= 0.8 * selects, (blends, selects)
