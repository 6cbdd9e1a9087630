"""Markdown tables of an ``insertion_order`` run's worst-order ratios to ``optimal``.

    python scripts/insertion_order_table.py RUN [METHOD ...] > tables.md

``RUN`` is the study's output folder (``findings.json`` or ``findings.json.gz``); the methods
default to stream ``avsm``, ``avsm_spare_exp`` and ``avsm_spare_exp_fit``.  Per scene and N,
for each method: the worst order's geometric mean over configurations of the ratio to
``optimal`` with its 95 % bootstrap interval over configurations (both from
``findings.json``; the worst order in brackets), first for the depth-uniform L2 (the worst
order by depth L2: ``goal``'s ``worst_ratio`` / ``worst_order``), then for the receiver RMSE
(the worst order by receiver RMSE); then each non-stream method's build and kernel time
ratios to stream AVSM (``goal``'s ``build_ratio`` / ``kernel_ratio``: geometric means over
configurations and orders) and whether it meets the goal (``goal``'s ``met``: within 1.5x of
``optimal`` in every order and within 1.3x of the build time).  Standard library only.
"""
from __future__ import annotations

import gzip
import json
import sys
from pathlib import Path

ORDERS = ("submission", "depth", "reverse_depth", "random")
DEFAULT = ("avsm", "avsm_spare_exp", "avsm_spare_exp_fit")


def load(run: Path) -> dict:
    """The run's findings.json (plain or gzipped)."""
    plain, packed = run / "findings.json", run / "findings.json.gz"
    if plain.is_file():
        return json.loads(plain.read_text())
    if packed.is_file():
        with gzip.open(packed, "rt") as f:
            return json.load(f)
    raise ValueError(f"run: no findings.json(.gz) in {run}")


def worst(cell: dict, method: str, metric: str) -> tuple[str, dict]:
    """The order with the largest geometric-mean ratio of ``metric`` and its interval."""
    order = max(ORDERS, key=lambda o: cell[o][method][metric]["estimate"])
    return order, cell[order][method][metric]


def fmt(order: str, e: dict) -> str:
    return f"{e['estimate']:.2f} [{e['low']:.2f}, {e['high']:.2f}] ({order})"


def short(method: str) -> str:
    return "stream" if method == "avsm" else method.removeprefix("avsm_")


def tables(found: dict, methods: tuple[str, ...]) -> str:
    """The depth-L2 table (with build / kernel ratios and the goal) and the receiver-RMSE table."""
    timed = [m for m in methods if m != "avsm"]
    head = ["scene", "N"] + [short(m) for m in methods] + [f"{short(m)} build / kernel" for m in timed]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    rhead = ["scene", "N"] + [short(m) for m in methods]
    rlines = ["| " + " | ".join(rhead) + " |", "|" + "---|" * len(rhead)]
    for scene, per_n in found.items():
        for key in sorted(per_n, key=lambda k: int(k.removeprefix("N="))):
            cell, n = per_n[key], key.removeprefix("N=")
            row = [scene, n]
            for m in methods:
                order, e = worst(cell, m, "depth_l2")
                assert order == cell["goal"][m]["worst_order"]
                text = fmt(order, e)
                row.append(f"**{text}**" if cell["goal"][m]["met"] else text)
            row += [f"{cell['goal'][m]['build_ratio']:.2f} / {cell['goal'][m]['kernel_ratio']:.2f}" for m in timed]
            lines.append("| " + " | ".join(row) + " |")
            rlines.append("| " + " | ".join([scene, n] + [fmt(*worst(cell, m, "rmse")) for m in methods]) + " |")
    return "\n".join(["Depth L2 (bold: goal met)", "", *lines, "", "Receiver RMSE", "", *rlines, ""])


def main(argv: list[str]) -> None:
    if not argv:
        raise SystemExit(__doc__)
    found = load(Path(argv[0]))
    print(tables(found, tuple(argv[1:]) or DEFAULT))


if __name__ == "__main__":
    main(sys.argv[1:])
