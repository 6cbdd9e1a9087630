"""Which kind, at N bytes per texel, for your volume, and how wrong is it.

``python -m experiments budget --volume my.vol --bytes 32`` captures your volume (a Mitsuba
``.vol`` or a NumPy ``.npy`` grid of extinction, :meth:`avsm_dr.Scene.from_grid`; without
``--volume`` the built-in plume) into a shadow map and, for every registered kind, tries its
settings: the values of its size parameter (nodes, harmonics, slices, moments, tolerance, ...;
the registry's sweep, ``describe(kind)['sweep']``, or its short ``quick_sweep`` with
``--quick``, plus the largest value the budget allows) on top of the kind's preset parameters
(``describe(kind)['preset']``); kinds without a size parameter (beer, exact) try the registry's
examples.  Bytes are the sparse layout, ``rep.nbytes_sparse_per_texel`` (an occupancy bit per
texel, each non-empty texel's payload, a CSR offset for variable-size kinds), measured on the
map itself and taken as the largest over the configurations: a setting fits when that is at
most ``--bytes``.  Settings are screened by their bytes at the largest occupancy over the
configurations (variable-size kinds: built on the first configuration's map); those that fit
(and the next one that does not, to show the curve crossing the budget) are measured.

Per kind the chosen setting is the fitting one with the lowest measured receiver RMSE (not
simply the largest that fits).  Error: RMS of T_rep - T at receivers in the medium (drawn by
their contribution to an image), T the float64 ground truth, bilinear lookups
(:func:`avsm_dr.evaluation.evaluate`); the RMSE is pooled over configurations (seed x light:
at least 4 in a full run; 2 with ``--quick``, whose results are then marked indicative) with a
95 % bootstrap interval whose unit is the configuration.  Beside it: ``depth_l2`` (the whole
curve against the exact one, every depth alike), the map floor (the ``exact`` kind's RMSE on
the same map: what resolution and capture cost before any compression), and build and lookup
wall times in the first configuration (after a warm-up call; a lookup is one batch of the
receivers).  Kinds that
fit in no setting are listed as such.  The run ends with a short table.

Fair-comparison columns: ``order`` (the capture's, 'depth', for the kinds whose build depends on
it; '-' otherwise), ``signed_mean`` and ``leak_share`` (error > 0.02) at the receivers, mean
over configurations, beside ``rmse`` and ``depth_l2``; the summary names the setting of least
``depth_l2`` too and ``metric_dependent`` when it is not the setting of least RMSE.  The
choice itself stays by receiver RMSE (the shadows a viewer sees).
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np

from avsm_dr import allows, build, describe, kinds
from avsm_dr.representations import REGISTRY
from ._study import Option, Study

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    "The guide's budget page (docs/budget.md): which kind, at a given number of sparse bytes per "
    "texel, for your own volume, with its receiver RMSE against ground truth, depth_l2 and the map floor."
)

#: Built-in scene used when no --volume is given.
DEFAULT_SCENE = "plume"
#: Largest size value searched for kinds whose schema has a larger (or no) maximum.
MAX_SIZE_VALUE = 256
#: Configurations below which results are marked indicative (as ``evaluation.compare``).
MIN_CONFIGURATIONS = 4
#: Names of the configuration lights (:data:`avsm_dr.evaluation.LIGHTS`).
LIGHT_NAMES = ("dir_a", "dir_b", "spot")

#: Parameters of the full and the quick run.
FULL = dict(volume=None, bytes=32.0, box=None, density_scale=1.0, light=["dir_a", "dir_b"], configurations=4,
            resolution=256, n_receivers=2048, n_decomp=256, sweep="sweep", beyond=1)
QUICK = dict(FULL, light=["dir_a"], configurations=2, resolution=64, n_receivers=256, n_decomp=64,
             sweep="quick_sweep")

OPTIONS = (
    Option("volume", "your volume: a Mitsuba .vol or a NumPy .npy (nz, ny, nx) grid of extinction per world "
           "unit (default: the built-in plume scene)", metavar="FILE"),
    Option("bytes", "the budget: sparse bytes per texel (rep.nbytes_sparse_per_texel), > 0 (default 32)",
           type=float, metavar="B"),
    Option("box", "world box of the whole grid, min then max corner (default: the .vol header's box, else "
           "voxels of side 1 centred at the origin)", type=float, nargs=6,
           metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1")),
    Option("density_scale", "factor the grid is multiplied by (extinction = S x value; default 1)", type=float,
           metavar="S"),
    Option("light", "configuration light(s): dir_a (the scene's own: from above for a grid), dir_b (it tilted "
           "25 degrees), spot, or a direction x,y,z (default: dir_a dir_b; --quick: dir_a)", nargs="+",
           metavar="LIGHT"),
    Option("resolution", "shadow-map texels per side (default 256; --quick: 64)", type=int, metavar="R"),
)


# ====================================================================== inputs
def _file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _finite(value, option: str, positive: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"--{option}: expected a number, got {value!r}") from None
    if isinstance(value, bool) or not math.isfinite(v) or (positive and v <= 0):
        raise ValueError(f"--{option}: expected a finite number{' > 0' if positive else ''}, got {value!r}")
    return v


def _parse_light(value):
    """A light name of :data:`LIGHT_NAMES`, or a DirectionalLight from ``'x,y,z'``."""
    from avsm_dr.scene import DirectionalLight
    if value in LIGHT_NAMES:
        return value
    parts = str(value).split(",")
    try:
        d = np.array([float(p) for p in parts], np.float64)
    except ValueError:
        d = None
    if d is None or d.shape != (3,) or not np.all(np.isfinite(d)) or not np.any(d):
        raise ValueError(f"--light: expected {', '.join(LIGHT_NAMES)} or a direction x,y,z (not all zero), "
                         f"got {value!r}")
    return DirectionalLight(direction=tuple(d / np.linalg.norm(d)))


def _resolve(P: dict, quick: bool) -> dict:
    """Check the options (ValueError naming the option) and fix the configurations."""
    P["bytes"] = _finite(P["bytes"], "bytes", positive=True)
    P["density_scale"] = _finite(P["density_scale"], "density-scale", positive=True)
    if P["box"] is not None:
        box = P["box"]
        if isinstance(box, (str, bytes)) or not hasattr(box, "__len__") or len(box) != 6:
            raise ValueError(f"--box: expected 6 numbers X0 Y0 Z0 X1 Y1 Z1, got {box!r}")
        box = [_finite(v, "box") for v in box]
        if not all(box[i + 3] > box[i] for i in range(3)):
            raise ValueError(f"--box: expected X1 > X0, Y1 > Y0 and Z1 > Z0, got {box[:3]} .. {box[3:]}")
        P["box"] = box
    if P["volume"] is None:
        if P["box"] is not None or P["density_scale"] != 1.0:
            raise ValueError("--box / --density-scale: they place and scale --volume; give a --volume file")
        P["volume_sha256"] = None
    else:
        path = Path(str(P["volume"])).expanduser()
        if not str(P["volume"]).strip() or not path.is_file():
            raise ValueError(f"--volume: no such file {str(P['volume'])!r}")
        if path.suffix.lower() not in (".vol", ".npy"):
            raise ValueError(f"--volume: expected a .vol or .npy file, got {str(P['volume'])!r}")
        P["volume"] = str(path.resolve())
        P["volume_sha256"] = _file_sha256(path)           # keys the results cache on the content
    lights = P["light"]
    lights = [lights] if isinstance(lights, str) else list(lights or [])
    if not lights:
        raise ValueError("--light: no light given")
    for li in lights:
        _parse_light(li)
    P["light"] = [str(li) for li in lights]
    P["resolution"] = int(_finite(P["resolution"], "resolution", positive=True))
    if not 8 <= P["resolution"] <= 4096:
        raise ValueError(f"--resolution: expected an integer in [8, 4096], got {P['resolution']}")
    n = int(P["configurations"])
    P["seeds"] = max(1, math.ceil(n / len(lights)))
    _scene(P)                                              # a file that is no volume fails here, in one line
    return P


def _scene(P: dict):
    """The built-in scene's name, or your volume as a Scene."""
    if P["volume"] is None:
        return DEFAULT_SCENE
    from avsm_dr.scene import Scene
    box = None if P["box"] is None else (P["box"][:3], P["box"][3:])
    try:
        return Scene.from_grid(P["volume"], bbox=box, density_scale=P["density_scale"])
    except (ValueError, OSError) as exc:
        raise ValueError(f"--volume: {Path(P['volume']).name}: {' '.join(str(exc).split())}") from None


def _configurations(P: dict):
    from avsm_dr import evaluation
    return evaluation.configurations(seeds=P["seeds"], lights=[_parse_light(li) for li in P["light"]])


def _first_capture(spec, cfg, resolution):
    """The first configuration's capture, as ``evaluate`` makes it (depth order)."""
    return cfg.capture(spec, resolution)[1]


def _occupancy(cap) -> float:
    """Share of the map's texels that hold a segment."""
    counts = np.asarray(cap.segments.counts)
    return float(np.count_nonzero(counts)) / max(counts.size, 1)


# ====================================================================== settings
def _fmt(v) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def setting_text(kind: str, params: dict) -> str:
    """A setting as text: its size value (``nodes=8``), or the parameters that differ from
    the kind's preset (``variant=two_node``); ``-`` for none."""
    d = describe(kind)
    if d["size"]:
        return f"{d['size']}={_fmt(params[d['size']])}"
    base = {**d["headline"], **d["preset"]}
    diff = {k: v for k, v in params.items() if base.get(k, object()) != v}
    shown = diff or {k: v for k, v in params.items() if k in d["headline"]}
    return " ".join(f"{k}={_fmt(v)}" for k, v in shown.items()) or "-"


_TOY_BYTES: dict = {}


def _toy_bytes(kind: str, params: dict) -> float:
    """Dense bytes per texel of a fixed-size kind (built once per setting on a one-segment map)."""
    key = (kind, json.dumps(params, sort_keys=True))
    if key not in _TOY_BYTES:
        from avsm_dr import Segments
        toy = Segments.from_arrays(np.array([0, 1]), np.array([0.2]), np.array([0.4]), optical_depth=np.array([0.5]))
        _TOY_BYTES[key] = float(build(kind, toy, **params).nbytes_per_texel)
    return _TOY_BYTES[key]


def _largest_fitting(kind: str, base: dict, occupied: float, budget: float):
    """The largest integer size value whose estimated sparse bytes, ``1/8 + occupied x dense``,
    fit ``budget`` (fixed-size kinds; bytes grow with the value), or None."""
    d = describe(kind)
    spec = d["params"][d["size"]]
    lo, hi = int(spec["min"] or 1), min(int(spec["max"] or MAX_SIZE_VALUE), MAX_SIZE_VALUE)
    values = [v for v in range(lo, hi + 1) if allows(kind, dict(base, **{d["size"]: v}))]
    fits = lambda v: 0.125 + occupied * _toy_bytes(kind, dict(base, **{d["size"]: v})) <= budget  # noqa: E731
    if not values or not fits(values[0]):
        return None
    a, b = 0, len(values) - 1                    # values[a] fits; find the last that does
    while a < b:
        m = (a + b + 1) // 2
        a, b = (m, b) if fits(values[m]) else (a, m - 1)
    return values[a]


def candidates(kind: str, P: dict, occupied: float) -> list[dict]:
    """Parameters of every setting of ``kind`` to screen: its preset with each value of the
    registry's sweep (``P['sweep']``: 'sweep' or 'quick_sweep') and the largest value the
    budget allows; kinds without a size parameter: the registry's examples (or the preset)."""
    d = describe(kind)
    base = {**d["headline"], **d["preset"]}
    if not d["size"]:
        out = [{**base, **e} for e in d["examples"]] or [base]
    else:
        size, spec = d["size"], d["params"][d["size"]]
        values = list(d[P["sweep"]]) or [d["headline"][size]]
        if spec["type"] == "int" and not REGISTRY[kind].variable_size:
            v = _largest_fitting(kind, base, occupied, P["bytes"])
            values += [v] if v is not None else []
        elif "bytes" in size and spec["type"] == "float":       # a size that is itself a byte target
            values.append(float(min(max(P["bytes"], spec["min"] or 0.0), spec["max"] or P["bytes"])))
        out = [{**base, size: v} for v in values if allows(kind, {**base, size: v})]
    unique = []
    for p in out:
        if p not in unique:
            unique.append(p)
    return unique


def _screen(cap, P, occupied=None) -> tuple[list[dict], list[dict]]:
    """Every candidate setting with its sparse bytes, and which of them are measured: those
    that fit and the ``beyond`` smallest that do not; and the settings the kind refuses on
    this map (e.g. a byte target below what it needs).  Fixed-size kinds: ``1/8 + occupied x
    dense`` with ``occupied`` the largest share of occupied texels over the configurations
    (default: the first configuration's, ``cap``), exact where bytes are counted as the
    largest over configurations; variable-size kinds: built on the first configuration's map."""
    seg = cap.segments
    occupied = _occupancy(cap) if occupied is None else occupied
    out, refused = [], []
    for kind in kinds():
        cls = REGISTRY[kind]
        screened = []
        for p in candidates(kind, P, occupied):
            if cls.variable_size:
                try:
                    b = float(build(kind, seg, **p).nbytes_sparse_per_texel)
                except ValueError as exc:
                    refused.append(dict(kind=kind, setting=setting_text(kind, p), reason=" ".join(str(exc).split())))
                    continue
            else:
                b = 0.125 + occupied * _toy_bytes(kind, p)
            screened.append(dict(kind=kind, params=p, setting=setting_text(kind, p), screened_bytes=b))
        screened.sort(key=lambda s: s["screened_bytes"])
        if kind == "exact":                     # the map floor: always measured
            out += screened
            continue
        fit = [s for s in screened if s["screened_bytes"] <= P["bytes"]]
        over = [s for s in screened if s["screened_bytes"] > P["bytes"]][:P["beyond"]]
        out += fit + over
    return out, refused


def screen_configurations(spec, cfgs, P) -> tuple[list[dict], list[dict]]:
    """:func:`_screen` at the largest occupancy over the configurations ``cfgs``: measured
    bytes are the largest over them, and the first map's occupancy alone put AVSM-16 on the
    plume at 31.1 B (33.1 B in another configuration), so the budget's largest value
    (AVSM-15) was never tried."""
    cap = _first_capture(spec, cfgs[0], P["resolution"])
    occupied = max([_occupancy(cap)] + [_occupancy(_first_capture(spec, c, P["resolution"])) for c in cfgs[1:]])
    return _screen(cap, P, occupied)


def _evaluate(methods: dict, spec, cfgs, **kw) -> tuple[list[dict], list[str]]:
    """``evaluation.evaluate`` rows; a method whose build is refused in some configuration (a
    variable-size kind whose byte target that map cannot meet) is measured nowhere and
    returned in the second list."""
    from avsm_dr import evaluation
    try:
        return list(evaluation.evaluate(methods, [spec], cfgs, **kw)), []
    except ValueError:
        pass
    rows, dropped = [], []
    for label, m in methods.items():                    # one at a time: find the method refused
        try:
            rows += list(evaluation.evaluate({label: m}, [spec], cfgs, progress=False, **kw))
        except ValueError:
            dropped.append(label)
    return rows, dropped


# ====================================================================== the study
def _aggregate(rows: list[dict], budget: float, n_cfg: int) -> dict:
    """One method's rows (one per configuration) -> its line of data.csv."""
    from avsm_dr.stats import bootstrap_ci
    rmse = np.array([r["rmse"] for r in rows], np.float64)
    if rmse.size >= 2 and np.all(np.isfinite(rmse)):
        ci = bootstrap_ci(rmse, "rmse", seed=0)
        est, low, high = ci["estimate"], ci["low"], ci["high"]
    else:
        est, low, high = float(np.sqrt(np.mean(rmse ** 2))), float("nan"), float("nan")
    byts = np.array([r["bytes"] for r in rows], np.float64)
    l2 = np.array([r["depth_l2"] for r in rows], np.float64)
    first = rows[0]
    from .error_curves.labels import order_dependent
    kind_order = first["order"] if first["kind"] in kinds() and order_dependent(first["kind"]) else "-"
    timed = next((r for r in rows if np.isfinite(r["build_s"])), first)     # the first configuration
    return dict(kind=first["kind"], setting=first["setting"], params=json.dumps(first["params"], sort_keys=True),
                bytes=float(byts.max()), bytes_mean=float(byts.mean()), bytes_dense=float(first["bytes_dense"]),
                fits=bool(byts.max() <= budget), rmse=float(est), rmse_low=float(low), rmse_high=float(high),
                configurations=len(rows), indicative=n_cfg < MIN_CONFIGURATIONS,
                depth_l2=float(np.sqrt(np.mean(l2 ** 2))), order=kind_order,
                signed_mean=float(np.mean([r["signed_mean"] for r in rows])),
                leak_share=float(np.mean([r["leak_share"] for r in rows])),
                build_ms=timed["build_s"] * 1e3, lookup_ms=timed["lookup_s"] * 1e3,
                lookup_ns_per_receiver=timed["lookup_s"] / max(timed["n_receivers"], 1) * 1e9,
                nonfinite=int(sum(r["nonfinite"] for r in rows)), screened_bytes=float(first["screened_bytes"]))


def _compute(res, P: dict) -> dict:
    spec = _scene(P)
    cfgs = _configurations(P)
    tried, refused = screen_configurations(spec, cfgs, P)
    methods = {f"{s['kind']} {s['setting']}": (s["kind"], s["params"]) for s in tried}
    info = {f"{s['kind']} {s['setting']}": s for s in tried}
    kw = dict(receivers=("in_volume",), resolution=P["resolution"], order="depth", n_volume=P["n_receivers"],
              n_decomp=P["n_decomp"])
    # build and lookup timed in the first configuration only (a timed build runs twice: warm-up,
    # then timed); the others measure the error alone
    table, dropped = _evaluate(methods, spec, cfgs[:1], **kw)
    if len(cfgs) > 1:
        more, dropped2 = _evaluate(methods, spec, cfgs[1:], metrics=("receiver_rmse", "depth_l2"), **kw)
        table += more
        dropped += dropped2
    for label in dropped:
        s = info[label]
        refused.append(dict(kind=s["kind"], setting=s["setting"], reason="refused in another configuration's map"))
    per_config, by_method = [], {}
    for r in table:
        if r["method"] in dropped:
            continue
        s = info[r["method"]]
        row = dict(kind=r["kind"], setting=s["setting"], params=s["params"], screened_bytes=s["screened_bytes"],
                   **{k: r[k] for k in ("seed", "light", "order", "n_receivers", "rmse", "depth_l2", "bytes",
                                        "bytes_dense", "signed_mean", "leak_share", "p99", "max", "nonfinite",
                                        "build_s", "lookup_s")})
        by_method.setdefault(r["method"], []).append(row)
        per_config.append(dict(row, params=json.dumps(s["params"], sort_keys=True)))
    n_cfg = len(cfgs)
    rows = [_aggregate(v, P["bytes"], n_cfg) for v in by_method.values()]
    floor = next(r for r in rows if r["kind"] == "exact")
    for r in rows:
        r["map_floor"] = floor["rmse"]
        r["rmse_over_floor"] = r["rmse"] / floor["rmse"] if floor["rmse"] > 0 else float("nan")
    best = _choose(rows, P["bytes"], refused)
    chosen = {(b["kind"], b["setting"]) for b in best if b["status"] == "chosen"}
    for r in rows:
        r["chosen"] = (r["kind"], r["setting"]) in chosen
    name = spec if isinstance(spec, str) else spec.name
    shape = None if isinstance(spec, str) else "x".join(str(n) for n in spec.meta["shape"])
    text = table_text(best, P, name, shape, n_cfg, res.dir)
    res.write_text("table.txt", text + "\n")
    _plot(res, rows, best, P, name, n_cfg)
    fitting = [b for b in best if b["status"] == "chosen"]
    top = fitting[0] if fitting else None
    # the same choice by the depth-uniform L2: the fitting setting of least depth_l2
    top_l2 = min((r for r in rows if r["kind"] != "exact" and r["fits"] and np.isfinite(r["depth_l2"])),
                 key=lambda r: (r["depth_l2"], r["bytes"]), default=None)
    summary = {
        "volume": P["volume"] or f"built-in scene {DEFAULT_SCENE!r}",
        "budget": f"{P['bytes']:g} sparse bytes per texel",
        "configurations": f"{n_cfg} (seed x light)" + (f"; indicative: fewer than {MIN_CONFIGURATIONS}"
                                                        if n_cfg < MIN_CONFIGURATIONS else ""),
        "lowest_rmse": (f"{top['kind']} {top['setting']}: {top['rmse']:.4g} at {top['bytes']:.3g} B" if top
                        else "no kind fits"),
        "lowest_depth_l2": (f"{top_l2['kind']} {top_l2['setting']}: {top_l2['depth_l2']:.4g} at {top_l2['bytes']:.3g} B"
                            if top_l2 else "no kind fits"),
        # the two metrics choose different settings (kind or setting)
        "metric_dependent": bool(top and top_l2 and (top["kind"], top["setting"]) != (top_l2["kind"],
                                                                                       top_l2["setting"])),
        "map_floor_rmse": floor["rmse"],
        "kinds_that_do_not_fit": ", ".join(b["kind"] for b in best if b["status"] != "chosen") or "none",
        "settings_measured": len(rows),
        "settings_refused": len(refused),
    }
    return dict(rows=rows, tables={"best.csv": best, "configurations.csv": per_config}, summary=summary,
                findings={"summary": summary, "refused": refused},
                result={"table": text})


def _choose(rows: list[dict], budget: float, refused=()) -> list[dict]:
    """Per kind the fitting setting with the lowest RMSE (ties: fewer bytes), or a line saying
    it does not fit (with its smallest bytes, or why every setting was refused); best first."""
    out = []
    for kind in dict.fromkeys(r["kind"] for r in rows):
        mine = [r for r in rows if r["kind"] == kind]
        fit = [r for r in mine if r["fits"]]
        if fit:
            r = min(fit, key=lambda r: (r["rmse"], r["bytes"]))
            out.append(dict(r, status="chosen"))
        else:
            r = min(mine, key=lambda r: r["bytes"])
            out.append(dict(r, status=f"does not fit (smallest measured: {r['bytes']:.3g} B)"))
    out.sort(key=lambda b: (b["status"] != "chosen", b["rmse"] if b["status"] == "chosen" else b["bytes"]))
    for kind in dict.fromkeys(r["kind"] for r in refused):
        if kind not in {b["kind"] for b in out}:
            why = next(r["reason"] for r in refused if r["kind"] == kind)
            out.append(dict(dict.fromkeys(BEST_COLUMNS, float("nan")), kind=kind, setting="", params="",
                            status=f"does not fit (every setting refused on this map: {why})"))
    return [{k: b[k] for k in BEST_COLUMNS} for b in out]


#: Columns of best.csv.
BEST_COLUMNS = ("kind", "status", "setting", "params", "order", "bytes", "bytes_mean", "bytes_dense", "rmse",
                "rmse_low", "rmse_high", "configurations", "indicative", "depth_l2", "signed_mean", "leak_share",
                "map_floor", "rmse_over_floor", "build_ms", "lookup_ms", "lookup_ns_per_receiver", "nonfinite")


def _ms(v: float) -> str:
    """Milliseconds in 3 significant digits, without an exponent."""
    return f"{v:.0f}" if v >= 1000 else f"{v:.3g}"


def table_text(best: list[dict], P: dict, name: str, shape: str | None, n_cfg: int, folder) -> str:
    """The table a run ends with (also ``table.txt``)."""
    what = f"volume {name}" + (f" ({shape} voxels)" if shape else "")
    note = f"; INDICATIVE: fewer than {MIN_CONFIGURATIONS}" if n_cfg < MIN_CONFIGURATIONS else ""
    n_rec = P["n_receivers"]
    lines = [f"budget {P['bytes']:g} B per texel (sparse), {what}, {P['resolution']}^2 map, "
             f"{n_cfg} configuration{'s' if n_cfg != 1 else ''} (seed x light){note}",
             f"{'kind':<14} {'setting':<20} {'bytes':>6}  {'rmse [95% interval]':<28} {'depth_l2':>8} "
             f"{'map floor':>9} {'build ms':>8} {'lookup ms':>9}"]
    for b in best:
        if b["status"] != "chosen":
            lines.append(f"{b['kind']:<14} {b['status']}")
            continue
        iv = (f"[{b['rmse_low']:.3g}, {b['rmse_high']:.3g}]" if math.isfinite(b["rmse_low"]) else "[no interval]")
        cell = f"{b['rmse']:.3g} {iv}"
        lines.append(f"{b['kind']:<14} {b['setting']:<20} {b['bytes']:>6.3g}  {cell:<28} "
                     f"{b['depth_l2']:>8.3g} {b['map_floor']:>9.3g} {_ms(b['build_ms']):>8} {_ms(b['lookup_ms']):>9}")
    lines.append(f"rmse: vs float64 truth at {n_rec} receivers in the medium, pooled over configurations; map floor: "
                 f"the exact kind's rmse; lookup ms: one batch of {n_rec} receivers")
    lines.append(f"files: {Path(folder)}/ (best.csv, data.csv: every setting tried, configurations.csv, "
                 f"error_vs_bytes.png)")
    return "\n".join(lines)


def _plot(res, rows, best, P, name, n_cfg):
    """RMSE against sparse bytes, one panel per family of kinds: the budget (vertical) and
    the map floor (horizontal), the chosen setting ringed."""
    import matplotlib
    matplotlib.use("Agg")
    from . import _plotstyle as plotstyle
    floor = next(r for r in rows if r["kind"] == "exact")
    fams = {f: ks for f, ks in plotstyle.families(list(dict.fromkeys(r["kind"] for r in rows))).items()
            if ks != ["exact"]}
    chosen = {b["kind"]: b for b in best if b["status"] == "chosen"}
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullLocator
    shown = [r for r in rows if r["kind"] != "exact"]
    finite = [r["rmse"] for r in shown if np.isfinite(r["rmse"]) and r["rmse"] > 0] + [floor["rmse"]]
    ylo, yhi = min(finite) / 1.6, max(finite) * 1.6
    xs = [r["bytes"] for r in shown if r["bytes"] > 0] + [P["bytes"]]
    xlo, xhi = min(xs) / 1.25, max(xs) * 1.25
    xticks = [2.0 ** k for k in range(math.floor(math.log2(xlo)), math.ceil(math.log2(xhi)) + 1)]
    ncol = min(len(fams), 2)
    nrow = math.ceil(len(fams) / ncol)
    with plotstyle.context():
        fig, axes = plotstyle.grid(nrow, ncol, panel=(3.4, 2.5))
        for ax in axes.flat[len(fams):]:
            ax.set_visible(False)
        for ax, (fam, ks) in zip(axes.flat, fams.items()):
            ax.axvline(P["bytes"], color="0.35", lw=1.0, ls="--", zorder=1)
            ax.axhline(floor["rmse"], color="k", lw=0.9, ls=":", zorder=1)
            for kind in ks:
                mine = sorted((r for r in rows if r["kind"] == kind), key=lambda r: r["bytes"])
                x = np.array([r["bytes"] for r in mine])
                y = np.array([r["rmse"] for r in mine])
                lo = np.array([r["rmse_low"] for r in mine])
                hi = np.array([r["rmse_high"] for r in mine])
                err = np.vstack([np.where(np.isfinite(lo), y - lo, 0), np.where(np.isfinite(hi), hi - y, 0)])
                st = plotstyle.style(kind)
                label = f"{kind}: {chosen[kind]['setting']}" if kind in chosen else f"{kind}: does not fit"
                ax.errorbar(x, y, yerr=np.clip(err, 0, None), capsize=1.5, label=label, **st)
                if kind in chosen:
                    c = chosen[kind]
                    ax.plot([c["bytes"]], [c["rmse"]], marker="o", ms=10, mfc="none", mec=st["color"], mew=1.2,
                            ls="none")
            ax.set_xscale("log", base=2)
            ax.set_yscale("log")
            ax.set_xlim(xlo, xhi)
            ax.set_ylim(ylo, yhi)
            ax.xaxis.set_major_locator(FixedLocator(xticks))
            ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            ax.xaxis.set_minor_locator(NullLocator())
            ax.set_title(fam)
        for ax in axes[-1]:
            ax.set_xlabel("sparse bytes per texel (log scale)")
        for ax in axes[:, 0]:
            ax.set_ylabel("receiver RMSE (log scale)")
        from matplotlib.lines import Line2D
        keys = [Line2D([], [], color="0.35", lw=1.0, ls="--", label=f"budget {P['bytes']:g} B"),
                Line2D([], [], color="k", lw=0.9, ls=":", label=f"map floor (exact, {floor['rmse']:.3g})"),
                Line2D([], [], marker="o", ms=8, mfc="none", mec="0.3", ls="none",
                       label="ringed: chosen (lowest RMSE that fits)")]
        seen = {}
        for ax in axes.flat:
            for h, lab in zip(*ax.get_legend_handles_labels()):
                seen.setdefault(lab, h)
        plotstyle.legend_below(fig, handles=list(seen.values()) + keys,
                               labels=list(seen) + [k.get_label() for k in keys], ncol=3)
        note = f", {n_cfg} configurations" + (" (indicative)" if n_cfg < MIN_CONFIGURATIONS else "")
        fig.suptitle(f"{name}, {P['resolution']}$^2$ map{note}: error against bytes")
        res.save_figure(fig, "error_vs_bytes.png")


class _BudgetStudy(Study):
    """The study, whose run ends with its table (``table.txt``) on standard output."""

    def run(self, quick: bool = False, out=None, force: bool = False, **options) -> dict:
        result = super().run(quick=quick, out=out, force=force, **options)
        path = Path(result["out"]) / "table.txt"
        text = path.read_text().rstrip("\n") if path.is_file() else result.get("table", "")
        print(text, flush=True)
        result["table"] = text
        return result


STUDY = _BudgetStudy("budget", "Which kind at N bytes per texel for your volume, and how wrong it is",
                     REPRODUCES, FULL, QUICK, _compute,
                     writes=("data.csv (every setting tried)", "best.csv (the chosen setting per kind)",
                             "configurations.csv (every setting per configuration)", "table.txt (the printed table)",
                             "findings.json (the summary; settings a kind refused on this map, and why)",
                             "error_vs_bytes.png (RMSE against bytes per kind; PDF beside it)"),
                     options=OPTIONS, resolve=lambda P, quick: _resolve(P, quick))
run = STUDY.run
