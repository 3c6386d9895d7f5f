"""The live telemetry stream behind ``stagectl scope``: the ``subscribe`` request on the control (or the
read-only observer) socket.

:class:`TelemetryStream` is a tap on the telemetry writer (it receives every block of rows the writer drains
from the loop's ring, in the writer thread) and keeps the newest ``capacity`` rows, each with its loop row
index. A client pulls with a cursor::

    → {"request": "subscribe", "since": null, "every": 20, "signals": ["t", "x", "e", "u"]}
    ← {"columns": ["t", "x", "e", "u"], "rows": [[...], ...], "next": 123460, "lost": 0, "every": 20}
    → {"request": "subscribe", "since": 123460, "every": 20, "signals": [...]}

``every = k`` keeps the rows whose index is a multiple of k (so successive pulls line up); ``lost`` counts
the rows of the requested range the stream no longer (or never) had: a client polling too slowly, or rows
the writer lost. The loop never sees a client: the stream lives on the daemon side of the telemetry ring.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from stagectl.runtime.requests import RequestError

__all__ = ["MAX_ROWS", "TelemetryStream", "parse_subscribe"]

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
