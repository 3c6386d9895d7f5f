"""The loop's telemetry sinks: registered from any thread, fed in the loop thread once per cycle."""

from __future__ import annotations

import logging
import threading

from stagectl.runtime.protocols import TelemetrySink

__all__ = ["SinkSet"]

log = logging.getLogger("stagectl.loop")


class SinkSet:
    """An immutable tuple of sinks swapped under a lock; :meth:`emit` reads it without locking."""

    def __init__(self) -> None:
        self._sinks: tuple[TelemetrySink, ...] = ()
        self._lock = threading.Lock()

    def add(self, sink: TelemetrySink) -> None:
        """Register ``sink`` (thread-safe). ``sink.append(row)`` must not block."""
        with self._lock:
            self._sinks = (*self._sinks, sink)

    def remove(self, sink: TelemetrySink) -> None:
        """Unregister ``sink`` (thread-safe; unknown sinks are ignored)."""
        with self._lock:
            self._sinks = tuple(s for s in self._sinks if s is not sink)

    def emit(self, row: tuple[float, ...]) -> None:
        """``append(row)`` to every sink (loop thread); a sink that raises is logged and removed."""
        for s in self._sinks:
            try:
                s.append(row)
            except Exception:  # a broken sink must not stop the loop
                log.exception("telemetry sink %r failed; removed", s)
                self.remove(s)
