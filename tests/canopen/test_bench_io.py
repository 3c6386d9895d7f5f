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
