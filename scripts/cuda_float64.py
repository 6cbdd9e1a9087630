"""Float64 accuracy on every available Dr.Jit backend: the elementary functions and their AD
derivatives against NumPy (log10 of the largest relative error), and the moments gradient against
central differences at four steps, as tests/test_representations.py checks it (seed 12345).

    python scripts/cuda_float64.py OUT.json      # run from the repository root (it reads tests/cases.py)

On an H200 with Dr.Jit's fast math on (its default) float64 rcp, rsqrt, tanh, tan, sinh and cosh
and the derivatives of sqrt, log, acos, atan, cbrt, ... came out at ~1e-6 relative, and the moments
gradient 1.8e-5 (8 power moments) and 7.3e-4 (3 trigonometric) off the finite differences at every
step (docs/data/gpu_h200/float64_before.json); the package now traces float64 on CUDA with it off
(avsm_dr.backend.exact_float64): float64_after.json.  The raw elementary functions are Dr.Jit's and
keep the flag."""

import sys
import json
import numpy as np
import drjit as dr

sys.path.insert(0, "tests")
import avsm_dr as ad
from avsm_dr import backend
from cases import random_segments

out = sys.argv[1]
res = {}
x = np.linspace(-0.999, 0.999, 2001)
xp = np.linspace(0.001, 5.0, 2001)
funcs = {
    "sin": (np.sin, x * 3, np.cos),
    "cos": (np.cos, x * 3, lambda v: -np.sin(v)),
    "acos": (np.arccos, x, lambda v: -1 / np.sqrt(1 - v * v)),
    "atan": (np.arctan, x * 4, lambda v: 1 / (1 + v * v)),
    "cbrt": (np.cbrt, xp, lambda v: 1 / (3 * np.cbrt(v) ** 2)),
    "sqrt": (np.sqrt, xp, lambda v: 0.5 / np.sqrt(v)),
    "tanh": (np.tanh, x * 3, lambda v: 1 - np.tanh(v) ** 2),
    "tan": (np.tan, x, lambda v: 1 / np.cos(v) ** 2),
    "sinh": (np.sinh, x * 3, np.cosh),
    "cosh": (np.cosh, x * 3, np.sinh),
    "asinh": (np.arcsinh, x * 3, lambda v: 1 / np.sqrt(v * v + 1)),
    "acosh": (np.arccosh, 1 + xp, lambda v: 1 / np.sqrt(v * v - 1)),
    "log": (np.log, xp, lambda v: 1 / v),
    "exp": (np.exp, x * 5, np.exp),
    "rcp": (lambda v: 1 / v, xp, lambda v: -1 / v**2),
    "rsqrt": (lambda v: 1 / np.sqrt(v), xp, lambda v: -0.5 * v**-1.5),
}
for name in ad.available_backends():
    with backend.use_backend(name):
        F64 = backend.types().Float64
        r = {}
        for fn, (ref, v, dref) in funcs.items():
            t = F64(v)
            dr.enable_grad(t)
            y = getattr(dr, fn)(t)
            dr.backward(dr.sum(y))
            yv, gv = y.numpy(), dr.grad(t).numpy()
            r[fn] = dict(
                rel=float(np.max(np.abs(yv - ref(v)) / np.maximum(np.abs(ref(v)), 1e-300))),
                grad_rel=float(np.max(np.abs(gv - dref(v)) / np.maximum(np.abs(dref(v)), 1e-300))),
            )
        t = F64(xp)
        r["div"] = dict(rel=float(np.max(np.abs((F64(x) / t).numpy() - x / xp) / np.maximum(np.abs(x / xp), 1e-300))))
        # the moments FD check, as tests/test_representations.py::_fd_check with seed 12345
        for params in ({"moments": 8}, {"family": "trigonometric", "moments": 3}):
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
                T = ad.build("moments", seg, **params).eval(tex, depth)
                return t, dr.sum(T * F64(w)), T

            t, L, T = loss(data["tau"], True)
            dr.backward(L)
            g = dr.grad(t).numpy()
            fds = {}
            for eps in (1e-4, 1e-5, 1e-6, 1e-7):
                fd = []
                for j in range(data["tau"].size):
                    tp, tm = data["tau"].copy(), data["tau"].copy()
                    tp[j] += eps
                    tm[j] -= eps
                    fd.append((loss(tp)[1][0] - loss(tm)[1][0]) / (2 * eps))
                fds[str(eps)] = float(np.max(np.abs(np.array(fd) - g)))
            r["moments:" + json.dumps(params)] = dict(T=T.numpy().tolist(), g=g.tolist(), fd_maxerr=fds)
        res[name] = r
json.dump(res, open(out, "w"))
for name, r in res.items():
    print(
        name,
        {
            k: (round(np.log10(max(v["rel"], 1e-30)), 1), round(np.log10(max(v.get("grad_rel", 1e-30), 1e-30)), 1))
            for k, v in r.items()
            if not k.startswith("moments")
        },
    )
    for k, v in r.items():
        if k.startswith("moments"):
            print(name, k, v["fd_maxerr"])
