"""Names and tuning values of the builds ``error_curves`` runs (shared with its plots and
findings, so that they need not import the experiment itself)."""
from __future__ import annotations

from avsm_dr import describe

#: Values swept for tuning parameters that are not choices: moments' overestimation beta at 0,
#: MBOIT's 0.25 (the default), 1 and the kind's preset (tuned by the moment_tuning study).
_PRESET_BETA = float(describe("moments")["preset"].get("overestimation", 0.25))
TUNING = {"overestimation": tuple(sorted({0.0, 0.25, 1.0, _PRESET_BETA}))}
#: Choice parameters not crossed with the rest: moments' ``warp='log'`` needs every depth
#: > 0, which scenes with the light inside the depth range violate (the learned_warp
#: experiment compares warps); moments' ``quantization`` applies to 16-bit storage only.
UNTUNED = {"warp", "quantization"}
#: Insertion orders of each texel's segments that the order-dependent kinds
#: (:func:`order_dependent`: AVSM and adaptive AVSM) are built under, on the same
#: receivers and the same capture (``Segments.in_order``; 'random' seeded with the
#: configuration's seed; 'submission' from ``capture(order='submission')``, whose segments
#: per texel are checked to be the same): the headline in quick mode, every variant but the
#: storage precisions in full mode.  'depth' (first) is the order every other row is built
#: in; order-independent kinds record order '-'.
ORDERS = ("depth", "reverse_depth", "random", "submission")
#: Storage precisions built at each kind's headline size (fp16 vs fp32 in findings.json).
PRECISIONS = ("float16", "unorm8")


def tuned(kind: str) -> dict:
    """Tuning parameters of ``kind`` and their values: every choice parameter's choices and
    the :data:`TUNING` values of the parameters its schema has (never the size)."""
    d = describe(kind)
    out = {}
    for name, p in d["params"].items():
        if name == d["size"] or name in UNTUNED:
            continue
        if p.get("type") == "choice" and p.get("choices"):
            out[name] = tuple(p["choices"])
        elif name in TUNING:
            out[name] = TUNING[name]
    return out


def label(kind: str, params: dict) -> str:
    """Readable name of a build: ``kind-size`` plus ``/name=value`` for every tuning value
    that differs from the kind's default, e.g. ``fom-16/depth_range=texel``, and the storage
    ``/precision=...`` when one is given."""
    d = describe(kind)
    size = d["size"]
    s = kind + (f"-{params[size]}" if size and size in params else "")
    for name in sorted(tuned(kind)):
        default = d["headline"].get(name, d["params"][name]["default"])
        if name in params and params[name] != default:
            s += f"/{name}={params[name]}"
    if params.get("precision") is not None:
        s += f"/precision={params['precision']}"
    return s


def with_size(kind, value):
    d = describe(kind)
    base = dict(d["headline"])
    if d["size"] is not None and value is not None:
        base[d["size"]] = value
    return base


def order_dependent(kind: str) -> bool:
    """Whether ``kind``'s build depends on the order of each texel's segments: the kinds
    inserting segments one at a time in their stored order (streaming insertion; the
    schema's ``sort`` parameter, default False, sorts them first instead)."""
    return "sort" in describe(kind)["params"]
