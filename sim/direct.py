"""PlantIO: the simulated plant wrapped directly as a position sensor, force actuator and SYNC producer.

The fast simulated twin of a drive + encoder: no bus, no protocol, just the plant. Used by benchmarks,
unit tests and the embedded simulation when no virtual CANopen devices are wanted. It is lock-step by
construction: the plant only moves when the loop calls :meth:`PlantIO.sync`.

Timing (mirrors a CANopen drive in cyclic synchronous torque mode)::

    sync() at t_k:  advance the plant from its time to t_k with the force being applied,
                    then apply the command latched ``delay_cycles`` SYNCs ago, then sample x_k
    read()      :   Measurement(x_k) taken at this SYNC (fresh once per SYNC)
    write(u_k)  :   latched; with delay_cycles = 1 it acts from the next SYNC, i.e. over [t_{k+1}, t_{k+2})
                    (one cycle of I/O delay, like a sync RPDO); with 0 it acts from t_k on (zero-order hold)

Command schedule (``command_schedule``, with a clock; off by default): the drive keeps its own slot clock and
a schedule of commands. :meth:`write_schedule` latches the force for the next period and the controller's
predicted force for the period after it. A SYNC missing for ``missed_sync_periods`` (1.5) periods after the
last one (the loop skipped a slot: it woke a period late) is replaced by the drive's own slot there, and a
slot (SYNC or own) that got no new write since the last slot applies the last write's predicted force
instead of holding the old one (then holds it)::

    loop writes (u_k, û_{k+1}) at t_k, then skips the slot t_k + T and wakes at t_k + 2T:
      held (no schedule):  [t_k, t_k+2T) u_{k−1},            [t_k+2T, t_k+3T) u_k,       then u_{k+2}
      schedule:            [t_k, t_k+1.5T) u_{k−1}, then u_k, [t_k+2T, t_k+3T) û_{k+1},  then u_{k+2}

i.e. the sequence of an on-time loop with u_{k+1} replaced by its prediction (and the slot of u_k half a
period late: the drive cannot tell a missing SYNC from a late one before then; the wake-up jitter of
``stagectl bench timing`` is ≤ 0.2 T). This is how drives that extrapolate a missing cyclic set-point
behave; CiA 402 has no standard object for a next-period torque, so the virtual CiA 402 drive does not do it.

Time comes from ``clock.now()`` when a clock is given (real time: the plant follows the wall clock, in
sub-steps of at most ``period_s``), otherwise each SYNC after the first advances the plant by exactly
``period_s``.

Fault injection for tests: :meth:`inject_fault` (a latched device fault, e.g. EMCY; ``persist``: its cause stays
present), :meth:`drop_samples` (the next N reads are stale), :meth:`glitch` (the next N reads return a given value,
e.g. NaN), :meth:`remove_cause` (a persisting cause goes away).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any, Protocol

from stagectl.clock import Timing
from stagectl.drivers.base import (
    DeviceFault,
    DeviceState,
    FaultKind,
    ForceActuator,
    Measurement,
    PositionSensor,
    SyncProducer,
)
from stagectl.errors import DriverError


class Plant(Protocol):
    """What PlantIO needs from :class:`stagectl.sim.plant.StagePlant`."""

    def step(self, u_n: float, dt_s: float) -> Any: ...

    def measure(self) -> float: ...


class _Clock(Protocol):
    def now(self) -> float: ...


class PlantIO(PositionSensor, ForceActuator, SyncProducer):
    """The plant as a lock-step device (see module docstring).

    Parameters
    ----------
    plant : Plant
        ``step(u_n, dt_s)`` advances the plant by ``dt_s`` [s] with force ``u_n`` [N];
        ``measure()`` returns the sensed position [m] (quantised, with noise); optional
        ``measure_counts()`` [counts] and ``resolution_m``.
    timing : Timing or float
        The loop's timing (or its nominal period [s]): advance per SYNC without a clock; sub-step size with one.
    delay_cycles : int
        Actuation delay in SYNC periods (0 or more; 1 mimics a sync RPDO).
    clock : optional
        Time source; None = exactly one period per SYNC.
    command_schedule : bool
        Keep a command schedule (module docstring; needs a clock to matter: without one no SYNC is missed).
    """

    name = "plant_io"

    def __init__(self, plant: Plant, timing: Timing | float, *, delay_cycles: int = 1,
                 clock: _Clock | None = None, command_schedule: bool = False) -> None:
        PositionSensor.__init__(self)
        t = Timing.of(timing)  # ConfigError (a ValueError) for a period that is not > 0
        if delay_cycles < 0:
            raise ValueError(f"delay_cycles: must be >= 0 (got {delay_cycles})")
        self.plant = plant
        self.timing = t
        self.period_s = t.period_s
        self.delay_cycles = int(delay_cycles)
        self.clock = clock
        self.schedules_commands = bool(command_schedule)
        self._u_next = 0.0  # the last write's predicted force for the slot after the one it is for
        self._new_write = False  # a write arrived since the last slot
        self._t_slot: float | None = None  # clock time of the last slot (SYNC or the drive's own)
        self.own_slots = 0  # slots the drive took itself for a missed SYNC (schedule)
        res = getattr(plant, "resolution_m", None)
        if res is None:  # StagePlant: cfg.sensor.resolution_m
            res = getattr(getattr(getattr(plant, "cfg", None), "sensor", None), "resolution_m", 1e-9)
        self.resolution_m = float(res) if isinstance(res, (int, float)) else 1e-9
        # commands latched at earlier SYNCs still waiting (delay_cycles − 1 of them)
        self._pipe: deque[float] = deque([0.0] * max(0, self.delay_cycles - 1))
        self._u_applied = 0.0
        self._u_latched = 0.0
        self._stopped = False
        self._t_plant: float | None = None
        self._meas = Measurement(0.0, False)
        self._drop = 0
        self._missed_after: int | None = None
        self._dropped_run = 0
        self._glitch: float | None = None
        self._glitch_n = 0
        self._offset, self._offset_n = 0.0, 0
        self._stall_n, self._stall_rate = 0, 1
        self._backlog: deque[tuple[float, int]] | None = None  # samples a stalled drive has yet to send
        self._inject: DeviceFault | None = None
        self._cause: DeviceFault | None = None
        self.n_sync = 0

    @property
    def force_limit_n(self) -> float:
        """The largest force the simulated actuator gives [N]: ``sim.plant.actuator.max_force_n`` (inf: none)."""
        act = getattr(getattr(self.plant, "cfg", None), "actuator", None)
        lim = getattr(act, "max_force_n", math.inf)
        return float(lim) if isinstance(lim, (int, float)) else math.inf

    force_limit_source = "sim.plant.actuator.max_force_n"

    # ------------------------------------------------------------------ lifecycle
    def _do_open(self) -> None:
        return None

    def _do_configure(self) -> None:
        return None

    def _do_enable(self) -> None:
        self._stopped = False
        self._zero()

    def _do_disable(self) -> None:
        self._zero()

    def _do_fault_reset(self) -> None:
        self._inject = self._cause  # a cause still present latches the fault again
        self._zero()

    def _do_close(self) -> None:
        self._zero()

    def _zero(self) -> None:
        self._u_applied = 0.0
        self._u_latched = 0.0
        self._u_next = 0.0
        self._new_write = False
        for i in range(len(self._pipe)):
            self._pipe[i] = 0.0

    # ------------------------------------------------------------------ fault injection
    def inject_fault(self, kind: FaultKind = FaultKind.EMCY, detail: str = "injected", code: int = 0,
                     persist: bool = False) -> None:
        """Latch a device fault now (reported with the next read); output goes to zero, like a drive.
        ``persist``: its cause stays present (:meth:`persisting_faults`, a reset is refused) until
        :meth:`remove_cause`, like a heartbeat that stays missing or a closed link."""
        self._inject = DeviceFault(kind, detail, code)
        if persist:
            self._cause = self._inject

    def remove_cause(self) -> None:
        """The cause of a persisting injected fault is gone (the heartbeat is back, the link reconnected), and
        so are endless dropped samples and glitches."""
        self._cause = None
        if self._drop < 0:
            self._drop = 0
        if self._glitch_n < 0:
            self._glitch, self._glitch_n = None, 0

    def persisting_faults(self) -> tuple[str, ...]:
        return (str(self._cause),) if self._cause is not None else ()

    def drop_samples(self, n: int, missed_after: int | None = None) -> None:
        """The next ``n`` reads return stale (not fresh) measurements (``n`` < 0: until :meth:`remove_cause`);
        ``missed_after``: latch ``MISSED_FRAME`` after that many in a row, as a drive's ``max_missed`` does."""
        self._drop = int(n)
        self._missed_after = missed_after
        self._dropped_run = 0

    def jump(self, offset_m: float, cycles: int = 1) -> None:
        """The next ``cycles`` reads report the position plus ``offset_m`` (a step glitch; ``cycles`` 0: for
        ever, as the virtual devices' ``position_jump``)."""
        self._offset, self._offset_n = float(offset_m), int(cycles)

    def glitch(self, value_m: float, cycles: int = 1) -> None:
        """The next ``cycles`` reads report ``value_m`` (e.g. NaN or a jump) as a fresh sample (``cycles`` < 0:
        until :meth:`remove_cause`)."""
        self._glitch = float(value_m)
        self._glitch_n = int(cycles)

    def stall(self, cycles: int, catch_up_per_cycle: int = 2) -> None:
        """A drive process held off the CPU (the HIL's sim-plant on a loaded machine), in device time: the
        plant moves on, but the next ``cycles`` reads are stale; then the drive works off its backlog of
        unanswered SYNCs at ``catch_up_per_cycle`` (>= 2) per period, so each read returns, as a *fresh*
        on-time sample, the position of the newest SYNC answered so far: the backlog b shrinks by
        ``catch_up_per_cycle`` − 1 per cycle, and the sample is b periods older than the loop believes (the
        CiA 402 driver cannot tell: a TPDO carries no SYNC number)."""
        if catch_up_per_cycle < 2:
            raise ValueError(f"catch_up_per_cycle: must be >= 2 (got {catch_up_per_cycle})")
        self._stall_n, self._stall_rate = int(cycles), int(catch_up_per_cycle)
        self._backlog = deque()

    def _stalled(self, x: float, counts: int) -> tuple[float, int, bool]:
        """(x, counts, fresh) of a stalled drive (see :meth:`stall`); the stall ends with its backlog."""
        bl = self._backlog
        assert bl is not None
        bl.append((x, counts))
        if self._stall_n > 0:
            self._stall_n -= 1
            return self._meas.position_m, self._meas.counts, False
        got = bl[0]
        for _ in range(min(self._stall_rate, len(bl))):
            got = bl.popleft()
        if not bl:
            self._backlog = None
        return got[0], got[1], True

    # ------------------------------------------------------------------ cyclic
    def sync(self) -> None:
        """Advance the plant to this SYNC, apply the latched command, sample the position. Real-time safe."""
        if self._state is DeviceState.CLOSED:
            raise DriverError(f"{self.name}: sync on a closed device")
        period = self.period_s
        if self.clock is None:
            if self.n_sync:  # the first SYNC samples time 0
                self._advance(period)
        else:
            now = self.clock.now()
            if self._t_plant is None:
                self._t_plant = now
            if self.schedules_commands and self._t_slot is not None:
                # SYNCs missed: the drive's own slots, missed_sync_periods after the last slot, then every period
                t_own = self._t_slot + self.missed_sync_periods * period
                while t_own < now - 1e-9 * period:
                    self._advance_to(t_own)
                    self.own_slots += 1
                    self._slot()
                    self._t_slot = t_own - (self.missed_sync_periods - 1.0) * period
                    t_own += period
            self._advance_to(now)
            self._t_slot = now
        self.n_sync += 1
        self._slot()
        plant = self.plant
        mc = getattr(plant, "measure_counts", None)
        if mc is not None:
            counts = int(mc())
            x = counts * self.resolution_m
        else:
            counts = round(float(plant.measure()) / self.resolution_m)
            x = counts * self.resolution_m
        fault = None
        if self._inject is not None and self._fault is None:
            fault = self._latch(self._inject)
            self._zero()
        fresh = True
        if self._backlog is not None:
            x, counts, fresh = self._stalled(x, counts)
        elif self._drop:
            if self._drop > 0:
                self._drop -= 1
            fresh = False
            x = self._meas.position_m
            self._dropped_run += 1
            if self._missed_after is not None and self._dropped_run >= self._missed_after and self._fault is None:
                fault = self._latch(DeviceFault(FaultKind.MISSED_FRAME,
                                                f"no fresh sample for {self._dropped_run} cycles"))
                self._zero()
        else:
            self._dropped_run = 0
        if self._offset:
            x += self._offset
            if self._offset_n > 0:
                self._offset_n -= 1
                if self._offset_n == 0:
                    self._offset = 0.0
        if self._glitch is not None:
            x = self._glitch
            if self._glitch_n > 0:
                self._glitch_n -= 1
                if self._glitch_n == 0:
                    self._glitch = None
        self._meas = Measurement(x, fresh, counts, 0, fault)

    def _advance_to(self, t: float) -> None:
        """Advance the plant from its time to clock time ``t`` [s] in sub-steps of at most a period."""
        assert self._t_plant is not None
        period = self.period_s
        rest = t - self._t_plant
        while rest > 1e-12:
            h = period if rest > period else rest
            self._advance(h)
            rest -= h
        self._t_plant = t

    def _slot(self) -> None:
        """A slot (SYNC, or the drive's own for a missed one): the command latched ``delay_cycles`` slots ago takes
        effect now; with a schedule, a slot with no new write since the last one takes the last write's
        predicted force (and holds it)."""
        if self.schedules_commands and not self._new_write:
            self._u_latched = self._u_next
            if not self.delay_cycles:
                self._u_applied = self._u_next
        self._new_write = False
        if self.delay_cycles:
            self._pipe.append(self._u_latched)
            self._u_applied = self._pipe.popleft()
        if self._stopped or self._state is not DeviceState.ENABLED:
            self._u_applied = 0.0

    def _advance(self, dt: float) -> None:
        self.plant.step(self._u_applied, dt)

    def read(self) -> Measurement:
        """The sample taken at the last SYNC (``fresh`` only the first time it is read)."""
        m = self._meas
        if m.fresh:
            self._meas = Measurement(m.position_m, False, m.counts, m.status, None)
        return m

    def write(self, force_n: float) -> None:
        """Latch ``force_n`` [N]; ignored unless enabled and not quick-stopped. Real-time safe."""
        if self._state is DeviceState.CLOSED:
            raise DriverError(f"{self.name}: write on a closed device")
        if self._state is not DeviceState.ENABLED or self._stopped:
            return
        self._u_latched = force_n
        self._u_next = force_n
        self._new_write = True
        if not self.delay_cycles:
            self._u_applied = force_n

    def write_schedule(self, force_n: float, next_force_n: float) -> None:
        """Latch ``force_n`` [N] for the next slot and ``next_force_n`` [N] for the slot after it, applied there only
        if no new write arrives before it (module docstring, ``command_schedule``); without a schedule ``write``."""
        self.write(force_n)
        if self.schedules_commands and self._new_write:  # (accepted: enabled, not quick-stopped)
            self._u_next = next_force_n

    def quick_stop(self) -> None:
        """Output to zero at once and ignore writes until re-enabled."""
        self._stopped = True
        self._zero()

    @property
    def applied_force_n(self) -> float:
        """The force acting on the plant now [N]."""
        return self._u_applied
