"""The live telemetry stream behind ``stagectl scope``: the ``subscribe`` request on the control socket
(no network listener).

:class:`TelemetryStream` is a tap on the telemetry writer (it receives every block of rows the writer drains
from the loop's ring, in the writer thread) and keeps the newest ``capacity`` rows, each with its loop row
index. A client pulls with a cursor::

    → {"request": "subscribe", "since": null, "every": 20, "signals": ["t", "x", "e", "u"]}
    ← {"columns": ["t", "x", "e", "u"], "rows": [[...], ...], "next": 123460, "lost": 0, "every": 20}
    → {"request": "subscribe", "since": 123460, "every": 20, "signals": [...]}

``every = k`` keeps the rows whose index is a multiple of k (so successive pulls line up); ``lost`` counts
the rows of the requested range the stream no longer (or never) had: a client polling too slowly, or rows
the writer lost. The loop never sees a client: the daemon's :func:`handle_subscribe` feeds the stream from a
:class:`LoopTap`, one more lock-free telemetry sink of the loop, in the control thread.
"""

from __future__ import annotations

import math
import threading
import weakref
from collections.abc import Mapping, Sequence
from typing import Any, Protocol

import numpy as np

from stagectl.runtime.requests import RequestError, check_fields

__all__ = ["MAX_ROWS", "LoopTap", "TelemetryStream", "handle_subscribe", "parse_subscribe", "stream_for"]

#: at most this many rows per reply (a reply stays far below the socket's 1 MiB limit)
MAX_ROWS = 2000


class TelemetryStream:
    """The newest ``capacity`` telemetry rows with their indices (see module docstring). Thread-safe."""

    def __init__(self, columns: Sequence[str], capacity: int = 16384) -> None:
        self.columns = tuple(columns)
        self._buf = np.zeros((int(capacity), len(self.columns)), dtype=np.float64)
        self._idx = np.full(int(capacity), -1, dtype=np.int64)
        self._next = 0  # index after the newest row received
        self._lock = threading.Lock()

    def __call__(self, first: int, rows: np.ndarray) -> None:
        """Tap: ``rows`` float64[n, columns] with loop indices ``first … first + n − 1`` (writer thread)."""
        n = int(rows.shape[0])
        if n == 0:
            return
        cap = self._buf.shape[0]
        if n > cap:  # only the newest fit
            first, rows, n = first + n - cap, rows[n - cap:], cap
        pos = (np.arange(first, first + n) % cap).astype(np.int64)
        with self._lock:
            self._buf[pos] = rows
            self._idx[pos] = np.arange(first, first + n)
            self._next = max(self._next, first + n)

    def read(self, since: int | None, every: int, signals: Sequence[str] | None = None,
             max_rows: int = MAX_ROWS) -> dict[str, Any]:
        """Rows with index ≥ ``since`` (``None``: the newest ``max_rows``) that are multiples of ``every``."""
        cols = list(self.columns) if not signals else list(signals)
        sel = [self.columns.index(c) for c in cols]
        cap = self._buf.shape[0]
        with self._lock:
            end = self._next
            start = end - max_rows * every if since is None else max(0, int(since))
            start = max(start, end - cap, 0)
            first = start + (-start) % every  # first multiple of every at or after start
            want = np.arange(first, end, every, dtype=np.int64)[:max_rows]
            pos = want % cap
            have = self._idx[pos] == want
            rows = self._buf[pos[have]][:, sel]
        nxt = int(want[-1]) + every if want.size == max_rows else end
        skipped = 0 if since is None else max(0, start - int(since)) // every  # overwritten before this pull
        return {"columns": cols, "every": every, "next": nxt,
                "rows": [[float(v) if math.isfinite(v) else None for v in r] for r in rows.tolist()],
                "lost": int(skipped + (~have).sum())}


def parse_subscribe(req: Mapping[str, object], columns: Sequence[str]) -> tuple[int | None, int, list[str]]:
    """``since``, ``every`` and ``signals`` of a ``subscribe`` request, each checked with the field's name."""
    since = req.get("since")
    if since is not None and (isinstance(since, bool) or not isinstance(since, int) or since < 0):
        raise RequestError("since", "must be null or the 'next' of the previous reply (an integer >= 0)")
    every = req.get("every", 1)
    if isinstance(every, bool) or not isinstance(every, int) or not 1 <= every <= 100000:
        raise RequestError("every", "must be an integer from 1 to 100000 (keep every k-th row)")
    signals = req.get("signals")
    if signals is None:
        return since, every, list(columns)
    if not isinstance(signals, list) or not all(isinstance(s, str) for s in signals) or not signals:
        raise RequestError("signals", "must be a list of column names")
    unknown = [s for s in signals if s not in columns][:3]
    if unknown:
        raise RequestError("signals", f"unknown {', '.join(repr(s[:40]) for s in unknown)} "
                                      f"(known: {', '.join(columns)})")
    return since, every, list(signals)


# ---------------------------------------------------------------------------------------------- the daemon side
class LoopTap:
    """A loop telemetry sink (``append(row)``, the interface the telemetry ring and the recorder use) that
    feeds a :class:`TelemetryStream` without a lock in the loop thread.

    The loop writes row ``k`` into ``buf[k mod C]`` and then publishes ``head = k + 1`` (single producer, no
    lock, no allocation, never raises). The control thread's :meth:`take` copies the rows it has not taken
    yet and re-reads ``head`` afterwards, dropping rows the loop may have overwritten during the copy; those
    reach the client as ``lost``.
    """

    def __init__(self, columns: Sequence[str], capacity: int = 8192) -> None:
        cap = 1 << (max(int(capacity), 64) - 1).bit_length()
        self.columns = tuple(columns)
        self._buf = np.zeros((cap, len(self.columns)), dtype=np.float64)
        self._mask = cap - 1
        self._head = 0  # loop thread only
        self._taken = 0  # control thread only

    def append(self, row: Sequence[float]) -> None:
        """Loop thread: store one row (a malformed row is skipped, never raised into the loop)."""
        h = self._head
        try:
            self._buf[h & self._mask] = row
        except (ValueError, TypeError):
            return
        self._head = h + 1

    def take(self) -> tuple[int, np.ndarray]:
        """Control thread: ``(first index, rows)`` appended since the previous call and still intact."""
        cap = self._mask + 1
        h = self._head
        start = max(self._taken, h - cap + cap // 8)
        idx = np.arange(start, h, dtype=np.int64)
        rows = self._buf[idx & self._mask].copy()
        ok = idx > self._head - cap  # not overwritten while copying (a prefix at worst)
        keep = int(np.argmax(ok)) if ok.any() else idx.size
        self._taken = h
        return start + keep, rows[keep:]


_TAPS: weakref.WeakKeyDictionary[Any, tuple[LoopTap, TelemetryStream]] = weakref.WeakKeyDictionary()
_TAPS_LOCK = threading.Lock()


class _HasLoop(Protocol):
    def need_loop(self) -> Any: ...


def stream_for(loop: Any) -> tuple[LoopTap, TelemetryStream]:
    """The loop's tap and stream, created on the first ``subscribe`` (the tap joins the loop's sinks)."""
    with _TAPS_LOCK:
        pair = _TAPS.get(loop)
        if pair is None:
            pair = (LoopTap(loop.columns), TelemetryStream(loop.columns))
            loop.add_sink(pair[0])
            _TAPS[loop] = pair
        return pair


def handle_subscribe(svc: _HasLoop, req: Mapping[str, object]) -> dict[str, Any]:
    """The ``subscribe`` request (control thread, never blocks): the new rows of the loop, decimated."""
    check_fields("subscribe", {k: v for k, v in req.items() if k not in ("request", "id")},
                 ("since", "every", "signals"))
    tap, stream = stream_for(svc.need_loop())
    since, every, signals = parse_subscribe(req, stream.columns)
    first, rows = tap.take()
    stream(first, rows)
    return stream.read(since, every, signals)
