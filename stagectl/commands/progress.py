"""Progress of long offline work on stderr: which step, how far, time left. Standard library only.

On a terminal the line is rewritten in place; otherwise (a log, a pipe) a plain line is printed at most every
``every_s`` seconds so logs stay short. ``quiet`` prints nothing (``--quiet`` for scripts).
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """``update(done)`` with ``done`` in [0, total] (any unit, e.g. simulated seconds); ``close()`` ends it."""

    def __init__(self, label: str, total: float, unit: str = "", *, quiet: bool = False,
                 stream: TextIO | None = None, every_s: float | None = None) -> None:
        self.label, self.total, self.unit, self.quiet = label, max(float(total), 1e-300), unit, quiet
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every_s = every_s if every_s is not None else (0.2 if self.tty else 2.0)
        self.t0 = time.monotonic()
        self._next = self.t0 + self.every_s
        self._shown = False

    def line(self, done: float, now: float) -> str:
        frac = min(max(done / self.total, 0.0), 1.0)
        elapsed = now - self.t0
        left = elapsed * (1.0 - frac) / frac if frac > 0 else float("nan")
        left_txt = f", {left:.0f} s left" if frac > 0 else ""
        return (f"{self.label}: {100 * frac:3.0f} % ({done:.4g} of {self.total:.4g}{' ' + self.unit if self.unit else ''})"
                f"{left_txt}")

    def update(self, done: float) -> None:
        if self.quiet:
            return
        now = time.monotonic()
        if now < self._next:
            return
        self._next = now + self.every_s
        self._shown = True
        if self.tty:
            self.stream.write("\r\033[K" + self.line(done, now))
        else:
            self.stream.write(self.line(done, now) + "\n")
        self.stream.flush()

    def close(self, note: str = "") -> None:
        if self.quiet or not self._shown:
            return
        if self.tty:
            self.stream.write("\r\033[K")
        if note:
            self.stream.write(f"{self.label}: {note}\n")
        self.stream.flush()


class ProgressSink:
    """A telemetry sink that reports the simulated time of the rows it sees (checked every 256 rows)."""

    def __init__(self, progress: Progress) -> None:
        self.progress = progress
        self._n = 0

    def append(self, row: tuple[float, ...]) -> None:
        self._n += 1
        if not self._n & 255:
            self.progress.update(float(row[0]))
