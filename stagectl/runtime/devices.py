"""The loop's device chores: start-up sampling, enabling, fault reset and the always-safe teardown.

The devices are the loop's sensor and actuator (one object when a drive does both), in that order, each
following the :class:`~stagectl.drivers.base.Device` lifecycle. These helpers run in the loop thread.
"""

from __future__ import annotations

import logging
import math

from stagectl.clock import Clock
from stagectl.drivers.base import (
    Device,
    DeviceFault,
    DeviceState,
    ForceActuator,
    Measurement,
    PositionSensor,
    SyncProducer,
)
from stagectl.runtime.status import LoopStateError

__all__ = ["DeviceSet"]

log = logging.getLogger("stagectl.loop")


class DeviceSet:
    """The loop's sensor and actuator as one group (``all``: unique, sensor first)."""

    def __init__(self, sensor: PositionSensor, actuator: ForceActuator, sync: SyncProducer | None) -> None:
        self.sensor = sensor
        self.actuator = actuator
        self.sync = sync
        self.all: tuple[Device, ...] = tuple(dict.fromkeys([sensor, actuator]))

    def ready(self) -> bool:
        """Every device is configured or enabled."""
        return all(d.state in (DeviceState.CONFIGURED, DeviceState.ENABLED) for d in self.all)

    def any_configured(self) -> bool:
        return any(d.state is DeviceState.CONFIGURED for d in self.all)

    def enable_configured(self) -> None:
        for d in self.all:
            if d.state is DeviceState.CONFIGURED:
                d.enable()

    def fault(self) -> DeviceFault | None:
        """The first device fault reported by a device (real-time safe)."""
        for d in self.all:
            if d.fault is not None:
                return d.fault
        return None

    def first_sample(self, clock: Clock, t0: float, period_s: float, n_max: int) -> tuple[Measurement, float, int]:
        """SYNC + read on absolute deadlines until a fresh sample (or a non-finite one, or a device fault)
        arrives, at most ``n_max`` times; returns (measurement, time of its SYNC, attempts − 1)."""
        for i in range(n_max):
            if i:
                t0 += period_s
                clock.sleep_until(t0)
            if self.sync is not None:
                self.sync.sync()
            m = self.sensor.read()
            if m.fresh or not math.isfinite(m.position_m) or m.fault is not None:
                return m, t0, i
        return m, t0, n_max - 1

    def persisting(self) -> tuple[str, ...]:
        """``"<device>: <cause>"`` for every fault cause a device reports as still present
        (:meth:`~stagectl.drivers.base.Device.persisting_faults`); a device whose check fails counts as one."""
        out: list[str] = []
        for d in self.all:
            try:
                out += [f"{d.name}: {c}" for c in d.persisting_faults()]
            except Exception as exc:  # noqa: BLE001 - a check that cannot run is no proof the cause is gone
                out.append(f"{d.name}: cannot check whether the fault persists ({type(exc).__name__}: {exc})")
        return tuple(out)

    def reset_faults(self) -> None:
        """Fault-reset every faulted device, disable the actuator, enable the configured devices.

        Raises LoopStateError if a device still reports a fault afterwards.
        """
        for d in self.all:
            if d.fault is not None or d.state is DeviceState.FAULT:
                d.fault_reset()
        self.actuator.disable()
        self.enable_configured()
        for d in self.all:
            if d.fault is not None:
                raise LoopStateError(f"reset: device {d.name} still reports {d.fault}")

    def quick_stop(self, why: object) -> None:
        """Quick-stop the actuator; a failure is logged (the original fault ``why`` is what gets reported)."""
        try:
            self.actuator.quick_stop()
        except Exception:
            log.exception("quick stop failed while handling fault %s", why)

    def shut_down(self, write_zero: bool) -> None:
        """Zero force (if ``write_zero`` and the actuator is enabled), then disable the actuator and the other
        devices. Never raises: each failure is logged and the next step still runs."""
        act = self.actuator
        try:
            if write_zero and act.state is DeviceState.ENABLED:
                act.write(0.0)
        except Exception:
            log.exception("writing zero force at stop failed")
        for d in (act, *[d for d in self.all if d is not act]):
            try:
                d.disable()
            except Exception:
                log.exception("disabling %s failed", d.name)
