"""`stagectl bench io` runs end to end (structure only: timing figures belong to the benchmark itself)."""

from __future__ import annotations

import argparse

import pytest

from stagectl.bench import io as bench_io


@pytest.mark.realtime  # 50 real 1 kHz cycles: on a loaded 2-core machine the enable can miss 50 TPDOs
def test_bench_io_smoke():
    parser = argparse.ArgumentParser()
    bench_io.add_arguments(parser)
    args = parser.parse_args(["--duration", "0.05", "--skip-serial", "--skip-socketcand"])
    out = bench_io.run(args)
    v = out["canopen_virtual"]
    assert v["slots"] == 50 and v["cycles_run"] + v["skipped_overrun"] == 50
    assert v["round_trip_us"]["p50"] > 0 and v["response_us"]["p50"] > 0
    assert 0.0 <= v["missed_pct"] <= 100.0
    assert 0 <= v["max_consecutive_missed_tpdo"] <= v["missed_tpdo"]
    assert set(out["targets"]["met"]) == {"canopen_virtual_missed_pct", "round_trip_p99_us"}
    assert out["baseline_sleep_loop"]["slots"] == 50
    assert out["targets"]["floor_missed_pct"] == out["baseline_sleep_loop"]["missed_pct"]
    assert {r["thread"] for r in v["threads"]} >= {"MainThread", "sim-world"}
    assert v["during_cycles"]["page_faults"] >= 0
    assert v["wake_late_us"]["p50"] >= 0.0


def test_cpus_option_parses_checks_and_pins(monkeypatch):
    """``--cpus``: a list, ``all``, or the default (one CPU, the highest allowed, under FIFO; else unchanged);
    a bad list is one ConfigError line naming the option. The process affinity is what the kernel reports."""
    import os

    from stagectl.errors import ConfigError

    allowed = sorted(os.sched_getaffinity(0))
    applied: list[list[int]] = []
    monkeypatch.setattr(os, "sched_setaffinity", lambda pid, cpus: applied.append(sorted(cpus)))
    assert bench_io._set_cpus(None, fifo=False) == allowed and applied == []
    bench_io._set_cpus(None, fifo=True)
    bench_io._set_cpus(f"{allowed[0]}", fifo=False)
    bench_io._set_cpus("all", fifo=True)
    assert applied == ([[allowed[-1]], [allowed[0]]] if len(allowed) > 1 else [])
    for bad in ("x", "1,a", f"{max(allowed) + 1}", ","):
        with pytest.raises(ConfigError, match="--cpus"):
            bench_io._set_cpus(bad, fifo=False)


def test_thread_scheduling_reads_back_every_thread():
    """The threads' policy, priority and CPUs as the kernel reports them (what ``--fifo`` really achieved)."""
    import os
    import threading

    release = threading.Event()
    t = threading.Thread(target=release.wait, name="bench-io-probe", daemon=True)
    t.start()
    try:
        rows = {r["thread"]: r for r in bench_io.thread_scheduling()}
    finally:
        release.set()
        t.join(10.0)
    assert {"MainThread", "bench-io-probe"} <= set(rows)
    main = rows["MainThread"]
    assert main["policy"] == bench_io._POLICIES[os.sched_getscheduler(0)]
    assert main["priority"] == os.sched_getparam(0).sched_priority
    assert main["cpus"] == sorted(os.sched_getaffinity(0))
    assert set(bench_io.rt_throttling()) == {"runtime_us", "period_us"}
