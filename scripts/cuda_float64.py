"""Float64 accuracy on the Dr.Jit backends, and what Dr.Jit's fast math does to it on CUDA.

    python scripts/cuda_float64.py OUT.json              # accuracy on every available backend
    python scripts/cuda_float64.py OUT.json --fast-math  # on CUDA: the flag on / off, forward / backward, cost

Run from the repository root (it reads tests/cases.py).  Accuracy: the elementary functions and
their AD derivatives against NumPy (log10 of the largest relative error), and the moments
gradient against central differences at four steps, as tests/test_representations.py checks it
(seed 12345).  ``--fast-math``: the same with ``JitFlag.FastMath`` on and off; the flag off only
while the forward pass is traced and only while the backward pass runs; the float32 kernel times
of the AVSM paper's table (grid 48) both ways, two rounds.

Measured on an H200 (docs/data/gpu_h200/): with fast math on (Dr.Jit's default) float64 rcp,
rsqrt, tanh, tan, sinh and cosh and the derivatives of sqrt, log, acos, atan, cbrt, ... came out
at ~1e-6 relative, and the moments gradient 1.8e-5 (8 power moments) and 7.3e-4 (3 trigonometric)
off the finite differences at every step (float64_before.json).  Off, float64 is IEEE-exact; the
flag's state when the forward pass is traced decides (Dr.Jit records derivatives then); float32
AVSM and OSM builds took 1.3-1.6x the kernel time with it off (FOM 0.85-1.34x, DSM 1.01-1.06x),
lookups 0.87-1.16x (fastmath.json).  The package traces float64 on CUDA with it off
(avsm_dr.backend.exact_float64): float64_after.json.  Dr.Jit's own functions keep the flag.
"""
import json
import sys

import drjit as dr
import numpy as np

sys.path[:0] = ["tests", "."]
import avsm_dr as ad  # noqa: E402
from avsm_dr import backend  # noqa: E402
from cases import random_segments  # noqa: E402

X, XP = np.linspace(-0.999, 0.999, 2001), np.linspace(0.001, 5.0, 2001)
#: name -> (NumPy reference, arguments, reference derivative)
FUNCTIONS = {
    "sin": (np.sin, X * 3, np.cos), "cos": (np.cos, X * 3, lambda v: -np.sin(v)),
    "acos": (np.arccos, X, lambda v: -1 / np.sqrt(1 - v * v)), "atan": (np.arctan, X * 4, lambda v: 1 / (1 + v * v)),
    "cbrt": (np.cbrt, XP, lambda v: 1 / (3 * np.cbrt(v) ** 2)), "sqrt": (np.sqrt, XP, lambda v: 0.5 / np.sqrt(v)),
    "tanh": (np.tanh, X * 3, lambda v: 1 - np.tanh(v) ** 2), "tan": (np.tan, X, lambda v: 1 / np.cos(v) ** 2),
    "sinh": (np.sinh, X * 3, np.cosh), "cosh": (np.cosh, X * 3, np.sinh),
    "asinh": (np.arcsinh, X * 3, lambda v: 1 / np.sqrt(v * v + 1)),
    "acosh": (np.arccosh, 1 + XP, lambda v: 1 / np.sqrt(v * v - 1)), "log": (np.log, XP, lambda v: 1 / v),
    "exp": (np.exp, X * 5, np.exp), "rcp": (lambda v: 1 / v, XP, lambda v: -1 / v**2),
    "rsqrt": (lambda v: 1 / np.sqrt(v), XP, lambda v: -0.5 * v**-1.5),
}
MOMENTS = ({"moments": 8}, {"family": "trigonometric", "moments": 3})


def _log_rel(a, ref) -> float:
    return float(np.log10(max(np.max(np.abs(a - ref) / np.maximum(np.abs(ref), 1e-300)), 1e-30)))


def elementary(F64) -> dict:
    """name -> (log10 relative error of the value, of the derivative)."""
    out = {}
    for fn, (ref, v, dref) in FUNCTIONS.items():
        t = F64(v)
        dr.enable_grad(t)
        y = getattr(dr, fn)(t)
        dr.backward(dr.sum(y))
        out[fn] = (_log_rel(y.numpy(), ref(v)), _log_rel(dr.grad(t).numpy(), dref(v)))
    out["div"] = (_log_rel((F64(X) / F64(XP)).numpy(), X / XP), None)
    return out


def moments_fd(F64, params, steps=(1e-4, 1e-5, 1e-6, 1e-7), forward_flag=None, backward_flag=None) -> dict:
    """Largest |reverse-mode gradient - central difference| per step; ``*_flag``: FastMath while the
    forward pass is traced / while the backward pass runs (None: as it is)."""
    rng = np.random.default_rng(12345)
    data = random_segments(rng, texels=12, max_count=10, opaque_fraction=0.0, zero_fraction=0.0)
    tex = np.repeat(np.arange(12), 6)
    depth, w = rng.uniform(0, 1, tex.size), rng.normal(size=tex.size)

    def loss(tau, grad=False):
        t = F64(tau)
        if grad:
            dr.enable_grad(t)
        seg = ad.Segments.from_arrays(data["offsets"], data["z0"], data["z1"], optical_depth=t)
        return t, dr.sum(ad.build("moments", seg, **params).eval(tex, depth) * F64(w))

    now = dr.flag(dr.JitFlag.FastMath)
    with dr.scoped_set_flag(dr.JitFlag.FastMath, now if forward_flag is None else forward_flag):
        t, L = loss(data["tau"], True)
    with dr.scoped_set_flag(dr.JitFlag.FastMath, now if backward_flag is None else backward_flag):
        dr.backward(L)
    g = dr.grad(t).numpy()
    out = {}
    for eps in steps:
        fd = [(loss(data["tau"] + eps * e)[1][0] - loss(data["tau"] - eps * e)[1][0]) / (2 * eps)
              for e in np.eye(data["tau"].size)]
        out[str(eps)] = float(np.max(np.abs(np.array(fd) - g)))
    return out


def accuracy() -> dict:
    res = {}
    for name in ad.available_backends():
        with backend.use_backend(name):
            F64 = backend.types().Float64
            res[name] = dict(elementary=elementary(F64), **{"moments:" + json.dumps(p): moments_fd(F64, p)
                                                              for p in MOMENTS})
    return res


def fast_math() -> dict:
    from experiments.bench.paper_table import table_rows
    out = {}
    with backend.use_backend("cuda"):
        F64 = backend.types().Float64
        for flag in (True, False):
            with dr.scoped_set_flag(dr.JitFlag.FastMath, flag):
                out[f"fastmath={flag}"] = dict(elementary=elementary(F64),
                                               **{json.dumps(p): moments_fd(F64, p, (1e-5,)) for p in MOMENTS})
        for fwd, bwd in ((False, True), (True, False)):
            out[f"forward={fwd},backward={bwd}"] = {json.dumps(p): moments_fd(F64, p, (1e-5,), fwd, bwd)
                                                    for p in MOMENTS}
        for rnd in range(2):
            for flag in (True, False):
                with dr.scoped_set_flag(dr.JitFlag.FastMath, flag):
                    out[f"timing{rnd}_fastmath={flag}"] = {
                        r["setting"]: (r["compress_kernel_ms"], r["lookup_kernel_ms"], r["capture_kernel_ms"])
                        for r in table_rows(48, repeats=5)}
    return out


if __name__ == "__main__":
    result = fast_math() if "--fast-math" in sys.argv[2:] else accuracy()
    with open(sys.argv[1], "w") as fh:
        json.dump(result, fh, indent=1)
    print(json.dumps(result, indent=1)[:4000])
