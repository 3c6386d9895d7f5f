"""The fixed-rate control loop: one scheduler for real time and simulated time.

Scheduling (absolute deadlines, never a relative sleep)::

    d[0] = start;  d[k+1] = d[k] + T          (T = period_s)
    sleep_until(d[k]);  lateness[k] = now − d[k]
    if lateness ≥ T:  skipped = floor(lateness / T);  d[k] += skipped·T;  overruns += skipped
                      (missed slots are skipped, never caught up in a burst)

Each cycle, in this order::

    sync()                       # the loop is the SYNC producer (CANopen SYNC)
    m = sensor.read()            # read once
    requests                     # move / stop / reset / retune / shutdown, at the cycle boundary
    safety checks                # device faults, NaN/inf, stale, soft limits, velocity, following error
    ref = reference.sample(t);  cmd = controller.step(dt, x, ref)
    u = safety.limit_force(cmd.force_n);  actuator.write(u)
    row -> sinks                 # telemetry, never blocking

The same code runs with :class:`~stagectl.clock.MonotonicClock` (``stagectl run``, the daemon) and with
:class:`~stagectl.clock.SimClock` plus lock-step devices (``stagectl simulate``, tests, benchmarks): with
a SimClock, ``sleep_until`` only advances time, so lateness is 0 and runs are deterministic.

Daemon API (stable; thread-safe unless noted)
---------------------------------------------
``loop.columns``
    Telemetry column names (SI, docs/recordings.md): ``t`` s, ``x`` m, ``u`` N, ``x_ref`` m, ``v_ref`` m/s,
    ``a_ref`` m/s², ``e`` m (x_ref − x), ``v`` m/s (filtered measured velocity), then the controller terms
    in N (``u_pid``, ``u_dob``, ``u_ff``, ``u_inertia``, ...).
``loop.run(cycles=None, duration_s=None, stop=None) -> LoopResult``
    Runs in the calling thread until ``cycles`` cycles, ``duration_s`` of loop time, ``stop.is_set()`` or a
    ``shutdown`` request. Enables the devices at start (state ``active``) and disables the drive on the way
    out (always, also on exceptions).
``loop.request(kind, **kw) -> concurrent.futures.Future``
    Queued and executed at the next cycle boundary in the loop thread. Kinds:

    * ``move(target_m=X | relative_m=D, [max_velocity_m_s=V])`` → ``{"target_m", "duration_s"}``;
      ``relative_m`` is relative to the current move's target.
    * ``stop()`` decelerate and hold → ``{"x_m"}``.
    * ``reset()`` clear a latched fault, re-enable the drive, restart the controller bumplessly at the
      measured position → ``{"state"}``. A no-op when no fault is latched.
    * ``retune(controller_config=CFG)`` → ``{"retuned": True}``. With a controller offering
      ``request_retune`` (StageController) the new tuning is designed in the *caller's* thread (a bad tuning
      raises there) and swapped in by the controller at its next step; otherwise ``retune`` runs in the loop
      thread between two cycles. Either way bumpless (the controller's job).
    * ``shutdown()`` → ``{"cycles": n}``, the loop returns after this cycle.

    Bad arguments raise ``ValueError`` naming the field at once (unknown kind or key, non-finite
    numbers, targets outside the soft limits, velocity above the limit); conditions known only in the loop
    (a relative target outside the limits, a move while in fault) are set on the future as ``ValueError`` /
    :class:`LoopStateError`. Futures still pending when ``run`` returns fail with :class:`LoopStateError`.
``loop.latch_fault(name, cause) -> dict``
    Before ``run`` only: latch fault ``name`` with ``cause``. ``run`` then starts in state ``fault`` without
    enabling the devices (SYNC and reads go on), and only a ``reset`` request clears it and enables them,
    like any latched fault. The daemon uses it to come up latched (``unclean_shutdown``) after an unclean end.
``loop.status() -> dict``
    Snapshot: ``state`` (unconfigured/configured/active/fault), ``fault`` (name, cause, t_s, cycle or None),
    ``x_m``, ``x_ref_m``, ``e_m``, ``u_n``, ``t_s``, ``cycle``, ``overruns``, ``lateness_us``
    {p50, p99, max}, ``exec_us`` {p50, p99, max}, ``running`` and ``healthy`` (running, active, recent
    overrun fraction ≤ ``loop.healthy_overrun_fraction``) for the systemd watchdog.
``loop.add_sink(sink)`` / ``loop.remove_sink(sink)``
    ``sink.append(row: tuple[float, ...]) -> None`` is called in the loop thread once per cycle with one
    value per column; it must not block. A sink that raises is removed and logged.
"""

from __future__ import annotations

import concurrent.futures
import enum
import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from stagectl.clock import Clock, apply_realtime
from stagectl.control.api import Command, Reference
from stagectl.drivers.base import Device, DeviceState, ForceActuator, Measurement, PositionSensor, SyncProducer
from stagectl.errors import StageError
from stagectl.safety import Safety
from stagectl.schema import param

log = logging.getLogger("stagectl.loop")

BASE_COLUMNS = ("t", "x", "u", "x_ref", "v_ref", "a_ref", "e", "v")
DEFAULT_TERMS = ("u_pid", "u_dob", "u_ff", "u_inertia")


class LoopStateError(StageError, RuntimeError):
    """A request cannot be executed in the loop's current state (e.g. a move while in fault)."""


class LoopState(enum.Enum):
    UNCONFIGURED = "unconfigured"
    CONFIGURED = "configured"
    ACTIVE = "active"
    FAULT = "fault"


# ------------------------------------------------------------------------------------------ config
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
    startup_cycles: int = param(
        200, unit="cycles", desc="at start, SYNC periods to wait for the first fresh position (a loaded machine or "
        "a late first TPDO); the stale-position check applies from the first active cycle on", ge=1, le=100000
    )


# ------------------------------------------------------------------------------------------ protocols
class Controller(Protocol):
    """What the loop needs from :class:`stagectl.control.controller.StageController`."""

    def reset(self, x_m: float) -> None: ...

    def step(self, dt: float, x_meas_m: float, ref: Reference) -> Command: ...

    def retune(self, cfg: Any) -> None: ...


class ReferenceSource(Protocol):
    """A reference generator the loop samples once per cycle (see :mod:`stagectl.app` for the adapter)."""

    def sample(self, t_s: float) -> Reference: ...

    def hold(self, t_s: float, x_m: float) -> None:
        """Stand still at ``x_m`` from ``t_s`` on (start, reset)."""

    def move(self, t_s: float, target_m: float, max_velocity_m_s: float | None) -> float:
        """Start a move at ``t_s`` to ``target_m``; returns its duration [s]."""

    def stop(self, t_s: float) -> float:
        """Decelerate and hold; returns the position where it will stand [m]."""

    @property
    def target_m(self) -> float:
        """The position the reference is heading to (or holding) [m]."""


class TelemetrySink(Protocol):
    def append(self, row: tuple[float, ...]) -> None: ...


@dataclass
class LoopResult:
    """Summary of one :meth:`ControlLoop.run`."""

    cycles: int
    overruns: int
    duration_s: float
    ended_by: str
    lateness_us: dict[str, float]
    exec_us: dict[str, float]
    cpu_fraction: float
    fault: dict[str, Any] | None
    realtime: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {
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
        }


_REQUEST_KEYS = {
    "move": {"target_m", "relative_m", "max_velocity_m_s"},
    "stop": set(),
    "reset": set(),
    "retune": {"controller_config"},
    "shutdown": set(),
}


def _finite(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name}: must be finite, got {value!r}")
    return v


def _stats(arr: np.ndarray, n: int, peak: float) -> dict[str, float]:
    if n <= 0:
        return {"p50": 0.0, "p99": 0.0, "max": 0.0}
    a = arr[: min(n, arr.size)]
    p50, p99 = np.percentile(a, (50.0, 99.0))
    return {"p50": float(p50) * 1e6, "p99": float(p99) * 1e6, "max": float(peak) * 1e6}


class ControlLoop:
    """Fixed-rate loop (see module docstring for the schedule and the daemon API).

    Parameters
    ----------
    clock : Clock
        :class:`~stagectl.clock.MonotonicClock` or :class:`~stagectl.clock.SimClock`.
    sensor : PositionSensor
        Read once per cycle.
    actuator : ForceActuator
        Written once per cycle; ``quick_stop()`` on a fault; disabled when ``run`` returns.
    controller : Controller
        ``reset(x)``, ``step(dt, x, ref) -> Command``, ``retune(cfg)``; optional ``term_names``.
    reference : ReferenceSource
    safety : Safety
    cfg : LoopConfig
    sync : SyncProducer, optional
        The SYNC producer (defaults to the sensor or actuator if it is one).
    term_names : tuple of str, optional
        Controller terms recorded as telemetry columns (default ``controller.term_names`` or
        ``u_pid, u_dob, u_ff, u_inertia``); a term missing from a step's ``Command.terms`` is recorded as 0.
    device_time : bool
        The devices' time advances exactly one period per SYNC (virtual devices served by the loop thread):
        loop time is then ``executed cycles × T`` and every step gets ``dt = T``, so skipped slots slow the
        simulation down instead of desynchronising reference and plant. False (default): loop time is
        ``clock.now() − start`` and ``dt = T·(1 + skipped)``, right for real devices and for PlantIO with a
        clock (its plant follows the clock).
    realtime : bool
        Apply ``cfg.realtime`` (FIFO, affinity, mlock, timer slack, gc.freeze) in the loop thread at start.
        False for simulated time.
    """

    def __init__(
        self,
        *,
        clock: Clock,
        sensor: PositionSensor,
        actuator: ForceActuator,
        controller: Controller,
        reference: ReferenceSource,
        safety: Safety,
        cfg: LoopConfig,
        sync: SyncProducer | None = None,
        realtime: bool = False,
        on_cycle: Callable[[], None] | None = None,
        term_names: tuple[str, ...] | None = None,
        device_time: bool = False,
    ) -> None:
        self.clock = clock
        self.sensor = sensor
        self.actuator = actuator
        self.controller = controller
        self.reference = reference
        self.safety = safety
        self.cfg = cfg
        self.period_s = float(cfg.period_s)
        if sync is None:
            sync = sensor if isinstance(sensor, SyncProducer) else actuator if isinstance(actuator, SyncProducer) else None
        self.sync = sync
        self.realtime = realtime
        self.device_time = device_time
        self.on_cycle = on_cycle
        self.devices: tuple[Device, ...] = tuple(dict.fromkeys([sensor, actuator]))  # unique, ordered
        terms = tuple(term_names or getattr(controller, "term_names", DEFAULT_TERMS))
        self.term_names: tuple[str, ...] = terms
        self.columns: tuple[str, ...] = BASE_COLUMNS + terms
        self.state = LoopState.CONFIGURED if all(
            d.state in (DeviceState.CONFIGURED, DeviceState.ENABLED) for d in self.devices
        ) else LoopState.UNCONFIGURED
        self._requests: queue.SimpleQueue[tuple[str, dict[str, Any], concurrent.futures.Future[Any]]] = (
            queue.SimpleQueue()
        )
        self._sinks: tuple[TelemetrySink, ...] = ()
        self._sink_lock = threading.Lock()
        self._running = False
        self._shutdown = False
        self._just_reset = False
        # statistics (preallocated)
        w = int(cfg.stats_window)
        self._late = np.zeros(w)
        self._exec = np.zeros(w)
        self._skip = np.zeros(w, dtype=np.int32)
        self.cycle = 0
        self.overruns = 0
        self._late_max = 0.0
        self._exec_max = 0.0
        self._snap: tuple[float, float, float, float, float] = (0.0, math.nan, math.nan, math.nan, 0.0)
        self._u = 0.0
        self._t0 = 0.0
        self.realtime_report: dict[str, Any] = {}

    # ------------------------------------------------------------------ sinks
    def add_sink(self, sink: TelemetrySink) -> None:
        """Register a telemetry sink (thread-safe). ``sink.append(row)`` must not block."""
        with self._sink_lock:
            self._sinks = (*self._sinks, sink)

    def remove_sink(self, sink: TelemetrySink) -> None:
        """Unregister a sink (thread-safe; unknown sinks are ignored)."""
        with self._sink_lock:
            self._sinks = tuple(s for s in self._sinks if s is not sink)

    # ------------------------------------------------------------------ requests
    def request(self, kind: str, **kw: Any) -> concurrent.futures.Future[Any]:
        """Queue a request for the next cycle boundary (thread-safe). See the module docstring."""
        if kind not in _REQUEST_KEYS:
            raise ValueError(f"kind: unknown request {kind!r} (known: {', '.join(_REQUEST_KEYS)})")
        unknown = set(kw) - _REQUEST_KEYS[kind]
        if unknown:
            raise ValueError(f"{sorted(unknown)[0]}: unknown argument for {kind!r} (known: {sorted(_REQUEST_KEYS[kind])})")
        if kind == "move":
            has_t, has_r = kw.get("target_m") is not None, kw.get("relative_m") is not None
            if has_t == has_r:
                raise ValueError("target_m: give exactly one of target_m or relative_m")
            if has_t:
                kw["target_m"] = self.safety.check_target(kw["target_m"], "target_m")
            else:
                kw["relative_m"] = _finite("relative_m", kw["relative_m"])
            if kw.get("max_velocity_m_s") is not None:
                v = _finite("max_velocity_m_s", kw["max_velocity_m_s"])
                vmax = self.safety.cfg.max_velocity_m_s
                if not 0.0 < v <= vmax:
                    raise ValueError(f"max_velocity_m_s: must be > 0 and <= {vmax:g} m/s (got {v:g} m/s)")
                kw["max_velocity_m_s"] = v
        if kind == "retune":
            if kw.get("controller_config") is None:
                raise ValueError("controller_config: required for retune")
            prepare = getattr(self.controller, "request_retune", None)
            if prepare is not None:
                # design (observer gains, model) here in the caller's thread; the controller swaps the prepared
                # parts in at its next step. Bad tunings raise here (ConfigError is a ValueError).
                prepare(kw["controller_config"])
                kw = {"controller_config": kw["controller_config"], "prepared": True}
        fut: concurrent.futures.Future[Any] = concurrent.futures.Future()
        self._requests.put((kind, kw, fut))
        return fut

    def _serve_requests(self, t: float, x: float) -> None:
        q = self._requests
        while True:
            try:
                kind, kw, fut = q.get_nowait()
            except queue.Empty:
                return
            if not fut.set_running_or_notify_cancel():
                continue
            try:
                fut.set_result(self._execute(kind, kw, t, x))
            except BaseException as exc:  # noqa: BLE001 - handed to the requester
                fut.set_exception(exc)

    def _execute(self, kind: str, kw: dict[str, Any], t: float, x: float) -> Any:
        if kind == "shutdown":
            self._shutdown = True
            return {"cycles": self.cycle}
        if kind == "reset":
            return self._reset(t, x)
        if kind == "retune":
            if not kw.get("prepared"):
                self.controller.retune(kw["controller_config"])
            return {"retuned": True}
        if self.state is not LoopState.ACTIVE:
            fault = self.safety.fault
            why = f" ({fault})" if fault else ""
            raise LoopStateError(f"{kind}: loop is {self.state.value}{why}; reset first")
        if kind == "stop":
            return {"x_m": float(self.reference.stop(t))}
        # move
        if kw.get("target_m") is not None:
            target = float(kw["target_m"])
        else:
            target = self.safety.check_target(self.reference.target_m + kw["relative_m"], "relative_m")
        duration = self.reference.move(t, target, kw.get("max_velocity_m_s"))
        return {"target_m": target, "duration_s": float(duration)}

    def _reset(self, t: float, x: float) -> dict[str, Any]:
        if self.state is not LoopState.FAULT:
            return {"state": self.state.value, "cleared": None}
        cleared = self.safety.fault
        for d in self.devices:
            if d.fault is not None or d.state is DeviceState.FAULT:
                d.fault_reset()
        act = self.actuator
        act.disable()
        for d in self.devices:
            if d.state is DeviceState.CONFIGURED:
                d.enable()
        for d in self.devices:
            if d.fault is not None:
                raise LoopStateError(f"reset: device {d.name} still reports {d.fault}")
        self.safety.clear()
        self.safety.restart(x)
        self.controller.reset(x)
        self.reference.hold(t, x)
        self._u = 0.0
        self.state = LoopState.ACTIVE
        self._just_reset = True
        log.warning("fault reset: %s cleared, loop active at x = %.9g m", cleared.name if cleared else "-", x)
        return {"state": self.state.value, "cleared": cleared.as_dict() if cleared else None}

    def latch_fault(self, name: str, cause: str) -> dict[str, Any]:
        """Latch fault ``name`` (``cause``: human-readable text) before :meth:`run` (see the module docstring).
        A fault already latched is kept (the first one wins, as in :meth:`Safety.latch`); returns the latched
        fault. Raises :class:`LoopStateError` while the loop runs (faults are latched in the loop thread then)."""
        if self._running:
            raise LoopStateError("latch_fault: only before run (the loop is running)")
        return self.safety.latch(name, cause, 0.0, self.cycle).as_dict()

    # ------------------------------------------------------------------ status
    def status(self, timing: bool = True) -> dict[str, Any]:
        """Thread-safe snapshot (see module docstring).

        ``timing=False`` leaves out ``lateness_us`` and ``exec_us``: their percentiles over the stats window
        take ~2 ms of interpreter time, which a frequent caller (the daemon's supervisor tick) should not take
        from the loop thread when it only needs the counters, state and health.
        """
        t, x, x_ref, u, cyc = self._snap
        n = min(self.cycle, self._late.size)
        skipped = int(self._skip[:n].sum()) if n else 0
        frac = skipped / max(1, n + skipped)
        fault = self.safety.fault
        out = {
            "state": self.state.value,
            "fault": fault.as_dict() if fault else None,
            "t_s": t,
            "x_m": x,
            "x_ref_m": x_ref,
            "e_m": x_ref - x,
            "u_n": u,
            "cycle": int(cyc),
            "overruns": self.overruns,
            "recent_overrun_fraction": frac,
            "period_s": self.period_s,
            "running": self._running,
            "healthy": bool(self._running and self.state is LoopState.ACTIVE
                            and frac <= self.cfg.healthy_overrun_fraction),
        }
        if timing:
            out["lateness_us"] = _stats(self._late, n, self._late_max)
            out["exec_us"] = _stats(self._exec, n, self._exec_max)
        return out

    # ------------------------------------------------------------------ fault
    def _enter_fault(self, t: float) -> None:
        if self.state is LoopState.FAULT:
            return
        self.state = LoopState.FAULT
        self._u = 0.0
        fault = self.safety.fault
        try:
            self.actuator.quick_stop()
        except Exception:  # noqa: BLE001 - still report the original fault
            log.exception("quick stop failed while handling fault %s", fault)
        log.error("FAULT %s; drive quick-stopped", fault)

    # ------------------------------------------------------------------ run
    def _first_sample(self, t0: float, n_max: int) -> tuple[Measurement, float, int]:
        """SYNC + read on absolute deadlines until a fresh sample (or a non-finite one, or a device fault)
        arrives, at most ``n_max`` times; returns (measurement, time of its SYNC, attempts − 1)."""
        period = self.period_s
        for i in range(n_max):
            if i:
                t0 += period
                self.clock.sleep_until(t0)
            if self.sync is not None:
                self.sync.sync()
            m = self.sensor.read()
            if m.fresh or not math.isfinite(m.position_m) or m.fault is not None:
                return m, t0, i
        return m, t0, n_max - 1

    def _start(self) -> float:
        """Enable the devices and take the first position.

        Start-up grace (``loop.startup_cycles``): while the devices are still *configured* (not enabled, so
        missed frames do not latch driver faults) the loop SYNCs until the sensor delivers a fresh sample
        (a loaded machine, a late first TPDO or interferometer frame); after enabling it again waits for
        the first fresh sample. The steady-state checks (stale_cycles, max_missed) apply from the first
        active cycle on, unchanged.
        """
        clock = self.clock
        faulted = self.safety.fault is not None
        n_max = 1 if faulted else int(self.cfg.startup_cycles)
        t0 = clock.now()
        waited = 0
        if not faulted and any(d.state is DeviceState.CONFIGURED for d in self.devices):
            m, t0, waited = self._first_sample(t0, n_max)
            if not m.fresh:
                raise StageError(f"no position from {self.sensor.name} within loop.startup_cycles {n_max} cycles "
                                 f"(devices configured, not yet enabled)")
            for d in self.devices:
                if d.state is DeviceState.CONFIGURED:
                    d.enable()
            t0 = max(t0 + self.period_s, clock.now())  # the next SYNC slot after the warm-up one
            clock.sleep_until(t0)
        m, t0, i = self._first_sample(t0, n_max)
        if waited or i:
            log.info("first fresh position after %d + %d start-up cycles", waited, i)
        self._t0 = t0
        x0 = m.position_m
        if faulted:  # a latched fault survives a restart of the loop: only reset clears it
            self.state = LoopState.FAULT
            x_ref = self._snap[2] if math.isfinite(self._snap[2]) else x0  # latched before the first run: x0
            self._snap = (0.0, x0, x_ref, 0.0, self.cycle)
            return t0
        if not (m.fresh and math.isfinite(x0)):
            raise StageError(f"no valid initial position from {self.sensor.name} (fresh={m.fresh}, x={x0} m) "
                             f"within loop.startup_cycles {n_max} cycles")
        self.safety.restart(x0)
        self.controller.reset(x0)
        self.reference.hold(0.0, x0)
        self.state = LoopState.ACTIVE
        self._snap = (0.0, x0, x0, 0.0, self.cycle)
        return t0

    def run(
        self,
        *,
        cycles: int | None = None,
        duration_s: float | None = None,
        stop: threading.Event | None = None,
    ) -> LoopResult:
        """Run the loop in the calling thread (see module docstring). Not re-entrant."""
        if self._running:
            raise LoopStateError("run: the loop is already running")
        self._running = True
        self._shutdown = False
        ended_by = "error"
        clock = self.clock
        period = self.period_s
        cpu0 = time.thread_time()
        wall0 = time.monotonic()
        cycle0 = self.cycle
        overruns0 = self.overruns
        try:
            if self.realtime:
                rt = self.cfg.realtime
                self.realtime_report = apply_realtime(
                    fifo_priority=rt.fifo_priority,
                    cpus=rt.cpus,
                    mlock=rt.mlock,
                    timer_slack_ns=rt.timer_slack_ns,
                    gc_freeze=rt.gc_freeze,
                ).as_dict()
                for note in self.realtime_report["notes"]:
                    log.info("real time: %s", note)
            t0 = self._start()
            ended_by = self._cycles(t0, period, cycles, duration_s, stop)
        finally:
            self._teardown()
            self._running = False
            self._fail_pending()
        cpu = time.thread_time() - cpu0
        wall = max(1e-9, time.monotonic() - wall0)
        n = min(self.cycle, self._late.size)
        fault = self.safety.fault
        return LoopResult(
            cycles=self.cycle - cycle0,
            overruns=self.overruns - overruns0,
            duration_s=clock.now() - self._t0,
            ended_by=ended_by,
            lateness_us=_stats(self._late, n, self._late_max),
            exec_us=_stats(self._exec, n, self._exec_max),
            cpu_fraction=cpu / wall,
            fault=fault.as_dict() if fault else None,
            realtime=self.realtime_report,
        )

    def _cycles(
        self, t0: float, period: float, cycles: int | None, duration_s: float | None, stop: threading.Event | None
    ) -> str:
        clock = self.clock
        sensor, actuator, sync = self.sensor, self.actuator, self.sync
        safety, controller, reference = self.safety, self.controller, self.reference
        term_names = self.term_names
        late_arr, exec_arr, skip_arr = self._late, self._exec, self._skip
        w = late_arr.size
        warn_late = self.cfg.lateness_warn_us * 1e-6
        warn_every = self.cfg.warn_interval_s
        next_warn = 0.0
        warn_count = 0
        on_cycle = self.on_cycle
        perf = time.perf_counter
        slot = 0  # deadline of slot n is t0 + n·T (no accumulated rounding)
        dt = period
        skipped = 0
        late = 0.0
        max_cycles = self.cycle + cycles if cycles is not None else -1
        t_end = duration_s if duration_s is not None else math.inf
        k = self.cycle
        k0 = k
        device_time = self.device_time
        x_prev_ref = Reference(self._snap[2])
        while True:
            # ------------------------------------------------------ stop conditions
            if k == max_cycles:
                return "cycles"
            if stop is not None and stop.is_set():
                return "stop"
            if self._shutdown:
                return "shutdown"
            if device_time:
                t = (k - k0) * period
            else:
                t = clock.now() - t0
            if t >= t_end - 1e-6 * period:
                return "duration"
            c0 = perf()
            # ------------------------------------------------------ one cycle
            try:
                if sync is not None:
                    sync.sync()
                m = sensor.read()
                x = m.position_m
                self._serve_requests(t, x)
                if self._just_reset:  # this cycle's sample predates the reset: restart cleanly next cycle
                    self._just_reset = False
                    m = Measurement(x, False)
                dev_fault = m.fault
                if dev_fault is None:
                    for d in self.devices:
                        if d.fault is not None:
                            dev_fault = d.fault
                            break
                if self.state is LoopState.ACTIVE:
                    if safety.check_measurement(t, k, x, m.fresh, dev_fault):
                        self._enter_fault(t)
                if self.state is LoopState.ACTIVE:
                    ref = reference.sample(t)
                    if safety.check_tracking(t, k, x, ref.x_m):
                        self._enter_fault(t)
                    elif m.fresh:
                        cmd = controller.step(dt, x, ref)
                        u = safety.limit_force(t, k, cmd.force_n)
                        if safety.fault is not None:
                            self._enter_fault(t)
                        else:
                            actuator.write(u)
                            self._u = u
                        terms = cmd.terms
                    else:  # stale sample (below the stale limit): hold the last force, no new estimate
                        actuator.write(self._u)
                        terms = {}
                else:
                    ref = x_prev_ref if self.state is LoopState.FAULT else reference.sample(t)
                    terms = {}
                x_prev_ref = ref
                u = self._u
                row = (t, x, u, ref.x_m, ref.v_m_s, ref.a_m_s2, ref.x_m - x, safety.v_est_m_s) + tuple(
                    [terms.get(n, 0.0) for n in term_names]
                )
                for s in self._sinks:
                    try:
                        s.append(row)
                    except Exception:  # noqa: BLE001 - a broken sink must not stop the loop
                        log.exception("telemetry sink %r failed; removed", s)
                        self.remove_sink(s)
                self._snap = (t, x, ref.x_m, u, k)
                if on_cycle is not None:
                    on_cycle()
            except Exception as exc:  # unexpected: safe stop, record, keep supervising
                if safety.fault is None:
                    log.exception("unexpected error in cycle %d", k)
                safety.latch("loop_error", f"{type(exc).__name__}: {exc}", t, k)
                self._enter_fault(t)
            # ------------------------------------------------------ statistics
            ex = perf() - c0
            i = k % w
            late_arr[i] = late
            exec_arr[i] = ex
            skip_arr[i] = skipped
            if late > self._late_max:
                self._late_max = late
            if ex > self._exec_max:
                self._exec_max = ex
            k += 1
            self.cycle = k
            # ------------------------------------------------------ schedule: absolute deadline
            slot += 1
            deadline = t0 + slot * period
            clock.sleep_until(deadline)
            late = clock.now() - deadline
            skipped = 0
            if late >= period:
                skipped = int(late // period)
                slot += skipped
                late -= skipped * period
                self.overruns += skipped
            dt = period if device_time else period * (1 + skipped)
            if (late > warn_late or skipped) and self.realtime:
                warn_count += 1
                if t >= next_warn:
                    log.warning(
                        "loop timing: %d late/overrun cycles in the last %.0f s (latest lateness %.0f us, "
                        "overruns total %d)", warn_count, warn_every, (late + skipped * period) * 1e6, self.overruns,
                    )
                    warn_count = 0
                    next_warn = t + warn_every

    def _teardown(self) -> None:
        act = self.actuator
        try:
            if self.state is LoopState.ACTIVE and act.state is DeviceState.ENABLED:
                act.write(0.0)
        except Exception:  # noqa: BLE001
            log.exception("writing zero force at stop failed")
        try:
            act.disable()
        except Exception:  # noqa: BLE001
            log.exception("disabling %s failed", act.name)
        for d in self.devices:
            if d is not act:
                try:
                    d.disable()
                except Exception:  # noqa: BLE001
                    log.exception("disabling %s failed", d.name)
        self._u = 0.0
        if self.state is LoopState.ACTIVE:
            self.state = LoopState.CONFIGURED

    def _fail_pending(self) -> None:
        while True:
            try:
                _, _, fut = self._requests.get_nowait()
            except queue.Empty:
                return
            if fut.set_running_or_notify_cancel():
                fut.set_exception(LoopStateError("the control loop is not running"))
