"""Progress of long offline work on stderr: which step, how far, time left. Standard library only.

On a terminal the line is rewritten in place; otherwise (a log, a pipe) a plain line is printed at most every
``every_s`` seconds so logs stay short. ``quiet`` prints nothing (``--quiet`` for scripts).

Time left is measured, never guessed: ``left = (total − done) / rate`` with ``rate`` the work units done
per second over the last ``window_s`` seconds (20 s; the whole run while it is shorter), so a slow start
(imports, compilation, a cheap first stage) does not skew it for long. :meth:`Progress.bounded` is for a
``total`` that is an upper bound on the work (an optimiser's evaluation budget, discovery's rounds): the line
says "at most ~N s left" (the work is bounded, its rate is measured); :meth:`Progress.estimate` for a
``total`` that is the planned work (a benchmark's cases): "about N s left". Both take a new ``total`` when
the plan changes, so the figure tightens as the work learns how much is left, and reads 0 when ``done``
reaches ``total``.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from types import TracebackType
from typing import Self, TextIO


class Progress:
    """``update(done)`` with ``done`` in [0, total] (any unit, e.g. simulated seconds); ``close()`` ends it."""

    def __init__(self, label: str, total: float, unit: str = "", *, quiet: bool = False,
                 stream: TextIO | None = None, every_s: float | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.label, self.total, self.unit, self.quiet = label, max(float(total), 1e-300), unit, quiet
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every_s = every_s if every_s is not None else (0.2 if self.tty else 2.0)
        self.clock = clock  # seconds; a test passes its own (no wall-clock sleeps)
        self.t0 = clock()
        self._next = self.t0 + self.every_s
        self._shown = False
        self.what = ""
        self.window_s = 20.0
        self._hist: list[tuple[float, float]] = [(self.t0, 0.0)]  # (time, done), one sample per 0.5 s

    def left_s(self, done: float, now: float) -> float:
        """Seconds left: the units still to do over the rate of the last ``window_s`` seconds (the whole run
        while it is shorter). nan (no figure) until the rate rests on a second of work with some done."""
        t_old, d_old = next(((t, d) for t, d in self._hist if t >= now - self.window_s and d < done),
                            self._hist[0])
        if not done > d_old or now - t_old < 1.0:
            t_old, d_old = self._hist[0]
        if not done > d_old or now - t_old < 1.0:
            return float("nan")
        return max(self.total - done, 0.0) * (now - t_old) / (done - d_old)

    def _sample(self, done: float, now: float) -> None:
        if now - self._hist[-1][0] >= 0.5:
            self._hist.append((now, done))
            if len(self._hist) > 4 * self.window_s + 8:
                cut = next(i for i, (t, _) in enumerate(self._hist) if t >= now - 2 * self.window_s)
                del self._hist[1:max(cut, 1)]  # keep the start: the fallback for a window with no progress

    def step(self, index: int, what: str) -> None:
        """Start step ``index`` (1-based) of ``total`` steps, named ``what``: shown at once on a terminal."""
        self.what = what
        if self.tty:
            self._next = 0.0
        self.update(float(index - 1))

    _left_word = ""  # "at most" (bounded) or "about" (estimate): the line gives the time left as such

    def line(self, done: float, now: float) -> str:
        if self._left_word:
            left_s = self.left_s(done, now)
            word = self._left_word + ("" if self._left_word.endswith("~") else " ")
            left = f", {word}{left_s:.0f} s left" if left_s == left_s else ""
            return f"{self.label}: {self.what} ({now - self.t0:.0f} s elapsed{left})"
        if self.what and self.total <= 1:
            return f"{self.label}: {self.what} ({now - self.t0:.0f} s elapsed)"
        if self.what:
            return (f"{self.label}: step {done + 1:.0f} of {self.total:.0f}, {self.what} "
                    f"({now - self.t0:.0f} s elapsed)")
        frac = min(max(done / self.total, 0.0), 1.0)
        secs = self.left_s(done, now)
        left_txt = f", {secs:.0f} s left" if secs == secs else ""
        return (f"{self.label}: {100 * frac:3.0f} % ({done:.4g} of {self.total:.4g}{' ' + self.unit if self.unit else ''})"
                f"{left_txt}")

    def bounded(self, done: float, what: str, total: float | None = None) -> None:
        """``done`` of at most ``total`` (work that may end early, e.g. discovery's rounds, an optimiser's
        evaluation budget): the line names ``what`` and gives the time left as an upper bound ("at most"),
        from the cost per unit so far. ``total`` replaces the bound when given (it may shrink as work ends
        early)."""
        self._plan(done, what, total, "at most ~")

    def estimate(self, done: float, what: str, total: float | None = None) -> None:
        """``done`` of the planned ``total`` (a benchmark's cases or seconds): as :meth:`bounded`, but the
        time left is an estimate ("about"), for a plan whose units may not all cost the same."""
        self._plan(done, what, total, "about")

    def _plan(self, done: float, what: str, total: float | None, word: str) -> None:
        if not self._left_word:  # the work starts now: its rate is measured from here (not from set-up)
            self._hist = [(self.clock(), 0.0)]
        if total is not None:
            self.total = max(float(total), 1e-300)
        if what != self.what and self.tty:  # a new step shows at once on a terminal
            self._next = 0.0
        self.what = what
        self._left_word = word
        self.update(done)

    def update(self, done: float) -> None:
        if self.quiet:
            return
        now = self.clock()
        self._sample(done, now)
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
    """For work that reports how far it is only now and then (a benchmark): a helper thread redraws the line.

    ``with Ticker("bench io", quiet=args.quiet) as t: ...`` rewrites one line every second on a terminal; in a
    log it prints a line every 30 s, so a long run still shows that it is alive. Until the work calls
    :meth:`tell` the line gives the elapsed time only; after it, which case runs and about how long is left.
    """

    def __init__(self, label: str, *, quiet: bool = False, stream: TextIO | None = None,
                 clock: Callable[[], float] = time.monotonic, every_s: float | None = None) -> None:
        self.progress = Progress(label, 1.0, quiet=quiet, stream=stream, clock=clock)
        self.progress.every_s = every_s if every_s is not None else 1.0 if self.progress.tty else 30.0
        self.progress._next = self.progress.t0 + self.progress.every_s
        self._plan: tuple[float, float, str, float, float] | None = None  # done, total, what, span, told at
        self._lock = threading.Lock()
        self._draw = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="stagectl-ticker", daemon=True)

    def tell(self, done: float, total: float, what: str, span: float = 0.0) -> None:
        """``done`` of ``total`` work units are finished and ``what`` runs now. ``span`` > 0: ``what`` is
        ``span`` units that pass at one per wall-clock second (a case that runs for a set time, units in
        seconds), so the line moves on during it. Safe to call from the work's thread."""
        with self._lock:
            self._plan = (float(done), float(total), what, float(span), self.progress.clock())
        self.tick()

    def done_now(self) -> tuple[float, float, str] | None:
        """(done, total, what) as the line shows it now: a timed case counts its seconds so far."""
        with self._lock:
            plan = self._plan
        if plan is None:
            return None
        done, total, what, span, told = plan
        return done + min(span, max(self.progress.clock() - told, 0.0)), total, what

    def tick(self) -> None:
        """Redraw the line if it is due (the helper thread calls this four times a second)."""
        now = self.done_now()
        with self._draw:  # the work's thread (tell) and the helper thread share the line
            if now is None:
                self.progress.what = "running"
                self.progress.update(0.0)
            else:
                self.progress.estimate(now[0], now[2], now[1])

    def _run(self) -> None:
        while not self._stop.wait(0.25):
            self.tick()

    def __enter__(self) -> Self:
        if not self.progress.quiet:
            self._thread.start()
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        self.progress.close()
