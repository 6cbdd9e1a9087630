"""Dr.Jit's JitFlag.FastMath on CUDA: does turning it off make float64 rcp and derivatives exact, must it
be off when the forward pass is traced or when the backward pass runs, and what does it cost float32
kernels (the paper table's kernel times at grid 48, two rounds each way)?

    python scripts/cuda_fast_math.py OUT.json [cuda|llvm]     # from the repository root

Measured on an H200 (docs/data/gpu_h200/fastmath.json): off, float64 is IEEE-exact; the flag's state
when the forward pass is traced decides (Dr.Jit records the derivatives then); float32 builds took
1.3-1.6x the kernel time with it off for AVSM and OSM (FOM 0.85-1.34x, DSM 1.01-1.06x), lookups 0.87-1.16x."""

import sys
import json
import numpy as np
import drjit as dr

sys.path.insert(0, "tests")
sys.path.insert(0, ".")
import avsm_dr as ad
from avsm_dr import backend
from cases import random_segments

xp = np.linspace(0.001, 5.0, 2001)
x = np.linspace(-0.999, 0.999, 2001)
F = {
    "rcp": (lambda v: 1 / v, xp, lambda v: -1 / v**2),
    "sqrt": (np.sqrt, xp, lambda v: 0.5 / np.sqrt(v)),
    "acos": (np.arccos, x, lambda v: -1 / np.sqrt(1 - v * v)),
    "tanh": (np.tanh, x * 3, lambda v: 1 - np.tanh(v) ** 2),
    "rsqrt": (lambda v: 1 / np.sqrt(v), xp, lambda v: -0.5 * v**-1.5),
    "log": (np.log, xp, lambda v: 1 / v),
}


def elem(F64):
    r = {}
    for fn, (ref, v, dref) in F.items():
        t = F64(v)
        dr.enable_grad(t)
        y = getattr(dr, fn)(t)
        dr.backward(dr.sum(y))
        r[fn] = (
            float(np.log10(max(np.max(np.abs(y.numpy() - ref(v)) / np.abs(ref(v))), 1e-30))),
            float(np.log10(max(np.max(np.abs(dr.grad(t).numpy() - dref(v)) / np.abs(dref(v))), 1e-30))),
        )
    return r


def fd_err(F64, params, fwd_flag=None, bwd_flag=None):
    rng = np.random.default_rng(12345)
    data = random_segments(rng, texels=12, max_count=10, opaque_fraction=0.0, zero_fraction=0.0)
    tex = np.repeat(np.arange(12), 6)
    depth = rng.uniform(0, 1, tex.size)
    w = rng.normal(size=tex.size)

    def loss(tau, grad=False):
        t = F64(tau)
        if grad:
            dr.enable_grad(t)
        seg = ad.Segments.from_arrays(data["offsets"], data["z0"], data["z1"], optical_depth=t)
        return t, dr.sum(ad.build("moments", seg, **params).eval(tex, depth) * F64(w))

    if fwd_flag is not None:
        dr.set_flag(dr.JitFlag.FastMath, fwd_flag)
    t, L = loss(data["tau"], True)
    if bwd_flag is not None:
        dr.set_flag(dr.JitFlag.FastMath, bwd_flag)
    dr.backward(L)
    g = dr.grad(t).numpy()
    eps = 1e-5
    fd = []
    for j in range(data["tau"].size):
        tp, tm = data["tau"].copy(), data["tau"].copy()
        tp[j] += eps
        tm[j] -= eps
        fd.append((loss(tp)[1][0] - loss(tm)[1][0]) / (2 * eps))
    return float(np.max(np.abs(np.array(fd) - g)))


with backend.use_backend(sys.argv[2] if len(sys.argv) > 2 else "cuda"):
    F64 = backend.types().Float64
    out = {}
    for flag in (True, False):
        dr.set_flag(dr.JitFlag.FastMath, flag)
        out[f"fastmath={flag}"] = dict(
            elem=elem(F64), m8=fd_err(F64, {"moments": 8}), trig3=fd_err(F64, {"family": "trigonometric", "moments": 3})
        )
        print(flag, out[f"fastmath={flag}"], flush=True)
    out["fwd_off_bwd_on"] = dict(
        m8=fd_err(F64, {"moments": 8}, False, True),
        trig3=fd_err(F64, {"family": "trigonometric", "moments": 3}, False, True),
    )
    out["fwd_on_bwd_off"] = dict(
        m8=fd_err(F64, {"moments": 8}, True, False),
        trig3=fd_err(F64, {"family": "trigonometric", "moments": 3}, True, False),
    )
    print(out["fwd_off_bwd_on"], out["fwd_on_bwd_off"], flush=True)
    from experiments.bench.paper_table import table_rows

    for rnd in range(2):
        for flag in (True, False):
            dr.set_flag(dr.JitFlag.FastMath, flag)
            rows = table_rows(48, repeats=5)
            out[f"timing{rnd}_fastmath={flag}"] = {
                r["setting"]: (r["compress_kernel_ms"], r["lookup_kernel_ms"], r["capture_kernel_ms"]) for r in rows
            }
            print(flag, out[f"timing{rnd}_fastmath={flag}"], flush=True)
    dr.set_flag(dr.JitFlag.FastMath, True)
json.dump(out, open(sys.argv[1], "w"))
