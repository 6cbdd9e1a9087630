"""AVSM's distance from the best N-node curve: streaming AVSM against offline greedy
(``greedy``: Visvalingam-Whyatt on the whole exact curve, AVSM's metric) and the best
breakpoint subset (``optimal``: DP; ``optimal_subset`` keeps the subset's exact values,
``optimal`` refits them by least squares, ``optimal_linf`` minimises the max error), per
built-in scene and node count N, all with linear interpolation; the engine-style
``avsm_march`` (cap N, exponential interpolation) and the Beer shadow map (3 floats) for
context.  AVSM -> greedy is the cost of streaming, greedy -> optimal_subset that of
greedy removal, optimal_subset -> optimal that of keeping on-curve values.

Two measures of each representation against the exact curve of the same segments:

* **the oracle's own objective**: per texel, uniform in depth over the texel's content
  ``[first entry, last exit]``: ``MSE_t = int (T_rep - T)^2 dz / (b - a)`` and
  ``max_t = max |T_rep - T|``, by Gauss-Legendre quadrature (6 points) on every piece
  between the texel's segment ends and the representation's node depths (both curves
  are smooth there); the max over those points, 16 evenly spaced ones per piece and the
  piece ends (a lower bound of the continuous max: ``optimal``'s own ``objective``
  is exact and is reported beside it).  Reported:
  ``depth_rms = sqrt(mean_t MSE_t)``, ``depth_max`` (max over texels of max_t),
  ``depth_mean_texel_max`` over the non-empty texels, and for AVSM the shares of texels
  where its RMS is below optimal_subset's and optimal's by more than ``BEATS_MARGIN``
  (AVSM's nodes may leave the curve, the subset's may not);
* **at the evaluation's receivers** (:func:`avsm_dr.receivers.receiver_sets`:
  in-volume by contribution, surface, the scene's uniform set), bilinear lookups through
  the capture: RMSE / max / mean signed error against the exact curve's lookups.

**Insertion order.** Streaming AVSM sees each texel's segments in their stored order; the
offline references see the whole curve.  AVSM is built under every order of ``orders``
(default all four of :func:`avsm_dr.capture.capture`: ``submission``, the renderer's draw
order, then ``depth`` front to back, ``reverse_depth`` and a seeded ``random`` shuffle) on the
same segments and the same receivers; the ``order`` column records it (``-`` for the kinds
that do not depend on it).  The headline rows (``method == "avsm"`` without a suffix in
``findings.json``) are front to back, as before; ``avsm_over_optimal_by_order`` gives each
order's ratio and ``intervals`` each order's interval (``avsm@<order>_over_optimal``).

The columns every study carries: ``rmse``, ``signed_mean`` and ``leak_share``
(error > 0.02) at the in-volume receivers; ``depth_l2``, the harness's depth-uniform L2
(:func:`avsm_dr.evaluation.depth_l2`, 64 midpoints per texel: the same measure as
``depth_rms`` by another quadrature, within 2.1 % on the quick run); ``bytes`` (the sparse
layout, ``nbytes_sparse_per_texel``) and ``bytes_dense``.  ``build_s``: wall seconds of the
build, cold (after :meth:`avsm_dr.Segments.drop_cache`: no exact-curve points of an earlier
build of the same segments reused).

``findings.json``: per scene and N, AVSM / greedy / optimal ``depth_rms`` and the
ratios AVSM / optimal and greedy / optimal, with the in-volume RMSE likewise (first
configuration), and under ``intervals`` the depth-RMS ratios to optimal with 95 %
bootstrap intervals: per configuration over texels in 8 x 8 tiles (paired), pooled over the
configurations (seed x light, :data:`FULL_CONFIGS`: ten in full mode, a spot light among
them; quick mode seed 0 with the scene's light only) by :func:`avsm_dr.stats.claim`.  Under ``claims``
(:func:`claims`) each ratio to optimal (AVSM in every order, greedy, the subset) and each
order's AVSM over front-to-back AVSM on both metrics, receiver RMSE and depth L2, with
``metric_dependent``, ``indicative`` (fewer than :data:`._two_metric.MIN_CONFIDENT` configurations:
always in quick mode), the order, ``preset`` (AVSM here interpolates
linearly, its preset) and each side's signed mean and leak share.
"""

from __future__ import annotations

import time

import numpy as np
from tqdm import tqdm

from avsm_dr import build, kinds
from avsm_dr.evaluation import curve_values, depth_grid, depth_l2
from avsm_dr.metrics import error_stats
from ._common import front_to_back_first
from ._two_metric import texel_blocks
from ._headline import interval
from ._study import Option, Study, write_data

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    'AVSM\'s distance from the best N-node curve: streaming AVSM '
    'against offline greedy Visvalingam-Whyatt and the best breakpoint subset (refitted), per '
    "scene and N, on the oracle's own objective and at in-volume receivers."
)


SCENES = ["plume", "three_columns", "hair_and_smoke"]
#: Gauss-Legendre points per smooth piece of the uniform-in-depth objective.
GAUSS_POINTS = 6
#: A texel's RMS counts as lower than another's only below it by more than this.
BEATS_MARGIN = 1e-6
#: Evenly spaced points per piece (and its ends) where the max error is also looked for.
MAX_POINTS = 16
#: The receiver set of the ``rmse`` / ``signed_mean`` / ``leak_share`` columns and the claims.
RECEIVERS = "in_volume"
#: Key of the 8 x 8 tiles of the objective's texels (which keep texels holding only an opaque
#: segment; the depth L2 cuts those to their front face and drops them).
OBJECTIVE = "objective"

#: Parameters of the full and the quick run (``scenes``: an option; ``methods`` filled in).
#: Insertion orders AVSM is built under (the first is the headline's: front to back).
ORDERS = ["depth", "submission", "reverse_depth", "random"]

#: Full mode: error_curves' ten configurations (4 seeds x both directional lights, 2 seeds x the
#: spot light: at least 10 per scene, one of them a spot light).
FULL_CONFIGS = [[s, li] for s in range(4) for li in ("dir_a", "dir_b", "spot") if li != "spot" or s < 2]

FULL = dict(scenes=SCENES, resolution=128, nodes=[2, 4, 8, 16, 32], configs=FULL_CONFIGS,
            n_volume=4096, n_surface=1024, gauss_points=GAUSS_POINTS, max_points=MAX_POINTS, filter="bilinear",
            methods=None, n_boot=1000, orders=ORDERS)
QUICK = dict(FULL, resolution=64, nodes=[4, 8], configs=[[0, "dir_a"]], n_volume=256, n_surface=128, n_boot=200)


def methods(n: int) -> list[tuple[str, str, dict]]:
    """(label, kind, parameters) compared at node count ``n``."""
    return [("avsm", "avsm", {"nodes": n}), ("greedy", "greedy", {"nodes": n}),
            ("optimal_subset", "optimal", {"nodes": n, "_refit": False}), ("optimal", "optimal", {"nodes": n}),
            ("optimal_linf", "optimal", {"nodes": n, "norm": "linf"}),
            ("avsm_march", "avsm_march", {"nodes": n})]


def node_depths(rep) -> tuple[np.ndarray, np.ndarray]:
    """(texel, depth) of every node of ``rep`` where its curve may kink (empty when the
    kind has none besides the segment ends)."""
    if hasattr(rep, "nodes_numpy") and rep.kind in ("avsm", "greedy", "optimal"):
        d, _ = rep.nodes_numpy()
        return np.repeat(np.arange(d.shape[0]), d.shape[1]), d.ravel()
    if rep.kind in ("avsm_march", "avsm_adaptive"):
        return np.repeat(np.arange(rep.n_texels), rep.node_counts), rep.node_depths()
    return np.zeros(0, np.int64), np.zeros(0)


class UniformObjective:
    """Quadrature of the per-texel uniform-in-depth error of any representation on the
    segments ``seg`` (see the module docstring).

    The exact curve's values on the pieces between the segment ends alone (and at those ends)
    are computed once: a representation's nodes split only the pieces they fall in, and only
    those are looked up again (the exact lookups were ~95 % of a call on 70-segment texels).
    The points, their order and every value are those of looking everything up each call."""

    def __init__(self, seg):
        h = seg.numpy()
        self.seg = seg
        off = h["offsets"]
        self.tex_seg = np.repeat(np.arange(seg.n_texels), np.diff(off))
        self.ends = np.r_[h["z0"], h["z1"]]
        self.ends_tex = np.r_[self.tex_seg, self.tex_seg]
        self.lo, self.hi = seg.texel_bounds()
        nz = np.diff(off) > 0
        self.texels = np.flatnonzero(nz & (self.hi > self.lo))
        self.exact = build("exact", seg)
        self._span = np.where(self.hi > self.lo, self.hi - self.lo, 1.0)
        tex, z, _ = self._cuts(self.ends_tex, self.ends, np.zeros(self.ends.size, bool))
        a, b, pt = self._pieces(tex, z)
        xg, _, xu = self._points(a, b)
        ref = self._exact(np.r_[np.repeat(pt, GAUSS_POINTS), np.repeat(pt, MAX_POINTS), tex],
                          np.r_[xg.ravel(), xu.ravel(), z])
        ng, nu = xg.size, xu.size
        self._base = dict(a=a, b=b, key=self._key(pt, a), ref_g=ref[:ng].reshape(xg.shape),
                          ref_u=ref[ng:ng + nu].reshape(xu.shape), ref_cut=ref[ng + nu:])

    def _exact(self, texel, depth) -> np.ndarray:
        return np.asarray(self.exact.eval(texel, depth), np.float64) if texel.size else np.zeros(0)

    def _key(self, tex, z) -> np.ndarray:
        """A float key increasing with (texel, depth) over the texels' ranges (rounding may
        merge close depths: a lookup by it is checked for equality)."""
        return tex + 0.5 * ((z - self.lo[tex]) / self._span[tex])

    def _cuts(self, tex, z, node):
        """The cuts inside each texel's range, sorted by (texel, depth), stable (segment ends
        before node depths at equal values)."""
        keep = (z >= self.lo[tex]) & (z <= self.hi[tex])
        tex, z, node = tex[keep], z[keep], node[keep]
        order = np.lexsort((z, tex))
        return tex[order], z[order], node[order]

    @staticmethod
    def _pieces(tex, z):
        """Pieces ``[a, b]`` of texel ``pt`` between consecutive distinct cuts."""
        same = np.r_[False, (tex[1:] == tex[:-1])]
        piece = np.flatnonzero(same & np.r_[False, z[1:] > z[:-1]])     # piece [z[i-1], z[i]] of texel tex[i]
        return z[piece - 1], z[piece], tex[piece]

    @staticmethod
    def _points(a, b):
        """Gauss-Legendre points (P, GAUSS_POINTS) and weights of each piece, and its
        MAX_POINTS evenly spaced points (P, MAX_POINTS)."""
        gx, gw = np.polynomial.legendre.leggauss(GAUSS_POINTS)
        x = (0.5 * (a + b))[:, None] + (0.5 * (b - a))[:, None] * gx[None, :]
        w = (0.5 * (b - a))[:, None] * gw[None, :]
        u = (np.arange(MAX_POINTS) + 0.5) / MAX_POINTS
        return x, w, a[:, None] + (b - a)[:, None] * u[None, :]

    def measure(self, rep) -> dict:
        """depth_rms, depth_max, depth_mean_texel_max and the per-texel RMS (T,)."""
        nt, nd = node_depths(rep)
        tex, z, node = self._cuts(np.r_[self.ends_tex, nt], np.r_[self.ends, nd],
                                  np.r_[np.zeros(self.ends.size, bool), np.ones(nd.size, bool)])
        a, b, pt = self._pieces(tex, z)
        x, w, xu = self._points(a, b)
        qt = np.repeat(pt, GAUSS_POINTS)
        # quadrature points, then evenly spaced points and every cut (for the max)
        at = np.r_[qt, np.repeat(pt, MAX_POINTS), tex]
        ax = np.r_[x.ravel(), xu.ravel(), z]
        est = np.asarray(rep.eval(at, ax), np.float64)
        # the exact curve: cached on the pieces no node splits and at the segment ends
        base = self._base
        j = np.searchsorted(base["key"], self._key(pt, 0.5 * (a + b)), side="right") - 1
        j = np.clip(j, 0, max(base["a"].size - 1, 0))
        hit = (base["a"][j] == a) & (base["b"][j] == b) if base["a"].size else np.zeros(a.size, bool)
        miss = ~hit
        fresh = self._exact(np.r_[np.repeat(pt[miss], GAUSS_POINTS), np.repeat(pt[miss], MAX_POINTS), tex[node]],
                            np.r_[x[miss].ravel(), xu[miss].ravel(), z[node]])
        ref_g, ref_u, ref_cut = np.empty(x.shape), np.empty(xu.shape), np.empty(z.size)
        ref_g[hit], ref_u[hit], ref_cut[~node] = base["ref_g"][j[hit]], base["ref_u"][j[hit]], base["ref_cut"]
        ng, nu = int(miss.sum()) * GAUSS_POINTS, int(miss.sum()) * MAX_POINTS
        ref_g[miss] = fresh[:ng].reshape(-1, GAUSS_POINTS)
        ref_u[miss] = fresh[ng:ng + nu].reshape(-1, MAX_POINTS)
        ref_cut[node] = fresh[ng + nu:]
        err = est - np.r_[ref_g.ravel(), ref_u.ravel(), ref_cut]
        nq = qt.size
        T = self.seg.n_texels
        mse = np.bincount(qt, weights=w.ravel() * err[:nq] ** 2, minlength=T) / self._span
        mx = np.zeros(T)
        np.maximum.at(mx, at, np.abs(err))
        sel = self.texels
        return {"depth_rms": float(np.sqrt(mse[sel].mean())) if sel.size else 0.0,
                "depth_max": float(mx[sel].max()) if sel.size else 0.0,
                "depth_mean_texel_max": float(mx[sel].mean()) if sel.size else 0.0,
                "_texel_rms": np.sqrt(mse)}


def _key(label: str, order: str) -> str:
    """The label of a method's errors: ``avsm`` front to back, ``avsm@<order>`` otherwise."""
    return label if order in ("-", "depth") else f"{label}@{order}"


def _scene_rows(name, P, rows, quick, seed=0, light="dir_a", texel_errors=None, receiver_errors=None,
                l2_errors=None, blocks=None):
    """Rows of one configuration (scene, seed, light); per-texel RMS of every method into
    ``texel_errors[(scene, config, N, method)]`` (for the intervals), its signed errors at the
    in-volume receivers into ``receiver_errors`` and its per-texel depth L2 into
    ``l2_errors`` (same keys; for the claims), the 8 x 8 texel tiles into ``blocks``."""
    import dataclasses
    from avsm_dr import capture, receivers
    from avsm_dr import scenes as scene_lib
    from avsm_dr.evaluation import light_variants
    sc0 = scene_lib.get(name, seed=seed)
    scene = dataclasses.replace(sc0, light=light_variants(sc0)[light])
    config = f"s{seed}-{light}"
    cap = capture(scene, resolution=P["resolution"], order="depth")
    seg = cap.segments
    sets = receivers.receiver_sets(scene, P["n_volume"], P["n_surface"], seed=seed)
    exact = build("exact", seg)
    ex = {s: np.asarray(cap.transmittance(exact, p, filter="bilinear"), np.float64) for s, p in sets.items()}
    obj = UniformObjective(seg)
    # the harness's depth-uniform L2 (every order: the same texels and exact curve) and the
    # 8 x 8 texel tiles of its texels and of the in-volume receivers (nearest texel)
    ex_curve = curve_values(exact, seg)
    l2_texels = depth_grid(seg)[0]
    if blocks is not None:
        blocks[(name, config)] = texel_blocks(l2_texels, cap.width)
        blocks[(name, config, RECEIVERS)] = texel_blocks(cap.lookup(sets[RECEIVERS])[0], cap.width)
        blocks[(name, config, OBJECTIVE)] = texel_blocks(obj.texels, cap.width)
    head = dict(scene=name, config=config, resolution=P["resolution"], texels=int(obj.texels.size),
                max_segments=int(seg.max_count))

    orders = {"depth": seg}
    for o in P.get("orders", ["depth"]):
        if o == "submission":
            sub = capture(scene, resolution=P["resolution"], order="submission").segments
            if not np.array_equal(sub.counts, seg.counts):
                raise RuntimeError(f"{name}/{config}: the submission-order capture has other segment counts")
            orders[o] = sub
        elif o != "depth":
            orders[o] = seg.in_order(o, seed=seed if o == "random" else None)

    def row(label, kind, params, n, order="-"):
        on = orders.get(order, seg).drop_cache()     # a cold build: no curve points of an earlier one
        t0 = time.perf_counter()
        rep = build(kind, on, **params)
        build_s = time.perf_counter() - t0
        m = obj.measure(rep)
        r = dict(head, method=label, kind=kind, order=order, nodes=n, bytes_per_texel=rep.nbytes_per_texel,
                 bytes_sparse=rep.nbytes_sparse_per_texel, build_s=build_s,
                 **{k: v for k, v in m.items() if not k.startswith("_")})
        per_l2 = depth_l2(rep, seg, exact=ex_curve, per_texel=True)
        for s, p in sets.items():
            est = np.asarray(cap.transmittance(rep, p, filter="bilinear"), np.float64)
            st = error_stats(est, ex[s])
            r.update({f"rmse_{s}": st["rmse"], f"max_{s}": st["max_error"], f"mean_{s}": st["mean_error"],
                      f"leak_{s}": st["leak_fraction"]})
            if s == RECEIVERS and receiver_errors is not None:
                receiver_errors[(name, config, n, _key(label, order))] = est - ex[s]
        if l2_errors is not None:
            l2_errors[(name, config, n, _key(label, order))] = per_l2
        s = RECEIVERS
        r.update(rmse=r[f"rmse_{s}"], signed_mean=r[f"mean_{s}"], leak_share=r[f"leak_{s}"],
                 depth_l2=float(np.sqrt(np.mean(per_l2 ** 2))) if per_l2.size else float("nan"),
                 bytes=rep.nbytes_sparse_per_texel, bytes_dense=rep.nbytes_per_texel)
        if kind == "optimal":
            r["objective_analytic"] = float(np.sqrt(np.mean(rep.objective[obj.texels] ** 2))) \
                if params.get("norm", "l2") == "l2" else float(rep.objective[obj.texels].max())
        rows.append(r)
        return r, m["_texel_rms"]

    from avsm_dr.validation import WorkLimitError
    for n in P["nodes"]:
        texel_rms, first = {}, len(rows)
        for label, kind, params in methods(n):
            if kind not in kinds():
                continue
            try:
                r, texel_rms[label] = row(label, kind, params, n, "depth" if kind == "avsm" else "-")
            except WorkLimitError as exc:     # optimal_linf (context only, its L-inf DP is cubic in the
                if label != "optimal_linf":   # points per texel): a row with a note; the claims' methods: raise
                    raise
                rows.append(dict(head, method=label, kind=kind, order="-", nodes=n,
                                 note=f"skipped: work above optimal.MAX_WORK at N = {n} ({exc.work:.3g} work "
                                      f"units, limit {exc.limit:.3g})"))
        for o in orders:
            if o != "depth" and "avsm" in kinds():
                _, texel_rms[f"avsm@{o}"] = row("avsm", "avsm", {"nodes": n}, n, o)
        sel = obj.texels
        if texel_errors is not None:
            for label, v in texel_rms.items():
                texel_errors[(name, config, n, label)] = v[sel]
        for other in ("optimal_subset", "optimal"):
            if "avsm" in texel_rms and other in texel_rms and sel.size:
                # lower by more than float32 lookup noise (~1e-7 in a texel's RMS)
                rows[first][f"avsm_beats_{other}_texels"] = float(  # the front-to-back row
                    np.mean(texel_rms["avsm"][sel] < texel_rms[other][sel] - BEATS_MARGIN))
    if "beer" in kinds():
        row("beer", "beer", {}, 0)


def intervals(texel_errors: dict, n_boot: int = 1000, blocks: dict | None = None) -> dict:
    """Per scene and N: AVSM / greedy / optimal_subset uniform-depth RMS over optimal's,
    the per-texel RMS paired, with :func:`avsm_dr.stats.claim`'s intervals (per
    configuration: bootstrap over texels, in 8 x 8 tiles with ``blocks``
    (``{(scene, config): tile of each texel}``); pooled: configurations, then texels)."""
    from avsm_dr import stats
    out: dict = {}
    keys = sorted({(k[0], k[2]) for k in texel_errors})
    for scene, n in keys:
        configs = sorted({k[1] for k in texel_errors if k[0] == scene and k[2] == n})
        labels = sorted({k[3] for k in texel_errors if k[0] == scene and k[2] == n and k[3].startswith("avsm@")})
        for m in ("avsm", "greedy", "optimal_subset", *labels):
            used = [c for c in configs if (scene, c, n, m) in texel_errors and (scene, c, n, "optimal") in texel_errors
                    and np.any(texel_errors[(scene, c, n, "optimal")] > 0)]
            if not used:
                continue
            r = stats.claim([texel_errors[(scene, c, n, m)] for c in used],
                            [texel_errors[(scene, c, n, "optimal")] for c in used], statistic="rmse",
                            compare="ratio", below=1.0, configs=used, n_boot=n_boot,
                            blocks_by_config=_blocks(blocks, scene, used, OBJECTIVE))
            out.setdefault(scene, {}).setdefault(f"N={n}", {})[f"{m}_over_optimal"] = dict(
                estimate=r["estimate"], low=r["low"], high=r["high"], level=r["level"], n_configs=r["n_configs"],
                per_config={pc["config"]: [pc["estimate"], pc["low"], pc["high"]] for pc in r["per_config"]})
    return out


def _blocks(blocks, scene, configs, *rest):
    """Per configuration the 8 x 8 texel tiles of ``blocks[(scene, config, *rest)]`` (None
    when any is missing: the bootstrap then resamples single texels / receivers)."""
    got = [(blocks or {}).get((scene, c, *rest)) for c in configs]
    return None if any(b is None for b in got) else got


#: Pairs (a, b) of each claim per scene and N: AVSM (every order), greedy and the subset
#: against the optimum, and AVSM in every other order against front to back.
def _pairs(labels) -> list[tuple[str, str]]:
    orders = [x for x in labels if x.startswith("avsm@")]
    return ([(m, "optimal") for m in ("avsm", *orders, "greedy", "optimal_subset") if m in labels]
            + [(m, "avsm") for m in orders])


def claims(receiver_errors: dict, l2_errors: dict, blocks: dict | None = None, n_boot: int = 1000) -> dict:
    """Per scene and N, each pair of :func:`_pairs` as a claim 'a below b' on both metrics
    (``error_curves``' form): the receiver RMSE ratio (in-volume receivers, signed errors
    against the exact curve, paired) and the depth-uniform L2 ratio (per texel, paired), each
    by :func:`avsm_dr.stats.claim` (unit: the configuration; within a configuration 8 x 8
    texel tiles), ``metric_dependent`` when their intervals lie on opposite sides of 1,
    ``indicative`` below :data:`._two_metric.MIN_CONFIDENT` configurations, the order, whether each side is
    its kind's preset, and each side's signed mean and leak share."""
    from ._two_metric import claim
    from .error_curves.findings import preset_differences
    kinds_ = {"avsm": "avsm", "greedy": "greedy", "optimal_subset": "optimal", "optimal": "optimal"}
    out: dict = {}
    for scene, n in sorted({(k[0], k[2]) for k in receiver_errors}):
        configs = sorted({k[1] for k in receiver_errors if k[0] == scene and k[2] == n})
        labels = {k[3] for k in receiver_errors if k[0] == scene and k[2] == n}
        for a, b in _pairs(labels):
            used = [c for c in configs if all((scene, c, n, m) in store for m in (a, b)
                                              for store in (receiver_errors, l2_errors))
                    and np.any(receiver_errors[(scene, c, n, b)] != 0) and np.any(l2_errors[(scene, c, n, b)] > 0)]
            if not used:
                continue
            pair = lambda store: tuple([store[(scene, c, n, m)] for c in used] for m in (a, b))  # noqa: E731
            r = claim(pair(receiver_errors), pair(l2_errors), used,
                      (_blocks(blocks, scene, used, RECEIVERS), _blocks(blocks, scene, used)), n_boot)
            sides = {k: m.split("@")[0] for k, m in (("a", a), ("b", b))}
            out.setdefault(scene, {}).setdefault(f"N={n}", {})[f"{a}_over_{b}"] = dict(
                statement=f"{a} below {b} at N = {n} (ratio < 1; linear interpolation"
                          + (", front to back" if "avsm" in (a, b) and "@" not in a else "") + ")",
                order=a.split("@")[1] if "@" in a else "depth" if sides["a"] == "avsm" else "-",
                preset={k: not preset_differences(dict(variant=f"{kinds_[v]}-{n}", opaque="inline"), False)
                        for k, v in sides.items()}, **r)
    return out


def findings(rows, texel_errors: dict | None = None, n_boot: int = 1000, receiver_errors: dict | None = None,
             l2_errors: dict | None = None, blocks: dict | None = None) -> dict:
    """Per scene and N (the first configuration): AVSM / greedy / optimal uniform-depth RMS
    and in-volume RMSE, and the ratios to optimal; with ``texel_errors``, the ratios'
    intervals over every configuration under ``"intervals"``; with ``receiver_errors`` and
    ``l2_errors``, the two-metric claims of :func:`claims` under ``"claims"``."""
    out = {}
    first = {}
    for r in rows:
        first.setdefault(r["scene"], r.get("config"))
    for r in rows:
        if r["method"] not in ("avsm", "greedy", "optimal_subset", "optimal") or r.get("config") != first[r["scene"]]:
            continue
        d = out.setdefault(r["scene"], {}).setdefault(f"N={r['nodes']}", {})
        if r["method"] == "avsm" and r.get("order", "depth") != "depth":
            d.setdefault("_avsm_by_order", {})[r["order"]] = r["depth_rms"]
            continue
        if r["method"] == "avsm":
            d["avsm_order"] = "depth"
        d[f"{r['method']}_depth_rms"] = r["depth_rms"]
        if "rmse_in_volume" in r:
            d[f"{r['method']}_rmse_in_volume"] = r["rmse_in_volume"]
        for k in ("avsm_beats_optimal_subset_texels", "avsm_beats_optimal_texels"):
            if k in r:
                d[k] = r[k]
    for scene in out.values():
        for d in scene.values():
            opt = d.get("optimal_depth_rms")
            for m in ("avsm", "greedy", "optimal_subset"):
                if opt and f"{m}_depth_rms" in d:
                    d[f"{m}_over_optimal"] = d[f"{m}_depth_rms"] / opt
            by = d.pop("_avsm_by_order", {})
            if opt and by:
                d["avsm_over_optimal_by_order"] = dict(
                    {"depth": d["avsm_over_optimal"]} if "avsm_over_optimal" in d else {},
                    **{o: v / opt for o, v in by.items()})
            oi = d.get("optimal_rmse_in_volume")
            for m in ("avsm", "greedy", "optimal_subset"):
                if oi and f"{m}_rmse_in_volume" in d:
                    d[f"{m}_over_optimal_in_volume"] = d[f"{m}_rmse_in_volume"] / oi
    if texel_errors:
        out["intervals"] = intervals(texel_errors, n_boot, blocks)
    if receiver_errors and l2_errors:
        out["claims"] = claims(receiver_errors, l2_errors, blocks, n_boot)
    return out


def _resolve(P: dict, quick: bool) -> dict:
    """The scenes as a list and the compared methods."""
    P["scenes"] = list(P["scenes"])
    P["methods"] = [m[0] for m in methods(0)] + ["beer"]
    P["orders"] = front_to_back_first(P.get("orders"), ORDERS)
    return P


def _compute(res, P: dict) -> dict:
    """Every configuration's rows, the findings and the figure."""
    quick, names = res.quick, P["scenes"]
    rows: list[dict] = []
    texel_errors, receiver_errors, l2_errors, blocks = {}, {}, {}, {}
    jobs = [(name, seed, light) for name in names for seed, light in P["configs"]]
    for name, seed, light in tqdm(jobs, desc="avsm_gap", unit="config"):
        _scene_rows(name, P, rows, quick, seed, light, texel_errors, receiver_errors, l2_errors, blocks)
    summary = findings(rows, texel_errors, n_boot=P["n_boot"], receiver_errors=receiver_errors,
                       l2_errors=l2_errors, blocks=blocks)
    write_data(res, dict(rows=rows, findings=summary))        # before the figures
    _plot(res, [r for r in rows if r.get("order") in ("-", "depth")], names)
    return dict(rows=rows, findings=summary, summary=summary)


def _style(label: str) -> dict:
    """Plot keywords of a compared method: its kind's style (``experiments._plotstyle``); the two
    other variants of ``optimal`` hollow in colours of their own, the L-infinity one dotted."""
    from . import _plotstyle as plotstyle
    if label == "optimal_subset":
        return dict(plotstyle.variant_style("optimal"), color=plotstyle.PALETTE["olive"], alpha=1)
    if label == "optimal_linf":
        return dict(plotstyle.variant_style("optimal"), color=plotstyle.PALETTE["indigo"], alpha=1, linestyle=":")
    return plotstyle.style(dict((m[0], m[1]) for m in methods(0)).get(label, label))


#: Scene panels a row in the figures (more scenes wrap onto rows filled evenly).
PANEL_COLUMNS = 4


def _plot(res, rows, names):
    """Per scene and N, each method's error (front-to-back rows) as the mean over
    configurations, bars from the smallest to the largest configuration."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker
    from . import _plotstyle as plotstyle
    labels = [m[0] for m in methods(0)]
    n_cfg = len({r["config"] for r in rows})
    for key, fname, ylabel in (("depth_rms", "gap_depth.png", "RMS error of T, uniform in depth per texel"),
                               ("rmse_in_volume", "gap_receivers.png", "RMSE of T at in-volume receivers")):
        with plotstyle.context():
            fig, axes = plotstyle.grid(*plotstyle.panel_shape(len(names), PANEL_COLUMNS), panel=(2.8, 2.4),
                                       sharex=False)
            panels = axes.ravel()
            for ax in panels[len(names):]:
                ax.set_visible(False)
            for ax, name in zip(panels, names):
                for lab in labels:
                    per: dict = {}
                    for r in rows:
                        if r["scene"] == name and r["method"] == lab and key in r:
                            per.setdefault(r["nodes"], []).append(max(r[key], 1e-7))
                    if per:
                        ns = sorted(per)
                        y = np.array([np.mean(per[n]) for n in ns])
                        bars = [y - [min(per[n]) for n in ns], [max(per[n]) for n in ns] - y]
                        ax.errorbar(ns, y, yerr=bars, capsize=2, **_style(lab), label=lab)
                beer = [max(r[key], 1e-7) for r in rows if r["scene"] == name and r["method"] == "beer" and key in r]
                if beer:
                    ax.axhline(float(np.mean(beer)), color=plotstyle.style("beer")["color"], linestyle=":",
                               linewidth=0.8, label="beer (3 floats)")
                ax.set_title(name)
                ax.set_xlabel("nodes N")
                ax.set_xscale("log", base=2)
                ax.set_yscale("log")
                ns = sorted({r["nodes"] for r in rows if r["nodes"]})
                ax.set_xticks(ns, [str(n) for n in ns])
                ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            if len(axes) > 1:                # one label for the rows (a long label per row overlaps)
                fig.supylabel(ylabel, fontsize=plt.rcParams["axes.labelsize"])
            else:
                axes[0][0].set_ylabel(ylabel)
            fig.suptitle(f"mean over {n_cfg} configuration{'s' * (n_cfg > 1)} (bars: min to max), "
                         "front-to-back AVSM", fontsize=9)
            plotstyle.legend_below(fig, panels[:len(names)], ncol=7)
            res.save_figure(fig, fname)


def _headline(s: dict) -> list[str]:
    """Per scene and N: AVSM's and greedy's uniform-in-depth RMS over the optimal N-node
    curve's (the interval over configurations where recorded), AVSM's worst insertion order."""
    ivs, out = s.get("intervals", {}), []
    for scene, per_n in s.items():
        for n, d in per_n.items() if scene not in ("intervals", "claims") else ():
            iv = ivs.get(scene, {}).get(n, {})
            by = d.get("avsm_over_optimal_by_order", {})
            worst = max(by, key=by.get) if by else None
            out.append(f"{scene} {n}: depth-uniform RMS over the optimum: AVSM "
                       f"{interval(iv.get('avsm_over_optimal', d.get('avsm_over_optimal')))}, greedy "
                       f"{interval(iv.get('greedy_over_optimal', d.get('greedy_over_optimal')))}"
                       + (f"; worst order {worst} {interval(iv.get(f'avsm@{worst}_over_optimal', by[worst]))}"
                          if worst and worst != "depth" else ""))
    dep = [f"{scene} {n} {c}" for scene, per_n in s.get("claims", {}).items() for n, cs in per_n.items()
           for c, v in cs.items() if v.get("metric_dependent")]
    if dep:
        out.append("metric-dependent (receiver RMSE and depth L2 disagree): " + ", ".join(dep))
    return out


STUDY = Study(
    "avsm_gap", "AVSM's distance from the best N-node curve: streaming AVSM against offline greedy and optimal",
    REPRODUCES, FULL, QUICK, _compute, resolve=_resolve, writes=("data.csv", "findings.json"),
    options=(Option("scenes", "built-in scenes to run (default: the mode's)", nargs="+", metavar="SCENE"),
             Option("orders", "insertion orders AVSM is built under besides front to back, the headline's "
                              "(default: submission reverse_depth random)", nargs="+", metavar="ORDER")),
    headline=_headline)
run = STUDY.run
