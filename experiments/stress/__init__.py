"""Numerical stability of every representation on adversarial synthetic rays.

Cases: opacities up to exactly 1, optical depths up to 1e4, segment lengths down to 0,
1e5 segments on one ray, depth ranges from 1e-4 to 1e6 units, float32 against float64,
and shuffled insertion order (AVSM unsorted vs sorted); each row's ``order`` column records
the order its kind saw (:func:`_order`).  Every estimate is compared
with the float64 exact curve; the CSV counts NaN / inf outputs (must be 0) and bound
violations, and reports RMSE / max error.

``reliability.csv``: adversarial input that must be refused with a ValueError naming the
argument or answered correctly in bounded time (float32 overflow, huge counts, long
sums, the DSM bound on sub-ulp opaque segments; see :mod:`.checks`), one row per
check with its ``failures`` (must be 0).

Storage precision: every kind (headline parameters) at every ``precision`` it accepts
runs on the cases too (float32 segments; both dtypes in the full run; ``--quick``: the
cases of ``PRECISION_QUICK_CASES``), rows with ``precision`` set (``native`` otherwise);
the reliability row ``precision`` fails on any NaN / inf / out-of-range estimate.
"""

from __future__ import annotations

import time

import numpy as np
from tqdm import tqdm

from avsm_dr import build, kinds
from avsm_dr.metrics import error_stats
from avsm_dr.segments import OPAQUE_OPTICAL_DEPTH, Segments
from .._headline import num
from .._study import Study
from .checks import PRECISION_QUICK_CASES, precision_check, precision_configs, run_checks

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    "The guide's reliability table: NaN / inf counts, bound violations and error growth of "
    'every representation on adversarial rays (float32 and float64).'
)


METHODS = [("exact", {}), ("avsm", {"nodes": 8}), ("avsm", {"nodes": 8, "sort": True}),
           ("dsm", {"tolerance": 0.01}), ("osm", {"slices": 32}), ("fom", {"harmonics": 8})]


def _smoke(rng, texels, count, lo, hi, tau_scale=0.05, length_scale=0.02):
    offsets = np.arange(texels + 1) * count
    n = texels * count
    z0 = rng.uniform(lo, hi, n)
    z1 = np.minimum(z0 + rng.exponential(length_scale * (hi - lo), n), hi)
    tau = rng.exponential(tau_scale, n)
    return offsets, z0, z1, tau


def _order(kind: str, params: dict) -> str:
    """The insertion order a row's kind saw: the cases' segments are drawn in random depth
    order ('random'); ``sort=True`` sorts them front to back ('depth'); '-' for the kinds that
    do not depend on the order."""
    from ..error_curves.labels import order_dependent
    if kind not in kinds() or not order_dependent(kind):
        return "-"
    return "depth" if params.get("sort") else "random"


def cases(quick: bool, rng):
    """(name, offsets, z0, z1, tau) adversarial inputs."""
    out = []
    off, z0, z1, tau = _smoke(rng, 64, 40, 0.0, 1.0)
    t_opaque = tau.copy()
    t_opaque[rng.random(tau.size) < 0.05] = OPAQUE_OPTICAL_DEPTH   # opacity exactly 1
    out.append(("opacity_1", off, z0, z1, t_opaque))
    t_big = rng.uniform(0, 1e4, tau.size) * (rng.random(tau.size) < 0.1)
    out.append(("optical_depth_1e4", off, z0, z1, t_big))
    out.append(("zero_length", off, z0, z0.copy(), tau))
    z1_tiny = z0 + rng.uniform(0, 1e-7, z0.size)
    out.append(("length_1e-7", off, z0, z1_tiny, tau))
    n_long = 10_000 if quick else 100_000
    zl = rng.uniform(0, 1, n_long)
    out.append((f"{n_long}_segments_one_ray", np.array([0, n_long]), zl,
                np.minimum(zl + rng.exponential(1e-3, n_long), 1.0), rng.exponential(3.0 / n_long, n_long)))
    for scale in (1e-4, 1.0, 1e3, 1e6):
        out.append((f"depth_range_{scale:g}", off, z0 * scale, z1 * scale, tau))
    offset_far = 1e6
    out.append(("depth_offset_1e6", off, z0 + offset_far, z1 + offset_far, tau))
    return out


#: Parameters of the full and the quick run (quick: fewer cases, see :func:`cases`).
FULL = dict(seed=7)
QUICK = dict(FULL)


def _compute(res, params: dict) -> dict:
    """Every method on every adversarial case, in float32 and float64; the reliability checks."""
    quick = res.quick
    rng = np.random.default_rng(params["seed"])
    rows = []
    todo = cases(quick, rng)
    t_precision = 0.0
    for name, off, z0, z1, tau in tqdm(todo, desc="stress", unit="case"):
        T = len(off) - 1
        seg64 = Segments.from_arrays(off, z0, z1, optical_depth=tau, dtype="float64")
        lo, hi = seg64.bounds()
        tex = np.repeat(np.arange(T), 64)
        depth = np.tile(np.linspace(lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo), 64), T)
        ref = np.asarray(build("exact", seg64).eval(tex, depth))
        for dtype in ("float32", "float64"):
            seg = Segments.from_arrays(off, z0, z1, optical_depth=tau, dtype=dtype) if dtype == "float32" else seg64
            for kind, p in METHODS:
                if kind not in kinds():
                    continue
                est = np.asarray(build(kind, seg, **p).eval(tex, depth))
                stats = error_stats(est, ref)
                rows.append(dict(case=name, method=kind, param=next(iter(p.values()), ""),
                                 sorted=p.get("sort", False), order=_order(kind, p), dtype=dtype,
                                 precision="native", **stats))
            if (quick and dtype == "float64") or (quick and name not in PRECISION_QUICK_CASES):
                continue
            t0 = time.perf_counter()
            for kind, p, precision in precision_configs(name):
                est = np.asarray(build(kind, seg, precision=precision, **p).eval(tex, depth))
                rows.append(dict(case=name, method=kind, param=next(iter(p.values()), ""),
                                 sorted=p.get("sort", False), order=_order(kind, p), dtype=dtype,
                                 precision=precision,
                                 **error_stats(est, ref)))
            t_precision += time.perf_counter() - t0
    # insertion order: AVSM on shuffled copies of the same smoke
    off, z0, z1, tau = _smoke(rng, 64, 60, 0.0, 1.0)
    seg64 = Segments.from_arrays(off, z0, z1, optical_depth=tau, dtype="float64")
    tex = np.repeat(np.arange(64), 64)
    depth = np.tile(np.linspace(0, 1, 64), 64)
    ref = np.asarray(build("exact", seg64).eval(tex, depth))
    for trial in range(3 if quick else 10):
        perm = np.concatenate([k * 60 + rng.permutation(60) for k in range(64)])
        seg = Segments.from_arrays(off, z0[perm], z1[perm], optical_depth=tau[perm], dtype="float32")
        for sort in (False, True):
            est = np.asarray(build("avsm", seg, nodes=8, sort=sort).eval(tex, depth))
            rows.append(dict(case=f"shuffled_order_{trial}", method="avsm", param=8, sorted=sort,
                             order="depth" if sort else "random", dtype="float32", precision="native",
                             **error_stats(est, ref)))
    checks = run_checks(quick) + [precision_check(rows, t_precision)]

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(10, 4))
    names = [c[0] for c in todo]
    for i, (kind, p) in enumerate(m for m in METHODS if m[0] in kinds()):
        label = kind + ("-sorted" if p.get("sort") else "")
        vals = [next((r["max_error"] for r in rows if r["case"] == n and r["method"] == kind
                      and r["sorted"] == p.get("sort", False) and r["dtype"] == "float32"
                      and r["precision"] == "native"), np.nan) for n in names]
        ax.semilogy(range(len(names)), np.maximum(vals, 1e-9), "o-", label=label)
    ax.set_xticks(range(len(names)), names, rotation=45, ha="right")
    ax.set_ylabel("max |T - exact(float64)| (float32 runs)")
    ax.legend(fontsize=8)
    res.save_figure(fig, "stress_max_error.png")
    bad = sum(r["nan_count"] + r["inf_count"] for r in rows)
    viol = sum(r["bounds_violations"] for r in rows)
    failed = sum(r["failures"] for r in checks)
    prec = [r for r in rows if r["precision"] != "native"]
    summary = {"nan_inf_total": bad, "bounds_violations_total": viol, "rows": len(rows),
               "reliability_checks": len(checks), "reliability_failures": failed,
               "precision_runs": len(prec),
               "precision_nan_inf_total": sum(r["nan_count"] + r["inf_count"] for r in prec),
               "precision_seconds": round(t_precision, 2)}
    print(f"stress: {len(rows)} runs, NaN+inf outputs: {bad}, bounds violations: {viol}; "
          f"reliability: {failed} of {len(checks)} checks failed")
    return dict(rows=rows, tables={"reliability.csv": checks}, summary=summary)

def _headline(s: dict) -> list[str]:
    """NaN / Inf and bound violations over every adversarial case, the hostile-input checks
    and the reduced-precision runs."""
    return [f"{s['rows']} adversarial runs (case x representation): {s['nan_inf_total']} NaN/Inf outputs, "
            f"{s['bounds_violations_total']} values outside [0, 1]",
            f"hostile input: {s['reliability_failures']} of {s['reliability_checks']} checks failed",
            f"reduced precision: {s['precision_runs']} runs, {s['precision_nan_inf_total']} NaN/Inf "
            f"({num(s['precision_seconds'])} s)"]


STUDY = Study("stress", "Numerical stability of every representation on adversarial synthetic rays", REPRODUCES,
              FULL, QUICK, _compute, writes=("data.csv", "reliability.csv (hostile input: refused or right)"),
              headline=_headline)
run = STUDY.run
