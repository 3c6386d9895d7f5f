"""Smoke test of the serial streaming benchmark plumbing (no timing assertions: figures live in the bench)."""

from __future__ import annotations

from stagectl.bench.io_serial import run_serial_bench


def test_serial_bench_runs_both_transports_without_loss_of_integrity():
    res = run_serial_bench(1000.0, 0.3)
    for t in ("pty", "tcp"):
        r = res[t]
        assert r["frames_sent"] > 0 and r["frames_received"] > 0
        assert r["crc_errors"] == 0 and r["bytes_discarded"] == 0
        assert r["frames_received"] <= r["frames_sent"]
        assert 0 < r["latency_us"]["p50"] <= r["latency_us"]["p99"] <= r["latency_us"]["max"]
