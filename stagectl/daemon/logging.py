"""Daemon logging: stderr with systemd priority prefixes, queued so the loop never blocks on a write.

journald reads a ``<N>`` prefix (syslog priority, ``sd-daemon.h``) at the start of each stderr line and
stores the line at that level, so ``journalctl -p warning -u stagectl`` works::

    CRITICAL -> <2>   ERROR -> <3>   WARNING -> <4>   INFO -> <6>   DEBUG -> <7>

Records go through a bounded queue to one listener thread that does the actual write: a logging call from
the loop thread costs a record construction and a ``put_nowait``; when the queue is full (stderr blocked)
the record is dropped and counted (:attr:`DroppingQueueHandler.dropped`) instead of blocking.

:class:`RateLimitFilter` keeps repeating warnings (overruns, late cycles) to at most ``burst`` per
``interval_s`` per message template and reports how many were suppressed in the next one that passes.
"""

from __future__ import annotations

import logging
import logging.handlers
import os
import queue
import sys
import threading
import time
from collections.abc import Callable
from typing import IO

from stagectl.daemon._sched import demote_to_normal_priority

#: Python level -> syslog priority used by journald
PRIORITIES = ((logging.CRITICAL, 2), (logging.ERROR, 3), (logging.WARNING, 4), (logging.INFO, 6),
              (logging.DEBUG, 7))


def syslog_priority(levelno: int) -> int:
    for level, prio in PRIORITIES:
        if levelno >= level:
            return prio
    return 7


class JournalFormatter(logging.Formatter):
    """``<prio>logger: message``; with ``prefix=False`` a timestamped human format for a terminal.

    Multi-line messages (tracebacks) get the prefix on every line so journald keeps the level.
    """

    def __init__(self, prefix: bool = True) -> None:
        fmt = "%(name)s: %(message)s" if prefix else "%(asctime)s %(levelname)-7s %(name)s: %(message)s"
        super().__init__(fmt)
        self.prefix = prefix

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        if not self.prefix:
            return text
        p = f"<{syslog_priority(record.levelno)}>"
        return "\n".join(p + line for line in text.split("\n"))


class DroppingQueueHandler(logging.handlers.QueueHandler):
    """QueueHandler on a bounded queue that drops (and counts) instead of blocking or raising."""

    def __init__(self, q: queue.Queue[logging.LogRecord]) -> None:
        super().__init__(q)
        self.dropped = 0

    def enqueue(self, record: logging.LogRecord) -> None:
        try:
            self.queue.put_nowait(record)
        except queue.Full:
            self.dropped += 1


class RateLimitFilter(logging.Filter):
    """Let at most ``burst`` records per ``interval_s`` through per (logger, message template) at or above
    ``min_level``; the next record that passes carries ``(N similar messages suppressed)``.
    """

    def __init__(self, interval_s: float = 10.0, burst: int = 1, min_level: int = logging.WARNING,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        self.interval_s = interval_s
        self.burst = burst
        self.min_level = min_level
        self._clock = clock
        self._lock = threading.Lock()
        self._state: dict[tuple[str, str], list[float]] = {}  # key -> [window start, passed, suppressed]
        self.suppressed_total = 0

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < self.min_level or record.levelno >= logging.ERROR:
            return True  # errors and faults are never suppressed
        key = (record.name, str(record.msg))
        now = self._clock()
        with self._lock:
            st = self._state.get(key)
            if st is None or now - st[0] >= self.interval_s:
                suppressed = int(st[2]) if st else 0
                self._state[key] = [now, 1.0, 0.0]
                if len(self._state) > 1000:  # bound memory for pathological message variety
                    self._state.clear()
                if suppressed:
                    record.msg = f"{record.msg} ({suppressed} similar messages suppressed)"
                return True
            if st[1] < self.burst:
                st[1] += 1
                return True
            st[2] += 1
            self.suppressed_total += 1
            return False


class _Listener(logging.handlers.QueueListener):
    """Drops to normal scheduling in its own thread before it handles the first record."""

    _demoted = False

    def dequeue(self, block: bool) -> logging.LogRecord:
        if not self._demoted:  # dequeue runs only in the listener thread
            self._demoted = True
            demote_to_normal_priority()
        return super().dequeue(block)


class DaemonLogging:
    """Install queued stderr logging on the ``stagectl`` logger tree (and root); ``close()`` restores."""

    def __init__(self, level: int = logging.INFO, *, stream: IO[str] | None = None, journal: bool | None = None,
                 queue_size: int = 10000, rate_interval_s: float = 10.0) -> None:
        stream = stream if stream is not None else sys.stderr
        if journal is None:  # prefixes when stderr goes to journald (systemd sets JOURNAL_STREAM)
            journal = bool(os.environ.get("JOURNAL_STREAM")) or not _isatty(stream)
        self.queue: queue.Queue[logging.LogRecord] = queue.Queue(queue_size)
        self.handler = DroppingQueueHandler(self.queue)
        self.rate_filter = RateLimitFilter(interval_s=rate_interval_s)
        self.handler.addFilter(self.rate_filter)
        self.stream_handler = logging.StreamHandler(stream)
        self.stream_handler.setFormatter(JournalFormatter(prefix=journal))
        self.listener = _Listener(self.queue, self.stream_handler, respect_handler_level=False)
        self.root = logging.getLogger()
        self._old_handlers = list(self.root.handlers)
        self._old_level = self.root.level
        for h in self._old_handlers:
            self.root.removeHandler(h)
        self.root.addHandler(self.handler)
        self.root.setLevel(level)
        # third-party protocol stacks are chatty at INFO (every SDO transfer); keep them to warnings
        self._quiet = {name: logging.getLogger(name).level for name in ("canopen", "can")}
        if level > logging.DEBUG:
            for name in self._quiet:
                logging.getLogger(name).setLevel(logging.WARNING)
        self.listener.start()

    @property
    def dropped(self) -> int:
        return self.handler.dropped

    def close(self, timeout_s: float | None = None) -> None:
        """Flush queued records and restore the previous handlers. ``timeout_s``: wait at most this long [s]
        for the writer (None: until it has written everything; a writer blocked on a full stderr, e.g. a
        stalled journal or a pipe nobody reads, then blocks this call for as long)."""
        writer = self.listener._thread
        try:
            if timeout_s is None:
                self.listener.stop()
            else:
                self.listener.enqueue_sentinel()
                if writer is not None:
                    writer.join(timeout_s)
                self.listener._thread = None
        except Exception:  # noqa: BLE001 - stopping twice, or the queue full (then the writer is not waited for)
            pass
        self.root.removeHandler(self.handler)
        for h in self._old_handlers:
            self.root.addHandler(h)
        self.root.setLevel(self._old_level)
        for name, lvl in self._quiet.items():
            logging.getLogger(name).setLevel(lvl)
        if writer is not None and writer.is_alive():
            return  # still blocked in a write, holding the stream handler's lock: a flush would wait for it
        try:
            self.stream_handler.flush()
        except Exception:  # noqa: BLE001
            pass


def _isatty(stream: IO[str]) -> bool:
    try:
        return stream.isatty()
    except Exception:  # noqa: BLE001
        return False
