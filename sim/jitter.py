"""Simulated time with a loaded PC's timing: late wake-ups, skipped slots and wake-up jitter.

:class:`JitterClock` is a :class:`~stagectl.clock.SimClock` whose ``sleep_until`` wakes late, like a
scheduler on a shared machine without a real-time kernel::

    wake = deadline + U(0, jitter_s) + (late_periods·T  with probability late_fraction, else 0)

drawn from a seeded generator (reproducible). With :class:`~stagectl.sim.direct.PlantIO` given the same
clock, the plant follows the clock (it keeps moving under the held force while the loop sleeps), so the
loop sees what a real stage shows: a lateness ≥ T skips a slot and the sample interval varies. With
device-time virtual devices (one plant period per SYNC) only the loop's statistics see it.
"""

from __future__ import annotations

import random

from stagectl.clock import SimClock

__all__ = ["JitterClock"]


class JitterClock(SimClock):
    """Simulated clock with random wake-up lateness (see module docstring).

    Parameters
    ----------
    period_s : float
        The loop period T [s].
    late_fraction : float
        Fraction of the wake-ups delayed by ``late_periods``·T (0..1).
    late_periods : float
        Extra lateness of those wake-ups [periods] (1: the next slot is skipped).
    jitter_s : float
        Every wake-up is late by U(0, jitter_s) [s] on top.
    seed : int
        Seed of the draws.
    """

    def __init__(self, period_s: float, *, late_fraction: float = 0.0, late_periods: float = 1.0,
                 jitter_s: float = 0.0, seed: int = 0, t0_s: float = 0.0) -> None:
        super().__init__(t0_s)
        if not (0.0 <= late_fraction <= 1.0) or late_periods < 0 or jitter_s < 0:
            raise ValueError(f"JitterClock: late_fraction must be in [0, 1], late_periods and jitter_s >= 0 (got "
                             f"{late_fraction}, {late_periods}, {jitter_s} s)")
        self.period_s = period_s
        self.late_fraction = late_fraction
        self.late_periods = late_periods
        self.jitter_s = jitter_s
        self._rng = random.Random(seed)
        self.wakeups = 0
        self.late_wakeups = 0

    def sleep_until(self, t_s: float) -> None:
        super().sleep_until(t_s)
        self.wakeups += 1
        late = self._rng.uniform(0.0, self.jitter_s) if self.jitter_s > 0 else 0.0
        if self.late_fraction > 0 and self._rng.random() < self.late_fraction:
            late += self.late_periods * self.period_s
            self.late_wakeups += 1
        self.t_s += late
