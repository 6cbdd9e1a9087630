"""The avsm_gap page's data files and tables from a run::

    python scripts/avsm_gap_tables.py RUN_DIR [RUN_DIR ...] [--csv OUT_DIR]

Each ``RUN_DIR`` holds an avsm_gap run's ``findings.json`` and ``data.csv`` (either may be
gzipped); several runs (one per scene) are merged.
Prints the page's two tables (each ratio to ``optimal`` with its interval over the
configurations: depth-uniform RMS for every AVSM order, greedy and the best subset; receiver
RMSE and depth L2 for front-to-back AVSM and greedy); with ``--csv``, writes ``claims.csv``
(every claim and interval with the per-configuration counts) and ``means.csv`` (every method,
order and N, means over the configurations) into ``OUT_DIR``, as committed beside the page.
"""
from __future__ import annotations

import argparse
import csv
import gzip
import io
import json
from collections import defaultdict
from pathlib import Path

CLAIM_COLUMNS = ("scene", "N", "claim", "order", "metric", "ratio", "low", "high",
                 "configs_interval_below_1", "configs_interval_above_1", "metric_dependent")
MEAN_COLUMNS = ("depth_rms", "depth_max", "rmse", "depth_l2", "signed_mean", "leak_share", "bytes")
#: The first table's columns: (heading, claim) of the depth-uniform RMS ratios to optimal.
DEPTH_COLUMNS = (("AVSM depth", "avsm_over_optimal"), ("AVSM submission", "avsm@submission_over_optimal"),
                 ("AVSM reverse", "avsm@reverse_depth_over_optimal"), ("AVSM random", "avsm@random_over_optimal"),
                 ("greedy", "greedy_over_optimal"), ("subset", "optimal_subset_over_optimal"))
#: The second table's columns: (heading, claim, metric).
METRIC_COLUMNS = (("AVSM receiver RMSE", "avsm_over_optimal", "receiver_rmse"),
                  ("AVSM depth L2", "avsm_over_optimal", "depth_l2"),
                  ("greedy receiver RMSE", "greedy_over_optimal", "receiver_rmse"),
                  ("greedy depth L2", "greedy_over_optimal", "depth_l2"))


def run_text(run_dir, name: str) -> str:
    """The text of ``run_dir/name``, or of ``run_dir/name.gz`` where only that exists
    (``experiments._common.run_text``, repeated: the scripts here run without the repository on
    ``sys.path``)."""
    plain, packed = Path(run_dir) / name, Path(run_dir) / (name + ".gz")
    if not plain.exists() and packed.exists():
        return gzip.decompress(packed.read_bytes()).decode()
    return plain.read_text()


def _round(x: float) -> float:
    """4 significant digits (the CSVs' precision)."""
    return float(f"{x:.4g}")


def _counts(per_config: dict) -> tuple[int, int]:
    """Configurations whose own interval lies below / above 1."""
    bounds = [(lo, hi) for _, lo, hi in per_config.values()]
    return sum(1 for lo, hi in bounds if hi < 1), sum(1 for lo, hi in bounds if lo > 1)


def claims_rows(findings: dict, digits: bool = True) -> list[dict]:
    """``claims.csv``: each two-metric claim on both metrics, then each depth-uniform RMS interval;
    values to 4 significant digits (``digits``) or as found (the tables round them once)."""
    _sig = _round if digits else float
    out = []
    for scene, per_n in findings.get("claims", {}).items():
        for n, cs in per_n.items():
            for name, c in cs.items():
                for metric in ("receiver_rmse", "depth_l2"):
                    m = c["metrics"][metric]
                    out.append(dict(scene=scene, N=int(n[2:]), claim=name, order=c["order"], metric=metric,
                                    ratio=_sig(m["estimate"]), low=_sig(m["low"]), high=_sig(m["high"]),
                                    **dict(zip(CLAIM_COLUMNS[8:10], _counts(m["per_config"]))),
                                    metric_dependent=c["metric_dependent"]))
    for scene, per_n in findings.get("intervals", {}).items():
        for n, cs in per_n.items():
            for name, c in cs.items():
                out.append(dict(scene=scene, N=int(n[2:]), claim=name, order="", metric="depth_rms",
                                ratio=_sig(c["estimate"]), low=_sig(c["low"]), high=_sig(c["high"]),
                                **dict(zip(CLAIM_COLUMNS[8:10], _counts(c["per_config"]))), metric_dependent=""))
    return out


def means_rows(rows: list[dict]) -> list[dict]:
    """``means.csv``: per (scene, method, order, N) the mean of each column over the configurations
    where the method ran (``configs`` counts those: a row with a note, such as ``optimal_linf``
    above its work limit, holds no values)."""
    groups = defaultdict(list)
    for r in rows:
        groups[(r["scene"], r["method"], r.get("order") or "-", int(float(r["nodes"])))].append(r)
    out = []
    for (scene, method, order, n), rs in groups.items():
        ran = {r.get("config") for r in rs if any(r.get(k) not in (None, "") for k in MEAN_COLUMNS)}
        row = dict(scene=scene, method=method, order=order, N=n, configs=len(ran))
        for k in MEAN_COLUMNS:
            vals = [float(r[k]) for r in rs if r.get(k) not in (None, "")]
            row[k] = _round(sum(vals) / len(vals)) if vals else ""
        out.append(row)
    return out


def _cell(r: dict | None) -> str:
    return "-" if r is None else f"{float(r['ratio']):.2f} [{float(r['low']):.2f}, {float(r['high']):.2f}]"


def tables(claims: list[dict], scenes, depth_ns=(4, 8, 16, 32), metric_ns=(4, 8, 16)) -> dict[str, list[str]]:
    """The page's two tables (Markdown lines) from ``claims.csv`` rows, for ``scenes`` in order."""
    at = {(r["scene"], int(r["N"]), r["claim"], r["metric"]): r for r in claims}
    depth = ["| scene | N | " + " | ".join(h for h, _ in DEPTH_COLUMNS) + " |",
             "|" + "---|" * (2 + len(DEPTH_COLUMNS))]
    metric = ["| scene | N | " + " | ".join(h for h, *_ in METRIC_COLUMNS) + " |",
              "|" + "---|" * (2 + len(METRIC_COLUMNS))]
    for scene in scenes:
        for n in depth_ns:
            depth.append(f"| {scene} | {n} | " + " | ".join(_cell(at.get((scene, n, c, "depth_rms")))
                                                           for _, c in DEPTH_COLUMNS) + " |")
        for n in metric_ns:
            metric.append(f"| {scene} | {n} | " + " | ".join(_cell(at.get((scene, n, c, m)))
                                                            for _, c, m in METRIC_COLUMNS) + " |")
    return {"depth": depth, "metrics": metric}


def write_csv(path, rows: list[dict], columns) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(columns))
        w.writeheader()
        w.writerows(rows)


def load(run_dirs) -> tuple[dict, list[dict], list[str]]:
    """(findings with every run's ``claims`` and ``intervals`` merged by scene, data.csv rows of
    every run, scenes in order) of one or more runs (e.g. one run per scene)."""
    merged, rows = {"claims": {}, "intervals": {}}, []
    for run in map(Path, run_dirs):
        f = json.loads(run_text(run, "findings.json"))
        for k in merged:
            merged[k].update(f.get(k, {}))
        rows += list(csv.DictReader(io.StringIO(run_text(run, "data.csv"), newline="")))
    return merged, rows, list(dict.fromkeys(r["scene"] for r in rows))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("::")[0])
    ap.add_argument("run_dir", nargs="+", help="one or more runs' folders (their scenes are merged)")
    ap.add_argument("--csv", help="folder for claims.csv and means.csv")
    a = ap.parse_args(argv)
    findings, rows, scenes = load(a.run_dir)
    for name, lines in tables(claims_rows(findings, digits=False), scenes).items():
        print(f"<!-- {name} -->\n" + "\n".join(lines) + "\n")
    if a.csv:
        out = Path(a.csv)
        out.mkdir(parents=True, exist_ok=True)
        write_csv(out / "claims.csv", claims_rows(findings), CLAIM_COLUMNS)
        write_csv(out / "means.csv", means_rows(rows), ("scene", "method", "order", "N", "configs", *MEAN_COLUMNS))


if __name__ == "__main__":
    main()
