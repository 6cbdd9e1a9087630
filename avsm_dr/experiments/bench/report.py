"""The benchmark's summary (``meta.json``) and the main numbers on stdout."""
from __future__ import annotations

from .scaling import slopes


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
        "lookup_speedup_vs_numba": {f"{r['setting']} | {r['map']}": r["lookup_speedup_vs_numba"]
                                    for r in data if r["impl"] == "drjit" and "lookup_speedup_vs_numba" in r},
        "machine_fraction_avsm8": machine.get("avsm", {}).get(8, {}).get("fraction_of_limit"),
        "machine_limit_avsm8_per_core_s": machine.get("avsm", {}).get(8, {}).get("limit_per_core_s"),
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
                             ("lookup_speedup_vs_numba", "Numba lookups")):
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
    for n, r in machine.get("avsm", {}).items():
        print(f"machine AVSM-{n}: {r['ops_per_insertion_packet']} vector ops / {r['lanes']} insertions; limit "
              f"{r['limit_per_core_s'] / 1e6:.0f} M/core-s (nominal {r['nominal_limit_per_core_s'] / 1e6:.0f}); "
              f"ours {r.get('measured_per_cpu_s', float('nan')) / 1e6:.1f} M/CPU-s = "
              f"{100 * r.get('fraction_of_limit', float('nan')):.0f} %")
    for name, r in machine.get("kinds", {}).items():
        if "ops_per_insertion_packet" in r:
            print(f"machine {name:32s} {r['ops_per_insertion_packet']:5d} vector ops / {r['lanes']} insertions "
                  f"({r['loop'] or 'no loop'}); limit {r.get('limit_per_core_s', float('nan')) / 1e6:8.1f} M/core-s; "
                  f"ours {r.get('measured_per_cpu_s', float('nan')) / 1e6:7.1f} M/CPU-s = "
                  f"{100 * r.get('fraction_of_limit', float('nan')):.0f} %")
        else:
            print(f"machine {name:32s} {r.get('note', '')}")
    for r in skip:
        print(f"skip {r['case'][:60]:60s} | {r['variant'][:48]:48s} {r['seconds'] * 1e3:9.2f} ms "
              f"(x{r.get('time_vs_skipping', float('nan')):.2f}; CPU x{r.get('cpu_vs_skipping', float('nan')):.2f}; "
              f"kernels x{r.get('kernel_vs_skipping', float('nan')):.2f})")
    for r in mem:
        print(f"memory {r['setting']:24s} formula {r['formula_bytes'] / 1e6:8.2f} MB | build peak "
              f"{r['build_peak'] / 1e6:8.2f} MB (RSS {r['build_peak_rss'] / 1e6:.2f}, Dr.Jit "
              f"{r['build_peak_jit'] / 1e6:.2f}) | lookup peak "
              f"{r['lookup_peak'] / 1e6:8.2f} MB")
    print(f"bench: {summary['seconds']:.0f} s; notes: {summary['notes']}")

