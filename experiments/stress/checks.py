"""Reliability checks of the stress experiment: adversarial input must be refused with a
``ValueError`` naming the argument, or give the right value in bounded time.

Classes (no crash, no hang, no silent wrong value): values that overflow the
float32 storage, huge counts (DSM polylines, thousands of coefficients, wide filters),
long optical-depth sums, the DSM error bound on curves that drop within one ulp,
subnormal depths, out-of-range indices and coordinates, non-differentiable requests.
Each check is one row ``(class, case, expected, outcome, failures, seconds, detail)``;
formerly crashing cases run in a subprocess, so a regression is a row, not a dead run.
"""
from __future__ import annotations

import dataclasses
import subprocess
import sys
import time

import numpy as np

from avsm_dr import build
from avsm_dr.segments import OPAQUE_OPTICAL_DEPTH, Segments


def _refused(name: str, fn) -> tuple[bool, str]:
    """(passed, detail): ``fn()`` raised ValueError starting with ``name:``."""
    try:
        fn()
    except ValueError as exc:
        msg = str(exc)
        return msg.startswith(f"{name}:"), msg[:160]
    except Exception as exc:          # noqa: BLE001 (any other outcome is the failure)
        return False, f"{type(exc).__name__}: {str(exc)[:140]}"
    return False, "accepted"


def _subprocess_refused(name: str, code: str) -> tuple[bool, str]:
    """The same in a fresh interpreter (the case used to segfault)."""
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    last = (p.stderr.strip().splitlines() or [""])[-1]
    ok = p.returncode == 1 and last.startswith(f"ValueError: {name}:")
    return ok, f"rc={p.returncode} {last[:150]}"


def _seg(z0, z1, tau, dtype="float32"):
    z0 = np.atleast_1d(np.asarray(z0, float))
    return Segments.from_arrays([0, z0.size], z0, z1, optical_depth=tau, dtype=dtype)


def _exact_host(z0, z1, tau, d):
    """exp(-sum tau_i f_i(d)) in float64 NumPy over one texel's stored segments."""
    z0, z1, tau = (np.asarray(x, np.float64) for x in (z0, z1, tau))
    length = z1 - z0
    pos = length > 0
    f = np.where(pos, np.clip((d[:, None] - z0) / np.where(pos, length, 1.0), 0, 1),
                 (d[:, None] >= z0).astype(float))
    return np.exp(-(f * np.minimum(tau, OPAQUE_OPTICAL_DEPTH)).sum(axis=1))


def _dsm_bound(quick: bool) -> tuple[bool, str]:
    """max |DSM - exact| / tolerance over opaque sub-ulp segments at large offsets and
    random adversarial texels, both dtypes and placements, at representable depths
    (dense grid plus the first 6 ulps after every segment end)."""
    rng = np.random.default_rng(11)
    worst = 0.0
    cases = [(1.0, 1.00005), (1e6, 1e6 + 4.0), (1e6, 1e6 + 1e-9), (-3e7, -3e7 + 2.0)]
    for _ in range(10 if quick else 60):
        off = rng.choice([0.0, 1.0, 1e3, 1e6, -1e6, 3e7])
        a = rng.uniform(0, 4)
        cases.append((off + a, off + a + rng.choice([0.0, 1e-9, 1e-6, 1e-3, 1.0])))
    for dtype in ("float32", "float64"):
        ft = np.float32 if dtype == "float32" else np.float64
        for z0, z1 in cases:
            seg = _seg([z0], [z1], [OPAQUE_OPTICAL_DEPTH], dtype)
            h = seg.numpy()
            ends = np.asarray([h["z0"][0], h["z1"][0]], ft)
            d = [np.linspace(ends[0] - 1, ends[1] + 1, 64).astype(ft), ends]
            for _ in range(6):
                d.append(np.nextafter(d[-1], ft(np.inf)))
            d = np.unique(np.concatenate(d)).astype(np.float64)
            ref = _exact_host(h["z0"], h["z1"], h["optical_depth"], d)
            for placement in ("midslope", "curve"):
                for tol in (0.01, 0.1):
                    rep = build("dsm", seg, tolerance=tol, placement=placement)
                    est = np.asarray(rep.eval(np.zeros(d.size, int), d), np.float64)
                    slack = 1e-6 if dtype == "float32" else 1e-12
                    worst = max(worst, float(np.max(np.abs(est - ref)) / (tol + slack)))
    return worst <= 1.0, f"max |DSM - exact| / tolerance = {worst:.3f} over {len(cases)} texels x 2 dtypes"


def _long_sum(n: int) -> tuple[bool, str]:
    z0 = np.arange(n) / n
    seg = _seg(z0, z0 + 1.0 / n, np.full(n, 3.0 / n))
    ref = float(np.exp(-np.sum(seg.numpy()["optical_depth"])))
    got = float(np.asarray(build("exact", seg).eval([0], [2.0]))[0])
    rel = abs(got - ref) / ref
    return rel <= 1e-5, f"exact T = {got:.8g}, float64 sum {ref:.8g}, rel. error {rel:.2g}"


def _subnormal_consistent() -> tuple[bool, str]:
    """A receiver at a subnormal depth gives the same T alone and in a 64-wide batch
    (Dr.Jit's worker threads flush subnormals, the calling thread does not)."""
    rep = build("exact", _seg([0.0], [0.0], [0.5]))
    small = np.asarray(rep.eval([0], [-1.4e-45]))
    big = np.asarray(rep.eval(np.zeros(64, int), np.full(64, -1.4e-45)))
    ok = bool(np.all(big == small[0]))
    return ok, f"T alone {small[0]:.6g}, batch {np.unique(big)}"


def _filters_linear() -> tuple[bool, str]:
    W = 16
    rng = np.random.default_rng(3)
    off = np.arange(W * W + 1) * 3
    z0 = rng.uniform(0, 1, 3 * W * W)
    rep = build("exact", Segments.from_arrays(off, z0, z0 + 0.1, optical_depth=rng.uniform(0, 1, z0.size)))
    xy = np.r_[rng.uniform(0, W, (8, 2)), [[2.0**31 + 5, 3.0]]]
    t = time.perf_counter()
    T = np.asarray(rep.eval(xy, np.full(9, 1.5), filter="gaussian", width=W, height=W, radius=15.0))
    tiny = np.asarray(rep.eval(xy, np.full(9, 1.5), filter="gaussian", width=W, height=W, radius=0.01))
    dt = time.perf_counter() - t
    ok = bool(np.all(np.isfinite(T)) and np.all(np.isfinite(tiny)) and np.all((T >= 0) & (T <= 1)))
    return ok, f"radius 15 and 0.01, 9 receivers (one at x = 2^31 + 5): finite, {dt:.2f} s"


def checks(quick: bool) -> list[tuple[str, str, str, callable]]:
    """(class, case, expected, check() -> (passed, detail))."""
    s1 = _seg([0.0], [1.0], [1.0])
    crash = ("import avsm_dr as ad\n"
             "seg = ad.Segments.from_arrays([0, 1], [0.0], [1e39], optical_depth=[1.0])\n"
             "ad.build('dsm', seg)\n")
    opaque = Segments.from_arrays(np.arange(4097), np.zeros(4096), np.ones(4096),
                                  optical_depth=np.full(4096, 30.0))
    n_long = 200_000 if quick else 4_000_000
    N = 200 if quick else 1000
    return [
        ("dtype_overflow", "z1 = 1e39 in float32 (was a segfault in dsm)", "ValueError z1",
         lambda: _subprocess_refused("z1", crash)),
        ("dtype_overflow", "depth range 6e38 in float32", "ValueError z1",
         lambda: _refused("z1", lambda: _seg([-3e38], [3e38], [1.0]))),
        ("dtype_overflow", "fom far = 1e39", "ValueError far",
         lambda: _refused("far", lambda: build("fom", s1, far=1e39))),
        ("dtype_overflow", "osm near = -3e38, far = 3e38 (range overflows)", "ValueError far",
         lambda: _refused("far", lambda: build("osm", s1, near=-3e38, far=3e38))),
        ("dtype_overflow", "avsm near = -1e39", "ValueError near",
         lambda: _refused("near", lambda: build("avsm", s1, near=-1e39))),
        ("dtype_overflow", "receiver depth -1e39 (avsm gave NaN)", "ValueError depth",
         lambda: _refused("depth", lambda: build("avsm", s1).eval([0], [-1e39]))),
        ("dtype_overflow", "subnormal receiver depth, alone vs batch", "same T",
         _subnormal_consistent),
        ("huge_counts", "dsm tolerance 1e-9 on 4096 opaque texels (~11 GiB)", "ValueError tolerance",
         lambda: _refused("tolerance", lambda: build("dsm", opaque, tolerance=1e-9))),
        ("huge_counts", f"osm slices = {N}, fom harmonics = {N}, legendre n = {N // 4}", "finite",
         lambda: _sizes(N)),
        ("huge_counts", "gaussian radius 15 / 0.01, x = 2^31 + 5", "finite", _filters_linear),
        ("huge_counts", "radius larger than the map", "ValueError radius",
         lambda: _refused("radius", lambda: build("exact", s1).eval(np.array([[0.5, 0.5]]), [0.5],
                                                                     filter="box", width=1, height=1,
                                                                     radius=3.0))),
        ("huge_counts", "select_texels([-2])", "ValueError texels",
         lambda: _refused("texels", lambda: s1.select_texels([-2]))),
        ("long_sums", f"exact over {n_long} equal segments, total 3", "rel. error <= 1e-5",
         lambda: _long_sum(n_long)),
        ("dsm_bound", "opaque sub-ulp segments at offsets up to 3e7", "|DSM - exact| <= tol",
         lambda: _dsm_bound(quick)),
        ("messages", "dsm midslope + dr.backward", "ValueError placement", _midslope_backward),
        ("behind_the_light", "receivers behind / outside a spot light's map, every kind", "T = 1",
         _behind_the_light),
    ]


def _behind_the_light() -> tuple[bool, str]:
    """Receivers behind a spot light, outside its map, and beside a directional map get
    T = 1 for every kind (they used to read a corner texel's shadow)."""
    from avsm_dr import builtin_scenes, capture, kinds
    from avsm_dr.scene import SpotLight
    scene = builtin_scenes.plume(size=12)
    lo, hi = (np.asarray(b, float) for b in scene.bbox)
    c = 0.5 * (lo + hi)
    spot = SpotLight(position=c - np.array([3.0, 0.0, 0.0]), direction=(1.0, 0.0, 0.0), fov=40.0)
    pts = np.array([c - [6.0, 0.0, 0.0],            # behind the spot light
                    c + [0.0, 50.0, 0.0],            # far outside its cone
                    c - [3.0, 0.0, 0.5]])            # beside it, behind its plane
    cap = capture(dataclasses.replace(scene, light=spot), resolution=64, order="depth")
    worst = 0.0
    for kind in kinds():
        if kind == "optimal":            # offline, seconds per build; its lookup is greedy's (NodeList)
            continue
        T = np.asarray(cap.transmittance(build(kind, cap.segments), pts), np.float64)
        worst = max(worst, float(np.max(np.abs(T - 1.0))))
    covered = cap.covers(pts)
    return worst == 0.0 and not covered.any(), f"max |T - 1| = {worst:g} over {len(kinds())} kinds; covered {covered}"


def _sizes(N: int) -> tuple[bool, str]:
    rng = np.random.default_rng(5)
    off = np.arange(65) * 20
    z0 = rng.uniform(0, 1, 1280)
    seg = Segments.from_arrays(off, z0, z0 + 0.05, optical_depth=rng.exponential(0.1, 1280))
    out = []
    t = time.perf_counter()
    for kind, p in (("osm", {"slices": N}), ("fom", {"harmonics": N}), ("basis", {"n": N // 4})):
        T = np.asarray(build(kind, seg, **p).eval(np.arange(64), np.full(64, 0.6)))
        out.append(bool(np.all(np.isfinite(T)) and np.all((T >= 0) & (T <= 1))))
    return all(out), f"3 builds + evals in {time.perf_counter() - t:.1f} s"


def _midslope_backward() -> tuple[bool, str]:
    import drjit as dr
    from avsm_dr import backend
    t = backend.types().Float([1.0])
    dr.enable_grad(t)
    seg = Segments.from_arrays([0, 1], [0.0], [1.0], optical_depth=t)
    T = build("dsm", seg).eval([0], [0.5])
    return _refused("placement", lambda: dr.backward(dr.sum(T)))


# ----------------------------------------------------------------------------
# Storage precision: every kind x every precision it accepts
# ----------------------------------------------------------------------------
#: Cases the precision sweep runs in --quick mode (all of them otherwise).
PRECISION_QUICK_CASES = ("opacity_1", "optical_depth_1e4", "depth_offset_1e6")


def precision_configs(case: str) -> list[tuple[str, dict, str]]:
    """(kind, headline parameters, precision) for every registered kind and every storage
    precision it accepts (``describe(kind)['precisions']``); offline kinds (host O(K^2)
    or more per texel) skip the one-ray case of thousands of segments."""
    from avsm_dr import describe, kinds
    out = []
    for kind in kinds():
        d = describe(kind)
        if d["offline"] and case.endswith("_segments_one_ray"):
            continue
        out += [(kind, dict(d["headline"]), p) for p in d["precisions"]]
    return out


def precision_check(rows: list[dict], seconds: float) -> dict:
    """Reliability row: the precision sweep's estimates are finite and in [0, 1]."""
    runs = [r for r in rows if r["precision"] != "native"]
    bad = sum(r["nan_count"] + r["inf_count"] + r["bounds_violations"] for r in runs)
    pairs = sorted({(r["method"], r["precision"]) for r in runs})
    return dict(check_class="precision", case=f"every kind x precision ({len(pairs)} pairs, {len(runs)} runs)",
                expected="0 NaN/inf, T in [0, 1]", failures=int(bad > 0), seconds=round(seconds, 3),
                detail=f"{bad} NaN/inf/out-of-range estimates")


def run_checks(quick: bool) -> list[dict]:
    """Every check as a CSV row."""
    rows = []
    for cls, case, expected, fn in checks(quick):
        t = time.perf_counter()
        ok, detail = fn()
        rows.append(dict(check_class=cls, case=case, expected=expected, failures=0 if ok else 1,
                         seconds=round(time.perf_counter() - t, 3), detail=detail))
    return rows
