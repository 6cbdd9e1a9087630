"""The benchmark skips, with a note, a setting whose build peak estimated from two small
probes would exceed its share of MemAvailable (experiments/bench/memory_guard.py)."""
import pytest

from experiments.bench import memory_guard, scaling
from experiments.bench.settings import counts_map


class _Progress:
    def update(self, n=1):
        pass


@pytest.fixture
def small_probes(monkeypatch):
    monkeypatch.setattr(memory_guard, "PROBE_SEGMENTS", 2000)


def test_available_bytes_reads_meminfo():
    avail = memory_guard.available_bytes()
    assert avail > 0
    with open("/proc/meminfo") as fh:
        total = next(float(line.split()[1]) * 1024 for line in fh if line.startswith("MemTotal:"))
    assert avail <= total


def test_too_big_under_a_tiny_limit_only(monkeypatch, small_probes):
    seg = counts_map(16, 20)                                      # 256 texels, ~5000 segments
    notes = []
    monkeypatch.setattr(memory_guard, "available_bytes", lambda: 1e12)
    assert not memory_guard.too_big("avsm", {"nodes": 4}, seg, "16^2 x 20", notes) and notes == []
    need, slope = memory_guard.estimate_peak("avsm", {"nodes": 4}, seg)
    assert need > 0 and slope >= 0
    monkeypatch.setattr(memory_guard, "available_bytes", lambda: 2 * need / 4)     # half of the need fits
    assert memory_guard.too_big("avsm", {"nodes": 4}, seg, "16^2 x 20", notes)
    assert len(notes) == 1 and notes[0].startswith(f"avsm-nodes=4 skipped on 16^2 x 20 ({seg.n_segments} segments)")
    assert "MemAvailable" in notes[0]


def test_maps_within_the_probe_are_not_probed(monkeypatch):
    monkeypatch.setattr(memory_guard, "available_bytes", lambda: 1.0)
    monkeypatch.setattr(memory_guard, "estimate_peak", lambda *a: pytest.fail("probed"))
    assert not memory_guard.too_big("avsm", {"nodes": 4}, counts_map(8, 10), "8^2 x 10", [])


def test_scaling_skips_every_setting_under_a_fake_tiny_limit(monkeypatch, small_probes):
    """A 1 kB MemAvailable: one note per setting but exact (its build allocates nothing: it
    fits and runs), no row for them."""
    monkeypatch.setattr(memory_guard, "available_bytes", lambda: 1e3)
    P = dict(scale_texels=[16], scale_counts=[], scale_side=16, scale_nodes=[], scale_repeats=1)
    notes = []
    rows = scaling.scaling(P, _Progress(), notes)
    assert {r["setting"] for r in rows} == {"exact"} and len(notes) >= 4
    assert all(" skipped on scaling texels=256 " in n for n in notes)


@pytest.mark.parametrize("rss, counted", [(64 * 1024, False), (float("nan"), False), (4 << 20, True)])
def test_rss_page_noise_is_not_extrapolated(monkeypatch, small_probes, rss, counted):
    """RSS growth under RSS_NOISE_BYTES (page noise of a build that allocates nothing, seen in
    2 of 60 exact probes) estimates no peak; larger growth and the watermark count."""
    class FakeMeter:
        heap_bytes, rss_bytes = 0.0, rss

        def __init__(self):
            FakeMeter.rss_bytes = rss if not calls else 2 * rss          # growth between probes
            calls.append(1)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False
    calls = []
    monkeypatch.setattr(memory_guard, "Meter", FakeMeter)
    need, slope = memory_guard.estimate_peak("exact", {}, counts_map(16, 20))
    assert len(calls) == 2
    assert (need > 0 and slope > 0) if counted else (need == 0 and slope == 0)
