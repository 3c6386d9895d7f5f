"""Loop timing and real-time settings (the ``loop:`` section); re-exported by :mod:`stagectl.loop`."""

from __future__ import annotations

from dataclasses import dataclass

from stagectl.schema import param

__all__ = ["LoopConfig", "RealtimeConfig"]


@dataclass(frozen=True)
class RealtimeConfig:
    """Best-effort real-time settings for the loop thread (each degrades gracefully without privileges)."""

    fifo_priority: int | None = param(None, desc="SCHED_FIFO priority (1-99); null = normal scheduling", ge=1, le=99)
    cpus: tuple[int, ...] | None = param(None, desc="CPU affinity of the loop thread; null = any CPU", ge=0)
    mlock: bool = param(False, desc="mlockall(MCL_CURRENT|MCL_FUTURE) at start")
    timer_slack_ns: int | None = param(1, unit="ns", desc="PR_SET_TIMERSLACK for the loop thread", ge=1)
    gc_freeze: bool = param(True, desc="gc.collect() + gc.freeze() after start-up")
    spin_us: float = param(0.0, unit="us", desc="busy-wait the last part of each sleep (hybrid wake-up; costs CPU)",
                           ge=0, le=500)


@dataclass(frozen=True)
class LoopConfig:
    """Loop timing."""

    period_s: float = param(1e-3, unit="s", desc="control period T", ge=5e-5, le=0.1)
    realtime: RealtimeConfig = param(default_factory=RealtimeConfig, desc="real-time settings")
    lateness_warn_us: float = param(
        500.0, unit="us", desc="log a (rate-limited) warning when a wake-up is later than this", gt=0
    )
    warn_interval_s: float = param(10.0, unit="s", desc="at most one timing warning per interval", gt=0)
    stats_window: int = param(65536, desc="recent cycles kept for lateness percentiles", ge=16)
    healthy_overrun_fraction: float = param(
        0.01, desc="watchdog health: largest recent fraction of skipped cycles", ge=0, le=1
    )
    slow_down_time_s: float = param(
        0.5, unit="s", desc="time constant of the average measured sample interval that slows the controller's "
        "feedback down when cycles are skipped (crossover / (interval / T), in steps); 0 = never", ge=0)
    device_time: bool = param(
        False, desc="loop time = executed cycles x period_s, the time of a plant stepped one period per SYNC "
        "(stagectl sim-plant without wall_clock_plant): a skipped slot then delays reference and plant alike; false: "
        "the clock's time, as a real stage, which moves on in real time, needs (embedded virtual devices: always "
        "device time)")
    pace_cycles: int = param(
        0, unit="cycles", desc="with device_time: the loop starts no cycle (no SYNC, no force) while this many of its "
        "SYNCs are unanswered, so the time of a drive process held off the CPU (its plant frozen) and the loop's "
        "wait for each other instead of the loop sending forces it cannot see answered (docs/control.md section 5); "
        "0 = off. Without device_time the loop ignores it (a real drive's silence is judged on the clock) and "
        "check-config refuses it for a CANopen drive", ge=0, le=1000)
    startup_cycles: int = param(
        200, unit="cycles", desc="at start, SYNC periods to wait for the first fresh position (a loaded machine or "
        "a late first TPDO); the stale-position check applies from the first active cycle on", ge=1, le=100000
    )
