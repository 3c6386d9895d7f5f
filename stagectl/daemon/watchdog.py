"""The systemd watchdog, fed by a health check rather than a timer (docs/platform.md section 5).

``WATCHDOG=1`` is sent from the supervisor's tick, never from a free-running thread, and only if since the
previous tick the loop's cycle counter advanced and the overrun fraction over the last 10 s
(:class:`HealthWindow`) is at or below ``loop.healthy_overrun_fraction``. A latched *fault* does not stop the
pings: the loop is still cycling and holding the stage safely; restarting the process would only lose the
latch. A hung or dead loop stops the pings, and systemd kills and restarts the service
(``Restart=on-failure``); the drive's own heartbeat consumer stops the stage if the process dies.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from typing import Any

from stagectl.daemon.sdnotify import SdNotifier
from stagectl.runtime.status import LoopStatus

__all__ = ["HealthWindow", "Watchdog"]

log = logging.getLogger("stagectl.daemon")


class HealthWindow:
    """Loop health as the supervisor sees it, over a sliding time window.

    Samples ``(t, cycle, overruns)`` from ``loop.status()``; the overrun fraction over the window is

        f = Δoverruns / (Δcycles + Δoverruns)        (skipped slots / all slots in the last ``window_s``)

    A time window (not "since start") keeps one start-up stall (JIT compile, first GC) from making a young
    process look unhealthy for minutes, and keeps a long-running one sensitive to a new problem.
    """

    def __init__(self, window_s: float = 10.0) -> None:
        self.window_s = window_s
        self.samples: deque[tuple[float, int, int]] = deque()

    def add(self, t_s: float, cycle: int, overruns: int) -> None:
        self.samples.append((t_s, int(cycle), int(overruns)))
        while len(self.samples) > 2 and self.samples[1][0] <= t_s - self.window_s:
            self.samples.popleft()

    def advancing(self) -> bool:
        """The cycle counter increased between the last two samples."""
        return len(self.samples) >= 2 and self.samples[-1][1] > self.samples[-2][1]

    def overrun_fraction(self) -> float:
        if len(self.samples) < 2:
            return 0.0
        _, c0, o0 = self.samples[0]
        _, c1, o1 = self.samples[-1]
        slots = (c1 - c0) + (o1 - o0)
        return (o1 - o0) / slots if slots > 0 else 0.0


class Watchdog:
    """Health-checked ``WATCHDOG=1`` pings (see the module docstring). ``limit``: the largest healthy
    overrun fraction (``loop.healthy_overrun_fraction``)."""

    def __init__(self, notify: SdNotifier, limit: float) -> None:
        self.notify = notify
        self.limit = limit
        self.health = HealthWindow()
        self.pings = 0
        self.withheld = 0
        self.reason = ""

    def sample(self, st: LoopStatus) -> None:
        """Add a health sample (start-up uses this alone, before any ping is due)."""
        self.health.add(time.monotonic(), st.cycle, st.overruns)

    def healthy(self) -> bool:
        return self.health.advancing() and self.health.overrun_fraction() <= self.limit

    def check(self, st: LoopStatus) -> None:
        """One supervisor tick: sample, then ping if healthy, else withhold (each change of cause logged once)."""
        self.sample(st)
        frac = self.health.overrun_fraction()
        if self.healthy():
            if self.notify.watchdog():
                self.pings += 1
            if self.reason:
                log.warning("watchdog pings resumed (loop healthy again)")
            self.reason = ""
            return
        self.withheld += 1
        reason = ("cycle counter not advancing" if not self.health.advancing()
                  else f"overruns in the last {self.health.window_s:g} s above "
                       f"loop.healthy_overrun_fraction {self.limit:.3%}")
        if reason != self.reason:
            log.error("watchdog withheld: %s (now %.3f%%)", reason, 100 * frac)
        self.reason = reason

    def as_json(self) -> dict[str, Any]:
        return {"interval_s": self.notify.watchdog_s, "pings": self.pings,
                "overrun_fraction_10s": self.health.overrun_fraction(), "withheld": self.withheld,
                "reason": self.reason or None}
