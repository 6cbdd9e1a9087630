"""Capture cost vs bounding box: a plume in its tight box and in 4x larger empty boxes.

The same plume density (same voxel size, same world position, same light and
shadow map) is embedded in zero-padded grids whose box is
  * 4x larger per axis  (64x the voxels, almost all zero), and
  * 4x larger in volume (4^(1/3) ~ 1.59x per axis).
Bar (issue 3): capture of the padded grid costs < 1.5x the tight one.

Timings: median of ``--repeats`` calls after one warm-up call (the first call's
time, which includes Dr.Jit's kernel compilation, is reported separately), for
  * ``capture`` - the full ``ad.capture(scene)`` from a NumPy array (host
    validation + occupancy grid, O(voxels), included), and
  * ``prepared`` - ``ad.capture`` with a :class:`GridVolume` prepared once
    (what repeated captures of one grid cost), and its kernels' execution time
    from ``dr.kernel_history``.

    python experiments/bench_capture.py [--size 48] [--resolution 256] [--repeats 5]
Writes results/bench_capture/{data.csv, meta.json}.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import time

import numpy as np

import avsm_dr as ad  # noqa: I001  (before drjit: picks libLLVM)
import drjit as dr
from avsm_dr.capture import GridVolume
from avsm_dr.scene import Scene


def embed(scene, factor_per_axis: float) -> Scene:
    """The scene's grid zero-padded (same voxel size, plume centred) by ~factor per axis."""
    d = scene.density
    lo, hi = (np.asarray(b, np.float64) for b in scene.bbox)
    h = (hi - lo) / np.array(d.shape[::-1])
    n_new = np.round(np.array(d.shape) * factor_per_axis).astype(int)       # (z, y, x)
    off = (n_new - np.array(d.shape)) // 2
    big = np.zeros(tuple(n_new), np.float32)
    big[off[0]:off[0] + d.shape[0], off[1]:off[1] + d.shape[1], off[2]:off[2] + d.shape[2]] = d
    lo_new = lo - off[::-1] * h
    hi_new = lo_new + n_new[::-1] * h
    return Scene(scene.name + f"_x{factor_per_axis:.3g}", scene.light, scene.receivers, density=big,
                 bbox=(lo_new, hi_new))


def run_once(fn, compile_info=None):
    """(wall seconds, kernel execution seconds from dr.kernel_history, capture); when
    ``compile_info`` is a dict, JIT compile seconds (codegen + LLVM backend) and the number of
    kernels compiled / found in Dr.Jit's on-disk cache are added to it."""
    dr.kernel_history()                                       # clear
    t0 = time.perf_counter()
    cap = fn()
    dr.eval(cap.segments.z0, cap.segments.z1, cap.segments.optical_depth)
    dr.sync_thread()
    wall = time.perf_counter() - t0
    hist = dr.kernel_history()
    kern = sum(k.get("execution_time", 0.0) for k in hist) / 1e3   # ms -> s
    if compile_info is not None:
        jit = [k for k in hist if k["type"] == dr.KernelType.JIT]
        compile_info["jit_s"] = sum(k.get("codegen_time", 0.0) + k.get("backend_time", 0.0) for k in jit) / 1e3
        compile_info["compiled"] = sum(1 for k in jit if not k.get("cache_hit") and not k.get("cache_disk"))
        compile_info["from_disk"] = sum(1 for k in jit if k.get("cache_disk"))
    return wall, kern, cap


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=48, help="plume voxels per world unit")
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", default="results/bench_capture")
    args = ap.parse_args(argv)
    dr.set_flag(dr.JitFlag.KernelHistory, True)

    tight = ad.scenes.plume(size=args.size)
    cases = [("tight", tight), ("4x per axis", embed(tight, 4.0)), ("4x volume", embed(tight, 4.0 ** (1 / 3)))]
    res = args.resolution
    fns = {}
    for name, sc in cases:
        grid = GridVolume.prepare(sc.density, sc.bbox)
        fns[name, "capture"] = (lambda sc=sc: ad.capture(sc, resolution=res))
        fns[name, "prepared"] = (lambda sc=sc, g=grid: ad.capture(sc, resolution=res, density=g))
    # warm-up (first call: includes JIT compilation of the march kernels)
    first, caps, jit = {}, {}, {}
    for key, fn in fns.items():
        jit[key] = {}
        first[key], _, caps[key] = run_once(fn, jit[key])
    # interleaved repeats, so that load from other processes hits every case alike
    walls = {k: [] for k in fns}
    kerns = {k: [] for k in fns}
    for _ in range(args.repeats):
        for key, fn in fns.items():
            w, k, _ = run_once(fn)
            walls[key].append(w)
            kerns[key].append(k)
    med = {k: float(np.median(v)) for k, v in walls.items()}
    kmed = {k: float(np.median(v)) for k, v in kerns.items()}

    rows = []
    for name, sc in cases:
        cap = caps[name, "capture"]
        assert caps[name, "prepared"].segments.n_segments == cap.segments.n_segments
        row = {
            "case": name, "voxels": int(sc.density.size), "shape": "x".join(map(str, sc.density.shape)),
            "segments": cap.segments.n_segments, "lanes": cap.stats["grid"]["lanes"],
            "iterations": cap.stats["grid"]["iterations"],
            "first_call_s": first[name, "capture"], "first_call_jit_s": jit[name, "capture"]["jit_s"],
            "kernels_compiled": jit[name, "capture"]["compiled"],
            "kernels_from_disk_cache": jit[name, "capture"]["from_disk"],
            "capture_s": med[name, "capture"], "prepared_s": med[name, "prepared"],
            "kernels_s": kmed[name, "prepared"],
            "ratio_capture": med[name, "capture"] / med["tight", "capture"],
            "ratio_prepared": med[name, "prepared"] / med["tight", "prepared"],
            "ratio_kernels": kmed[name, "prepared"] / kmed["tight", "prepared"],
        }
        rows.append(row)
        print(f"{name:12s} {row['shape']:>13s} voxels={row['voxels']:>9d} segments={row['segments']:>7d} "
              f"iters={row['iterations']:>7d} first={row['first_call_s'] * 1e3:6.1f} ms "
              f"(jit {row['first_call_jit_s'] * 1e3:5.1f} ms: {row['kernels_compiled']} compiled, "
              f"{row['kernels_from_disk_cache']} from disk) | "
              f"capture={row['capture_s'] * 1e3:6.1f} ms (x{row['ratio_capture']:.2f}) "
              f"prepared={row['prepared_s'] * 1e3:6.1f} ms (x{row['ratio_prepared']:.2f}) "
              f"kernels={row['kernels_s'] * 1e3:5.1f} ms (x{row['ratio_kernels']:.2f})")

    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "data.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    with open(os.path.join(args.out, "meta.json"), "w") as f:
        json.dump({"args": vars(args), "machine": platform.processor() or platform.machine(),
                   "cpus": os.cpu_count(), "backend": ad.get_backend(),
                   "note": "median of interleaved repeats after one warm-up call per case; "
                           "first_call_s includes JIT compilation (first_call_jit_s; only the first "
                           "case compiles, and Dr.Jit's on-disk kernel cache may serve it)"},
                  f, indent=2)


if __name__ == "__main__":
    main()
