"""Telemetry that loses nothing: a preallocated ring buffer written by the loop, drained by a writer thread.

Data path::

    loop thread --append(row)--> TelemetryRing (numpy, capacity C rows, single producer / single consumer)
                                        |
    writer thread (non-RT) <--drain-----+--> continuous CSV files (rotated, oldest deleted)
                                        +--> named recording ``<dir>/<NAME>.csv`` (``record start NAME``)

CSV follows docs/recordings.md, written by :class:`stagectl.ident.recording.RecordingCsv` (the same writer as
``stagectl simulate``'s): one header row with the loop's column names, ``,`` separator, one row per control
sample, SI units. Every file (each rotated piece and each recording) has its own header and feeds
``stagectl identify`` unchanged.

Ring protocol (lock-free under the GIL): the producer owns ``_head`` (rows written so far), the consumer
owns ``_tail`` (rows consumed so far); row k lives at ``buf[k mod C]``. The producer writes the row first
and then publishes ``_head = k + 1``; when ``_head - _tail == C`` the ring is full and the row is counted in
``dropped`` instead of overwriting unread data. No lock, no allocation beyond numpy's row assignment, no
syscall: :meth:`TelemetryRing.append` is real-time safe and never raises.

A write error (full disk, unwritable or missing directory) never reaches the loop: the writer keeps draining
the ring (counting ``lost`` rows), reports the error in :meth:`TelemetryWriter.status`, and retries opening
a file every ``retry_s``.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import re
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
import numpy as np

from stagectl.daemon._sched import demote_to_normal_priority
from stagectl.config.daemon import TelemetryConfig
from stagectl.errors import short
from stagectl.ident.recording import RecordingCsv

log = logging.getLogger("stagectl.telemetry")

#: a recording name: letters, digits, ``._-``; no path separators, no leading dot (so no ``..``)
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,99}$")


class TelemetryRing:
    """Preallocated single-producer/single-consumer ring of float64 rows.

    Parameters
    ----------
    columns : sequence of str
        Column names (one per element of every row).
    capacity_rows : int
        Minimum capacity [rows]; rounded up to a power of two. At 1 kHz, 65536 rows hold 65 s of backlog.
    """

    def __init__(self, columns: Sequence[str], capacity_rows: int = 65536) -> None:
        if not columns:
            raise ValueError("columns: at least one column is needed")
        if capacity_rows < 2:
            raise ValueError(f"capacity_rows: must be >= 2 (got {capacity_rows})")
        cap = 1 << (int(capacity_rows) - 1).bit_length()
        self.columns: tuple[str, ...] = tuple(columns)
        self.capacity = cap
        self._mask = cap - 1
        self._buf = np.zeros((cap, len(self.columns)), dtype=np.float64)
        self._head = 0  # written by the producer only
        self._tail = 0  # written by the consumer only
        self.dropped = 0  # producer only: rows not stored because the ring was full
        self.bad_rows = 0  # producer only: rows of the wrong length / not numbers

    # ------------------------------------------------------------------ producer (loop thread)
    def append(self, row: Sequence[float]) -> None:
        """Store one row. Real-time safe: no lock, no syscall, never blocks, never raises."""
        h = self._head
        if h - self._tail > self._mask:
            self.dropped += 1
            return
        try:
            self._buf[h & self._mask] = row
        except (ValueError, TypeError):
            self.bad_rows += 1
            return
        self._head = h + 1

    # ------------------------------------------------------------------ consumer (writer thread)
    @property
    def head(self) -> int:
        """Index of the next row the producer will write (= rows written so far)."""
        return self._head

    @property
    def backlog(self) -> int:
        """Rows written but not yet consumed."""
        return self._head - self._tail

    def drain(self, max_rows: int | None = None) -> tuple[int, np.ndarray]:
        """Copy out the unread rows (oldest first) and release them.

        Returns ``(first_index, rows)`` where ``first_index`` is the ring index of ``rows[0]``.
        Consumer side only (one thread).
        """
        t = self._tail
        h = self._head
        n = h - t
        if max_rows is not None:
            n = min(n, max_rows)
        if n <= 0:
            return t, self._buf[:0].copy()
        i0 = t & self._mask
        i1 = i0 + n
        if i1 <= self.capacity:
            out = self._buf[i0:i1].copy()
        else:
            out = np.concatenate((self._buf[i0:], self._buf[: i1 - self.capacity]))
        self._tail = t + n  # publish after the copy: the producer may now reuse these slots
        return t, out


class SharedTelemetryRing:
    """The same single-producer/single-consumer ring as :class:`TelemetryRing`, with its rows and counters in
    shared memory (:class:`stagectl.runtime.shm.LoopShm`): the loop process appends, the daemon's writer
    thread drains. ``buf`` float64[capacity, columns] (capacity a power of two), ``ctl`` the block's int64
    counters (head, tail, dropped, bad rows at the :mod:`~stagectl.runtime.shm` indices)."""

    def __init__(self, columns: Sequence[str], buf: np.ndarray, ctl: np.ndarray) -> None:
        from stagectl.runtime.shm import TEL_BAD, TEL_DROPPED, TEL_HEAD, TEL_TAIL

        cap = int(buf.shape[0])
        if cap < 2 or cap & (cap - 1) or buf.shape[1] != len(columns):
            raise ValueError(f"buf: needs a power-of-two row count and {len(columns)} columns (got {buf.shape})")
        self.columns: tuple[str, ...] = tuple(columns)
        self.capacity = cap
        self._mask = cap - 1
        self._buf = buf
        self._ctl = ctl
        self._h, self._t, self._d, self._b = TEL_HEAD, TEL_TAIL, TEL_DROPPED, TEL_BAD

    # ------------------------------------------------------------------ producer (loop process)
    def append(self, row: Sequence[float]) -> None:
        """Store one row. Real-time safe: no lock, no syscall, never blocks, never raises."""
        ctl = self._ctl
        h = int(ctl[self._h])
        if h - int(ctl[self._t]) > self._mask:
            ctl[self._d] += 1
            return
        try:
            self._buf[h & self._mask] = row
        except (ValueError, TypeError):
            ctl[self._b] += 1
            return
        ctl[self._h] = h + 1  # publish after the row is stored

    # ------------------------------------------------------------------ consumer (daemon writer thread)
    @property
    def dropped(self) -> int:
        return int(self._ctl[self._d])

    @property
    def bad_rows(self) -> int:
        return int(self._ctl[self._b])

    @property
    def head(self) -> int:
        return int(self._ctl[self._h])

    @property
    def backlog(self) -> int:
        return int(self._ctl[self._h]) - int(self._ctl[self._t])

    def drain(self, max_rows: int | None = None) -> tuple[int, np.ndarray]:
        """Copy out the unread rows (oldest first) and release them (see :meth:`TelemetryRing.drain`)."""
        t = int(self._ctl[self._t])
        n = int(self._ctl[self._h]) - t
        if max_rows is not None:
            n = min(n, max_rows)
        if n <= 0:
            return t, self._buf[:0].copy()
        i0 = t & self._mask
        i1 = i0 + n
        if i1 <= self.capacity:
            out = self._buf[i0:i1].copy()
        else:
            out = np.concatenate((self._buf[i0:], self._buf[: i1 - self.capacity]))
        self._ctl[self._t] = t + n  # publish after the copy: the producer may now reuse these slots
        return t, out


#: what the writer drains
Ring = TelemetryRing | SharedTelemetryRing


@dataclass(frozen=True)
class WriterSettings:
    """How the writer stores telemetry (built from :class:`stagectl.config.daemon.TelemetryConfig`)."""

    directory: Path
    continuous: bool = True
    prefix: str = "telemetry"
    rotate_bytes: int = 100_000_000
    rotate_s: float = 3600.0
    keep_files: int = 48
    flush_interval_s: float = 0.2
    retry_s: float = 5.0
    float_format: str = "%.12g"
    chunk_rows: int = 256


class _CsvFile:
    """One open CSV file with a header; counts bytes and rows.

    Rows go to the kernel in whole chunks with ``os.write`` (no Python buffer between): a chunk is either
    in the file completely or not at all. A failed or short write (full disk ``ENOSPC``, file-size limit
    ``EFBIG``) is undone with ``ftruncate`` back to the last complete row, so a file never ends in a
    truncated row, and the caller counts the chunk's rows as lost.
    """

    def __init__(self, path: Path, fmt: RecordingCsv, *, exclusive: bool) -> None:
        self.path = path
        self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC | (os.O_EXCL if exclusive else os.O_TRUNC),
                          0o640)
        self.bytes = 0
        self.rows = 0
        try:
            self._write_all(fmt.header.encode("ascii"))
        except OSError:
            self.close()
            try:
                path.unlink()
            except OSError:
                pass
            raise
        self.opened_mono = time.monotonic()

    def _write_all(self, data: bytes) -> None:
        view = memoryview(data)
        done = 0
        try:
            while done < len(view):
                n = os.write(self.fd, view[done:])
                if n <= 0:  # pragma: no cover - a regular file never returns 0 for a non-empty write
                    raise OSError(errno.EIO, "write returned 0")
                done += n
        except OSError:
            if done:
                try:  # undo the partial chunk: the file keeps only whole rows
                    os.ftruncate(self.fd, self.bytes)
                    os.lseek(self.fd, self.bytes, os.SEEK_SET)
                except OSError:
                    pass
            raise
        self.bytes += len(view)

    def write(self, text: str, rows: int) -> None:
        """Append ``rows`` complete rows (``text``), all or nothing. Raises OSError (nothing written then)."""
        self._write_all(text.encode("ascii"))
        self.rows += rows

    def flush(self, sync: bool = False) -> None:
        if sync:
            os.fsync(self.fd)

    def close(self) -> None:
        try:
            os.close(self.fd)
        except OSError:
            pass
        self.fd = -1


class _Recording:
    def __init__(self, name: str, csv: _CsvFile, start_index: int) -> None:
        self.name = name
        self.csv = csv
        self.start_index = start_index
        self.stop_index: int | None = None
        self.error: str | None = None


class TelemetryWriter:
    """Writer thread: drains a :class:`TelemetryRing` into CSV files.

    Not real-time; runs at normal priority (it demotes itself from SCHED_FIFO if the process was started
    with it, so it never competes with the loop). Thread-safe public methods: :meth:`record_start`,
    :meth:`record_stop`, :meth:`flush`, :meth:`status`, :meth:`stop`.
    """

    def __init__(self, ring: Ring, settings: WriterSettings) -> None:
        self.ring = ring
        self.settings = settings
        self.columns = ring.columns
        self._csv = RecordingCsv(self.columns, settings.float_format)
        self._lock = threading.Lock()  # guards the recording and the status fields (never the ring)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._flush_req = 0
        self._flush_done = 0
        self._flush_cv = threading.Condition(self._lock)
        self._thread: threading.Thread | None = None
        self._cont: _CsvFile | None = None
        self._cont_files: list[Path] = []
        self._rec: _Recording | None = None
        self._last_recording: dict[str, object] | None = None
        self._next_retry = 0.0
        self._seq = 0
        self.rows_written = 0  # rows consumed from the ring and written to the continuous file
        self.rows_drained = 0
        self.lost = 0  # rows drained but not written (write error)
        self.error: str | None = None
        self.error_count = 0
        self.files_rotated = 0
        self._taps: tuple[Callable[[int, np.ndarray], None], ...] = ()

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name="stagectl-telemetry", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> bool:
        """Drain everything still in the ring, close all files (fsync). Returns True if the thread ended."""
        self._stop.set()
        self._wake.set()
        th = self._thread
        if th is None:
            self._final_drain()
            return True
        th.join(timeout)
        return not th.is_alive()

    def flush(self, timeout: float = 2.0) -> bool:
        """Ask the writer to drain the ring now and fsync its files; wait until done (True) or timeout."""
        if self._thread is None or not self._thread.is_alive():
            self._drain_all(sync=True)
            return True
        with self._flush_cv:
            self._flush_req += 1
            want = self._flush_req
            self._wake.set()
            return self._flush_cv.wait_for(lambda: self._flush_done >= want, timeout)

    # ------------------------------------------------------------------ taps (live streams)
    def add_tap(self, tap: Callable[[int, np.ndarray], None]) -> None:
        """Call ``tap(first_index, rows)`` in the writer thread with every block of rows drained from the ring
        (``rows`` float64[n, len(columns)], a private copy; ``first_index`` the ring index of ``rows[0]``, so a
        gap in the indices is a gap in the data). A live stream (``subscribe``) decimates and queues them
        itself; a tap must not block, and one that raises is removed (logged). Thread-safe."""
        with self._lock:
            self._taps = (*self._taps, tap)

    def remove_tap(self, tap: Callable[[int, np.ndarray], None]) -> None:
        with self._lock:
            self._taps = tuple(t for t in self._taps if t is not tap)

    def _feed_taps(self, first: int, rows: np.ndarray) -> None:
        for tap in self._taps:
            try:
                tap(first, rows)
            except Exception:  # noqa: BLE001 - a broken stream must not stop telemetry
                log.exception("telemetry tap %r failed; removed", tap)
                self.remove_tap(tap)

    # ------------------------------------------------------------------ recordings
    def record_start(self, name: str) -> Path:
        """Start capturing every row from now on into ``<dir>/<name>.csv``.

        Raises
        ------
        ValueError
            ``name`` is not a plain file name (path traversal, separators, empty), a recording is already
            running, or the file exists. The message starts with the field name ``name``.
        OSError
            The file cannot be created (reported as is).
        """
        if not isinstance(name, str) or not NAME_RE.match(name) or ".." in name:
            raise ValueError(f"name: must be a plain file name of letters, digits, '._-' (got {short(name)})")
        fname = name if name.endswith(".csv") else name + ".csv"
        path = self.settings.directory / fname
        with self._lock:
            if self._rec is not None and self._rec.stop_index is None:
                raise ValueError(f"name: recording {self._rec.name!r} is already running; stop it first")
        self.settings.directory.mkdir(parents=True, exist_ok=True)
        try:
            csv = _CsvFile(path, self._csv, exclusive=True)
        except FileExistsError:
            raise ValueError(f"name: {fname} already exists in {self.settings.directory}") from None
        with self._lock:
            old = self._rec
            if old is not None and old.stop_index is None:  # raced with another start
                csv.close()
                path.unlink(missing_ok=True)
                raise ValueError(f"name: recording {old.name!r} is already running; stop it first")
            if old is not None:  # stopped but not yet finished by the writer: finish it here
                self._finish_recording_locked(old)
            self._rec = _Recording(name, csv, self.ring.head)
        self._wake.set()
        log.info("recording %s started: %s", name, path)
        return path

    def record_stop(self, timeout: float = 2.0) -> dict[str, object]:
        """Stop the running recording; its rows up to now are written and the file is closed (fsync).

        Returns ``{"name", "path", "rows", "error"}``. Raises ValueError (field ``action``) if none runs.
        """
        with self._lock:
            rec = self._rec
            if rec is None or rec.stop_index is not None:
                raise ValueError("action: no recording is running")
            rec.stop_index = self.ring.head
        self.flush(timeout)
        with self._lock:
            if self._rec is rec:
                self._finish_recording_locked(rec)
            return dict(self._last_recording or {})

    def _finish_recording_locked(self, rec: _Recording) -> None:
        try:
            rec.csv.flush(sync=True)
        except OSError as exc:
            rec.error = rec.error or _describe(exc, rec.csv.path)
        rec.csv.close()
        self._last_recording = {"name": rec.name, "path": str(rec.csv.path), "rows": rec.csv.rows,
                                "error": rec.error}
        log.info("recording %s stopped: %d rows in %s", rec.name, rec.csv.rows, rec.csv.path)
        if self._rec is rec:
            self._rec = None

    # ------------------------------------------------------------------ status
    def status(self) -> dict[str, object]:
        """Snapshot (thread-safe): rows written, dropped (ring full), lost (write errors), error, files."""
        with self._lock:
            rec = self._rec
            recording = None
            if rec is not None:
                recording = {"name": rec.name, "path": str(rec.csv.path), "rows": rec.csv.rows,
                             "error": rec.error}
            return {
                "directory": str(self.settings.directory),
                "continuous": self.settings.continuous,
                "file": str(self._cont.path) if self._cont else None,
                "recording": recording,
                "last_recording": self._last_recording,
                "rows_written": self.rows_written,
                "rows_drained": self.rows_drained,
                "dropped": self.ring.dropped,
                "bad_rows": self.ring.bad_rows,
                "lost": self.lost,
                "backlog": self.ring.backlog,
                "capacity": self.ring.capacity,
                "error": self.error,
                "recording_ok": self.error is None,
                "error_count": self.error_count,
                "files_rotated": self.files_rotated,
            }

    # ------------------------------------------------------------------ writer thread
    def _run(self) -> None:
        demote_to_normal_priority()
        s = self.settings
        try:
            while not self._stop.is_set():
                self._wake.wait(s.flush_interval_s)
                self._wake.clear()
                with self._lock:
                    want = self._flush_req
                self._drain_all(sync=want > self._flush_done)
                if want > self._flush_done:
                    with self._flush_cv:
                        self._flush_done = want
                        self._flush_cv.notify_all()
        except Exception:  # pragma: no cover - a bug here must not kill telemetry silently
            log.exception("telemetry writer crashed")
            with self._lock:
                self.error = "writer thread crashed (see log)"
        finally:
            self._final_drain()
            with self._flush_cv:
                self._flush_done = self._flush_req
                self._flush_cv.notify_all()

    def _final_drain(self) -> None:
        self._drain_all(sync=True)
        with self._lock:
            rec = self._rec
            if rec is not None:
                if rec.stop_index is None:
                    rec.stop_index = self.ring.head
                self._finish_recording_locked(rec)
            self._close_continuous_locked()

    def _drain_all(self, sync: bool) -> None:
        s = self.settings
        while True:
            first, rows = self.ring.drain(s.chunk_rows)
            n = len(rows)
            if n:
                self.rows_drained += n
                text = self._csv.rows(rows)
                self._write_continuous(text, n)
                self._write_recording(first, rows, text, n)
                if self._taps:
                    self._feed_taps(first, rows)
            if n < s.chunk_rows:
                break
            time.sleep(0)  # let the loop thread take the GIL between chunks
        # every interval Python's buffers go to the kernel (a crash loses at most flush_interval_s); on request
        # (flush(): fault, recording stop, shutdown) they are fsync'ed. An error drops the continuous file (retried
        # after retry_s) or latches on the recording, like a write error.
        with self._lock:
            rec = self._rec
            for f in (self._cont, rec.csv if rec and rec.error is None else None):
                if f is None:
                    continue
                try:
                    f.flush(sync=sync)
                except OSError as exc:
                    msg = _describe(exc, f.path)
                    self._set_error(msg)
                    if f is self._cont:
                        self._drop_continuous()
                    elif rec is not None:
                        rec.error = msg

    def _write_continuous(self, text: str, n: int) -> None:
        s = self.settings
        if not s.continuous:
            return
        with self._lock:
            f = self._cont
            if f is not None and (f.bytes >= s.rotate_bytes or (s.rotate_s > 0 and
                                                                 time.monotonic() - f.opened_mono >= s.rotate_s)):
                self._rotate_locked()
                f = self._cont
            if f is None:
                now = time.monotonic()
                if now < self._next_retry:
                    self.lost += n
                    return
                f = self._open_continuous_locked()
                if f is None:
                    self.lost += n
                    return
            try:
                f.write(text, n)
                self.rows_written += n
            except OSError as exc:
                self._set_error(_describe(exc, f.path))
                self.lost += n
                self._drop_continuous()

    def _write_recording(self, first: int, rows: np.ndarray, text: str, n: int) -> None:
        with self._lock:
            rec = self._rec
            if rec is None or rec.error is not None:
                return
            lo = max(rec.start_index - first, 0)
            hi = n if rec.stop_index is None else min(max(rec.stop_index - first, 0), n)
            if hi <= lo:
                return
            part = text if (lo == 0 and hi == n) else self._csv.rows(rows[lo:hi])
            try:
                rec.csv.write(part, hi - lo)
            except OSError as exc:
                rec.error = _describe(exc, rec.csv.path)
                self._set_error(rec.error)

    def _open_continuous_locked(self) -> _CsvFile | None:
        s = self.settings
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        try:
            s.directory.mkdir(parents=True, exist_ok=True)
            while True:
                self._seq += 1
                path = s.directory / f"{s.prefix}-{stamp}-{self._seq:04d}.csv"
                try:
                    f = _CsvFile(path, self._csv, exclusive=True)
                    break
                except FileExistsError:
                    continue
        except OSError as exc:
            self._set_error(_describe(exc, s.directory))
            self._next_retry = time.monotonic() + s.retry_s
            return None
        if self.error is not None:
            log.warning("telemetry: writing again to %s after error: %s", path, self.error)
            self.error = None
        self._cont = f
        self._cont_files.append(path)
        self._prune_locked()
        return f

    def _rotate_locked(self) -> None:
        if self._cont is not None:
            self._close_continuous_locked()
            self.files_rotated += 1

    def _close_continuous_locked(self) -> None:
        """fsync and close the continuous file (the next rows open a new one)."""
        f = self._cont
        if f is None:
            return
        try:
            f.flush(sync=True)
        except OSError as exc:
            self._set_error(_describe(exc, f.path))
        f.close()
        self._cont = None

    def _prune_locked(self) -> None:
        keep = self.settings.keep_files
        while keep > 0 and len(self._cont_files) > keep:
            old = self._cont_files.pop(0)
            try:
                old.unlink()
            except FileNotFoundError:
                pass
            except OSError as exc:
                log.warning("telemetry: cannot delete old file %s: %s", old, exc)

    def _drop_continuous(self) -> None:
        if self._cont is not None:
            self._cont.close()
            self._cont = None
        self._next_retry = time.monotonic() + self.settings.retry_s

    def report_error(self, msg: str) -> None:
        """Mark telemetry as failing with ``msg`` (thread-safe; e.g. the start-up probe's finding): reported
        in :meth:`status` and ``STATUS=`` until a file is written again."""
        with self._lock:
            self._set_error(msg)

    def _set_error(self, msg: str) -> None:
        if msg != self.error:
            log.error("telemetry: %s (the loop keeps running; samples are counted as lost)", msg)
        self.error = msg
        self.error_count += 1


def _describe(exc: OSError, path: Path) -> str:
    what = exc.strerror or type(exc).__name__
    return f"{exc.filename or path}: {what}"


def check_writable(directory: Path) -> str | None:
    """None if a file can be created, written and removed in ``directory`` (created if missing); else the
    reason (``<path>: <strerror>``). Used at start-up, before any device is opened, for the
    ``daemon.telemetry.on_error`` policy."""
    probe = directory / f".stagectl-probe-{os.getpid()}"
    try:
        directory.mkdir(parents=True, exist_ok=True)
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o600)
        try:
            os.write(fd, b"t\n")
            os.fsync(fd)
        finally:
            os.close(fd)
        probe.unlink()
    except OSError as exc:
        return _describe(exc, directory)
    return None


def ring_rows(tc: TelemetryConfig, period_s: float) -> int:
    """Ring capacity for ``tc.buffer_s`` of loop time [rows], a power of two, at least 1024."""
    n = max(1024, int(math.ceil(tc.buffer_s / period_s)))
    return 1 << (n - 1).bit_length()


def start_telemetry(tc: TelemetryConfig, directory: Path, columns: Sequence[str], period_s: float,
                    ring: Ring | None = None) -> TelemetryWriter | None:
    """The daemon's telemetry set-up: a ring holding ``tc.buffer_s`` of rows (or ``ring``, e.g. the loop
    process's shared one) and its writer thread, started; None when ``tc.enabled`` is false. The ring is
    ``writer.ring`` (a loop sink)."""
    if not tc.enabled:
        return None
    if ring is None:
        ring = TelemetryRing(columns, ring_rows(tc, period_s))
    writer = TelemetryWriter(ring, WriterSettings(
        directory=directory, continuous=tc.continuous, rotate_bytes=int(tc.rotate_mb * 1e6), rotate_s=tc.rotate_s,
        keep_files=tc.keep_files, flush_interval_s=tc.flush_interval_s, retry_s=tc.retry_s))
    writer.start()
    log.info("telemetry: %s (%d-row ring, %.0f s at %g Hz)", directory, ring.capacity, ring.capacity * period_s,
             1.0 / period_s)
    return writer
