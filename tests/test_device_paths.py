"""Device-side paths of the pipeline: filtered lookups reuse their
compiled kernels, ``Representation.eval`` validates Dr.Jit input without copying it to the
host, and ``Segments.sorted()`` orders each texel on the device exactly like a host lexsort."""
from __future__ import annotations

import ctypes

import numpy as np
import pytest

import avsm_dr as ad
from helpers import compiled_kernels
import drjit as dr


def _segments(rng, w=24, h=20, max_count=6):
    counts = rng.integers(0, max_count + 1, w * h)
    off = np.concatenate([[0], np.cumsum(counts)])
    n = int(off[-1])
    z0 = rng.uniform(0.0, 10.0, n)
    return ad.Segments.from_arrays(off, z0, z0 + rng.uniform(0.0, 1.0, n), optical_depth=rng.uniform(0, 2, n))


def _compiled(fn):
    """Number of JIT kernels ``fn`` compiled (kernel cache misses) while running."""
    return compiled_kernels(fn)


@pytest.mark.parametrize("filt", ["point", "bilinear", "box", "gaussian"])
def test_filtered_lookup_reuses_kernels(backend, rng, filt):
    """A second lookup with new data of the same shape compiles nothing.  Host inputs of a
    few KB land at random 16-byte offsets mod 64, and Dr.Jit hashes the alignment of a
    mapped NumPy input into the kernel: before the inputs were copied to aligned buffers,
    bilinear DSM lookups recompiled on ~every call (measured 0.25 s each at 64^2, seconds
    for larger kernels)."""
    seg = _segments(rng)
    rep = ad.build("dsm", seg)
    k = 700      # 2.8 KB per input: small heap blocks, whose alignment varies call to call

    def lookup():
        c = rng.uniform(-1.0, 25.0, (k, 2))
        return rep.eval(c, rng.uniform(0.0, 12.0, k), filter=filt, width=24, height=20, radius=1.5)

    dr.eval(lookup())     # the warm-up evaluated, as the count does (its last kernel too)
    assert [_compiled(lookup) for _ in range(4)] == [0, 0, 0, 0]


@pytest.mark.parametrize("kind", ["avsm", "fom", "moments", "dsm"])
def test_build_on_a_new_depth_range_reuses_kernels(backend, rng, kind):
    """A capture with another depth range must not recompile the build: AVSM's far depth
    was a literal in its loop state (``dr.full``), measured 0.42 s of compile per AVSM-8
    build (seconds at N = 24) for every new capture; it is opaque now."""
    def build(scale):
        seg = _segments(rng)
        h = seg.numpy()
        seg = ad.Segments.from_arrays(h["offsets"], h["z0"] * scale, h["z1"] * scale,
                                      optical_depth=h["optical_depth"])
        rep = ad.build(kind, seg)
        return rep.eval(np.arange(seg.n_texels), np.full(seg.n_texels, 5.0 * scale))

    build(1.0)
    assert [_compiled(lambda: build(s)) for s in (1.7, 3.1)] == [0, 0]


@pytest.mark.parametrize("grad", [False, True])
def test_avsm_traces_each_loop_once(rng, capfd, grad):
    """Without gradients AVSM's loops run with ``OptimizeLoops`` off: Dr.Jit would trace each body a
    second time to drop the state it leaves unchanged (measured 0.4 ms per build; LLVM drops that state
    itself).  With gradients the default stays (Dr.Jit 1.5 aborts an unoptimised loop there).  Read
    from Dr.Jit's debug log: "re-recording loop" is the second trace."""
    seg = _segments(rng, max_count=12)
    if grad:
        h = seg.numpy()
        tau = ad.backend.types().Float(h["optical_depth"])
        dr.enable_grad(tau)
        seg = ad.Segments.from_arrays(h["offsets"], h["z0"], h["z1"], optical_depth=tau)
    level = dr.log_level()
    capfd.readouterr()
    try:
        dr.set_log_level(dr.LogLevel.Debug)
        rep = ad.build("avsm", seg, nodes=4)
        dr.eval(rep.depths)
    finally:
        dr.set_log_level(level)
        ctypes.CDLL(None).fflush(None)                        # Dr.Jit logs through C stdio (stdout)
    log = "".join(capfd.readouterr())
    assert 'created a loop ("avsm_compress")' in log          # the log was read
    assert ('re-recording loop "avsm_' in log) == grad

# ---------------------------------------------------------------- eval validation
def test_eval_of_drjit_input_makes_no_host_copy(backend, rng, monkeypatch):
    """Point lookups of Dr.Jit texels / depths validate on the device: ``A.host`` (the copy
    to NumPy) is never called, and the result equals the NumPy-input lookup bit for bit,
    with broadcasting of a single texel or depth and every index / depth dtype."""
    from avsm_dr import _arrays
    t = ad.backend.types()
    seg = _segments(rng)
    rep = ad.build("avsm", seg, nodes=4)
    k = 300
    tex = rng.integers(0, seg.n_texels, k)
    dep = rng.uniform(-1.0, 12.0, k)
    want = np.asarray(rep.eval(tex, dep))
    want1 = np.asarray(rep.eval(tex[:1], dep))
    wantd = np.asarray(rep.eval(tex, dep[:1]))

    def boom(*a, **kw):
        raise AssertionError("host copy of a Dr.Jit lookup argument")

    monkeypatch.setattr(_arrays, "host", boom)
    for T in (t.UInt32, t.Int32, t.Float, t.Float64):
        assert np.array_equal(np.asarray(rep.eval(T(tex), t.Float(dep))), want)
    assert np.array_equal(np.asarray(rep.eval(t.UInt32(tex), t.Float64(dep))), want)
    assert np.array_equal(np.asarray(rep.eval(t.UInt32(tex[:1]), t.Float(dep))), want1)
    assert np.array_equal(np.asarray(rep.eval(t.UInt32(tex), t.Float(dep[:1]))), wantd)
    assert np.array_equal(np.asarray(rep.eval(tex, t.Float(dep))), want)


@pytest.mark.parametrize("texel, depth, message", [
    ("nan_tex", 1.0, "texel: contains 1 NaN or inf value(s)"),
    ("frac_tex", 1.0, "texel: indices must be integers in [0, 480)"),
    ("big_tex", 1.0, "texel: indices must be integers in [0, 480)"),
    ("neg_tex", 1.0, "texel: indices must be integers in [0, 480)"),
    (3, "nan_dep", "depth: contains 1 NaN or inf value(s)"),
    (3, "huge_dep", "depth: 1 value(s) overflow"),
    (3, "short_dep", "depth: length 2 does not match 5 texels"),
])
def test_eval_of_bad_drjit_input_keeps_the_host_messages(backend, rng, texel, depth, message):
    """What the device checks refuse goes through the host checks: same ValueError text."""
    t = ad.backend.types()
    rep = ad.build("avsm", _segments(rng), nodes=4)
    tex = {"nan_tex": t.Float([1, np.nan, 2, 3, 4]), "frac_tex": t.Float([1, 2.5, 2, 3, 4]),
           "big_tex": t.UInt32([1, 480, 2, 3, 4]), "neg_tex": t.Int32([1, -1, 2, 3, 4])}.get(texel, texel)
    if depth == "nan_dep":
        depth = t.Float([1, np.nan, 2, 3, 4])
    elif depth == "huge_dep":
        depth = t.Float64([1, 1e300, 2, 3, 4])
    elif depth == "short_dep":
        tex, depth = t.UInt32([1, 2, 3, 4, 5]), t.Float([1, 2])
    with pytest.raises(ValueError, match="^" + message.replace("(", r"\(").replace(")", r"\)")
                       .replace("[", r"\[")):
        rep.eval(tex, depth)


def test_eval_of_subnormal_drjit_depth_matches_numpy(backend, rng):
    """Subnormal float32 depths (flushed to 0 by the host path) give the NumPy-input result."""
    t = ad.backend.types()
    seg = ad.Segments.from_arrays([0, 1], [0.0], [0.0], optical_depth=[1.0])   # a step at 0
    rep = ad.build("avsm", seg, nodes=4)
    d = np.array([-1.4e-45, 1.4e-45, 0.0, -1.0], np.float32)
    assert np.array_equal(np.asarray(rep.eval(t.UInt32([0] * 4), t.Float(d))),
                          np.asarray(rep.eval(np.zeros(4, int), d)))


# ---------------------------------------------------------------- per-texel ordering
def _lexsorted(seg):
    h = seg.numpy()
    perm = np.lexsort((h["z1"], h["z0"], np.repeat(np.arange(seg.n_texels), seg.counts)))
    return {k: h[k][perm] for k in ("z0", "z1", "optical_depth")}


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_sorted_on_the_device_equals_a_host_lexsort(backend, rng, dtype, monkeypatch):
    """Ties in z0 and z1 (kept in stored order), -0.0 next to 0.0 (equal, as for NumPy),
    empty texels: the device sort gives the host lexsort's segments (float64: the rank sort
    and the key passes of long texels alike)."""
    from avsm_dr import segments as S
    counts = rng.integers(0, 12, 150)
    counts[:3] = 0
    off = np.concatenate([[0], np.cumsum(counts)])
    n = int(off[-1])
    z0 = rng.integers(0, 4, n) * 0.5
    z1 = z0 + rng.integers(0, 3, n) * 0.25
    seg = ad.Segments.from_arrays(off, z0, z1, optical_depth=rng.random(n), dtype=dtype)
    F = seg.Float
    seg.z0 = dr.select(seg.z0 == 0, F(-0.0), seg.z0)            # -0.0 on the device
    assert np.signbit(np.asarray(seg.z0)).any()
    want = _lexsorted(seg)
    got = seg.sorted()
    assert got.sorted_by_depth and np.array_equal(got.offsets, seg.offsets)
    for k, v in got.numpy().items():
        if k != "offsets":
            assert np.array_equal(v, want[k]), k
    assert np.array_equal(np.asarray(seg.texel_of_segment()), np.repeat(np.arange(150), counts))
    monkeypatch.setattr(S, "DEVICE_SORT_WORK", 0)                     # float64: key passes
    for k, v in seg.sorted().numpy().items():
        if k != "offsets":
            assert np.array_equal(v, want[k]), k


def test_sorted_input_is_recognised_without_a_permutation(backend, rng):
    seg = _segments(rng).sorted()
    fresh = ad.Segments(seg.offsets, seg.z0, seg.z1, seg.optical_depth, seg.dtype)
    assert fresh.depth_order() is None
    assert fresh.sorted().z0 is seg.z0


@pytest.mark.parametrize("layout", ["runs", "arrays", "sorted_single", "unsorted_single"])
def test_capture_assembly_on_the_device_matches_the_host_order(backend, rng, layout):
    """Merged pieces (texel arrays or TexelRuns) are ordered by (texel, z0 quantised to 32
    bits, piece order) exactly like the host's stable argsort of ``texel << 32 | zq``."""
    from avsm_dr.capture import assembly as asm
    from avsm_dr.segments import Segments
    T = 60
    Float = ad.backend.types().Float
    pieces = []
    for p in range(1 if layout.endswith("single") else 3):
        n = int(rng.integers(50, 400))
        tex = rng.integers(0, T, n)
        if layout != "unsorted_single":
            tex = np.sort(tex)
        z0 = rng.integers(0, 6, n) * 0.25 + (rng.random(n) * 1e-3 if p else 0.0)   # ties and near-ties
        if layout == "runs" and p == 0:
            lanes = np.unique(tex)
            tex = asm.TexelRuns(lanes, np.bincount(tex, minlength=T)[lanes])
        pieces.append((tex, z0, z0 + rng.random(n), rng.random(n)))
    tex_h = np.concatenate([np.asarray(p[0], np.int64) for p in pieces])
    z0_h = np.concatenate([np.asarray(p[1], np.float32) for p in pieces]).astype(np.float64)
    zq = ((z0_h - z0_h.min()) * ((2.0 ** 32 - 1) / np.ptp(z0_h))).astype(np.uint64)    # z0 in 32 bits
    perm = np.argsort((tex_h.astype(np.uint64) << np.uint64(32)) | zq, kind="stable")   # stable by texel, zq
    off = np.concatenate([[0], np.cumsum(np.bincount(tex_h, minlength=T))])
    seg = asm.combine(pieces, T, Float)
    assert isinstance(seg, Segments) and seg.sorted_by_depth
    assert np.array_equal(seg.offsets, off)
    assert np.array_equal(seg.numpy()["z0"], z0_h[perm])


def test_combine_of_new_piece_sizes_reuses_kernels(backend, rng):
    """Merging pieces of other sizes (a mixed scene at a new resolution) compiles nothing,
    texel sort included: the pieces' offsets in the concatenation are opaque, not literals
    in the kernel hash.  Both maps have their largest texel in one size class
    (9..16 segments): the sort traces one network per class up to the largest, so a new
    largest class is a new kernel by design (measured to compile in 0.25 s up to 8, 3.4 s up
    to 64)."""
    from avsm_dr.capture import assembly as asm
    Float = ad.backend.types().Float

    def pieces(sizes, T):
        out = []
        for i, n in enumerate(sizes):        # texel 0: 12 segments of the first piece and more
            tex = np.sort(np.r_[np.zeros(12 * (i == 0), np.int64), rng.integers(1, T, n - 12 * (i == 0))])
            z0 = rng.random(n)
            out.append((tex, z0, z0 + rng.random(n), rng.random(n)))
        return out

    def run(sizes, T):
        seg = asm.combine(pieces(sizes, T), T, Float)
        assert 8 < seg.counts.max() <= 16                 # the sizes of the networks: (2, 4, 8, 16)
        return seg.z0, seg.z1, seg.optical_depth

    dr.eval(run((50, 70), 40))
    assert [_compiled(lambda: run(n, T)) for n, T in (((90, 33), 30), ((64, 40), 30))] == [0, 0]
