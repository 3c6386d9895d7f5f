"""Driver interface shared by real devices and their simulated twins (docs/architecture.md section 1.3).

Lifecycle (explicit, checked)::

    CLOSED --open()--> OPEN --configure()--> CONFIGURED --enable()--> ENABLED
    ENABLED --disable()--> CONFIGURED;   any --close()--> CLOSED   (close is idempotent)
    any fault --> FAULT (latched; ``fault_reset()`` clears it if the cause is gone)

Cyclic exchange, once per control period, driven by the loop::

    io.sync()                 # the loop is the SYNC producer (CANopen SYNC; no-op for streaming sensors)
    m = sensor.read()         # the measurement sampled at this cycle's SYNC (never an older one)
    actuator.write(force_n)   # command for the next period

``read()`` never blocks longer than the device's configured receive timeout and never raises for an
*expected* condition: a missing/stale frame gives ``Measurement.fresh = False``, and device faults
(EMCY, heartbeat loss, drive FAULT, bus-off, CRC errors, sensor glitches) are reported as a
:class:`DeviceFault` in ``Measurement.fault`` (and latched in ``device.fault``). Unexpected errors
raise :class:`~stagectl.errors.DriverError` subclasses; vendor exceptions are converted at this boundary.

Lock-step simulated time: a device may be given a ``pump`` callable (``set_pump``); when set, waiting for
a frame means calling ``pump()`` (which runs the virtual devices up to idle, synchronously) and then
polling without blocking, so a simulated run is deterministic and never waits on the wall clock.
"""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType

from stagectl.errors import DriverError


class DeviceState(enum.Enum):
    CLOSED = "closed"
    OPEN = "open"
    CONFIGURED = "configured"
    ENABLED = "enabled"
    FAULT = "fault"


class FaultKind(enum.Enum):
    """Why a device is not healthy. The loop latches a named fault from these."""

    DRIVE_FAULT = "drive_fault"  # CiA 402 statusword fault bit / FAULT state
    EMCY = "emcy"  # emergency message received
    HEARTBEAT_LOST = "heartbeat_lost"  # producer heartbeat not seen within the consumer time
    BUS_ERROR = "bus_error"  # CAN error frames / transmit failures
    BUS_OFF = "bus_off"  # CAN controller bus-off
    MISSED_FRAME = "missed_frame"  # cyclic frame missing or late for N consecutive cycles
    SENSOR_ERROR = "sensor_error"  # sensor status bits: signal lost, glitch, error flag
    CRC_ERRORS = "crc_errors"  # serial link: too many CRC errors
    SEQUENCE_GAP = "sequence_gap"  # serial link: frames lost
    DISCONNECTED = "disconnected"  # port/socket closed by the other end


@dataclass(frozen=True, slots=True)
class DeviceFault:
    """A fault reported by a device: kind, CiA 301 error code (or 0) and a human-readable detail."""

    kind: FaultKind
    detail: str = ""
    code: int = 0

    def __str__(self) -> str:
        code = f" (code 0x{self.code:04X})" if self.code else ""
        return f"{self.kind.value}{code}: {self.detail}" if self.detail else f"{self.kind.value}{code}"


@dataclass(slots=True)
class Measurement:
    """One position sample.

    Attributes
    ----------
    position_m : float
        Position [m] (unwrapped counts × resolution); the last good value if ``fresh`` is False.
    fresh : bool
        True if this sample was taken at this cycle's SYNC / is newer than the previous read.
    counts : int
        Unwrapped raw position in sensor counts.
    status : int
        Raw device status (CiA 402 statusword, sensor status flags).
    fault : DeviceFault | None
        A fault detected during this read, if any.
    age_cycles : int
        0: sampled at this cycle's SYNC; n > 0: a late frame sampled n SYNCs ago (its answer came after the
        wait of its own cycle; still newer than the previous read, so ``fresh``). The loop places it at
        ``t − n·T``.
    """

    position_m: float
    fresh: bool
    counts: int = 0
    status: int = 0
    fault: DeviceFault | None = None
    age_cycles: int = 0


class Device(ABC):
    """Lifecycle common to every device. Subclasses implement the ``_do_*`` hooks."""

    name: str = "device"

    def __init__(self) -> None:
        self._state = DeviceState.CLOSED
        self._fault: DeviceFault | None = None
        self._pump: Callable[[], object] | None = None

    # -------------------------------------------------------------- state
    @property
    def state(self) -> DeviceState:
        return self._state

    @property
    def fault(self) -> DeviceFault | None:
        """The latched fault, or None."""
        return self._fault

    def persisting_faults(self) -> tuple[str, ...]:
        """Names of faults whose cause is still present right now (heartbeat still missing, bus-off, link down,
        device still in FAULT); a reset is refused while this is not empty. Default: none."""
        return ()

    def set_pump(self, pump: Callable[[], object] | None) -> None:
        """Lock-step mode: ``pump()`` runs the simulated peers synchronously instead of waiting."""
        self._pump = pump

    def _latch(self, fault: DeviceFault) -> DeviceFault:
        if self._fault is None:
            self._fault = fault
        if self._state is not DeviceState.CLOSED:
            self._state = DeviceState.FAULT
        return fault

    def _require(self, *allowed: DeviceState) -> None:
        if self._state not in allowed:
            want = " or ".join(s.value for s in allowed)
            raise DriverError(f"{self.name}: operation needs state {want}, device is {self._state.value}")

    # -------------------------------------------------------------- lifecycle
    def open(self) -> None:
        self._require(DeviceState.CLOSED)
        self._do_open()
        self._state = DeviceState.OPEN

    def configure(self) -> None:
        self._require(DeviceState.OPEN, DeviceState.CONFIGURED)
        self._do_configure()
        self._state = DeviceState.CONFIGURED

    def enable(self) -> None:
        self._require(DeviceState.CONFIGURED)
        self._do_enable()
        self._state = DeviceState.ENABLED

    def disable(self) -> None:
        """Stop output and leave the device configured. Safe to call in any open state, including FAULT."""
        if self._state in (DeviceState.CLOSED, DeviceState.OPEN):
            return
        self._do_disable()
        if self._state is DeviceState.ENABLED:
            self._state = DeviceState.CONFIGURED

    def fault_reset(self) -> None:
        """Clear a latched fault (device-level reset, e.g. CiA 402 fault reset)."""
        if self._state is DeviceState.CLOSED:
            return
        self._do_fault_reset()
        self._fault = None
        if self._state is DeviceState.FAULT:
            self._state = DeviceState.CONFIGURED

    def close(self) -> None:
        """Release everything. Idempotent; never raises for an already closed device."""
        if self._state is DeviceState.CLOSED:
            return
        try:
            self._do_close()
        finally:
            self._state = DeviceState.CLOSED

    def __enter__(self) -> Device:
        self.open()
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        self.close()

    # -------------------------------------------------------------- hooks
    @abstractmethod
    def _do_open(self) -> None: ...

    @abstractmethod
    def _do_configure(self) -> None: ...

    def _do_enable(self) -> None:
        return None

    def _do_disable(self) -> None:
        return None

    def _do_fault_reset(self) -> None:
        return None

    @abstractmethod
    def _do_close(self) -> None: ...


class SyncProducer(ABC):
    """Something that starts a cycle (CANopen SYNC). Real-time safe."""

    @abstractmethod
    def sync(self) -> None:
        """Start this cycle: devices sample their inputs now."""


class PositionSensor(Device):
    """A position-measuring device (drive encoder, CiA 406 encoder, serial interferometer)."""

    #: sensor resolution [m per count]
    resolution_m: float = 1e-9

    @abstractmethod
    def read(self) -> Measurement:
        """The measurement of this cycle. Real-time safe; bounded wait (see module docstring)."""


class ForceActuator(Device):
    """A force-producing device (CiA 402 drive in cyclic synchronous torque mode)."""

    #: the device keeps a command schedule (:meth:`write_schedule`): in a slot that got no new write (a missed
    #: SYNC) it applies the last write's predicted force instead of holding the old one
    schedules_commands: bool = False
    #: with a schedule: a SYNC missing this many periods after the last slot is replaced by the device's own slot
    missed_sync_periods: float = 1.5

    @abstractmethod
    def write(self, force_n: float) -> None:
        """Command ``force_n`` [N] for the next period. Real-time safe."""

    def write_schedule(self, force_n: float, next_force_n: float) -> None:
        """Command ``force_n`` [N] for the next period and ``next_force_n`` [N], the controller's prediction, for
        the period after it: a device that keeps a schedule (``schedules_commands``) applies ``next_force_n`` in
        its next slot if no new write arrived before it (a skipped cycle of the loop), as a drive extrapolating
        a missing cyclic set-point does. Default (no schedule): ``write(force_n)``. Real-time safe."""
        self.write(force_n)

    @abstractmethod
    def quick_stop(self) -> None:
        """Command the device's quick stop (CiA 402 QUICK STOP ACTIVE; output to zero). Real-time safe."""
