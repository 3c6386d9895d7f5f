"""Progress of long offline work on stderr: which step, how far, time left. Standard library only.

On a terminal the line is rewritten in place; otherwise (a log, a pipe) a plain line is printed at most every
``every_s`` seconds so logs stay short. ``quiet`` prints nothing (``--quiet`` for scripts).
"""

from __future__ import annotations

import sys
import threading
import time
from types import TracebackType
from typing import Self, TextIO


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
        self.what = ""

    def step(self, index: int, what: str) -> None:
        """Start step ``index`` (1-based) of ``total`` steps, named ``what``: shown at once on a terminal."""
        self.what = what
        if self.tty:
            self._next = 0.0
        self.update(float(index - 1))

    _bounded = False

    def line(self, done: float, now: float) -> str:
        if self._bounded:
            frac = min(max(done / self.total, 0.0), 1.0)
            elapsed = now - self.t0
            bound = f", at most {elapsed * (1.0 - frac) / frac:.0f} s left" if frac > 0 else ""
            return f"{self.label}: {self.what} ({elapsed:.0f} s elapsed{bound})"
        if self.what and self.total <= 1:
            return f"{self.label}: {self.what} ({now - self.t0:.0f} s elapsed)"
        if self.what:
            return (f"{self.label}: step {done + 1:.0f} of {self.total:.0f}, {self.what} "
                    f"({now - self.t0:.0f} s elapsed)")
        frac = min(max(done / self.total, 0.0), 1.0)
        elapsed = now - self.t0
        left = elapsed * (1.0 - frac) / frac if frac > 0 else float("nan")
        left_txt = f", {left:.0f} s left" if frac > 0 else ""
        return (f"{self.label}: {100 * frac:3.0f} % ({done:.4g} of {self.total:.4g}{' ' + self.unit if self.unit else ''})"
                f"{left_txt}")

    def bounded(self, done: float, what: str) -> None:
        """``done`` of at most ``total`` (work that may end early, e.g. discovery's rounds): the line names
        ``what`` and gives the time left as an upper bound, from the rate so far."""
        self.what = what
        self._bounded = True
        self.update(done)

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


class Ticker:
    """For work that cannot report how far it is (a benchmark): the elapsed time, from a helper thread.

    ``with Ticker("bench io", quiet=args.quiet): ...`` rewrites one line every second on a terminal; in a log
    it prints a line every 30 s, so a long silent run still shows that it is alive.
    """

    def __init__(self, label: str, *, quiet: bool = False, stream: TextIO | None = None) -> None:
        self.progress = Progress(label, 1.0, quiet=quiet, stream=stream)
        self.progress.every_s = 1.0 if self.progress.tty else 30.0
        self.progress._next = self.progress.t0 + self.progress.every_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="stagectl-ticker", daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(0.25):
            self.progress.what = "running"
            self.progress.update(0.0)

    def __enter__(self) -> Self:
        if not self.progress.quiet:
            self._thread.start()
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        self.progress.close()
