"""Telemetry ring + writer: wraparound, drop counting, flush, rotation, write errors, docs/recordings.md CSV."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np
import pytest

from stagectl.daemon.telemetry import TelemetryRing, TelemetryWriter, WriterSettings

COLS = ("t", "x", "u", "x_ref", "v_ref", "a_ref", "e", "u_pid", "u_dob", "u_ff")


def _row(k: int) -> tuple[float, ...]:
    t = k * 1e-3
    return (t, 1e-9 * k, 0.5 * k, 2e-9 * k, 0.0, 0.0, 1e-9 * k, 0.1, 0.2, 0.3)


def _read_csv(path: Path) -> tuple[list[str], np.ndarray]:
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array([[float(c) for c in r] for r in rows[1:]], dtype=float).reshape(-1, len(rows[0]))


def test_ring_wraparound_keeps_order_and_values():
    dut = TelemetryRing(COLS, capacity_rows=8)
    assert dut.capacity == 8
    got = []
    for k in range(37):  # several wraps, draining in uneven pieces
        dut.append(_row(k))
        if k % 3 == 2:
            first, rows = dut.drain()
            assert first == len(got)
            got.extend(rows.tolist())
    got.extend(dut.drain()[1].tolist())
    assert dut.dropped == 0
    np.testing.assert_array_equal(np.array(got), np.array([_row(k) for k in range(37)]))


def test_ring_full_counts_drops_without_overwriting():
    dut = TelemetryRing(COLS, capacity_rows=5)  # rounded up to 8
    for k in range(20):
        dut.append(_row(k))
    assert dut.dropped == 12
    first, rows = dut.drain()
    assert first == 0
    np.testing.assert_array_equal(rows[:, 0], np.arange(8) * 1e-3)  # the oldest rows survive
    dut.append(_row(99))
    assert dut.drain()[1][0, 0] == pytest.approx(0.099)


def test_ring_bad_row_counted_never_raises():
    dut = TelemetryRing(COLS, capacity_rows=4)
    dut.append((1.0, 2.0))  # wrong length
    dut.append(("a",) * len(COLS))  # not numbers
    assert dut.bad_rows == 2
    assert dut.backlog == 0


def _settings(tmp_path: Path, **kw) -> WriterSettings:
    base = dict(directory=tmp_path / "telemetry", flush_interval_s=0.05, retry_s=0.0)
    base.update(kw)
    return WriterSettings(**base)


def test_writer_writes_recordings_csv_and_flushes_on_stop(tmp_path):
    ring = TelemetryRing(COLS, 1024)
    dut = TelemetryWriter(ring, _settings(tmp_path))
    dut.start()
    for k in range(500):
        ring.append(_row(k))
    assert dut.flush(timeout=10.0)
    st = dut.status()
    assert st["rows_written"] == 500 and st["dropped"] == 0 and st["error"] is None
    for k in range(500, 1700):  # more than the capacity overall: the writer keeps up
        ring.append(_row(k))
        if k % 512 == 0:
            assert dut.flush(timeout=10.0)
    assert dut.stop(timeout=10.0)
    files = sorted((tmp_path / "telemetry").glob("telemetry-*.csv"))
    assert len(files) == 1
    header, data = _read_csv(files[0])
    assert header == list(COLS)
    assert data.shape == (1700, len(COLS))
    np.testing.assert_allclose(data, np.array([_row(k) for k in range(1700)]), rtol=1e-11, atol=0)
    assert np.all(np.diff(data[:, 0]) > 0)  # docs/recordings.md: time strictly increasing


def test_named_recording_captures_exactly_between_start_and_stop(tmp_path):
    ring = TelemetryRing(COLS, 256)
    dut = TelemetryWriter(ring, _settings(tmp_path, continuous=False))
    dut.start()
    for k in range(100):
        ring.append(_row(k))
    path = dut.record_start("run-1")
    assert path == tmp_path / "telemetry" / "run-1.csv"
    for k in range(100, 250):
        ring.append(_row(k))
    info = dut.record_stop()
    for k in range(250, 300):
        ring.append(_row(k))
    dut.stop()
    assert info["rows"] == 150 and info["error"] is None
    header, data = _read_csv(path)
    assert header == list(COLS)
    np.testing.assert_allclose(data[:, 0], np.arange(100, 250) * 1e-3, rtol=1e-12)


@pytest.mark.parametrize("name", ["../evil", "/etc/passwd", "a/b", "", ".hidden", "x..y", "a\nb", 5])
def test_record_rejects_path_traversal(tmp_path, name):
    dut = TelemetryWriter(TelemetryRing(COLS, 16), _settings(tmp_path))
    with pytest.raises(ValueError, match="^name:"):
        dut.record_start(name)
    assert not (tmp_path / "evil.csv").exists()


def test_record_rejects_existing_file_and_second_start(tmp_path):
    dut = TelemetryWriter(TelemetryRing(COLS, 16), _settings(tmp_path, continuous=False))
    dut.record_start("a")
    with pytest.raises(ValueError, match="already running"):
        dut.record_start("b")
    dut.record_stop()
    with pytest.raises(ValueError, match="already exists"):
        dut.record_start("a")
    with pytest.raises(ValueError, match="^action:"):
        dut.record_stop()
    dut.stop()


def test_rotation_splits_files_each_with_header_and_prunes(tmp_path):
    ring = TelemetryRing(COLS, 4096)
    dut = TelemetryWriter(ring, _settings(tmp_path, rotate_bytes=20_000, keep_files=3, chunk_rows=64))
    for k in range(3000):
        ring.append(_row(k))
        if k % 64 == 63:
            dut.flush()  # no thread: drains synchronously
    dut.stop()
    files = sorted((tmp_path / "telemetry").glob("telemetry-*.csv"))
    st = dut.status()
    assert st["files_rotated"] >= 4
    assert len(files) == 3  # older ones deleted
    ts = []
    for f in files:
        header, data = _read_csv(f)
        assert header == list(COLS)
        ts.extend(data[:, 0])
    # the kept files are the newest ones, contiguous and complete up to the last row
    assert ts[-1] == pytest.approx(2.999)
    np.testing.assert_allclose(np.diff(ts), 1e-3, rtol=1e-6)


def test_unwritable_directory_is_reported_and_recovers(tmp_path):
    blocker = tmp_path / "telemetry"
    blocker.write_text("a file where the directory should be")  # works even as root
    ring = TelemetryRing(COLS, 64)
    dut = TelemetryWriter(ring, _settings(tmp_path))
    for k in range(10):
        ring.append(_row(k))
    dut.flush()
    st = dut.status()
    assert st["error"] and "telemetry" in st["error"]
    assert st["lost"] == 10 and st["dropped"] == 0 and ring.backlog == 0  # the ring keeps draining
    blocker.unlink()
    for k in range(10, 15):
        ring.append(_row(k))
    dut.flush()
    dut.stop()
    st = dut.status()
    assert st["error"] is None and st["rows_written"] == 5


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="/dev/full not available")
def test_full_disk_is_reported(tmp_path):
    ring = TelemetryRing(COLS, 64)
    dut = TelemetryWriter(ring, _settings(tmp_path, continuous=False))
    d = tmp_path / "telemetry"
    d.mkdir()
    path = dut.record_start("full")
    path.unlink()
    path.symlink_to("/dev/full")  # the recording's file now writes to a device that is always full
    os.close(dut._rec.csv.fd)  # reopen onto the full device: same object, real ENOSPC from the kernel
    dut._rec.csv.fd = os.open(path, os.O_WRONLY)
    for k in range(10):
        ring.append(_row(k))
    dut.flush()
    st = dut.status()
    assert st["error"] and "No space left" in st["error"]
    info = dut.record_stop()
    assert "No space left" in str(info["error"])
    dut.stop()


def test_taps_get_every_drained_row_with_its_ring_index_and_a_failing_tap_is_removed(tmp_path):
    ring = TelemetryRing(COLS, 64)
    dut = TelemetryWriter(ring, _settings(tmp_path, continuous=False))
    got: list[tuple[int, int]] = []

    def bad(first, rows):
        raise RuntimeError("stream broke")

    dut.add_tap(lambda first, rows: got.append((first, len(rows))))
    dut.add_tap(bad)
    for k in range(10):
        ring.append(_row(k))
    dut.flush()
    for k in range(10, 15):
        ring.append(_row(k))
    dut.flush()
    dut.stop()
    idx = [i for first, n in got for i in range(first, first + n)]
    assert idx == list(range(15))  # every row once, in order, indices without gaps
    assert bad not in dut._taps
