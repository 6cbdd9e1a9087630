"""The AVSM paper's Table 1 at equal work, on the active backend (a GPU when there is one).

Salvi et al., "Adaptive Volumetric Shadow Maps" (EGSR 2010), Table 1: a 256^2 shadow map of a
smoke scene with "hundreds of occluders per light ray", AVSM with 4 / 8 / 16 nodes, OSM with
32 slices, FOM with 16 expansion terms, DSM at error 0.01 and the uncompressed curves; per
setting the bilinear shadow lookups, the capture of the occluders, the compression and the
memory, on a 2010 GPU.  The same settings here (FOM: 8 harmonics, 2 x 8 + 1 = 17 coefficients,
the nearest to 16 terms), on the plume at the map's resolution, for two grids: ``size`` 48 (the
frame study's, 30 segments per occupied texel with the marched capture) and 256 (155 per
occupied texel, up to 240: the paper's "hundreds").

Per (scene, setting), medians of ``repeats`` interleaved synced calls
(:func:`avsm_dr.evaluation.measure`):

* ``capture_ms`` - ``capture(scene, 256, method='march')`` (host preparation included);
* ``sort_ms``    - AVSM's build with ``sort=True`` minus ``sort=False`` on the same segments
  shuffled inside every texel (the paper's optional sort, 3 ms);
* ``compress_ms`` - ``build(kind, segments, **params)`` on the capture, evaluated;
* ``lookup_ms``  - ``rep.eval(coords, depth, 'bilinear')`` for ``lookups`` receivers (default
  1280 x 720; the paper's screen size is not in its text), continuous map coordinates from the
  host, as a renderer hands them over;
* ``*_kernel_ms`` - the Dr.Jit kernel time of the same calls (``dr.kernel_history``);
* ``memory_mb``  - the captured segments (12 B each plus the CSR offsets) and, in parentheses
  as in the paper, the representation's own bytes (``nbytes_sparse``).

    python -m experiments.bench.paper_table [--out DIR] [--repeats 5] [--sizes 48 256]

Writes ``paper_table.csv`` and ``paper_table.md`` (ours beside the paper's figures).  Absolute
times only as context: the paper's GPU is 15 years older than any device this runs on.
"""
from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import drjit as dr
import numpy as np

#: (label, kind, parameters): the columns of the paper's Table 1.
SETTINGS = (("AVSM 4", "avsm", {"nodes": 4}), ("AVSM 8", "avsm", {"nodes": 8}),
            ("AVSM 16", "avsm", {"nodes": 16}), ("OSM 32", "osm", {"slices": 32}),
            ("FOM 16", "fom", {"harmonics": 8}), ("DSM 0.01", "dsm", {"tolerance": 0.01}),
            ("Uncompressed", "exact", {}))
#: The paper's Table 1 in ms and MB (memory: total, compressed map in parentheses; None: N/A).
PAPER = {"AVSM 4": (3, 0.4, 0.5, 9.7, "22 (2)"), "AVSM 8": (5.4, 0.4, 0.7, 12.1, "24 (4)"),
         "AVSM 16": (9.5, 0.4, 1.6, 17.43, "28 (8)"), "OSM 32": (1.4, None, 1, 8.6, "8"),
         "FOM 16": (8.9, None, 1.1, 15, "8"), "DSM 0.01": (52, 0.4, 193, 251, "40"),
         "Uncompressed": (278, 0.4, None, 285, "20")}
PAPER_SORT_MS = 3.0
RESOLUTION = 256
LOOKUPS = 1280 * 720


def table_rows(size: int, resolution: int = RESOLUTION, lookups: int = LOOKUPS, repeats: int = 5,
               settings=SETTINGS, seed: int = 0) -> list[dict]:
    """One row per setting for the plume at grid ``size`` (module docstring)."""
    from avsm_dr import build, capture
    from avsm_dr.evaluation import measure
    from ..frame import builtin_scenes, lookup_points, random_order
    rng = np.random.default_rng(seed)
    scene = builtin_scenes(size, ["plume"])["plume"]
    cap = capture(scene, resolution=resolution, method="march", order="depth")
    seg = cap.segments
    coords, depth = cap.lookup(lookup_points(scene, lookups, rng), continuous=True)
    shuffled = random_order(seg, rng)
    built = {}

    def make(label, kind, params):
        built[label] = build(kind, seg, **params)
        dr.eval(vars(built[label]))
        return built[label]

    fns = {("capture",): lambda: capture(scene, resolution=resolution, method="march", order="depth").segments}
    for srt in (False, True):
        fns["random", srt] = lambda srt=srt: build("avsm", shuffled.drop_cache(keep=()), nodes=8, sort=srt).depths
    for label, kind, params in settings:
        fns["build", label] = lambda a=(label, kind, params): make(*a)
        fns["lookup", label] = lambda label=label: built[label].eval(coords, depth, "bilinear", width=cap.width,
                                                                     height=cap.height)
    r = measure(fns, repeats=repeats)
    counts = seg.counts[seg.counts > 0]
    seg_mb = (12 * seg.n_segments + 4 * (seg.n_texels + 1)) / 1e6
    sort_ms = 1e3 * (r["random", True]["wall_s"] - r["random", False]["wall_s"])
    rows = []
    for label, kind, params in settings:
        b, lk, rep = r["build", label], r["lookup", label], built[label]
        capture_ms = 1e3 * r["capture",]["wall_s"]
        compress_ms = 0.0 if kind == "exact" else 1e3 * b["wall_s"]
        rows.append(dict(backend=dr.backend_v(seg.z0).name, grid_size=size, resolution=resolution,
                         segments=seg.n_segments, occupied_texels=counts.size,
                         segments_per_occupied_texel=float(counts.mean()) if counts.size else 0.0,
                         max_segments_per_texel=int(counts.max()) if counts.size else 0, setting=label,
                         kind=kind, params=params, lookups=lookups, capture_ms=capture_ms,
                         capture_kernel_ms=1e3 * r["capture",]["kernel_s"], sort_ms=sort_ms,
                         sort_kernel_ms=1e3 * (r["random", True]["kernel_s"] - r["random", False]["kernel_s"]),
                         compress_ms=compress_ms, compress_kernel_ms=1e3 * b["kernel_s"],
                         lookup_ms=1e3 * lk["wall_s"], lookup_kernel_ms=1e3 * lk["kernel_s"],
                         frame_ms=capture_ms + compress_ms + 1e3 * lk["wall_s"],
                         map_mb=float(rep.nbytes_sparse) / 1e6, capture_mb=seg_mb))
    return rows


def markdown(rows: list[dict]) -> str:
    """Per grid size, the paper's layout: ours (the paper's) per setting."""
    def f(x):
        return "N/A" if x is None else f"{x:.3g}"
    out = []
    for size in sorted({r["grid_size"] for r in rows}):
        mine = [r for r in rows if r["grid_size"] == size]
        r0 = mine[0]
        out.append(f"Plume grid {size} ({r0['backend']}): {r0['segments']} segments, "
                   f"{r0['segments_per_occupied_texel']:.0f} per occupied texel (max {r0['max_segments_per_texel']}), "
                   f"{r0['resolution']}^2 map, {r0['lookups']} bilinear lookups; sort (AVSM 8) "
                   f"{r0['sort_ms']:.3g} ms, kernels {r0['sort_kernel_ms']:.3g} ms ({PAPER_SORT_MS:g}). Ours (paper), "
                   "ms and MB; wall times include the host's share (a kernel row: Dr.Jit kernel time alone).\n")
        out.append("| | " + " | ".join(r["setting"] for r in mine) + " |")
        out.append("|---|" + "---|" * len(mine))
        lines = (("Shadow lookup (bilinear)", "lookup_ms", 0), ("  its kernels", "lookup_kernel_ms", 0),
                 ("Capture occluders", "capture_ms", 1), ("  its kernels", "capture_kernel_ms", 1),
                 ("Compress", "compress_ms", 2), ("  its kernels", "compress_kernel_ms", 2),
                 ("Total frame time", "frame_ms", 3))
        for name, key, i in lines:
            cells = []
            for r in mine:
                paper = PAPER[r["setting"]][i]
                ours = None if (key.startswith("compress") and r["kind"] == "exact") else r[key]
                cells.append(f"{f(ours)} ({f(paper)})")
            out.append(f"| {name} | " + " | ".join(cells) + " |")
        out.append("| Memory usage | " + " | ".join(f"{r['capture_mb'] + r['map_mb']:.3g} ({r['map_mb']:.3g})"
                                                 for r in mine) + " |")
        out.append("| Memory usage, paper | " + " | ".join(PAPER[r["setting"]][4] for r in mine) + " |\n")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/paper_table")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--sizes", type=int, nargs="+", default=[48, 256])
    ap.add_argument("--lookups", type=int, default=LOOKUPS)
    ap.add_argument("--resolution", type=int, default=RESOLUTION)
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for size in a.sizes:
        rows += table_rows(size, a.resolution, a.lookups, a.repeats)
        print(f"[paper_table] grid {size} done", file=sys.stderr, flush=True)
    with (out / "paper_table.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    text = markdown(rows)
    (out / "paper_table.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
