"""Clocks for the control loop, and best-effort real-time process settings.

The loop never sleeps for a *relative* interval. It computes the next deadline as
``deadline[k+1] = deadline[k] + period_s`` and asks its clock to sleep until that absolute time
(docs/platform.md section 4: a relative ``time.sleep(T)`` runs 11 % slow at 1 kHz and drifts).

Two clocks share one interface (``now() -> float`` seconds, ``sleep_until(t_s)``):

* :class:`MonotonicClock` -- real time. ``sleep_until`` calls
  ``clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, ...)`` through ctypes (restarted on EINTR); where
  that is unavailable it falls back to ``time.sleep(deadline - now)``.
* :class:`SimClock` -- simulated time. ``sleep_until`` just sets the time; nothing waits on the wall
  clock, so a simulated run is deterministic and as fast as the computation allows.

:class:`Timing` is the loop's one timing value (``period_s``); every consumer (drive, encoder, safety,
simulated I/O, controller) derives its cycle counts from it with :meth:`Timing.cycles` / :meth:`Timing.every`
instead of doing its own arithmetic on a bare ``period_s``.

Real-time helpers (:func:`apply_realtime`) try SCHED_FIFO, CPU affinity, ``mlockall``,
``PR_SET_TIMERSLACK`` and ``gc.freeze``; each degrades gracefully (returns a note, never raises) when
the process lacks the privilege.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import gc
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from stagectl.errors import ConfigError, short

CLOCK_MONOTONIC = 1
TIMER_ABSTIME = 1
MCL_CURRENT = 1
MCL_FUTURE = 2
PR_SET_TIMERSLACK = 29


@dataclass(frozen=True)
class Timing:
    """The loop's timing: one nominal period ``period_s`` [s], from which consumers derive cycle counts.

    Raises
    ------
    ConfigError
        ``period_s`` not a finite number > 0.
    """

    period_s: float

    def __post_init__(self) -> None:
        p = self.period_s
        if isinstance(p, bool) or not isinstance(p, (int, float)) or not (p > 0 and math.isfinite(p)):
            raise ConfigError(f"period_s: must be > 0 s (got {short(p)})")
        object.__setattr__(self, "period_s", float(p))

    @classmethod
    def of(cls, timing: Timing | float) -> Timing:
        """``timing`` itself, or a :class:`Timing` for a bare period [s]."""
        return timing if isinstance(timing, Timing) else cls(timing)

    @property
    def rate_hz(self) -> float:
        """Loop rate 1/period_s [Hz]."""
        return 1.0 / self.period_s

    def cycles(self, duration_s: float) -> int:
        """Whole cycles needed to cover ``duration_s`` [s]: ``ceil(duration_s / period_s)`` (time-outs)."""
        return math.ceil(duration_s / self.period_s)

    def every(self, interval_s: float) -> int:
        """Cycles between two events ``interval_s`` [s] apart, rounded, at least 1 (periodic messages)."""
        return max(1, round(interval_s / self.period_s))

    def per_cycle(self, rate_per_s: float) -> float:
        """How much of a rate (e.g. a speed [m/s]) accumulates in one cycle: ``rate_per_s * period_s``."""
        return rate_per_s * self.period_s


class Clock(Protocol):
    """What the loop needs from a clock. ``now`` in seconds on an arbitrary monotonic origin."""

    def now(self) -> float: ...

    def sleep_until(self, t_s: float) -> None: ...


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


def _load_libc() -> ctypes.CDLL | None:
    try:
        name = ctypes.util.find_library("c") or "libc.so.6"
        return ctypes.CDLL(name, use_errno=True)
    except OSError:
        return None


_LIBC = _load_libc()


class MonotonicClock:
    """Real time on CLOCK_MONOTONIC with absolute-deadline sleeps.

    ``now()`` is ``time.monotonic_ns() * 1e-9`` [s] (same clock as ``clock_nanosleep(CLOCK_MONOTONIC)``).
    ``sleep_until(t_s)`` returns at or after ``t_s``; returns at once if ``t_s`` is already past.
    With ``spin_s > 0`` it sleeps until ``t_s − spin_s`` and busy-waits the rest ("hybrid": sub-µs median
    lateness for ~5–10 % more CPU at 1 kHz, docs/platform.md section 4; never spin under SCHED_FIFO when
    other threads of the process must run). Real-time safe (one reused ctypes struct).
    """

    def __init__(self, spin_s: float = 0.0) -> None:
        self.spin_ns = max(0, int(spin_s * 1e9))
        self._ts = _Timespec()
        self._nanosleep = None
        if _LIBC is not None and hasattr(_LIBC, "clock_nanosleep"):
            fn = _LIBC.clock_nanosleep
            fn.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.POINTER(_Timespec), ctypes.c_void_p]
            fn.restype = ctypes.c_int
            self._nanosleep = fn
        self._ts_ref = ctypes.byref(self._ts)

    @property
    def absolute(self) -> bool:
        """True when absolute-deadline sleeping (clock_nanosleep TIMER_ABSTIME) is in use."""
        return self._nanosleep is not None

    def now(self) -> float:
        return time.monotonic_ns() * 1e-9

    def sleep_until(self, t_s: float) -> None:
        ns = int(t_s * 1e9)
        spin = self.spin_ns
        if spin:
            self._sleep_ns(ns - spin)
            mono = time.monotonic_ns
            while mono() < ns:
                pass
            return
        self._sleep_ns(ns)

    def _sleep_ns(self, ns: int) -> None:
        if self._nanosleep is None:  # fallback: relative sleep to the absolute deadline
            rest = ns - time.monotonic_ns()
            if rest > 0:
                time.sleep(rest * 1e-9)
            return
        self._ts.tv_sec, self._ts.tv_nsec = divmod(ns, 1_000_000_000)
        while True:
            rc = self._nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, self._ts_ref, None)
            if rc != errno.EINTR:  # clock_nanosleep returns the error number, not -1
                return


class SimClock:
    """Simulated time: ``sleep_until`` advances the time to the deadline without waiting.

    Parameters
    ----------
    t0_s : float
        Start time [s].
    """

    def __init__(self, t0_s: float = 0.0) -> None:
        self.t_s = float(t0_s)

    def now(self) -> float:
        return self.t_s

    def sleep_until(self, t_s: float) -> None:
        if t_s > self.t_s:
            self.t_s = t_s

    def advance(self, dt_s: float) -> None:
        """Let ``dt_s`` [s] pass (e.g. to emulate a slow cycle in a test)."""
        self.t_s += dt_s


# ----------------------------------------------------------------------------------- real-time helpers
@dataclass
class RealtimeReport:
    """What :func:`apply_realtime` achieved; ``notes`` explains each setting that was not applied."""

    fifo_priority: int | None = None
    cpus: tuple[int, ...] | None = None
    mlocked: bool = False
    timer_slack_ns: int | None = None
    gc_frozen: bool = False
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, object]:
        return {
            "fifo_priority": self.fifo_priority,
            "cpus": list(self.cpus) if self.cpus is not None else None,
            "mlocked": self.mlocked,
            "timer_slack_ns": self.timer_slack_ns,
            "gc_frozen": self.gc_frozen,
            "notes": list(self.notes),
        }


def set_fifo(priority: int) -> str | None:
    """SCHED_FIFO at ``priority`` for the calling thread. Returns None on success or a note why not."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return None
    except (PermissionError, OSError, AttributeError) as exc:
        return f"SCHED_FIFO {priority} not applied ({exc}); needs CAP_SYS_NICE or LimitRTPRIO"


def set_affinity(cpus: tuple[int, ...]) -> str | None:
    """Pin the calling thread to ``cpus``. Returns None on success or a note why not."""
    try:
        os.sched_setaffinity(0, set(cpus))
        return None
    except (OSError, ValueError, AttributeError) as exc:
        return f"CPU affinity {list(cpus)} not applied ({exc})"


def lock_memory() -> str | None:
    """``mlockall(MCL_CURRENT | MCL_FUTURE)``. Returns None on success or a note why not."""
    if _LIBC is None:
        return "mlockall not available (no libc)"
    rc = _LIBC.mlockall(MCL_CURRENT | MCL_FUTURE)
    if rc != 0:
        err = ctypes.get_errno()
        return f"mlockall failed ({os.strerror(err)}); needs CAP_IPC_LOCK or LimitMEMLOCK=infinity"
    return None


def set_timer_slack(ns: int) -> str | None:
    """``prctl(PR_SET_TIMERSLACK, ns)`` for the calling thread (no privilege needed)."""
    if _LIBC is None:
        return "prctl not available (no libc)"
    rc = _LIBC.prctl(PR_SET_TIMERSLACK, ctypes.c_ulong(ns), 0, 0, 0)
    if rc != 0:
        return f"PR_SET_TIMERSLACK failed ({os.strerror(ctypes.get_errno())})"
    return None


def freeze_gc() -> None:
    """Collect, then move every existing object to the permanent generation (``gc.freeze``).

    After this a full collection no longer walks the ~10⁵ start-up objects (numpy, scipy, canopen),
    which otherwise costs 3–50 ms per gen-2 collection (docs/platform.md section 4).
    """
    gc.collect()
    gc.freeze()


def apply_realtime(
    *,
    fifo_priority: int | None = None,
    cpus: tuple[int, ...] | None = None,
    mlock: bool = False,
    timer_slack_ns: int | None = 1,
    gc_freeze: bool = True,
) -> RealtimeReport:
    """Apply the requested real-time settings to the calling thread; never raises.

    Call from the loop thread after every import and allocation is done.
    """
    rep = RealtimeReport()
    # (requested, apply -> note or None, report field, value when applied); FIFO last
    steps: tuple[tuple[bool, Callable[[], str | None], str, object], ...] = (
        (timer_slack_ns is not None, lambda: set_timer_slack(int(timer_slack_ns or 0)), "timer_slack_ns",
         timer_slack_ns),
        (bool(cpus), lambda: set_affinity(tuple(cpus or ())), "cpus", tuple(cpus or ())),
        (mlock, lock_memory, "mlocked", True),
        (fifo_priority is not None, lambda: set_fifo(int(fifo_priority or 0)), "fifo_priority", fifo_priority),
    )
    for wanted, apply, name, value in steps:
        if wanted:
            note = apply()
            if note:
                rep.notes.append(note)
            else:
                setattr(rep, name, value)
    if gc_freeze:
        freeze_gc()
        rep.gc_frozen = True
    return rep
