"""The benchmark's summary (``meta.json``), the machine table (``machine.csv``: vector
operations per insertion and the achieved fraction of the machine's limit for every
setting) and the main numbers on stdout."""
from __future__ import annotations

import math

from .scaling import slopes

#: Columns of ``machine.csv`` (one row per benchmarked setting).  ``lanes``: float32 lanes per
#: SIMD packet (the LLVM vector width); ``isa``, ``llvm_cpu``, ``executed_bits`` (the vector
#: datapath: 256 on AMD Zen 4, which runs 512-bit operations as two halves): the same on every row.
#: ``kernel_share``: the build's Dr.Jit kernel time over its wall time on the measured map (low:
#: host work, e.g. DSM's float64 polyline, dominates and the operation count says little).
#: ``limit_per_core_s``: the larger of ``nominal_limit_per_core_s`` (pipes x clock) and
#: ``mix_limit_per_core_s`` (a loop of the kernel's own operation mix in short independent chains, :mod:`.op_mix`).
#: ``model_fraction`` (AVSM rows, where llvm-mca is installed): the most of the limit the compress loop's machine
#: code can reach by llvm-mca's model of this CPU (:mod:`.mca`), the ceiling of ``fraction_of_limit``.
MACHINE_COLUMNS = ("setting", "loop", "ops_per_insertion_packet", "lanes", "isa", "llvm_cpu", "executed_bits",
                   "ops_per_insertion", "limit_per_core_s", "nominal_limit_per_core_s", "mix_limit_per_core_s",
                   "microbench_limit_per_core_s",
                   "measured_map", "measured_per_cpu_s", "fraction_of_limit", "measured_best_per_cpu_s",
                   "fraction_of_limit_best", "model_fraction", "kernel_share", "note")


def _limit_row(machine: dict, setting: str) -> dict:
    """The machine figures of ``setting``: ``machine['kinds']`` (every setting), AVSM's own
    rows (``machine['avsm']``, the compress loop) where the setting is plain AVSM-N."""
    row = dict(machine.get("kinds", {}).get(setting, {}))
    for n, r in machine.get("avsm", {}).items():
        if setting == f"avsm-nodes={n}":
            row.update({k: r[k] for k in ("ops_per_insertion_packet", "lanes", "limit_per_core_s",
                                          "microbench_limit_per_core_s", "nominal_limit_per_core_s",
                                          "mix_limit_per_core_s", "model_fraction") if k in r})
    return row


def annotate(data: list[dict], machine: dict) -> None:
    """Add the machine figures to our rows of ``data`` (in place): vector operations per
    packet of ``lanes`` insertions, the limit they allow per core-second and the fraction
    of it reached on that row's map (median, and fastest repeat where recorded)."""
    for r in data:
        if r.get("impl") != "drjit":
            continue
        lim = _limit_row(machine, r["setting"])
        if not lim.get("ops_per_insertion_packet") or not lim.get("limit_per_core_s"):
            continue
        r.update(ops_per_insertion_packet=lim["ops_per_insertion_packet"], lanes=lim["lanes"],
                 limit_per_core_s=lim["limit_per_core_s"],
                 fraction_of_limit=r.get("insertions_per_cpu_s", math.nan) / lim["limit_per_core_s"])
        if "insertions_per_cpu_s_best" in r:
            r["fraction_of_limit_best"] = r["insertions_per_cpu_s_best"] / lim["limit_per_core_s"]


def machine_rows(data: list[dict], machine: dict) -> list[dict]:
    """``machine.csv``: one row per setting of ``machine['kinds']`` (:data:`MACHINE_COLUMNS`):
    vector operations per insertion packet (from the build kernel's LLVM IR), the limit per
    core-second, and our rate on the map with the most segments per texel as a fraction of
    it, as the median of the repeats and as their fastest."""
    out = []
    for setting in machine.get("kinds", {}):
        lim = _limit_row(machine, setting)
        row = {k: lim.get(k, machine.get(k, "")) for k in MACHINE_COLUMNS}
        row["setting"] = setting
        n, lanes = lim.get("ops_per_insertion_packet"), lim.get("lanes")
        ours = [r for r in data if r.get("impl") == "drjit" and r.get("setting") == setting
                and "fraction_of_limit" in r]
        if n and lanes:
            row["ops_per_insertion"] = n / lanes
        if ours:
            best = max(ours, key=lambda r: r["mean_count"])
            row.update(measured_map=best["map"], measured_per_cpu_s=best["insertions_per_cpu_s"],
                       fraction_of_limit=best["fraction_of_limit"],
                       measured_best_per_cpu_s=best.get("insertions_per_cpu_s_best", ""),
                       fraction_of_limit_best=best.get("fraction_of_limit_best", ""))
            if best.get("build_s"):
                row["kernel_share"] = best.get("build_kernel_s", math.nan) / best["build_s"]
        out.append(row)
    return out


def summary(data, peers, machine, scal, skip, notes, seconds) -> dict:
    """Headline numbers of one run: AVSM-8 rates and speed-ups on the ~100 segments per
    texel map, machine fraction, Mitsuba time ratios, scaling slopes, skipping savings."""
    def pick(setting, impl="drjit", key="insertions_per_s", mp=None):
        rs = [r for r in data if r["setting"] == setting and r["impl"] == impl and (mp is None or r["map"] == mp)]
        return max((r.get(key, float("nan")) for r in rs), default=float("nan"))
    mid = [m for m in dict.fromkeys(r["map"] for r in data) if m.endswith("x 100")]
    mid = mid[0] if mid else None
    return {
        "avsm8_insertions_per_s": pick("avsm-nodes=8", mp=mid),
        "avsm8_insertions_per_cpu_s": pick("avsm-nodes=8", key="insertions_per_cpu_s", mp=mid),
        "avsm8_lookups_per_s": pick("avsm-nodes=8", key="lookups_per_s", mp=mid),
        "avsm8_speedup_vs_numpy": pick("avsm-nodes=8", key="speedup_vs_numpy_same_subset", mp=mid),
        "avsm8_speedup_vs_numba": pick("avsm-nodes=8", key="speedup_vs_numba", mp=mid),
        "fom8_speedup_vs_numba": pick("fom-harmonics=8", key="speedup_vs_numba", mp=mid),
        "avsm8_speedup_vs_warp": pick("avsm-nodes=8", key="speedup_vs_warp", mp=mid),
        "fom8_speedup_vs_warp": pick("fom-harmonics=8", key="speedup_vs_warp", mp=mid),
        "warp_module_load_s": {r["setting"]: r["jit_s"] for r in data if r["impl"] == "warp"},
        "lookup_speedup_vs_numba": {f"{r['setting']} | {r['map']}": r["lookup_speedup_vs_numba"]
                                    for r in data if r["impl"] == "drjit" and "lookup_speedup_vs_numba" in r},
        "machine_fraction_avsm8": machine.get("avsm", {}).get(8, {}).get("fraction_of_limit"),
        "machine_fraction_avsm8_best": pick("avsm-nodes=8", key="fraction_of_limit_best",
                                            mp=max(data, key=lambda r: r["mean_count"])["map"] if data else None),
        "machine_fraction_best_by_setting": {r["setting"]: r["fraction_of_limit_best"]
                                             for r in machine_rows(data, machine) if r["fraction_of_limit_best"] != ""},
        "machine_limit_avsm8_per_core_s": machine.get("avsm", {}).get(8, {}).get("limit_per_core_s"),
        "machine_model_fraction_avsm8": machine.get("avsm", {}).get(8, {}).get("model_fraction"),
        "machine_fraction_by_setting": {k: r.get("fraction_of_limit") for k, r in machine.get("kinds", {}).items()},
        "ops_per_insertion_packet_by_setting": {k: r.get("ops_per_insertion_packet")
                                                for k, r in machine.get("kinds", {}).items()},
        "mitsuba_time_ratio": {r["setting"]: r["ratio"] for r in peers
                               if r.get("peer") == "mitsuba" and "ratio" in r},
        "scaling_slopes": slopes(scal),
        "skipping_time_without_over_with": {f"{r['case']} | {r['variant']}": r["time_vs_skipping"]
                                            for r in skip if r["skipping"] is False},
        "seconds": seconds,
        "notes": notes,
    }


def print_report(data, peers, machine, skip, mem, summary):
    """The main numbers on stdout."""
    for r in data:
        extra = ""
        if r["impl"] == "drjit":
            for key, lab in (("speedup_vs_numpy_same_subset", "NumPy"), ("speedup_vs_numba", "Numba"),
                             ("lookup_speedup_vs_numba", "Numba lookups"), ("speedup_vs_warp", "Warp"),
                             ("lookup_speedup_vs_warp", "Warp lookups")):
                if key in r:
                    extra += f"  x{r[key]:.1f} vs {lab}"
        print(f"{r['map']:>12s} {r['impl']:6s} {r['setting']:32s} {r['insertions_per_s'] / 1e6:9.2f} M ins/s "
              f"({r.get('insertions_per_cpu_s', float('nan')) / 1e6:8.2f} per CPU-s) "
              f"{r['lookups_per_s'] / 1e6:8.2f} M lookups/s{extra}")
    for r in peers:
        if r.get("peer") == "mitsuba" and "ratio" in r:
            print(f"mitsuba {r['setting']:18s} rmse {r['rep_rmse_vs_exact']:.4f} -> spp {r['spp']:6d}: "
                  f"{r['seconds']:.3f} s vs ours {r['ours_total_s']:.4f} s (x{r['ratio']:.1f}; "
                  f"equal cost at {r['break_even_receivers']:.0f} receivers)")
    best = {r["setting"]: r for r in machine_rows(data, machine)}

    def frac_best(setting):
        f = best.get(setting, {}).get("fraction_of_limit_best", "")
        return f"; fastest repeat {100 * f:.0f} %" if f != "" else ""
    for n, r in machine.get("avsm", {}).items():
        print(f"machine AVSM-{n}: {r['ops_per_insertion_packet']} vector ops / {r['lanes']} insertions; limit "
              f"{r['limit_per_core_s'] / 1e6:.0f} M/core-s (nominal {r['nominal_limit_per_core_s'] / 1e6:.0f}, its op "
              f"mix {r['mix_limit_per_core_s'] / 1e6:.0f}); "
              f"ours {r.get('measured_per_cpu_s', float('nan')) / 1e6:.1f} M/CPU-s = "
              f"{100 * r.get('fraction_of_limit', float('nan')):.0f} %{frac_best(f'avsm-nodes={n}')}")
    for name, r in machine.get("kinds", {}).items():
        if "ops_per_insertion_packet" in r:
            print(f"machine {name:32s} {r['ops_per_insertion_packet']:5d} vector ops / {r['lanes']} insertions "
                  f"({r['loop'] or 'no loop'}); limit {r.get('limit_per_core_s', float('nan')) / 1e6:8.1f} M/core-s; "
                  f"ours {r.get('measured_per_cpu_s', float('nan')) / 1e6:7.1f} M/CPU-s = "
                  f"{100 * r.get('fraction_of_limit', float('nan')):.0f} %{frac_best(name)}")
        else:
            print(f"machine {name:32s} {r.get('note', '')}")
    for r in skip:
        print(f"skip {r['case'][:60]:60s} | {r['variant'][:48]:48s} {r['seconds'] * 1e3:9.2f} ms "
              f"(x{r.get('time_vs_skipping', float('nan')):.2f}; CPU x{r.get('cpu_vs_skipping', float('nan')):.2f}; "
              f"kernels x{r.get('kernel_vs_skipping', float('nan')):.2f})")
    for r in mem:
        print(f"memory {r['setting']:24s} formula {r['formula_bytes'] / 1e6:8.2f} MB | build peak "
              f"{r['build_peak'] / 1e6:8.2f} MB (RSS {r['build_peak_rss'] / 1e6:.2f}, Dr.Jit "
              f"{r['build_peak_jit'] / 1e6:.2f}; x{r.get('build_peak_over_formula', float('nan')):.1f} of the formula) "
              f"| lookup peak "
              f"{r['lookup_peak'] / 1e6:8.2f} MB")
    print(f"bench: {summary['seconds']:.0f} s; notes: {summary['notes']}")

