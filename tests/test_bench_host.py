"""benchmarks/_host.py: the host's CPU accounting (steal, idle, busy) printed beside timings."""

from __future__ import annotations

import pytest

from _benchmarks import load_benchmark

# two readings of /proc/stat (proc(5) layout: user nice system idle iowait irq softirq steal
# guest guest_nice), 100 ticks apart on 2 CPUs
BEFORE = """cpu  1000 10 200 5000 20 0 5 300 0 0
cpu0 500 5 100 2500 10 0 3 150 0 0
intr 12345
"""
AFTER = """cpu  1060 10 210 5020 25 0 5 330 0 0
cpu0 530 5 105 2510 12 0 3 165 0 0
"""


def test_shares_against_the_tick_differences():
    host = load_benchmark("_host")
    before, after = host.parse_cpu_line(BEFORE), host.parse_cpu_line(AFTER)
    assert before["steal"] == 300 and after["user"] == 1060 and before["iowait"] == 20
    s = host.shares(before, after)
    # differences: user 60, system 10, idle 20, iowait 5, steal 30: 125 ticks
    assert s["steal_pct"] == pytest.approx(100 * 30 / 125)
    assert s["idle_pct"] == pytest.approx(100 * 25 / 125)
    assert s["busy_pct"] == pytest.approx(100 * 70 / 125)
    assert s["steal_pct"] + s["idle_pct"] + s["busy_pct"] == pytest.approx(100.0)


def test_missing_or_empty_readings_give_no_shares(tmp_path):
    host = load_benchmark("_host")
    assert host.parse_cpu_line("intr 1\n") is None
    assert host.cpu_ticks(tmp_path / "no_such_file") is None
    reading = host.parse_cpu_line(BEFORE)
    assert host.shares(None, reading) == {} and host.shares(reading, reading) == {}
    # a kernel without the steal column (before Linux 2.6.11) reads as zero steal
    short = host.parse_cpu_line("cpu 1 2 3 4\n")
    assert short["steal"] == 0 and short["idle"] == 4


def test_the_speed_probe_repeats_one_fixed_amount_of_work():
    """The probe times the same work every call and in every process (a change of its time is
    the host's): two builds of its workload give bit-identical reduced systems, call after
    call, of the documented size."""
    import numpy as np

    host = load_benchmark("_host")
    a, b = host.probe_workload(), host.probe_workload()
    assert a.num_poses == 14 and 2500 <= a.num_observations <= 3600
    first = a()
    H = first.H.copy()
    assert H.shape == (84, 84) and np.all(np.isfinite(H)) and np.abs(H).max() > 0
    np.testing.assert_array_equal(b().H, H)
    np.testing.assert_array_equal(a().H, H)
    probe = host.speed_probe(repeats=3)
    assert probe["probe_ms"] > 0 and np.isfinite(probe["probe_spread"])
    assert host.probe_text(probe).startswith("host probe ")
