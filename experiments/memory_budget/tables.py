"""The memory-budget page's tables from a finished run, and its savings recomputed from the
run's rows, without rerunning it::

    python -m experiments.memory_budget.tables RUN_DIR

``RUN_DIR`` holds a run's ``data.csv``, ``findings.json`` and ``meta.json`` (each may be
gzipped, as in the committed run ``docs/research/memory_budget/run_gaussian_blobs``).  Prints
every table of ``docs/research/memory_budget.md`` (Markdown, one per heading) from
``findings.json``.  :func:`recompute` redoes the savings at equal error from ``data.csv``'s
rows (:func:`experiments.memory_budget.savings`); the RMSE ratios and claims need the
receivers' errors, which ``data.csv`` does not hold.
"""
from __future__ import annotations

import argparse
import csv
import io
import json
from pathlib import Path

from .._headline import interval
from .._common import run_text as _text

#: Budgets of the savings tables: (findings key, column heading).
SAVING_BUDGETS = (("N=2", "16 B (N=2)"), ("N=4", "32 B (N=4)"), ("N=8", "64 B (N=8)"))
#: Savings recomputed from the rows: findings key -> (metric, method, bytes column, order, interpolation).
SAVINGS = {
    "bytes_saved_at_equal_rmse": ("rmse", "adaptive", "bytes_sparse", "depth", "linear"),
    "bytes_saved_at_equal_depth_rms": ("depth_rms", "adaptive", "bytes_sparse", "depth", "linear"),
    "bytes_saved_at_equal_rmse_uniform_allocation": ("rmse", "adaptive_uniform", "bytes_sparse", "depth", "linear"),
    "bytes_saved_at_equal_rmse_dense_baseline": ("rmse", "adaptive", "bytes_per_texel", "depth", "linear"),
    "bytes_saved_at_equal_rmse_exp": ("rmse", "adaptive", "bytes_sparse", "depth", "exp"),
    "bytes_saved_at_equal_depth_rms_exp": ("depth_rms", "adaptive", "bytes_sparse", "depth", "exp"),
}
METRICS = (("receiver RMSE", "rmse"), ("depth-uniform", "depth_rms"))


def load(run_dir) -> tuple[list[dict], dict, dict]:
    """(rows of ``data.csv`` with numbers parsed, ``findings.json``, ``meta.json``) of the
    memory-budget run in ``run_dir``; ValueError naming ``run_dir`` for anything else."""
    from .._replot import typed
    run_dir = Path(run_dir)
    try:
        meta = json.loads(_text(run_dir, "meta.json"))
        findings = json.loads(_text(run_dir, "findings.json"))
        rows = typed(list(csv.DictReader(io.StringIO(_text(run_dir, "data.csv"), newline=""))))
    except (OSError, ValueError) as exc:
        raise ValueError(f"run_dir: {run_dir} does not hold a memory_budget run ({exc})") from None
    if meta.get("experiment") != "memory_budget":
        raise ValueError(f"run_dir: {run_dir} holds the results of {meta.get('experiment')!r}, not 'memory_budget'")
    return rows, findings, meta


def recompute(rows) -> dict:
    """The savings keys of :data:`SAVINGS` from the run's rows (front to back unless the key
    says otherwise), as :func:`experiments.memory_budget.findings` computes them."""
    from . import savings

    def pick(order, interpolation):
        return [r for r in rows if r["order"] in ("-", order)
                and (r["interpolation"] in ("-", "linear") if interpolation == "linear"
                     else r["interpolation"] == interpolation)]
    return {k: savings(pick(o, i), metric, method, key) for k, (metric, method, key, o, i) in SAVINGS.items()}


def _content(scene: str) -> str:
    from avsm_dr.builtin_scenes import SCENES
    return ", ".join(SCENES.entry(scene).content) if scene in SCENES else ""


def saving_cell(e: dict | None) -> str:
    """``saving [low, high]`` (two decimals) of a savings entry, censored configurations noted."""
    if not e:
        return "-"
    if e.get("saving") is None:
        return f">= {e['censored_saving_at_least']:.2f} (all censored)"
    text = f"{e['saving']:.2f} [{e['low']:.2f}, {e['high']:.2f}]" if "low" in e else f"{e['saving']:.2f}"
    return text + (f" ({e['censored']} censored)" if e.get("censored") else "")


def _row(cells) -> str:
    return "| " + " | ".join(cells) + " |"


def _head(*columns) -> list[str]:
    return [_row(columns), _row(["---"] * len(columns))]


def _sign_differs(a: dict | None, b: dict | None) -> bool:
    """Whether two savings estimates lie on opposite sides of 0 (one of them strictly)."""
    if not a or not b or a.get("saving") is None or b.get("saving") is None:
        return False
    return (a["saving"] > 0 > b["saving"]) or (a["saving"] < 0 < b["saving"])


def savings_table(f: dict, suffix: str = "") -> list[str]:
    """Bytes saved at equal error against sparse fixed AVSM, both metrics per scene; a dagger
    where the two metrics' estimates differ in sign."""
    rm, dr = f[f"bytes_saved_at_equal_rmse{suffix}"], f[f"bytes_saved_at_equal_depth_rms{suffix}"]
    out = _head("scene", "content", "metric", *(h for _, h in SAVING_BUDGETS))
    for scene in f["scenes"]:
        for i, (name, src) in enumerate((("receiver RMSE", rm), ("depth-uniform", dr))):
            cells = []
            for n, _ in SAVING_BUDGETS:
                e = src.get(scene, {}).get(n)
                dag = " †" if _sign_differs(rm.get(scene, {}).get(n), dr.get(scene, {}).get(n)) else ""
                cells.append(saving_cell(e) + dag)
            out.append(_row([scene if i == 0 else "", _content(scene) if i == 0 else "", name, *cells]))
    return out


def single_savings_table(f: dict, key: str) -> list[str]:
    """One savings key per scene (receiver RMSE), at the three budgets."""
    out = _head("scene", "content", *(h for _, h in SAVING_BUDGETS))
    for scene in f["scenes"]:
        out.append(_row([scene, _content(scene), *(saving_cell(f[key].get(scene, {}).get(n))
                                                   for n, _ in SAVING_BUDGETS)]))
    return out


def by_order_table(f: dict, key: str) -> list[str]:
    """A saving under each insertion order (receiver RMSE), three budgets per scene."""
    orders = list(f[key])
    out = _head("scene", "budget", *("depth (front to back)" if o == "depth" else o for o in orders))
    for scene in f["scenes"]:
        for i, (n, h) in enumerate(SAVING_BUDGETS):
            out.append(_row([scene if i == 0 else "", h.split(" (")[0],
                             *(saving_cell(f[key][o].get(scene, {}).get(n)) for o in orders)]))
    return out


def ratio_table(f: dict, key: str, ns, bytes_heading: bool = True) -> list[str]:
    """RMSE ratios ``estimate [low, high]`` (three significant digits) per scene and N."""
    heads = [f"{8 * n} B (N={n})" if bytes_heading else f"N={n}" for n in ns]
    out = _head("scene", *heads)
    for scene in f["scenes"]:
        out.append(_row([scene, *(interval(f[key][scene][f"N={n}"]) if f"N={n}" in f[key].get(scene, {})
                                  else "-" for n in ns)]))
    return out


def exp_over_linear_claims_table(f: dict, n: int = 8) -> list[str]:
    """AVSM-``n`` with exp over linear in each insertion order, both metrics (``claims``); a
    dagger where the claim is metric-dependent."""
    from . import key
    orders = list(f["bytes_saved_at_equal_rmse_by_order"])
    out = _head("scene", "metric", *("depth (front to back)" if o == "depth" else o for o in orders))
    for scene in f["scenes"]:
        cs = f["claims"].get(scene, {}).get(f"N={n}", {})
        for i, (name, m) in enumerate((("receiver RMSE", "receiver_rmse"), ("depth-uniform L2", "depth_l2"))):
            cells = []
            for o in orders:
                c = cs.get(f"{key('avsm', o, 'exp')}_over_{key('avsm', o)}")
                cells.append("-" if c is None else interval(c["metrics"][m]) + (" †" if c["metric_dependent"] else ""))
            out.append(_row([scene if i == 0 else "", name, *cells]))
    return out


def others_table(f: dict) -> list[str]:
    """Adaptive AVSM over DSM and over the best subset, and the best subset over fixed AVSM,
    at equal dense budgets (front to back, linear)."""
    ns = (2, 4, 8)
    out = _head("scene", *(f"{what} {8 * n} B" for what in ("adaptive / DSM",) for n in ns),
                *(f"{what} N={n}" for what in ("adaptive / optimal", "optimal / AVSM") for n in ns))
    for scene in f["scenes"]:
        cells = []
        for k in ("rmse_ratio_adaptive_over_dsm", "rmse_ratio_adaptive_over_optimal", "rmse_ratio_optimal_over_avsm"):
            cells += [interval(f[k][scene][f"N={n}"]) if f"N={n}" in f[k].get(scene, {}) else "-" for n in ns]
        out.append(_row([scene, *cells]))
    return out


def page_tables(f: dict) -> dict[str, list[str]]:
    """Every table of the page (name -> Markdown lines) from a run's findings."""
    return {
        "savings": savings_table(f),
        "savings_exp": savings_table(f, "_exp"),
        "avsm_exp_over_linear": ratio_table(f, "rmse_ratio_avsm_exp_over_linear", (2, 4, 8, 16, 32, 64), False),
        "adaptive_over_avsm_exp": ratio_table(f, "rmse_ratio_adaptive_over_avsm_exp", (2, 4, 8, 16)),
        "by_order": by_order_table(f, "bytes_saved_at_equal_rmse_by_order"),
        "by_order_exp": by_order_table(f, "bytes_saved_at_equal_rmse_by_order_exp"),
        "exp_over_linear_claims": exp_over_linear_claims_table(f),
        "dense_baseline": single_savings_table(f, "bytes_saved_at_equal_rmse_dense_baseline"),
        "uniform_allocation": single_savings_table(f, "bytes_saved_at_equal_rmse_uniform_allocation"),
        "adaptive_over_uniform": ratio_table(f, "rmse_ratio_adaptive_over_adaptive_uniform", (2, 4, 8, 16)),
        "adaptive_over_avsm": ratio_table(f, "rmse_ratio_adaptive_over_avsm", (2, 4, 8, 16)),
        "others": others_table(f),
    }


def with_scenes(f: dict, meta: dict) -> dict:
    """``f`` with ``scenes``: the run's scenes in its order (``meta['params']['scenes']``)."""
    return dict(f, scenes=list(meta["params"]["scenes"]))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m experiments.memory_budget.tables",
                                 description=__doc__.split("::")[0])
    ap.add_argument("run_dir", help="a memory_budget run's folder (data.csv, findings.json, meta.json; gzip allowed)")
    a = ap.parse_args(argv)
    _, f, meta = load(a.run_dir)
    for name, lines in page_tables(with_scenes(f, meta)).items():
        print(f"<!-- {name} -->")
        print("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
