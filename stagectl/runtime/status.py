"""What the loop reports: its state, a typed status snapshot, the result of a run, timing statistics.

* :class:`LoopState` -- ``unconfigured → configured → active ⇄ fault``.
* :class:`LoopStatus` -- :meth:`stagectl.loop.ControlLoop.status`'s snapshot (thread-safe to take). Its
  plain-JSON form (:func:`stagectl.outputs.plain` with ``json=True``) is the ``loop`` object of the daemon's
  ``status`` reply: ``state``, ``fault`` {name, cause, t_s, cycle} or null, ``t_s``, ``x_m``, ``x_ref_m``,
  ``e_m``, ``u_n``, ``cycle``, ``overruns``, ``recent_overrun_fraction``, ``period_s``, ``running``,
  ``healthy``, ``lateness_us`` and ``exec_us`` {p50, p99, max} (null when taken with ``timing=False``),
  ``faults`` (faults entered so far).
* :class:`LoopResult` -- the summary of one :meth:`~stagectl.loop.ControlLoop.run`.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from stagectl.errors import StageError
from stagectl.outputs import plain
from stagectl.safety import SafetyFault

__all__ = ["FaultInfo", "LoopResult", "LoopState", "LoopStateError", "LoopStatus", "TimingStats", "timing_stats"]

#: a latched fault: ``name`` (the safety table's), ``cause`` (text), ``t_s`` [s], ``cycle``
FaultInfo = SafetyFault


class LoopStateError(StageError, RuntimeError):
    """A request cannot be executed in the loop's current state (e.g. a move while in fault)."""


class LoopState(enum.Enum):
    UNCONFIGURED = "unconfigured"
    CONFIGURED = "configured"
    ACTIVE = "active"
    FAULT = "fault"


@dataclass(frozen=True)
class TimingStats:
    """Percentiles over the recent-cycles window and the all-time maximum, in µs."""

    p50: float = 0.0
    p99: float = 0.0
    max: float = 0.0


def timing_stats(arr: npt.NDArray[np.float64], n: int, peak_s: float) -> TimingStats:
    """p50/p99 of the first ``n`` entries of ``arr`` [s] and ``peak_s``, as µs (zeros when ``n`` ≤ 0)."""
    if n <= 0:
        return TimingStats()
    a = arr[: min(n, arr.size)]
    p50, p99 = np.percentile(a, (50.0, 99.0))
    return TimingStats(float(p50) * 1e6, float(p99) * 1e6, float(peak_s) * 1e6)


@dataclass(frozen=True)
class LoopStatus:
    """A snapshot of the loop (positions in m, force in N, times in s)."""

    state: LoopState
    fault: FaultInfo | None
    t_s: float
    x_m: float
    x_ref_m: float
    e_m: float
    u_n: float
    cycle: int
    overruns: int
    recent_overrun_fraction: float
    period_s: float
    running: bool
    healthy: bool
    lateness_us: TimingStats | None = None
    exec_us: TimingStats | None = None
    faults: int = 0  #: faults entered since the loop was built (a fault and its reset between two looks show here)
    ilc: dict[str, Any] | None = None  #: the learner's state (iteration, RMS per repetition ...); None: no learner
    #: the controller's settle detector: reference at rest and |e| inside its window for its dwell time (None: the
    #: controller has no detector)
    in_position: bool | None = None

    def as_json(self) -> dict[str, Any]:
        """The plain-JSON form (NaN → null), as sent on the control socket (``ilc`` only with a learner)."""
        out: dict[str, Any] = plain(self, json=True)
        if out.get("ilc") is None:
            out.pop("ilc", None)
        return out


@dataclass
class LoopResult:
    """Summary of one :meth:`~stagectl.loop.ControlLoop.run`."""

    cycles: int
    overruns: int
    duration_s: float
    ended_by: str
    lateness_us: TimingStats
    exec_us: TimingStats
    cpu_fraction: float
    fault: FaultInfo | None
    realtime: dict[str, Any] = field(default_factory=dict)
    #: wall slots the loop waited for a device behind its SYNCs (``loop.pace_cycles``, device time)
    device_waits: int = 0

    def as_dict(self) -> dict[str, Any]:
        """Plain data for summaries (timing as {p50, p99, max} µs, the fault as {name, cause, t_s, cycle})."""
        out: dict[str, Any] = plain({
            "cycles": self.cycles,
            "overruns": self.overruns,
            "overrun_fraction": self.overruns / max(1, self.cycles + self.overruns),
            "duration_s": self.duration_s,
            "ended_by": self.ended_by,
            "lateness_us": self.lateness_us,
            "exec_us": self.exec_us,
            "cpu_fraction": self.cpu_fraction,
            "fault": self.fault,
            "realtime": self.realtime,
            "device_waits": self.device_waits,
        })
        return out
