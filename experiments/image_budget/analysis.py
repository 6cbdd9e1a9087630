"""The answer of the ``image_budget`` study from its table: per animation and shadow-map
resolution, which kind is best at each byte budget (the map), and the smallest budget beyond
which compression is no longer visible (the threshold), with a bootstrap interval whose unit
is the configuration (scene seed x light).

Arrays per (animation, resolution), one entry per configuration ``c``: ``comp[k, b, c]`` the
compression FLIP of kind ``k`` at budget ``b`` (FLIP of its render against ``exact``'s at the
same resolution and seed), mean over the configuration's frames; ``nbytes[k, b, c]`` its stored
bytes per texel (mean over frames); ``fits[k, b, c]`` whether the kind has a size within budget
``b`` (chosen on the configuration's frame 0); ``noise[c]`` the visibility floor (FLIP between
the reference's two independent halves, mean over frames).  Means over configurations decide
(a kind fits a budget when it fits in every configuration):

* **invisible** ``(k, b)``: fits, and mean_c comp < mean_c noise;
* **best kind of a cell** ``b``: the cheapest invisible kind (least mean stored bytes; ties:
  the lower FLIP), or, when none is invisible, the kind with the least mean compression FLIP,
  where FLIPs within :data:`TIE` (relative) of the least count as equal and the fewest bytes
  wins among them (``avsm`` with 2 nodes and ``exp`` interpolation and ``beer`` store the same
  homogeneous curve: their FLIPs differ by rounding); kinds that do not fit are never chosen;
* **threshold**: the smallest budget ``b*`` at which some kind is invisible at ``b*`` and at
  every larger budget of the grid (compression no longer visible beyond it), and the
  cheapest such kind; not reached when no kind is.
"""
from __future__ import annotations

import numpy as np

#: Relative FLIP difference below which two kinds' visible compression counts as equal.
TIE = 0.01


def best_in_cell(comp_mean, bytes_mean, fits, noise_mean) -> tuple[int | None, bool]:
    """(index of the best kind of one cell, whether it is invisible) from per-kind means over
    frames (module docstring); (None, False) when no kind fits."""
    comp_mean, bytes_mean, fits = (np.asarray(a) for a in (comp_mean, bytes_mean, fits))
    idx = np.flatnonzero(fits)
    if idx.size == 0:
        return None, False
    inv = idx[comp_mean[idx] < noise_mean]
    if inv.size:
        order = np.lexsort((comp_mean[inv], bytes_mean[inv]))        # bytes first, then FLIP
        return int(inv[order[0]]), True
    near = idx[comp_mean[idx] <= comp_mean[idx].min() * (1 + TIE)]     # the least FLIP, up to ties
    order = np.lexsort((comp_mean[near], bytes_mean[near]))          # then the fewest bytes
    return int(near[order[0]]), False


def threshold_index(comp_mean, bytes_mean, fits, noise_mean) -> tuple[int | None, int | None]:
    """(budget index b*, kind index) of the threshold (module docstring) from (K, B) means
    over frames; (None, None) when no kind stays invisible up to the largest budget."""
    comp_mean, bytes_mean, fits = (np.asarray(a) for a in (comp_mean, bytes_mean, fits))
    inv = fits & (comp_mean < noise_mean)                                  # (K, B)
    stays = np.flip(np.logical_and.accumulate(np.flip(inv, axis=1), axis=1), axis=1)   # invisible from b on
    for b in range(inv.shape[1]):
        ks = np.flatnonzero(stays[:, b])
        if ks.size:
            order = np.lexsort((comp_mean[ks, b], bytes_mean[ks, b]))
            return b, int(ks[order[0]])
    return None, None


def threshold_ci(comp, nbytes, fits, noise, budgets, n_boot: int = 1000, seed: int = 0) -> dict:
    """Threshold budget with a bootstrap 95 % percentile interval whose unit is the
    configuration (configurations resampled with replacement, :func:`avsm_dr.stats.bootstrap_ci`;
    at least 2); a replicate that never reaches invisibility counts as 2 x the largest budget,
    and a bound there is reported as None (beyond the grid).  ``comp``, ``nbytes``, ``fits``:
    (K, B, C); ``noise``: (C,)."""
    from avsm_dr.stats import bootstrap_ci
    comp, nbytes, noise = (np.asarray(a, np.float64) for a in (comp, nbytes, noise))
    fits = np.asarray(fits, bool)
    budgets = np.asarray(budgets, np.float64)
    beyond = 2.0 * float(budgets.max())
    C = comp.shape[2]

    def stat(x, axis):
        idx = np.atleast_2d(np.asarray(x)).astype(np.int64)
        out = np.empty(idx.shape[0])
        for r, sel in enumerate(idx):
            b, _ = threshold_index(comp[:, :, sel].mean(-1), nbytes[:, :, sel].mean(-1), fits[:, :, sel].all(-1),
                                   noise[sel].mean())
            out[r] = beyond if b is None else budgets[b]
        return out
    ci = bootstrap_ci(np.arange(C, dtype=np.float64), stat, n_boot=n_boot, seed=seed)
    return {k: (None if ci[k] >= beyond else float(ci[k])) for k in ("estimate", "low", "high")} | {
        "level": ci["level"], "n": int(C), "unit": "configuration"}


def summarise(comp, nbytes, fits, noise, budgets, kinds, labels, n_boot: int, min_configs: int) -> dict:
    """The map cells and the threshold of one (animation, resolution) (arrays: module docstring).

    ``labels[k][b]``: the size label of kind ``k`` at budget ``b``.  Returns ``cells`` (one
    dict per budget), ``threshold`` (budget, kind, label, stored bytes, FLIPs, interval over
    configurations, ``per_config``: each configuration's own threshold budget (None: not
    reached), ``n_configs``, ``indicative`` when fewer than ``min_configs`` configurations)."""
    comp, nbytes, noise = (np.asarray(a, np.float64) for a in (comp, nbytes, noise))
    cfits = np.asarray(fits, bool)
    cm, bm, nm, fits = comp.mean(-1), nbytes.mean(-1), float(noise.mean()), cfits.all(-1)
    cells = []
    for b, budget in enumerate(budgets):
        k, invisible = best_in_cell(cm[:, b], bm[:, b], fits[:, b], nm)
        cells.append(dict(budget=budget, best_kind=kinds[k] if k is not None else "",
                          best_label=labels[k][b] if k is not None else "",
                          best_bytes=float(bm[k, b]) if k is not None else float("nan"),
                          best_flip_compression=float(cm[k, b]) if k is not None else float("nan"),
                          noise_flip=nm, invisible=bool(invisible), kinds_within_budget=int(fits[:, b].sum())))
    b, k = threshold_index(cm, bm, fits, nm)
    ci = threshold_ci(comp, nbytes, cfits, noise, budgets, n_boot=n_boot)
    own = [threshold_index(comp[..., c], nbytes[..., c], cfits[..., c], noise[c])[0] for c in range(noise.size)]
    thr = dict(reached=b is not None, bytes=None if b is None else float(budgets[b]),
               kind=None if k is None else kinds[k], label=None if k is None else labels[k][b],
               stored_bytes=None if k is None else float(bm[k, b]),
               flip_compression=None if k is None else float(cm[k, b]), noise_flip=nm,
               interval=ci, per_config=[None if o is None else float(budgets[o]) for o in own],
               n_configs=int(noise.size), indicative=bool(noise.size < min_configs))
    return dict(cells=cells, threshold=thr)
