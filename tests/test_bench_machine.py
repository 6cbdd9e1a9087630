"""The benchmark's machine table (``machine.csv`` and the machine columns of ``data.csv``):
every setting's vector operations per insertion and achieved fraction of the limit."""
import math
import os

import pytest

from experiments.bench import report, simd, throughput


def _machine():
    return {
        "isa": "avx2", "llvm_cpu": "znver3", "executed_bits": 256, "vector_width": 8,
        "avsm": {8: {"ops_per_insertion_packet": 600, "lanes": 8, "limit_per_core_s": 60e6}},
        "kinds": {
            "avsm-nodes=8": {"ops_per_insertion_packet": 600, "lanes": 8, "loop": "avsm_compress",
                             "limit_per_core_s": 60e6},
            "fom-harmonics=8": {"ops_per_insertion_packet": 90, "lanes": 8, "loop": "",
                                "limit_per_core_s": 400e6},
            "greedy": {"note": "no Dr.Jit build kernel (a host build, or no build work)"},
        },
    }


def _data():
    row = dict(impl="drjit", setting="avsm-nodes=8", map="32^2 x 10", mean_count=10,
               insertions_per_cpu_s=20e6, insertions_per_cpu_s_best=24e6)
    return [row, dict(row, map="32^2 x 1000", mean_count=1000, insertions_per_cpu_s=30e6,
                      insertions_per_cpu_s_best=45e6, build_s=0.2, build_kernel_s=0.15),
            dict(row, impl="numba", map="32^2 x 1000", mean_count=1000),
            dict(impl="drjit", setting="fom-harmonics=8", map="32^2 x 1000", mean_count=1000,
                 insertions_per_cpu_s=100e6),
            dict(impl="drjit", setting="greedy", map="32^2 x 10", mean_count=10, insertions_per_cpu_s=1e5)]


def test_annotate_adds_the_limit_and_fractions_to_our_rows():
    data = _data()
    report.annotate(data, _machine())
    assert data[0]["fraction_of_limit"] == pytest.approx(20 / 60)
    assert data[1]["fraction_of_limit"] == pytest.approx(30 / 60)
    assert data[1]["fraction_of_limit_best"] == pytest.approx(45 / 60)
    assert data[1]["ops_per_insertion_packet"] == 600 and data[1]["lanes"] == 8
    assert "fraction_of_limit" not in data[2]                  # the Numba peer's row
    assert data[3]["fraction_of_limit"] == pytest.approx(0.25) and "fraction_of_limit_best" not in data[3]
    assert "fraction_of_limit" not in data[4]                  # no Dr.Jit kernel: no limit


def test_machine_rows_one_per_setting_on_the_densest_map():
    data = _data()
    report.annotate(data, _machine())
    rows = {r["setting"]: r for r in report.machine_rows(data, _machine())}
    assert set(rows) == {"avsm-nodes=8", "fom-harmonics=8", "greedy"}
    assert all(set(r) == set(report.MACHINE_COLUMNS) for r in rows.values())
    avsm = rows["avsm-nodes=8"]
    assert avsm["measured_map"] == "32^2 x 1000" and avsm["ops_per_insertion"] == 75
    assert all((r["isa"], r["llvm_cpu"], r["executed_bits"]) == ("avx2", "znver3", 256) for r in rows.values())
    assert rows["greedy"]["lanes"] == ""                       # no kernel: no packet width
    assert avsm["kernel_share"] == pytest.approx(0.75) and rows["fom-harmonics=8"]["kernel_share"] == ""
    assert avsm["fraction_of_limit"] == pytest.approx(0.5) and avsm["fraction_of_limit_best"] == pytest.approx(0.75)
    assert rows["fom-harmonics=8"]["fraction_of_limit_best"] == ""
    assert rows["greedy"]["note"] and rows["greedy"]["fraction_of_limit"] == ""
    s = report.summary(data, [], _machine(), [], [], [], 1.0)
    assert s["machine_fraction_best_by_setting"] == {"avsm-nodes=8": pytest.approx(0.75)}
    assert s["machine_fraction_avsm8_best"] == pytest.approx(0.75)
    assert math.isnan(s["avsm8_insertions_per_s"])             # no '... x 100' map in this data


def test_cpu_logged_records_every_call():
    log = []
    fn = throughput._cpu_logged(lambda: 3, log)
    assert [fn(), fn()] == [3, 3] and len(log) == 2 and all(c >= 0 for c in log)


def test_executed_width_splits_zen4_avx512_into_halves():
    """Zen 4 executes a 16-lane (512-bit) packet as two 256-bit halves on its four pipes: 2
    packet operations per cycle at 16 lanes, 4 at 8 lanes, the same 32 lanes per cycle; other
    CPUs: the register width, 2 per cycle."""
    z16, z8 = simd.executed("znver4", "avx512f", 16), simd.executed("znver4", "avx512f", 8)
    assert (z16["executed_bits"], z16["register_bits"], z16["nominal_ops_per_cycle"]) == (256, 512, 2.0)
    assert z8["nominal_ops_per_cycle"] == 4.0
    assert 16 * z16["nominal_ops_per_cycle"] == 8 * z8["nominal_ops_per_cycle"]
    intel = simd.executed("sapphirerapids", "avx512f", 16)
    assert (intel["executed_bits"], intel["nominal_ops_per_cycle"]) == (512, 2.0)
    assert simd.executed("haswell", "avx2", 8)["executed_bits"] == 256


def test_target_reports_the_isa_and_set_vector_width_applies_to_later_kernels():
    """``simd.target`` names the ISA LLVM compiles for (one the CPU flags list) and the lanes
    per packet; ``set_vector_width`` changes the width of the kernels compiled afterwards
    (their IR's vectors), with the same results; bad widths are refused naming the argument."""
    import drjit as dr
    from avsm_dr import backend
    from avsm_dr.evaluation.timing import jit_kernels
    before = simd.target()
    flags = open("/proc/cpuinfo").read() if os.path.exists("/proc/cpuinfo") else ""
    assert before["isa"] in ("avx512f", "avx2", "avx", "neon", "sse")
    assert before["isa"] in flags.split() or before["isa"] in ("sse", "neon") or not flags
    assert before["register_bits"] == 32 * before["vector_width"]
    Float = backend.types().Float
    irs = {}
    try:
        for width in (4, before["vector_width"]):
            simd.set_vector_width(width)
            assert simd.target()["vector_width"] == width
            with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
                dr.kernel_history()
                x = dr.arange(Float, 37) * 3 + 1
                dr.eval(x)
                irs[width] = "".join(k["ir"].getvalue() for k in jit_kernels(dr.kernel_history()) if "ir" in k)
            assert x.numpy()[-1] == 109
    finally:
        simd.set_vector_width(before["vector_width"])
    assert "<4 x float>" in irs[4] and f"<{before['vector_width']} x float>" in irs[before["vector_width"]]
    for bad in (6, 0, 128, 8.0):
        with pytest.raises(ValueError, match="width"):
            simd.set_vector_width(bad)
