"""``evaluate``: methods x scenes x configurations x receiver sets -> one tidy :class:`Table`
(the steps of ``error_curves``: receivers drawn with the seed, a capture per resolution and
order, a :class:`~.probe.Probe` per receiver set).  The columns of a row:

=========================================  ==========================================================
method, kind                               the label given, the registered kind (or the class name)
params                                     the parameters given
scene, seed, light                         the configuration (light: its name or a description)
receivers, n_receivers                     the receiver set and its size
n_decomp                                   the receivers of the capture / spatial terms
order, resolution, opaque                  the capture: insertion order, texels per side, blockers
                                           'inline' or 'separate' (in their own depth map)
rmse                                       RMS of ``T_rep - T`` at the receivers (T: float64 truth)
compression_rms, capture_rms, spatial_rms  RMS of the terms of :mod:`.probe`: vs the exact curve,
                                           and capture / spatial on the first ``n_decomp`` receivers
signed_mean                                mean of ``T_rep - T`` (> 0: light leaking)
leak_share, dark_share                     shares of receivers with ``T_rep - T`` above +0.02 /
                                           below -0.02 (:data:`avsm_dr.metrics.THRESHOLD`)
p99, p99_9, max                            99th / 99.9th percentile and maximum of ``|T_rep - T|``
nonfinite                                  receivers with a NaN or inf estimate (left out above)
depth_l2                                   :func:`~.curves.depth_l2` over the map's non-empty texels
bytes                                      ``nbytes_sparse_per_texel`` (sparse layout, every kind alike)
bytes_dense                                ``nbytes_per_texel`` (dense: every texel stored)
build_s, lookup_s                          wall seconds of the build and of the row's lookups, median
                                           after one warm-up call (:func:`~.timing.measure`)
build_first_s                              the first build, JIT compilation included
=========================================  ==========================================================
"""
from __future__ import annotations

import collections
import inspect
from numbers import Integral

import drjit as dr
import numpy as np

from .. import builtin_scenes
from .. import validation as V
from ..capture import ORDERS as CAPTURE_ORDERS, capture
from ..capture.opaque_map import OPAQUE_MODES, compose
from ..metrics import THRESHOLD, error_stats
from ..receivers import BYTES_PER_POINT, receiver_sets
from ..receivers import NAMES as RECEIVER_SETS
from ..representations import REGISTRY, Representation, build, describe
from ..scene import Scene
from ..segments import Segments
from .configuration import Configuration
from .configuration import configurations as _configurations
from .curves import DEPTHS, curve_values, depth_l2, rms
from .probe import Built, Probe, SubsetBuilder
from .table import Table
from .timing import timed

#: Optional metric groups: the receiver statistics are always computed (every row is about
#: a receiver set); without 'depth_l2' or 'timing' that work is skipped and the columns are NaN.
METRICS = ("receiver_rmse", "depth_l2", "timing")
#: Receivers and taps of ``error_curves``' full mode (its quick mode: 512, 256, 128).
N_VOLUME, N_SURFACE, N_DECOMP = 4096, 1024, 512
#: Timed repeats of each lookup (after one warm-up call).
LOOKUP_REPEATS = 3


_Method = collections.namedtuple("_Method", "label cls params kind")


def _methods(methods) -> list[_Method]:
    if not isinstance(methods, dict) or not methods:
        raise ValueError(f"methods: expected a non-empty dict {{label: (kind, params)}}, got {methods!r}")
    toy = Segments.from_arrays([0, 1], [0.2], [0.4], optical_depth=[0.5])
    out = []
    for label, spec in methods.items():
        if not isinstance(label, str) or not label:
            raise ValueError(f"methods: labels must be non-empty strings, got {label!r}")
        pair = (spec, {}) if isinstance(spec, (str, type)) else spec
        kind, params = pair if isinstance(pair, (tuple, list)) and len(pair) == 2 else (None, None)
        preset = isinstance(params, str) and params == "preset"
        if not (preset or isinstance(params, dict)):
            raise ValueError(f"methods[{label!r}]: expected (kind, params dict or 'preset'), got {spec!r}")
        try:
            if isinstance(kind, str):
                describe(kind)
                cls, name = REGISTRY[kind], kind
            elif isinstance(kind, type) and issubclass(kind, Representation) and not inspect.isabstract(kind):
                cls = kind
                name = cls.kind if REGISTRY.get(cls.kind) is cls else cls.__name__
            else:
                raise ValueError(f"expected a kind name or a Representation subclass (with _eval_texels and "
                                 f"nbytes_per_texel), got {kind!r}")
            params = dict(cls.PRESET) if preset else params     # the kind's best practice (describe)
            cls(toy, **params)                                   # parameters checked before any capture
        except ValueError as exc:
            raise ValueError(f"methods[{label!r}]: {exc}") from None
        out.append(_Method(label, cls, dict(params), name))
    return out


def _scenes(scenes) -> list[tuple[str, object]]:
    known = builtin_scenes.SCENES
    out = []
    for s in _names(scenes, "scenes"):
        if not isinstance(s, (str, Scene)):
            raise ValueError(f"scenes: expected built-in scene names or Scene objects, got {s!r}")
        if isinstance(s, str) and s not in known:
            raise ValueError(f"scenes: unknown built-in scene {s!r}; known: {sorted(known)}"
                             f"{V.did_you_mean(s, known)}")
        out.append((s, s) if isinstance(s, str) else (s.name, s))
    names = [n for n, _ in out]
    if len(set(names)) != len(names):
        raise ValueError(f"scenes: two scenes share a name in {names} (give Scene objects distinct names)")
    return out


def _configs(configurations) -> list[Configuration]:
    if configurations is None:
        return _configurations()
    out = []
    for c in _names(configurations, "configurations"):
        if not (isinstance(c, Configuration) or isinstance(c, (tuple, list)) and len(c) == 2):
            raise ValueError(f"configurations: expected a list of Configuration or (seed, light) items, got {c!r}")
        out.append(c if isinstance(c, Configuration) else Configuration(*c))
    return out


def _names(value, name, choices=None) -> list:
    one = isinstance(value, (str, bytes, Integral)) or value is None or not hasattr(value, "__iter__")
    vals = [value] if one else list(value)
    if not vals:
        raise ValueError(f"{name}: none given")
    if choices is not None:
        for v in vals:
            V.one_of(v, name, choices)
    return vals


def _synced_build(cls, segments, params):
    """``cls(segments, **params)`` with its Dr.Jit buffers evaluated (lazy ones too)."""
    rep = cls(segments, **params)
    values = [x for v in vars(rep).values() for x in (v if isinstance(v, (list, tuple)) else [v])]
    arrays = [x for x in values if dr.is_array_v(x)]
    if arrays:
        dr.eval(*arrays)
    return rep


def _capture(scene, resolution, order, opaque, seed):
    """``ad.capture`` -> (capture, its recorded order); 'random' shuffles with ``seed``."""
    cap = capture(scene, resolution=resolution, opaque=opaque, order=order,
                  **({"order_seed": seed} if order == "random" else {}))
    return cap, cap.order


def _timed(fn, want: bool, repeats: int):
    """(result, median wall seconds, first-call seconds) of ``fn`` (:func:`~.timing.timed`);
    NaN times and one call when not ``want``."""
    if not want:
        return fn(), float("nan"), float("nan")
    wall, first, out = timed(fn, repeats)
    return out, wall, first


def _stats(probe, est, exact) -> dict:
    t = probe.terms(est, exact)
    s = error_stats(est, probe.truth, THRESHOLD)
    return dict(rmse=s["rmse"], compression_rms=rms(t["compression"]), capture_rms=rms(t["capture"]),
                spatial_rms=rms(t["spatial"]), signed_mean=s["mean_error"], leak_share=s["leak_fraction"],
                dark_share=s["dark_fraction"], p99=s["p99_error"], p99_9=s["p999_error"], max=s["max_error"],
                nonfinite=s["nan_count"] + s["inf_count"])


def evaluate(methods, scenes, configurations=None, receivers=("in_volume", "surface"), metrics=METRICS,
             resolution: int = 256, order="depth", *, n_volume: int = N_VOLUME, n_surface: int = N_SURFACE,
             n_decomp: int = N_DECOMP, opaque="inline", subset: bool = False, n_depths: int = DEPTHS,
             progress: bool = True) -> Table:
    """A :class:`Table` of one row (columns: module docstring) per method x scene x
    configuration x resolution x order x opaque mode x receiver set.

    methods: {label: (kind, params)}; kind a registered name or a
    :class:`~avsm_dr.Representation` subclass; ``label: kind`` alone means default
    parameters, ``(kind, "preset")`` the kind's ``describe(kind)["preset"]`` (its
    ``preset_capture`` is the caller's ``opaque=``).  scenes: built-in scene names and
    :class:`~avsm_dr.Scene` objects.  configurations: :class:`~.configuration.Configuration`
    items or (seed, light) pairs (default: seed 0, the scene's own light).  receivers: names
    of :data:`RECEIVER_SETS` (sets a scene cannot make are left out), or {name: (K, 3)
    points}.  metrics: names of :data:`METRICS`.

    resolution, order: texels per side of the light map; the capture's insertion order
    (``avsm_dr.capture.ORDERS``), default 'depth', not ad.capture's own 'submission';
    'random' shuffles with the configuration's seed.  Either may be a sequence: a row per
    value.  n_volume, n_surface: receivers per set; n_decomp: receivers of the capture /
    spatial terms.  opaque: 'inline' | 'separate' (or both; 'separate' only for scenes with
    blockers).  subset: build on the texels the receivers touch only
    (:class:`~.probe.SubsetBuilder`); ``bytes`` and ``depth_l2`` then cover those texels.
    n_depths: depths per texel of ``depth_l2``.  progress: a progress bar over the cells."""
    meths, scs, cfgs = _methods(methods), _scenes(scenes), _configs(configurations)
    fixed = {k: V.points(v, f"receivers[{k!r}]") for k, v in receivers.items()} if isinstance(receivers, dict) \
        else None
    if fixed is None:
        receivers = _names(receivers, "receivers", RECEIVER_SETS)
    metrics = _names(metrics, "metrics", METRICS)
    resolutions = [V.integer(r, "resolution", 1) for r in _names(resolution, "resolution")]
    orders = _names(order, "order", CAPTURE_ORDERS)
    modes = _names(opaque, "opaque", OPAQUE_MODES)
    for v, name in ((n_volume, "n_volume"), (n_surface, "n_surface"), (n_decomp, "n_decomp")):
        V.integer(v, name, 0)
        V.check_memory(name, int(v), lambda m: float(m) * BYTES_PER_POINT, lo=0, what="receivers")
    V.integer(n_depths, "n_depths", 1)
    want_l2, want_time = "depth_l2" in metrics, "timing" in metrics

    from tqdm import tqdm
    rows: list[dict] = []
    cells = [(s, c) for s in scs for c in cfgs]
    for (label, spec), cfg in tqdm(cells, desc="evaluate", unit="cell", disable=not progress):
        scene = cfg.scene(spec)                  # a built-in one regenerated with the seed
        points = fixed if fixed is not None else receiver_sets(scene, n_volume, n_surface, cfg.seed, names=receivers)
        if not points:
            raise ValueError(f"receivers: scene {label!r} has none of the receiver sets {list(receivers)}")
        truth = {}
        for res in resolutions:
            probes = None
            for o in orders:
                for mode in modes:
                    if mode == "separate" and not scene.blockers:
                        continue
                    cap, order_label = _capture(scene, res, o, mode, cfg.seed)
                    if probes is None:           # taps and truth of the first capture, shared
                        probes = {s: Probe(cap, scene, p, n_decomp, truth.get(s)) for s, p in points.items()}
                        truth = {s: p.truth for s, p in probes.items()}
                    pr = {s: p.with_capture(cap) for s, p in probes.items()}
                    head = dict(scene=label, seed=cfg.seed, light=cfg.light_label, order=order_label,
                                resolution=res, opaque=mode)
                    rows += _run_capture(meths, cap, pr, head, subset, want_l2, want_time, n_depths)
    return Table(rows)


def _run_capture(meths, cap, probes, head, subset, want_l2, want_time, n_depths) -> list[dict]:
    """The rows of every method on one capture."""
    if subset:
        sub = SubsetBuilder(cap.segments, np.concatenate([p.tex.ravel() for p in probes.values()]), cap.opaque_depth)
        segs, od = sub.segments, sub.opaque_depth
        exact = sub.build("exact", {})
    else:
        segs, od = cap.segments, cap.opaque_depth
        exact = build("exact", segs)
    exact_rep = compose(exact.rep if subset else exact, od)
    ex = {s: p.lookup(exact) for s, p in probes.items()}
    ex_curve = curve_values(exact_rep, segs, n_depths) if want_l2 else None
    rows = []
    for m in meths:
        params = sub.params(m.cls, m.params) if subset else m.params

        rep, build_s, first_s = _timed(lambda m=m, params=params: _synced_build(m.cls, segs, params), want_time, 1)
        target = Built(rep, sub.remap, od) if subset else rep
        l2 = depth_l2(compose(rep, od), segs, exact=ex_curve, n_depths=n_depths) if want_l2 else float("nan")
        for s, p in probes.items():
            est, lookup_s, _ = _timed(lambda p=p: p.lookup(target), want_time, LOOKUP_REPEATS)
            rows.append(dict(method=m.label, kind=m.kind, params=dict(m.params),
                             **{k: head[k] for k in ("scene", "seed", "light")}, receivers=s,
                             **{k: head[k] for k in ("order", "resolution", "opaque")}, n_receivers=p.k,
                             n_decomp=p.n_decomp, **_stats(p, est, ex[s]), depth_l2=l2,
                             bytes=float(rep.nbytes_sparse_per_texel), bytes_dense=float(rep.nbytes_per_texel),
                             build_s=build_s, lookup_s=lookup_s, build_first_s=first_s))
    return rows
