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
    ref = reference.sample(t);  cmd = controller.step(dt, x, ref)      (fresh sample only)
    u = safety.limit_force(cmd.force_n);  actuator.write(u)
                                 # (io.command_schedule: write_schedule(u, u + predicted increment))
    row -> sinks                 # telemetry, never blocking

Timing of the control law (a PC without a real-time kernel wakes late, skips slots and gets stale samples):

* ``dt`` is the *measured* interval between the sample the controller steps on and the previous one it
  stepped on, in loop time: ``dt = min(t_k − t_prev, MAX_DT_PERIODS·T)`` (exactly T when within 1e-6 T of it,
  so simulated time stays bit-exact). A skipped slot gives
  ``dt ≈ 2T``; after stale samples the first fresh one gets the whole gap, so the velocity estimate
  Δx/dt, the integrator (∫e dt), the observer and the derivative filter see the time that really passed
  (no derivative kick when samples resume). The reference is sampled at loop time ``t`` too.
* A late sample (``Measurement.age_cycles`` n > 0: a TPDO that answered the previous SYNC after its wait)
  is placed at ``t − n·T`` for the velocity estimate and extrapolated to ``t`` with it
  (x + v̂·n·T) for the controller, the tracking check and the telemetry.
* A sample ``STALE_AGE_CYCLES`` (2) or more periods old (a drive working off a backlog of SYNCs after its
  process was held off the CPU: the CiA 402 driver ties each TPDO to its SYNC by counting) is stale, not
  fresh: stepping the observer on a position 2–3 periods old as if current gave force spikes of 26 N.
* A stale sample (no new position: late or dropped TPDO, missing frame) is not stepped on: a controller
  with ``hold(dt, ref)`` (StageController) is called instead. It steps its first
  ``controller.stale_predict_cycles`` stale cycles in a row on a predicted position (the last measured
  tracking error held) and after that keeps its feedback terms (nothing integrates, no estimate moves) while
  its feed-forward follows the reference; any other controller holds its last force.
  ``safety.stale_cycles`` in a row is a fault.
  Nor does a sample less than T/2 after the last stepped one (a late wake-up followed by an on-time one):
  Δx/dt over such a short interval is mostly quantisation noise; its row is marked stale.
* Slow-down: the controller's step intervals, plus the age of a late sample, are averaged (time constant
  ``loop.slow_down_time_s``): T_eff += min(1, dt/τ)·(dt + n·T − T_eff). When T_eff/T reaches the next of ``SLOW_DOWN_LEVELS`` (1.5, 2, 2.5,
  ...) the loop calls ``controller.set_timing_scale(level)``: the feedback crossover is divided by it
  (the design keeps the margins it has for T at the interval actually seen); it steps back when T_eff/T
  falls 10 % below the level. Logged at each change. The motion slows down with it: while the level is s the
  reference's own time runs at 1/s of the loop's (t_r += Δt/s, so v_r and a_r are scaled by 1/s and 1/s²):
  feedback at crossover/s cannot hold a full-speed reference (the HIL demo at load 12: at s = 4 the stage
  stuck in static friction and the 2 mm/s reference ran 60 µm ahead, ``following_error``). At s = 1 t_r = t
  exactly (simulated time unchanged); moves and stops are timed in t_r, and a move's reply gives its
  duration on the loop's clock (s × the planned duration while slowed).
* Fault reaction: after ``following_error``, ``velocity_limit`` or ``position_limit`` (position valid,
  drive obeying) the loop brakes the stage to standstill on a velocity ramp within ``max_force_n``
  (:class:`~stagectl.runtime.quickstop.QuickStopBrake`, deceleration ``safety.quick_stop_deceleration_m_s2``),
  then commands the actuator's ``quick_stop()``; the fault is latched and logged at once, the state is
  FAULT while braking. An actuator that brakes by itself (``brakes_itself``: a CiA 402 drive that took quick
  stop option code 3/4/7/8, slow down on its current / voltage limit, on its own encoder and clock) gets its
  ``quick_stop()`` at once instead: its braking does not depend on the loop getting CPU time or fresh samples. Every other fault (device, drive, NaN, stale position, loop error) quick-stops at
  once (zero force). Braking needs the moving mass (the controller's ``mass_kg``); without one the loop
  quick-stops at once.

The same code runs with :class:`~stagectl.clock.MonotonicClock` (``stagectl run``, the daemon) and with
:class:`~stagectl.clock.SimClock` plus lock-step devices (``stagectl simulate``, tests, benchmarks): with
a SimClock, ``sleep_until`` only advances time, so lateness is 0 and runs are deterministic.

API (thread-safe unless noted; the types live in :mod:`stagectl.runtime`)
-------------------------------------------------------------------------
* ``loop.columns`` -- telemetry column names (SI, docs/recordings.md): ``t`` s, ``x`` m, ``u`` N, ``x_ref`` m,
  ``v_ref`` m/s, ``a_ref`` m/s², ``e`` m (x_ref − x), ``v`` m/s (filtered measured velocity), then the
  controller terms in N (``u_pid``, ``u_dob``, ``u_ff``, ``u_inertia``, ...), then ``stale`` (1: this
  cycle's sample was stale, the force and its terms are the last cycle's, held) and ``skipped`` (slots skipped
  before this cycle: its ``t`` follows the previous row by ``(1 + skipped)·T``).
* ``loop.run(cycles=None, duration_s=None, stop=None) -> LoopResult`` -- in the calling thread (not
  thread-safe; :class:`~stagectl.runtime.host.LoopHost` gives it a thread) until ``cycles``, ``duration_s``
  of loop time, ``stop.is_set()`` or a shutdown request. Enables the devices at start and always disables
  the drive on the way out; futures still pending then fail with :class:`LoopStateError`.
* ``loop.submit(request) -> Future[dict]`` -- a typed request (:mod:`stagectl.runtime.requests`), checked
  against the stage's limits here and executed at the next cycle boundary; conditions known only there (a
  relative target outside the limits, a move in fault) are set on the future. A retune is designed in the
  caller's thread when the controller offers ``request_retune``.
* ``learner`` (optional, :class:`~stagectl.runtime.protocols.Learner`, ``ilc:``): stepped before the
  controller in every active cycle with a fresh sample, ``u_l = learner.step(t, e, moving=v_r ≠ 0 or a_r ≠ 0)``
  (the reference moves: the learning window); u_l goes to the
  controller's learned-force input (``step(..., u_learn_n=u_l)``) or, for a controller without one, is added to
  its command. Its columns (``u_ilc``, ``ilc_iteration``, ``ilc_rms_m``) follow the controller terms; a fault
  freezes it; ``IlcRequest`` drives it (``loop.status().ilc`` shows it).
* ``loop.latch_fault(name, cause)`` -- before ``run`` only: ``run`` then starts in fault without enabling the
  devices, and only a reset clears it (the daemon's ``unclean_shutdown``).
* ``loop.status(timing=True) -> LoopStatus`` -- a typed snapshot, with ``healthy`` for the watchdog.
* ``loop.add_sink(sink)`` / ``loop.remove_sink(sink)`` -- ``sink.append(row)`` once per cycle in the loop
  thread; it must not block; a sink that raises is removed and logged.
* ``loop.on_wait`` -- optional callable, run in the loop thread once per wall slot while a paced wait holds the
  cycles back (``loop.pace_cycles``, device time: no cycle, so no ``on_cycle``); the requests queued by then are
  served in that slot at the next cycle's loop time (a ``stop`` is answered and planned at once, and acts on the
  drive at the next cycle, when the drive answers again). Must not block.
* ``loop.on_state_change`` -- optional callable, run in the loop thread when the loop enters FAULT or a reset
  makes it ACTIVE (must not block; the daemon wakes its supervisor with it).
"""

from __future__ import annotations

import logging
import math
import operator
import threading
import time
from collections.abc import Callable
from typing import Any

from stagectl.clock import Clock, apply_realtime
from stagectl.control.api import Reference
from stagectl.control.trajectory import ForceBudget, Move
from stagectl.drivers.base import (
    Device,
    DeviceState,
    ForceActuator,
    Measurement,
    PositionSensor,
    SyncProducer,
)
from stagectl.errors import StageError
from stagectl.runtime.config import LoopConfig, RealtimeConfig
from stagectl.runtime.devices import DeviceSet
from stagectl.runtime.inbox import Reply, RequestInbox
from stagectl.runtime.protocols import (
    Controller,
    HoldsOnStale,
    KnowsStop,
    Learner,
    NamesTerms,
    PacesDevice,
    PredictsNextForce,
    PreparesRetune,
    ReferenceSource,
    RunsScenarios,
    ScalesWithTiming,
    TakesLearnedForce,
    TelemetrySink,
    UsesStop,
)
from stagectl.runtime.quickstop import BRAKE_FAULTS, QuickStopBrake
from stagectl.runtime.requests import (
    IlcRequest,
    LoopRequest,
    MotionLimits,
    MoveRequest,
    RequestError,
    ResetRequest,
    RetuneRequest,
    ShutdownRequest,
    StopRequest,
)
from stagectl.runtime.sinks import SinkSet
from stagectl.runtime.stats import CycleStats, LatenessWarner
from stagectl.runtime.status import FaultInfo, LoopResult, LoopState, LoopStateError, LoopStatus
from stagectl.safety import Safety

__all__ = [
    "BASE_COLUMNS",
    "FLAG_COLUMNS",
    "DEFAULT_TERMS",
    "ControlLoop",
    "Controller",
    "LoopConfig",
    "LoopResult",
    "LoopState",
    "LoopStateError",
    "LoopStatus",
    "RealtimeConfig",
    "ReferenceSource",
    "TelemetrySink",
]

log = logging.getLogger("stagectl.loop")

BASE_COLUMNS = ("t", "x", "u", "x_ref", "v_ref", "a_ref", "e", "v")
#: appended after the controller terms: stale sample (force and terms held) and skipped slots before the row
FLAG_COLUMNS = ("stale", "skipped")
DEFAULT_TERMS = ("u_pid", "u_dob", "u_ff", "u_inertia")
#: the controller's dt is clamped to [MIN_DT_PERIODS·T, MAX_DT_PERIODS·T] (module docstring)
#: a sample this many periods old (``Measurement.age_cycles``) is treated as stale, not stepped on
STALE_AGE_CYCLES = 2
MIN_DT_PERIODS = 0.5
MAX_DT_PERIODS = 10.0
#: the longest move a request may plan [s]; a slower ``max_velocity_m_s`` is refused as a likely typo
MAX_MOVE_S = 86400.0
#: feedback slow-down steps (effective sample interval / T); a step down needs the average 10 % below it
SLOW_DOWN_LEVELS = (1.0, 1.5, 2.0, 2.5, 3.0, 4.0)


def _next_level(lvl: float) -> float:
    i = SLOW_DOWN_LEVELS.index(lvl)
    return SLOW_DOWN_LEVELS[min(i + 1, len(SLOW_DOWN_LEVELS) - 1)]


def _term_getter(names: tuple[str, ...]) -> Callable[[dict[str, float]], tuple[float, ...]]:
    """``terms -> tuple(terms[n] for n in names)`` (KeyError for a missing name) at C speed."""
    if len(names) == 1:
        name = names[0]
        return lambda terms: (terms[name],)
    if not names:
        return lambda terms: ()
    get: Callable[[dict[str, float]], tuple[float, ...]] = operator.itemgetter(*names)
    return get


def _prev_level(lvl: float) -> float:
    return SLOW_DOWN_LEVELS[max(SLOW_DOWN_LEVELS.index(lvl) - 1, 0)]


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
        loop time is then ``executed cycles × T`` (a step after stale samples gets the whole gap), so skipped
        slots slow the simulation down instead of desynchronising reference and plant. False (default): loop
        time is ``clock.now() − start`` (a skipped slot gives ``dt ≈ T·(1 + skipped)``), right for real devices
        and for PlantIO with a clock (its plant follows the clock).
    realtime : bool
        Apply ``cfg.realtime`` (FIFO, affinity, mlock, timer slack, gc.freeze) in the loop thread at start.
        False for simulated time.
    """

    def __init__(
        self,
        *,
        clock: Clock, sensor: PositionSensor, actuator: ForceActuator, controller: Controller,
        reference: ReferenceSource, safety: Safety, cfg: LoopConfig, sync: SyncProducer | None = None,
        realtime: bool = False, on_cycle: Callable[[], None] | None = None, term_names: tuple[str, ...] | None = None,
        device_time: bool = False, learner: Learner | None = None,
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
        #: called in the loop thread right after the loop enters FAULT or a reset makes it ACTIVE again (must not
        #: block: the daemon wakes its supervisor with it, so the service state does not wait for its next tick)
        self.on_state_change: Callable[[], None] | None = None
        #: called in the loop thread once per wall slot of a paced wait (``loop.pace_cycles``: no cycle runs, so
        #: ``on_cycle`` is not called), right before the queued requests are served (must not block: the daemon's
        #: loop process takes the requests its clients queued and publishes its status with it)
        self.on_wait: Callable[[], None] | None = None
        self._devs = DeviceSet(sensor, actuator, sync)
        self.devices: tuple[Device, ...] = self._devs.all  # unique, ordered
        named = controller.term_names if isinstance(controller, NamesTerms) else DEFAULT_TERMS
        terms: tuple[str, ...] = tuple(term_names) if term_names else tuple(named)
        self.term_names = terms
        self.learner = learner
        self._learn_ctl = controller if learner is not None and isinstance(controller, TakesLearnedForce) else None
        extra = tuple(learner.columns) if learner is not None else ()
        self.columns: tuple[str, ...] = BASE_COLUMNS + terms + extra + FLAG_COLUMNS
        self.state = LoopState.CONFIGURED if self._devs.ready() else LoopState.UNCONFIGURED
        self._inbox = RequestInbox()
        self._sinks = SinkSet()
        self._running = False
        self._shutdown = False
        self._just_reset = False
        self._fresh = False  # this cycle's sample is fresh (read by a reset's persisting-cause check)
        self.stats = CycleStats(cfg.stats_window)  # preallocated
        self.cycle = 0
        self.overruns = 0
        #: wall slots the loop waited for a device behind its SYNCs (``loop.pace_cycles``, device time)
        self.device_waits = 0
        self.faults = 0  # faults entered since construction (a fault cleared by a reset between two looks counts)
        self._snap: tuple[float, float, float, float, float] = (0.0, math.nan, math.nan, math.nan, 0.0)
        self._u = 0.0
        self._act_lim_warned = math.nan  # the actuator limit last warned about [N] (_adopt_actuator_limit)
        self._moves_slowed = 0  # moves planned slower than asked to stay within the force (_tell_move_slowed)
        self._budget: ForceBudget | None = None  # the move force budget handed to the reference last
        self._budget_short_warned: tuple[float, float] | None = None  # (F_s, budget) last told to take it all
        self._budget_stale = False  # a prepared retune lands at the next step: plan moves on its model after it
        self._t0 = 0.0
        self._t_step: float | None = None  # loop time of the last sample the controller stepped on
        self.t_eff_s = self.period_s  # average measured sample interval of the controller's steps [s]
        self.slow_down = 1.0  # the feedback slow-down factor in force (SLOW_DOWN_LEVELS)
        self.slow_downs = 0  # level changes so far
        self.ref_lag_s = 0.0  # loop time minus the reference's own time (the motion slowed down with the feedback)
        self.brake: QuickStopBrake | None = None  # the fault reaction's brake while it runs
        self.last_brake: QuickStopBrake | None = None  # the last one that ran (diagnostics, tests)
        #: False: release at once on every fault (the reaction before active braking; benchmarks compare)
        self.active_braking = True
        #: False: the reference keeps the loop's time while the feedback is slowed down (the loop before the
        #: motion slowed down with it; tests and benchmarks compare)
        self.slow_motion = True
        self.realtime_report: dict[str, Any] = {}

    # ------------------------------------------------------------------ sinks
    def add_sink(self, sink: TelemetrySink) -> None:
        """Register a telemetry sink (thread-safe). ``sink.append(row)`` must not block."""
        self._sinks.add(sink)

    def remove_sink(self, sink: TelemetrySink) -> None:
        """Unregister a sink (thread-safe; unknown sinks are ignored)."""
        self._sinks.remove(sink)

    # ------------------------------------------------------------------ requests
    @property
    def limits(self) -> MotionLimits:
        """Soft limits and velocity limit a move is checked against (the safety section's)."""
        c = self.safety.cfg
        return MotionLimits(c.min_position_m, c.max_position_m, c.max_velocity_m_s, c.move_velocity_fraction)

    def submit(self, req: LoopRequest) -> Reply:
        """Queue a typed request for the next cycle boundary (thread-safe; see the module docstring).

        Raises RequestError (a ValueError naming the field) for a move outside the limits, and whatever a
        controller's ``request_retune`` raises for a bad tuning (ConfigError is a ValueError).
        """
        prepared = False
        if isinstance(req, MoveRequest):
            req.check_limits(self.limits)
        elif isinstance(req, RetuneRequest):
            if isinstance(self.controller, PreparesRetune):
                # design (observer gains, model) here in the caller's thread; the controller swaps the prepared
                # parts in at its next step. Bad tunings raise here.
                self.controller.request_retune(req.controller_config)
                prepared = True
        elif isinstance(req, IlcRequest):
            if self.learner is None:
                raise RequestError("request", "learning is not enabled (ilc.enabled: false in the config)")
            if req.action == "start":
                self.learner.prepare()  # the design of the running motion, here in the caller's thread
        return self._inbox.put(req, prepared)

    def _execute(self, req: LoopRequest, prepared: bool, t: float, x: float) -> dict[str, Any]:
        if isinstance(req, ShutdownRequest):
            self._shutdown = True
            return {"cycles": self.cycle}
        if isinstance(req, ResetRequest):
            return self._reset(t, x)
        if isinstance(req, IlcRequest):
            if self.learner is None:
                raise RequestError("request", "learning is not enabled (ilc.enabled: false in the config)")
            try:
                out: dict[str, Any] = {}
                if req.action == "start" and req.motion is not None:  # run that motion, repeated, and learn it
                    if self.state is not LoopState.ACTIVE:
                        raise LoopStateError(f"ilc: loop is {self.state.value}; reset first")
                    if not isinstance(self.reference, RunsScenarios):
                        raise RequestError("motion", "this reference source runs no named motions")
                    out["repetition_s"] = self.reference.run_scenario(t - self.ref_lag_s, req.motion)
                return {**self.learner.request(req.action, req.motion if req.action != "start" else None), **out}
            except ValueError as exc:
                field, _, msg = str(exc).partition(": ")
                raise RequestError(field if msg else "action", msg or str(exc)) from None
        if isinstance(req, RetuneRequest):
            if not prepared:
                self.controller.retune(req.controller_config)
                self._plan_moves_within_force()  # (its mass, friction model and max_force_n may have changed)
            else:
                self._budget_stale = True  # swapped in at the controller's next step: the budget after it
            return {"retuned": True}
        if self.state is not LoopState.ACTIVE:
            fault = self.safety.fault
            why = f" ({fault})" if fault else ""
            raise LoopStateError(f"{req.KIND}: loop is {self.state.value}{why}; reset first")
        if isinstance(req, StopRequest):
            return {"x_m": float(self.reference.stop(t - self.ref_lag_s))}
        if req.target_m is not None:
            target = req.target_m
        else:
            rel = req.relative_m if req.relative_m is not None else 0.0
            target = self.limits.check_relative(self.reference.target_m, rel)
        v = req.max_velocity_m_s
        if v is not None:  # a typo (1e-250 for 1e-5) would otherwise plan a move that outlives the machine
            dist = abs(target - self.reference.target_m)
            if dist / v > MAX_MOVE_S:
                raise RequestError("max_velocity_m_s", f"{v:g} m/s over {dist:g} m would take {dist / v:.3g} s, "
                                   f"more than {MAX_MOVE_S:g} s (a day)")
        duration = self.reference.move(t - self.ref_lag_s, target, v)
        if self.slow_motion and self.slow_down != 1.0:  # the reference runs at 1/s of loop time while slowed
            duration *= self.slow_down
        return {"target_m": target, "duration_s": float(duration)}

    def _reset(self, t: float, x: float) -> dict[str, Any]:
        if self.state is not LoopState.FAULT:
            return {"state": self.state.value, "cleared": None}
        if self.brake is not None:
            raise LoopStateError("reset: the fault reaction is still braking the stage; retry when it stands")
        cleared = self.safety.fault
        # refused while a cause persists (heartbeat still missing, bus-off, link closed, stage outside the soft
        # limits, ...): it would latch again at once, or worse, enable a drive nobody can supervise
        persisting = self._devs.persisting() + self.safety.persisting(x, self._fresh)
        if persisting:
            why = "; ".join(persisting)
            log.warning("reset refused: %s (fault %s stays latched)", why, cleared.name if cleared else "-")
            raise LoopStateError(f"reset refused: cause still present: {why}; the fault stays latched")
        self._devs.reset_faults()
        self.safety.clear()
        self.safety.restart(x, t)
        self._adopt_actuator_limit()  # (a drive configured again may report another max torque)
        self.controller.reset(x)
        self.reference.hold(t - self.ref_lag_s, x)
        self._u = 0.0
        self._t_step = None
        self.state = LoopState.ACTIVE
        self._just_reset = True
        log.warning("fault reset: %s cleared, loop active at x = %.9g m", cleared.name if cleared else "-", x)
        self._state_changed()
        return {"state": self.state.value, "cleared": cleared.as_dict() if cleared else None}

    def latch_fault(self, name: str, cause: str) -> FaultInfo:
        """Latch fault ``name`` (``cause``: human-readable text) before :meth:`run` (see the module docstring).
        A fault already latched is kept (the first one wins, as in :meth:`Safety.latch`); returns the latched
        fault. Raises :class:`LoopStateError` while the loop runs (faults are latched in the loop thread then)."""
        if self._running:
            raise LoopStateError("latch_fault: only before run (the loop is running)")
        return self.safety.latch(name, cause, 0.0, self.cycle)

    # ------------------------------------------------------------------ status
    def status(self, timing: bool = True) -> LoopStatus:
        """Thread-safe snapshot (see :class:`~stagectl.runtime.status.LoopStatus`).

        ``timing=False`` leaves out ``lateness_us`` and ``exec_us`` (None): their percentiles over the stats
        window take ~2 ms of interpreter time, which a frequent caller (the daemon's supervisor tick) should
        not take from the loop thread when it only needs the counters, state and health.
        """
        t, x, x_ref, u, cyc = self._snap
        frac = self.stats.overrun_fraction(self.cycle)
        state = self.state
        return LoopStatus(
            state=state, fault=self.safety.fault, t_s=t, x_m=x, x_ref_m=x_ref, e_m=x_ref - x, u_n=u,
            cycle=int(cyc), overruns=self.overruns, recent_overrun_fraction=frac, period_s=self.period_s,
            faults=self.faults,
            running=self._running,
            healthy=bool(self._running and state is LoopState.ACTIVE and frac <= self.cfg.healthy_overrun_fraction),
            lateness_us=self.stats.lateness(self.cycle) if timing else None,
            exec_us=self.stats.execution(self.cycle) if timing else None,
            ilc=self.learner.status() if self.learner is not None else None,
            in_position=_in_position(self.controller),
        )

    # ------------------------------------------------------------------ fault
    def _write_scheduled(self, actuator: ForceActuator, pred: PredictsNextForce, u_n: float) -> None:
        """``write_schedule(u, û)`` with û = u + the controller's predicted increment within safety's ±L
        (io.command_schedule); a non-finite prediction holds u (min/max would turn NaN into full force)."""
        u_nx = u_n + pred.next_force_increment_n()
        f_lim = self.safety.force_limit_n
        actuator.write_schedule(u_n, max(-f_lim, min(f_lim, u_nx)) if math.isfinite(u_nx) else u_n)

    def _enter_fault(self, t: float, x: float = math.nan) -> None:
        if self.state is LoopState.FAULT:
            return
        self.state = LoopState.FAULT
        self.faults += 1
        self._u = 0.0
        fault = self.safety.fault
        if self.learner is not None:
            self.learner.freeze(fault.name if fault is not None else "fault")
        brake = self._make_brake(t, x) if fault is not None and fault.name in BRAKE_FAULTS else None
        if brake is None:
            self._devs.quick_stop(fault)
            by_drive = getattr(self.actuator, "brakes_itself", False) is True
            log.error("FAULT %s; drive quick-stopped%s", fault,
                      " (it brakes the stage on its current limit)" if by_drive else "")
            self._state_changed()
            return
        self.brake = self.last_brake = brake
        log.error("FAULT %s; braking from %.4g m/s at %.3g m/s^2 (force within %.3g N), then quick stop", fault,
                  brake.v0_m_s, brake.a_m_s2, brake.max_force_n)
        self._brake_cycle(t, x, True)
        self._state_changed()

    def _state_changed(self) -> None:
        cb = self.on_state_change
        if cb is not None:
            try:
                cb()
            except Exception:  # a wake-up that fails must not turn into a loop error
                log.exception("on_state_change failed")

    def _set_slow_down(self, level: float, t: float) -> None:
        """Slow the controller's feedback down to ``level`` (see the module docstring); logged."""
        prev, self.slow_down = self.slow_down, level
        self.controller.set_timing_scale(level)  # type: ignore[attr-defined]
        self.slow_downs += 1
        lvl = logging.WARNING if self.slow_downs == 1 else logging.INFO  # first one a warning, then info
        log.log(lvl, "loop timing: average sample interval %.2f T: feedback %s to crossover / %g (t=%.3f s)",
                self.t_eff_s / self.period_s, "slowed" if level > prev else "restored", level, t)

    def _adopt_actuator_limit(self) -> None:
        """Hand the actuator's own force limit (``force_limit_n``: a CiA 402 drive's max torque 0x6072 read at
        configure, a simulated actuator's ``max_force_n``) to the controller (output clamp, anti-windup) and to
        safety (hard clamp), so that the force commanded, written and recorded is the force applied. A limit
        below ``controller.max_force_n`` or ``safety.max_force_n`` is told once per value as a warning naming
        both and where each comes from; the master never raises the drive's limit itself."""
        self._adopt_limit()
        self._plan_moves_within_force()

    def _plan_moves_within_force(self) -> None:
        """Moves are planned within ``safety.move_force_fraction`` of the usable force (the least of the
        controller's and safety's clamps, which hold the actuator's own limit by now) on the controller's mass
        and friction model (:class:`~stagectl.control.trajectory.ForceBudget`); a move planned slower than asked
        is logged (warning the first time, then info)."""
        setter = getattr(self.reference, "set_force_budget", None)
        terms = getattr(self.controller, "move_force_terms", None)
        frac = float(getattr(self.safety.cfg, "move_force_fraction", 0.0))
        self._budget = None
        if not callable(setter):
            return
        if not (callable(terms) and frac > 0.0):
            setter(None)
            return
        m, static, visc = terms()
        usable = min(float(getattr(self.controller, "force_limit_n", math.inf)), self.safety.force_limit_n)
        if not (m > 0.0 and math.isfinite(usable) and usable > 0.0):
            setter(None)
            return
        budget = ForceBudget(m, frac * usable, static, visc)
        if static >= budget.force_n and (static, budget.force_n) != self._budget_short_warned:
            # (ForceBudget.fit then leaves every move as asked: say so rather than plan nothing silently)
            self._budget_short_warned = (static, budget.force_n)
            log.warning("moves cannot be planned within the force: the friction model's %.3g N alone takes the "
                        "%.3g N budget (safety.move_force_fraction %g x %.3g N usable); moves run as asked",
                        static, budget.force_n, frac, usable)
        self._budget = budget
        setter(budget, self._tell_move_slowed)

    def _tell_move_slowed(self, asked: Move, planned: Move) -> None:
        self._moves_slowed += 1
        lvl = logging.WARNING if self._moves_slowed == 1 else logging.INFO
        b = self._budget  # the budget the move was planned within
        if b is None:
            return
        frac = self.safety.cfg.move_force_fraction
        log.log(lvl, "move planned slower: it asks up to %.3g N (m*a %.3g kg x %.3g m/s^2 + friction %.3g N + "
                "viscous %.3g N s/m x %.3g m/s), over the %.3g N budget (safety.move_force_fraction %g of %.3g N "
                "usable): planned at a_max %.3g m/s^2, v_max %.3g m/s, j_max %.3g m/s^3", b.move_force_n(asked),
                b.mass_kg, asked.max_acceleration_m_s2, b.static_n, b.viscous_n_s_m, asked.max_velocity_m_s,
                b.force_n, frac, b.force_n / frac if frac > 0 else math.nan,
                planned.max_acceleration_m_s2, planned.max_velocity_m_s, planned.max_jerk_m_s3)

    def _adopt_limit(self) -> None:
        lim = getattr(self.actuator, "force_limit_n", None)
        if isinstance(lim, (int, float)) and lim <= 0.0 and lim != self._act_lim_warned:
            # (a drive whose max torque 0x6072 reads 0 clamps every command to nothing: say so, or the first
            # sign of it is a following-error fault with the controller wound up against an unseen clamp)
            self._act_lim_warned = float(lim)
            log.warning("%s: the force is limited to %.4g N by %s: the stage gets no force; raise the drive's "
                        "limit (the integrator's setting, 0x6072 on a CiA 402 drive)", self.actuator.name, lim,
                        getattr(self.actuator, "force_limit_source", "its own limit"))
        if not isinstance(lim, (int, float)) or not (lim > 0.0 and math.isfinite(lim)):
            return
        lim = float(lim)
        setter = getattr(self.controller, "set_actuator_limit", None)
        if callable(setter):
            setter(lim)
        self.safety.set_actuator_limit(lim)
        ctl_cfg = getattr(self.controller, "cfg", None)
        ctl_lim = getattr(ctl_cfg, "max_force_n", None)
        above = [f"{key} {v:g} N" for key, v in (("controller.max_force_n", ctl_lim),
                                                 ("safety.max_force_n", self.safety.cfg.max_force_n))
                 if isinstance(v, (int, float)) and lim < v * (1.0 - 1e-9)]
        if above and lim != self._act_lim_warned:
            self._act_lim_warned = lim
            src = getattr(self.actuator, "force_limit_source", "its own limit")
            log.warning("%s: the force is limited to %.4g N by %s, below %s: the controller saturates (and stops "
                        "integrating) and safety clamps at %.4g N, and the force recorded is the force applied; "
                        "raise the drive's limit (the integrator's setting, 0x6072 on a CiA 402 drive) or lower "
                        "max_force_n to agree", self.actuator.name, lim, src, " and ".join(above), lim)

    def _make_brake(self, t: float, x: float) -> QuickStopBrake | None:
        """The fault reaction's brake, or None when braking is not possible (no mass, actuator not enabled)."""
        mass = getattr(self.controller, "mass_kg", None)
        if not self.active_braking or not (isinstance(mass, (int, float)) and mass > 0 and math.isfinite(x)):
            return None
        if self.actuator.state is not DeviceState.ENABLED:
            return None
        if getattr(self.actuator, "brakes_itself", False) is True:
            return None  # the drive brakes on its own velocity (CiA 402 0x605A 3/4/7/8), starved master or not
        c = self.safety.cfg
        lim = self.safety.force_limit_n  # and the actuator's own limit when it has one (CiA 402: 0x6072 max torque)
        act_lim = getattr(self.actuator, "force_limit_n", None)
        if isinstance(act_lim, (int, float)) and 0.0 < act_lim < lim:
            lim = float(act_lim)
        a = c.quick_stop_deceleration_m_s2 or 0.9 * lim / float(mass)
        return QuickStopBrake(t, x, self.safety.v_est_m_s, mass_kg=float(mass), max_force_n=lim,
                              deceleration_m_s2=a, standstill_m_s=c.quick_stop_standstill_m_s,
                              stale_limit=c.stale_cycles)

    def _brake_cycle(self, t: float, x: float, fresh: bool) -> None:
        """One cycle of the fault reaction's brake; at its end the actuator's quick stop (force 0)."""
        brake = self.brake
        assert brake is not None
        u = brake.step(t, x, fresh)
        if not brake.done:
            self.actuator.write(u)
            self._u = u
            return
        self.brake = None
        self._u = 0.0
        self._devs.quick_stop(self.safety.fault)
        log.error("fault reaction: brake ended (%s) after %.1f ms, %.3g m from where it began; drive "
                  "quick-stopped", brake.why, (t - brake.t0_s) * 1e3, x - brake.x0_m)

    # ------------------------------------------------------------------ run
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
        if not faulted and self._devs.any_configured():
            m, t0, waited = self._devs.first_sample(clock, t0, self.period_s, n_max)
            if not m.fresh:
                raise StageError(f"no position from {self.sensor.name} within loop.startup_cycles {n_max} cycles "
                                 f"(devices configured, not yet enabled)")
            self._devs.enable_configured()
            t0 = max(t0 + self.period_s, clock.now())  # the next SYNC slot after the warm-up one
            clock.sleep_until(t0)
        m, t0, i = self._devs.first_sample(clock, t0, self.period_s, n_max)
        if waited or i:
            log.info("first fresh position after %d + %d start-up cycles", waited, i)
        self._t0 = t0
        self._t_step = None
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
        self._adopt_actuator_limit()
        self.controller.reset(x0)
        self.ref_lag_s = 0.0
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
        waits0 = self.device_waits
        try:
            if self.realtime:
                rt = self.cfg.realtime
                report = apply_realtime(fifo_priority=rt.fifo_priority, cpus=rt.cpus, mlock=rt.mlock,
                                        timer_slack_ns=rt.timer_slack_ns, gc_freeze=rt.gc_freeze)
                self.realtime_report = report.as_dict()
                for note in report.notes:
                    log.info("real time: %s", note)
            t0 = self._start()
            ended_by = self._cycles(t0, period, cycles, duration_s, stop)
        finally:
            self._teardown()
            self._running = False
            self._fail_pending()
        cpu = time.thread_time() - cpu0
        wall = max(1e-9, time.monotonic() - wall0)
        fault = self.safety.fault
        return LoopResult(
            cycles=self.cycle - cycle0,
            overruns=self.overruns - overruns0,
            duration_s=clock.now() - self._t0,
            ended_by=ended_by,
            lateness_us=self.stats.lateness(self.cycle),
            exec_us=self.stats.execution(self.cycle),
            cpu_fraction=cpu / wall,
            fault=fault,
            realtime=self.realtime_report,
            device_waits=self.device_waits - waits0,
        )

    def _cycles(
        self, t0: float, period: float, cycles: int | None, duration_s: float | None, stop: threading.Event | None
    ) -> str:
        clock = self.clock
        sensor, actuator, sync = self.sensor, self.actuator, self.sync
        safety, controller, reference = self.safety, self.controller, self.reference
        term_names = self.term_names
        record = self.stats.record
        devs, sinks = self._devs, self._sinks
        warner = LatenessWarner(self.cfg.lateness_warn_us * 1e-6, self.cfg.warn_interval_s) if self.realtime else None
        on_cycle = self.on_cycle
        perf = time.perf_counter
        slot = 0  # deadline of slot n is t0 + n·T (no accumulated rounding)
        dt_min, dt_max = MIN_DT_PERIODS * period, MAX_DT_PERIODS * period
        skipped = 0
        late = 0.0
        max_cycles = self.cycle + cycles if cycles is not None else -1
        t_end = duration_s if duration_s is not None else math.inf
        k = self.cycle
        k0 = k
        device_time = self.device_time
        x_prev_ref = Reference(self._snap[2])
        held: dict[str, float] = {}  # the last fresh cycle's terms, recorded again while a stale sample holds u
        learner, learn_ctl = self.learner, self._learn_ctl
        lrow: tuple[float, ...] = ()
        stale_row = False
        holds = isinstance(controller, HoldsOnStale)
        # where the reference next rests without reversing, for the controller's feed-forward look-ahead
        stop_of = reference.stop_m if isinstance(reference, KnowsStop) else None
        set_stop = controller.set_reference_stop if stop_of is not None and isinstance(controller, UsesStop) else None
        # a command schedule (io.command_schedule): each write also carries the controller's predicted force
        # for the period after it, which the actuator applies in a slot the loop skips
        pred = controller if isinstance(controller, PredictsNextForce) else None
        sched = pred is not None and bool(getattr(actuator, "schedules_commands", False))
        tau_slow = float(self.cfg.slow_down_time_s) if isinstance(controller, ScalesWithTiming) else 0.0
        t_ctl = self._t_step  # loop time of the last controller step or hold
        lvl_at, up = math.nan, math.inf  # slow-down level whose step-up threshold ``up`` is current
        term_row = _term_getter(term_names)  # the terms, in column order
        no_terms = (0.0,) * len(term_names)
        serve, execute = self._inbox.serve, self._execute
        t_last = math.nan  # the previous cycle's loop time (the reference's own time: module docstring)
        slow_motion = self.slow_motion
        pace = int(self.cfg.pace_cycles) if device_time and isinstance(sync, PacesDevice) else 0
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
            s_ref = self.slow_down if slow_motion else 1.0
            if s_ref != 1.0 and t_last == t_last:
                self.ref_lag_s += (t - t_last) * (1.0 - 1.0 / s_ref)
            t_last = t  # (a paced wait repeats the same t: it adds nothing more)
            if pace and self.state is LoopState.ACTIVE and sync.behind(pace, 1 + skipped):  # type: ignore[union-attr]
                # device time: the drive has not answered our last SYNCs (its process held off the CPU, its
                # plant frozen); the loop's time waits with it: no SYNC, no force, no row in this slot. Requests
                # are still served, at the loop time t of the next cycle (a stop's reply does not wait for the drive)
                self.device_waits += 1 + skipped
                self._serve_waiting(t)
                slot, late, skipped = _sleep_to_slot(clock, t0, slot + 1, period)
                self.overruns += skipped
                continue
            t_r = t - self.ref_lag_s if self.ref_lag_s else t
            c0 = perf()
            # ------------------------------------------------------ one cycle
            try:
                if sync is not None:
                    sync.sync()
                m = sensor.read()
                if m.age_cycles >= STALE_AGE_CYCLES and m.fresh:  # too old to step on: stale (predicted/held)
                    m = Measurement(m.position_m, False, m.counts, m.status, m.fault, m.age_cycles)
                x = m.position_m
                self._fresh = m.fresh
                serve(execute, t, x)
                if self._just_reset:  # this cycle's sample predates the reset: restart cleanly next cycle
                    self._just_reset = False
                    m = Measurement(x, False)
                dev_fault = m.fault if m.fault is not None else devs.fault()
                t_m = t
                if m.age_cycles and m.fresh:  # a late sample from age·T ago: its own time for the velocity
                    t_m = t - m.age_cycles * period  # estimate, then extrapolated to now with it
                if self.state is LoopState.ACTIVE and safety.check_measurement(t_m, k, x, m.fresh, dev_fault):
                    self._enter_fault(t, x)
                if t_m != t and math.isfinite(x):
                    x += safety.v_est_m_s * (t - t_m)
                if self.state is LoopState.ACTIVE:
                    ref = reference.sample(t_r)
                    if s_ref != 1.0:  # the motion slowed down with the feedback
                        ref = Reference(ref.x_m, ref.v_m_s / s_ref, ref.a_m_s2 / (s_ref * s_ref))
                    safety.reference_speed_m_s = abs(ref.v_m_s)
                    if set_stop is not None:
                        set_stop(stop_of())  # type: ignore[misc]
                    if safety.check_tracking(t, k, x, ref.x_m, m.fresh):
                        self._enter_fault(t, x)
                    elif m.fresh and (self._t_step is None or t - self._t_step >= dt_min):
                        t_prev = self._t_step
                        dt = period if t_prev is None else min(dt_max, t - t_prev)
                        if abs(dt - period) <= 1e-6 * period:  # on time (rounding of t aside): exactly T
                            dt = period
                        self._t_step = t_ctl = t
                        if tau_slow > 0.0:
                            d_eff = dt + m.age_cycles * period  # a late sample adds its age as delay
                            self.t_eff_s += min(1.0, dt / tau_slow) * (d_eff - self.t_eff_s)
                            r = self.t_eff_s / period
                            lvl = self.slow_down
                            if lvl != lvl_at:  # the next level up, looked up once per level change
                                lvl_at = lvl
                                up = _next_level(lvl) if lvl < SLOW_DOWN_LEVELS[-1] else math.inf
                            if r >= up:
                                lvl = up
                            elif lvl > 1.0 and r < 0.9 * lvl:
                                lvl = _prev_level(lvl)
                            if lvl != self.slow_down:
                                self._set_slow_down(lvl, t)
                        if learner is None:
                            cmd = controller.step(dt, x, ref)
                        else:  # the learned feed-forward of a repeated motion (ilc:)
                            u_l = learner.step(t_r, ref.x_m - x, moving=ref.v_m_s != 0.0 or ref.a_m_s2 != 0.0)
                            if learn_ctl is not None:
                                cmd = learn_ctl.step(dt, x, ref, u_l, learner.active)
                            else:
                                cmd = controller.step(dt, x, ref)
                                cmd.force_n += u_l
                        u = safety.limit_force(t, k, cmd.force_n, "force" in cmd.limited)
                        if safety.fault is not None:
                            self._enter_fault(t, x)
                        elif sched and pred is not None:
                            self._write_scheduled(actuator, pred, u)
                            self._u = u
                        else:
                            actuator.write(u)
                            self._u = u
                        terms = held = cmd.terms
                        if self._budget_stale:  # a prepared retune was swapped in at this step (mass, model, limit)
                            self._budget_stale = False
                            self._plan_moves_within_force()
                    else:  # stale sample (below the stale limit), or one less than T/2 after the last
                        # stepped one (a late wake-up right before an on-time one): feedback held, no new
                        # estimate (the next step gets the whole gap); the feed-forward follows the reference
                        # when the controller can (hold), else the last force is held
                        stale_row = True
                        terms = held
                        if holds and self._t_step is not None and t_ctl is not None and t - t_ctl >= dt_min:
                            dt_h = min(dt_max, t - t_ctl)
                            if learner is None:
                                cmd = controller.hold(dt_h, ref)  # type: ignore[attr-defined]
                            else:  # the learned force goes on along the motion (not recorded)
                                u_l = learner.step(t_r, ref.x_m - x, fresh=False)
                                if learn_ctl is not None:
                                    cmd = controller.hold(dt_h, ref, u_l)  # type: ignore[attr-defined]
                                else:
                                    cmd = controller.hold(dt_h, ref)  # type: ignore[attr-defined]
                                    cmd.force_n += u_l
                            t_ctl = t
                            u = safety.limit_force(t, k, cmd.force_n, "force" in cmd.limited)
                            if safety.fault is not None:
                                self._enter_fault(t, x)
                            else:
                                self._u = u
                                terms = cmd.terms
                        if self.state is LoopState.ACTIVE:
                            if sched and pred is not None and holds and t_ctl == t:  # (held by the controller now)
                                self._write_scheduled(actuator, pred, self._u)
                            else:
                                actuator.write(self._u)
                else:
                    if self.brake is not None and self.brake.t_last_s < t:  # (not the cycle it began in)
                        if dev_fault is not None:  # the drive no longer obeys: release at once
                            self.brake.step(t, math.nan, False)
                        self._brake_cycle(t, x, m.fresh)
                    ref = x_prev_ref if self.state is LoopState.FAULT else reference.sample(t_r)
                    terms = {}
                x_prev_ref = ref
                if stale_row:
                    fresh_row, stale_row = 0.0, False
                else:
                    fresh_row = 1.0 if m.fresh else 0.0
                u = self._u
                if learner is not None:
                    lrow = learner.row()
                if not terms:
                    tvals = no_terms
                else:
                    try:  # a step's terms name every column (one C-speed lookup); else a missing one is 0
                        tvals = term_row(terms)
                    except KeyError:
                        tvals = tuple([terms.get(n, 0.0) for n in term_names])
                xr, vr, ar = ref
                row = (t, x, u, xr, vr, ar, xr - x, safety.v_est_m_s, *tvals, *lrow, 1.0 - fresh_row, float(skipped))
                sinks.emit(row)
                self._snap = (t, x, xr, u, k)
                if on_cycle is not None:
                    on_cycle()
            except Exception as exc:  # unexpected: safe stop, record, keep supervising
                if safety.fault is None:
                    log.exception("unexpected error in cycle %d", k)
                safety.latch("loop_error", f"{type(exc).__name__}: {exc}", t, k)
                if self.brake is not None:  # braking itself failed: release to the drive's quick stop
                    self.brake = None
                    self._u = 0.0
                    self._devs.quick_stop(safety.fault)
                self._enter_fault(t)
            # ------------------------------------------------------ statistics
            record(k, late, perf() - c0, skipped)
            k += 1
            self.cycle = k
            # ------------------------------------------------------ schedule: absolute deadline
            slot, late, skipped = _sleep_to_slot(clock, t0, slot + 1, period)
            self.overruns += skipped
            if warner is not None:
                warner.note(t, late, skipped, period, self.overruns)

    def _serve_waiting(self, t: float) -> None:
        """One wall slot of a paced wait (the loop thread): the ``on_wait`` hook (the daemon's loop process takes
        its queued requests and publishes its status there), then the queued requests, executed at loop time
        ``t`` (the next cycle's: the plant stands still with the loop's time) with the last cycle's position. A
        stop is thus answered and planned in the slot it arrives in, and acts on the drive at the next cycle.
        An error in the hook is a loop error (as in a cycle's ``on_cycle``): fault, quick stop."""
        x = self._snap[1]
        try:
            hook = self.on_wait
            if hook is not None:
                hook()
            self._inbox.serve(self._execute, t, x)
        except Exception as exc:
            log.exception("unexpected error while waiting for the device at cycle %d", self.cycle)
            self.safety.latch("loop_error", f"{type(exc).__name__}: {exc}", t, self.cycle)
            self._enter_fault(t)

    def _teardown(self) -> None:
        if self.brake is not None:  # the run ends while braking: the drive's own quick stop takes over
            self.brake = None
            self._devs.quick_stop(self.safety.fault)
        self._devs.shut_down(write_zero=self.state is LoopState.ACTIVE)
        self._u = 0.0
        if self.state is LoopState.ACTIVE:
            self.state = LoopState.CONFIGURED

    def _fail_pending(self) -> None:
        self._inbox.fail_pending(lambda: LoopStateError("the control loop is not running"))


def _sleep_to_slot(clock: Clock, t0: float, slot: int, period: float) -> tuple[int, float, int]:
    """Sleep until ``slot``'s deadline ``t0 + slot·period`` [s]; returns ``(slot, late, skipped)``: a wake-up a
    period or more late skips the slots it missed (``slot`` advanced by ``skipped``, ``late`` [s] within the
    slot now current)."""
    deadline = t0 + slot * period
    clock.sleep_until(deadline)
    late = clock.now() - deadline
    skipped = 0
    if late >= period * (1.0 - 1e-9):  # (a wake-up one period late is a skipped slot, rounding aside)
        skipped = max(1, int(late // period))
        slot += skipped
        late -= skipped * period
    return slot, late, skipped


def _in_position(controller: object) -> bool | None:
    """The controller's settle-detector flag (``controller.settle.state.in_position``), None without one."""
    st = getattr(getattr(controller, "settle", None), "state", None)
    flag = getattr(st, "in_position", None)
    return bool(flag) if flag is not None else None
