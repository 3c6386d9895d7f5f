"""Preallocated per-cycle timing statistics of the loop (lateness, execution time, skipped slots).

The last ``window`` cycles live in three ring arrays (cycle k at index k mod window); the maxima are
all-time. :meth:`CycleStats.record` is real-time safe (three array stores, two compares, no allocation).
"""

from __future__ import annotations

import logging

import numpy as np
import numpy.typing as npt

from stagectl.runtime.status import TimingStats, timing_stats

__all__ = ["CycleStats", "LatenessWarner"]

log = logging.getLogger("stagectl.loop")


class CycleStats:
    """Timing of the recent cycles: ``record`` in the loop thread, the readers from any thread."""

    def __init__(self, window: int, buffers: tuple[npt.NDArray[np.float64], npt.NDArray[np.float64],
                                                 npt.NDArray[np.int32]] | None = None) -> None:
        """``buffers``: (late, exec, skip) arrays of length ``window`` to record into (shared memory: the
        daemon computes the percentiles in its own process); default: private arrays."""
        w = int(window)
        if buffers is not None:
            self.late, self.exec, self.skip = buffers
            if not (self.late.size == self.exec.size == self.skip.size == w):
                raise ValueError(f"buffers: three arrays of length {w} needed")
        else:
            self.late = np.zeros(w)
            self.exec = np.zeros(w)
            self.skip = np.zeros(w, dtype=np.int32)
        self.late_max = 0.0
        self.exec_max = 0.0

    def record(self, k: int, late_s: float, exec_s: float, skipped: int) -> None:
        """Cycle ``k`` woke ``late_s`` after its deadline, ran ``exec_s`` and followed ``skipped`` skipped
        slots. Real-time safe."""
        i = k % self.late.size
        self.late[i] = late_s
        self.exec[i] = exec_s
        self.skip[i] = skipped
        self.late_max = max(self.late_max, late_s)
        self.exec_max = max(self.exec_max, exec_s)

    def _n(self, cycles: int) -> int:
        return min(cycles, self.late.size)

    def overrun_fraction(self, cycles: int) -> float:
        """Skipped slots / all slots over the recent window (``cycles`` executed so far)."""
        n = self._n(cycles)
        skipped = int(self.skip[:n].sum()) if n else 0
        return skipped / max(1, n + skipped)

    def lateness(self, cycles: int) -> TimingStats:
        """Wake-up lateness p50/p99 (recent window) and max (all-time) [µs]."""
        return timing_stats(self.late, self._n(cycles), self.late_max)

    def execution(self, cycles: int) -> TimingStats:
        """Cycle execution time p50/p99 (recent window) and max (all-time) [µs]."""
        return timing_stats(self.exec, self._n(cycles), self.exec_max)


class LatenessWarner:
    """Rate-limited timing warnings: at most one log line per ``interval_s`` of loop time, counting the late
    (> ``late_s``) or overrun cycles since the previous line."""

    def __init__(self, late_s: float, interval_s: float) -> None:
        self.late_s = late_s
        self.interval_s = interval_s
        self._next = 0.0
        self._count = 0
        self._hinted = False

    def note(self, t_s: float, late_s: float, skipped: int, period_s: float, overruns: int) -> None:
        """After each wake-up (loop thread): ``late_s`` behind its deadline after ``skipped`` skipped slots."""
        if not (late_s > self.late_s or skipped):
            return
        self._count += 1
        if t_s >= self._next:
            log.warning("loop timing: %d late/overrun cycles in the last %.0f s (latest lateness %.0f us, "
                        "overruns total %d)", self._count, self.interval_s, (late_s + skipped * period_s) * 1e6,
                        overruns)
            if not self._hinted:  # once: what a user on an ordinary PC needs to know about these lines
                self._hinted = True
                log.warning("loop timing: late cycles are expected without real-time scheduling (a loaded PC, "
                            "no SCHED_FIFO); the systemd unit and `realtime:` in the config request it, see "
                            "README 'Installing on a stage PC'")
            self._count = 0
            self._next = t_s + self.interval_s
