"""experiments.bench.mca: the compress loop's machine code for AVX2 / AVX-512 and its pipeline model."""
import avsm_dr  # noqa: F401  (first: picks Dr.Jit's libLLVM)
import pytest

from avsm_dr import backend
from experiments.bench import mca, simd

FEATURES = '"target-cpu"="znver4" "target-features"="+avx2,-avx512f,-avx512vl,+fma,-avx512bw"'

ROTATED = """\
\tjmp\t.LBB0_3
.LBB0_1:                                # the loop's second half
\tvaddps\t%ymm0, %ymm1, %ymm2
\t#APP
\t# MCA_END
\t#NO_APP
\tjne\t.LBB0_3
\tretq
.LBB0_3:
\t#APP
\t# MCA_BEGIN
\t#NO_APP
\tvmulps\t%ymm0, %ymm1, %ymm2           # comment
\tje\t.LBB0_5
\tvmovaps\t(%rsp), %ymm3                # 32-byte Reload
.LBB0_5:                                # %else
\t.p2align\t4
\tjmp\t.LBB0_1
"""


def test_retarget_switches_the_avx512_family_and_back():
    wide = mca.retarget(FEATURES, "avx512")
    assert '"target-features"="+evex512,+avx2,+avx512f,+avx512vl,+fma,+avx512bw"' in wide
    back = mca.retarget(wide, "avx2")
    assert '"target-features"="-evex512,+avx2,-avx512f,-avx512vl,+fma,-avx512bw"' in back
    assert "+avx512" not in back and "+avx2" in back and "+fma" in back
    assert mca.retarget(FEATURES, "avx2") == FEATURES
    with pytest.raises(ValueError, match="isa"):
        mca.retarget(FEATURES, "sse")


def test_loop_body_follows_a_rotated_loop_from_marker_to_marker():
    assert mca.loop_body(ROTATED) == ["vmulps\t%ymm0, %ymm1, %ymm2", "vmovaps\t(%rsp), %ymm3",
                                      "vaddps\t%ymm0, %ymm1, %ymm2"]
    endless = ROTATED.replace("\t# MCA_END\n", "")
    with pytest.raises(ValueError, match="MCA_END"):
        mca.loop_body(endless)


@pytest.mark.skipif(backend.get_backend() != "llvm", reason="LLVM IR of the CPU backend")
def test_the_avsm_loop_compiles_to_blends_on_avx2_and_masked_moves_on_avx512():
    """The real AVSM-4 compress loop: AVX2 code selects with ``vblendvps`` and spills (16 registers);
    the same IR retargeted to AVX-512 selects with mask registers and spills less (32); the
    width Dr.Jit had is restored."""
    pytest.importorskip("llvmlite.binding")
    width = simd.target()["vector_width"]
    ir = mca.kernel_ir(4, 8)
    assert simd.target()["vector_width"] == width and "<8 x float>" in ir
    with pytest.raises(ValueError, match="label"):
        mca.mark_loop(ir, "no_such_loop")
    bodies = {isa: mca.loop_body(mca.compile_ir(mca.mark_loop(mca.retarget(ir, isa), "avsm_compress")))
              for isa in ("avx2", "avx512")}
    narrow, wide = bodies["avx2"], bodies["avx512"]
    assert sum(x.startswith("vblendvps") for x in narrow) > 50 and not any("{%k" in x for x in narrow)
    assert sum("{%k" in x for x in wide) > 20 and not any(x.startswith("vblendvps") for x in wide)
    spills = {isa: sum("(%rsp)" in x for x in b) for isa, b in bodies.items()}
    assert spills["avx512"] < spills["avx2"], spills


def test_the_model_reads_llvm_mca_cycles_and_pipes():
    """Four independent 256-bit additions: Zen 4 adds on two pipes (FP2, FP3), 2 cycles per pass."""
    path = mca.llvm_mca()
    if path is None:
        pytest.skip("no llvm-mca with a znver4 model (LLVM >= 17)")
    body = [f"vaddps\t%ymm0, %ymm1, %ymm{k}" for k in range(2, 6)]
    m = mca.model(body, path)
    assert m["bound"] == pytest.approx(2.0) and m["cycles"] == pytest.approx(2.0, abs=0.1)
    top = list(m["pipes"])[:2]
    assert sorted(top) == ["Zn4FP2", "Zn4FP3"] and m["pipes"]["Zn4FP2"] == pytest.approx(2.0)


def test_the_ceiling_is_a_note_where_the_model_cannot_run():
    """The bench goes on without the model: no CPU name, a CPU no llvm-mca knows, IR that does not parse."""
    pytest.importorskip("llvmlite.binding")
    assert mca.ceiling("", "", 100.0) == {"model_note": "no llvm-mca with a (unknown CPU) model"}
    assert mca.ceiling("", "no_such_cpu", 100.0) == {"model_note": "no llvm-mca with a no_such_cpu model"}
    if mca.llvm_mca() is not None:
        assert mca.ceiling("not IR", "znver4", 100.0)["model_note"].startswith("pipeline model failed: ValueError")
