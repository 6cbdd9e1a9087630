"""Shared plumbing for experiments: output folder, CSV/JSON writers, timing."""
from __future__ import annotations

import csv
import json
import platform
import statistics
import time
from pathlib import Path
from typing import Any, Callable, Iterable

import drjit as dr


class Results:
    """``results/<name>/`` with ``data.csv``, ``meta.json`` and figures."""

    def __init__(self, name: str, out: str | Path | None, quick: bool, params: dict[str, Any]):
        self.name = name
        self.dir = Path(out) if out is not None else Path("results") / name
        self.dir.mkdir(parents=True, exist_ok=True)
        self.quick = quick
        self.params = dict(params, quick=quick)
        self.figures: list[str] = []

    def exists(self, csv_name: str = "data.csv") -> bool:
        meta = self.dir / "meta.json"
        if not (self.dir / csv_name).exists() or not meta.exists():
            return False
        try:
            return json.loads(meta.read_text()).get("params") == json.loads(json.dumps(self.params, default=str))
        except (OSError, ValueError):
            return False

    def write_csv(self, rows: Iterable[dict], csv_name: str = "data.csv") -> Path:
        rows = list(rows)
        path = self.dir / csv_name
        fields: list[str] = []
        for r in rows:
            for k in r:
                if k not in fields:
                    fields.append(k)
        with path.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=fields)
            w.writeheader()
            for r in rows:
                w.writerow({k: _fmt(v) for k, v in r.items()})
        return path

    def save_figure(self, fig, filename: str) -> Path:
        path = self.dir / filename
        fig.savefig(path, dpi=110, bbox_inches="tight")
        import matplotlib.pyplot as plt
        plt.close(fig)
        self.figures.append(str(path))
        return path

    def write_meta(self, summary: dict | None = None) -> Path:
        from .. import backend
        meta = {
            "experiment": self.name,
            "params": self.params,
            "summary": summary or {},
            "figures": [Path(f).name for f in self.figures],
            "backend": backend.get_backend(),
            "drjit": dr.__version__,
            "machine": platform.platform(),
            "processor": platform.processor(),
        }
        path = self.dir / "meta.json"
        path.write_text(json.dumps(meta, indent=2, default=str))
        return path


def read_csv(path: str | Path) -> list[dict]:
    with Path(path).open() as fh:
        return list(csv.DictReader(fh))


def _fmt(v):
    if isinstance(v, float):
        return f"{v:.9g}"
    return v


def timed(fn: Callable[[], Any], repeats: int = 5, warmup: int = 1) -> tuple[float, float, Any]:
    """(median seconds after warm-up, first-call seconds incl. JIT compile, last result).

    Every call is followed by ``dr.eval`` + ``dr.sync_thread`` so lazy kernels are timed."""
    t0 = time.perf_counter()
    out = fn()
    sync(out)
    first = time.perf_counter() - t0
    for _ in range(max(warmup - 1, 0)):
        sync(fn())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        sync(out)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), first, out


def sync(out):
    """Evaluate ``out`` (if it holds Dr.Jit arrays) and wait for the device."""
    try:
        dr.eval(out)
    except Exception:
        pass
    dr.sync_thread()
