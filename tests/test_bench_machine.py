"""The benchmark's machine table (``machine.csv`` and the machine columns of ``data.csv``):
every setting's vector operations per insertion and achieved fraction of the limit."""
import math

import pytest

from experiments.bench import report, throughput


def _machine():
    return {
        "avsm": {8: {"ops_per_insertion_packet": 600, "lanes": 8, "limit_per_core_s": 60e6}},
        "kinds": {
            "avsm-nodes=8": {"ops_per_insertion_packet": 600, "lanes": 8, "loop": "avsm_compress",
                             "limit_per_core_s": 60e6},
            "fom-harmonics=8": {"ops_per_insertion_packet": 90, "lanes": 8, "loop": "",
                                "limit_per_core_s": 400e6},
            "greedy": {"note": "no Dr.Jit build kernel (a host build, or no build work)"},
        },
    }


def _data():
    row = dict(impl="drjit", setting="avsm-nodes=8", map="32^2 x 10", mean_count=10,
               insertions_per_cpu_s=20e6, insertions_per_cpu_s_best=24e6)
    return [row, dict(row, map="32^2 x 1000", mean_count=1000, insertions_per_cpu_s=30e6,
                      insertions_per_cpu_s_best=45e6),
            dict(row, impl="numba", map="32^2 x 1000", mean_count=1000),
            dict(impl="drjit", setting="fom-harmonics=8", map="32^2 x 1000", mean_count=1000,
                 insertions_per_cpu_s=100e6),
            dict(impl="drjit", setting="greedy", map="32^2 x 10", mean_count=10, insertions_per_cpu_s=1e5)]


def test_annotate_adds_the_limit_and_fractions_to_our_rows():
    data = _data()
    report.annotate(data, _machine())
    assert data[0]["fraction_of_limit"] == pytest.approx(20 / 60)
    assert data[1]["fraction_of_limit"] == pytest.approx(30 / 60)
    assert data[1]["fraction_of_limit_best"] == pytest.approx(45 / 60)
    assert data[1]["ops_per_insertion_packet"] == 600 and data[1]["lanes"] == 8
    assert "fraction_of_limit" not in data[2]                  # the Numba peer's row
    assert data[3]["fraction_of_limit"] == pytest.approx(0.25) and "fraction_of_limit_best" not in data[3]
    assert "fraction_of_limit" not in data[4]                  # no Dr.Jit kernel: no limit


def test_machine_rows_one_per_setting_on_the_densest_map():
    data = _data()
    report.annotate(data, _machine())
    rows = {r["setting"]: r for r in report.machine_rows(data, _machine())}
    assert set(rows) == {"avsm-nodes=8", "fom-harmonics=8", "greedy"}
    assert all(set(r) == set(report.MACHINE_COLUMNS) for r in rows.values())
    avsm = rows["avsm-nodes=8"]
    assert avsm["measured_map"] == "32^2 x 1000" and avsm["ops_per_insertion"] == 75
    assert avsm["fraction_of_limit"] == pytest.approx(0.5) and avsm["fraction_of_limit_best"] == pytest.approx(0.75)
    assert rows["fom-harmonics=8"]["fraction_of_limit_best"] == ""
    assert rows["greedy"]["note"] and rows["greedy"]["fraction_of_limit"] == ""
    s = report.summary(data, [], _machine(), [], [], [], 1.0)
    assert s["machine_fraction_best_by_setting"] == {"avsm-nodes=8": pytest.approx(0.75)}
    assert s["machine_fraction_avsm8_best"] == pytest.approx(0.75)
    assert math.isnan(s["avsm8_insertions_per_s"])             # no '... x 100' map in this data


def test_cpu_logged_records_every_call():
    log = []
    fn = throughput._cpu_logged(lambda: 3, log)
    assert [fn(), fn()] == [3, 3] and len(log) == 2 and all(c >= 0 for c in log)
