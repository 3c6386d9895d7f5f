"""CiA 406 encoder over CANopen: a separate position-measuring node with its own node id.

Start-up (``configure``, SDO only): NMT pre-operational, device type 0x1000 must be profile 406, heartbeat
producer 0x1017, communication cycle period 0x1006, TPDO1 = position value 0x6004 (UNSIGNED32) with
transmission type 1 (every SYNC), NMT start; then the Notifier stops and the loop thread reads the bus.

Cyclic: the drive (:class:`~stagectl.drivers.cia402.Cia402Drive`) is normally the SYNC producer and the
encoder shares the bus; ``read()`` then takes the newest encoder TPDO that follows the latest SYNC frame
*seen on the bus* (received-order, so a TPDO from before that SYNC is stale and ignored). With
``sync_producer: true`` the encoder's own ``sync()`` drains stale frames and sends SYNC (encoder-only rigs).

Position: ``position_m = counts × resolution_m``; 0x6004 wraps modulo 2³², unwrapped like the drive's
(the first reading is taken as signed 32-bit so small negative positions start near zero).
Faults: EMCY → ``EMCY``; heartbeat older than ``heartbeat_timeout_s`` (counted as cycles × period) →
``HEARTBEAT_LOST``; error frames → ``BUS_ERROR``/``BUS_OFF``; ``max_missed`` reads in a row without a fresh
TPDO → ``MISSED_FRAME``; a step faster than ``max_speed_m_s`` → ``SENSOR_ERROR``.
"""

from __future__ import annotations

import logging
import struct
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from stagectl.clock import Timing
from stagectl.drivers.base import DeviceFault, DeviceState, FaultKind, Measurement, PositionSensor, SyncProducer
from stagectl.drivers.canbus import CanopenNode, error_frame_is_bus_off, link_closed, pumping
from stagectl.drivers.cia402 import SYNC_COB_ID, _default_can, cob_id_writes, explain_sdo_error, unwrap32
from stagectl.errors import ConfigError, DriverInitError, DriverIOError
from stagectl.resources import EDS_DIR
from stagectl.schema import param

log = logging.getLogger(__name__)

DEFAULT_EDS = EDS_DIR / "stagectl_cia406.eds"
_POS = struct.Struct("<I")


@dataclass(frozen=True)
class Cia406Config:
    """Configuration of a CiA 406 encoder node (YAML ``encoder:`` section)."""

    node_id: int = param(desc="CANopen node id of the encoder", ge=1, le=127)
    can: dict[str, Any] = param(desc="mapping passed to can.Bus (same bus as the drive)", default_factory=_default_can)
    resolution_m: float = param(1e-9, unit="m", desc="position per count of 0x6004 (measuring step)", gt=0)
    sync_producer: bool = param(False, desc="the encoder driver sends SYNC itself (no drive on the bus)")
    heartbeat_producer_s: float = param(0.05, unit="s", desc="encoder heartbeat period written to 0x1017 (0 = off)",
                                        ge=0, le=65.535)
    heartbeat_timeout_s: float = param(0.2, unit="s", desc="encoder heartbeat older than this -> HEARTBEAT_LOST", gt=0)
    rx_timeout_s: float = param(0.0008, unit="s", desc="how long read() waits for SYNC + TPDO (real-time mode)", gt=0)
    max_missed: int = param(3, desc="consecutive reads without a fresh TPDO before MISSED_FRAME", ge=1)
    max_speed_m_s: float = param(2.0, unit="m/s", desc="steps faster than this are a glitch (SENSOR_ERROR)", gt=0)
    sdo_timeout_s: float = param(0.5, unit="s", desc="SDO response timeout during configure", gt=0)
    eds_file: str = param("", desc="EDS of the encoder (empty = stagectl's config/eds/stagectl_cia406.eds)")

    def __post_init__(self) -> None:
        if self.heartbeat_producer_s > 0 and self.heartbeat_timeout_s <= self.heartbeat_producer_s:
            raise ConfigError(f"heartbeat_timeout_s: must be > heartbeat_producer_s ({self.heartbeat_timeout_s:g} s "
                              f"<= {self.heartbeat_producer_s:g} s)")


class Cia406Encoder(CanopenNode, PositionSensor, SyncProducer):
    """CiA 406 encoder node (see module docstring)."""

    def __init__(self, cfg: Cia406Config, timing: Timing | float) -> None:
        """``timing``: the loop's timing (or its period [s]); written to 0x1006, per-cycle time-outs derive
        from it. Raises ConfigError for a period that is not a finite number > 0."""
        super().__init__()
        t = Timing.of(timing)
        self.timing = t
        self.cfg = cfg
        self.name = f"cia406[node {cfg.node_id}]"
        self.resolution_m = cfg.resolution_m
        self.period_s = t.period_s
        self._tpdo_id = 0x180 + cfg.node_id
        self._emcy_id = 0x080 + cfg.node_id
        self._hb_id = 0x700 + cfg.node_id
        self._sync_msg = can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False)
        self._hb_timeout_cycles = t.cycles(cfg.heartbeat_timeout_s)
        self._max_step = t.per_cycle(cfg.max_speed_m_s) / cfg.resolution_m
        self._reset_cyclic()
        self._rebooted = self._link_dead = self._bus_off = False

    def _reset_cyclic(self) -> None:
        self._after_sync = False
        self._missed = 0
        self._skipped = 0
        self._hb_age = 0
        self._pending: DeviceFault | None = None
        self._have = False
        self._raw = 0
        self._counts = 0
        self.missed_total = 0

    # ------------------------------------------------------------------ lifecycle
    def _do_open(self) -> None:
        eds = Path(self.cfg.eds_file) if self.cfg.eds_file else DEFAULT_EDS
        self._open_canopen(self.cfg.can, "encoder.can", self.cfg.node_id, eds, self.cfg.sdo_timeout_s)

    def _do_close(self) -> None:
        self._teardown()

    def _sdo(self, index: int, sub: int, fmt: str, value: int | None, what: str) -> int:
        from canopen.sdo.exceptions import SdoError

        try:
            if value is None:
                return int(struct.unpack_from(fmt, self._node.sdo.upload(index, sub))[0])
            self._node.sdo.download(index, sub, struct.pack(fmt, value))
            return value
        except (SdoError, struct.error, can.CanError, OSError) as exc:
            if index == 0x1006 and getattr(exc, "code", None) in (0x06020000, 0x06090011):
                log.info("%s: encoder has no 0x1006: it follows SYNC only", self.name)
                return value or 0
            op = "reading" if value is None else f"writing 0x{value & 0xFFFFFFFF:X} to"
            raise DriverInitError(f"{self.name}: configure: {op} {what} 0x{index:04X}:{sub:02X} failed: "
                                  f"{explain_sdo_error(exc, self.cfg.sdo_timeout_s, 'encoder.sdo_timeout_s')}") from exc

    def _do_configure(self) -> None:
        self._start_notifier()
        nid = self.cfg.node_id
        with pumping(None if self._sdo_lockstep else self._pump, self.name):
            self._node.nmt.send_command(0x80)
            dtype = self._sdo(0x1000, 0, "<I", None, "device type")
            if dtype & 0xFFFF != 406:
                raise DriverInitError(f"{self.name}: device type 0x1000 = 0x{dtype:08X} is not a CiA 406 encoder")
            self._sdo(0x1006, 0, "<I", round(self.period_s * 1e6), "communication cycle period [µs]")
            self._sdo(0x1017, 0, "<H", round(self.cfg.heartbeat_producer_s * 1000), "producer heartbeat [ms]")
            cob = 0x180 + nid
            writes, valid = cob_id_writes(self._sdo(0x1800, 1, "<I", None, "TPDO1 COB-ID"), cob)
            for value, step in writes:
                self._sdo(0x1800, 1, "<I", value, f"TPDO1 {step}")
            self._sdo(0x1A00, 0, "<B", 0, "TPDO1 mapping count")
            self._sdo(0x1A00, 1, "<I", 0x60040020, "TPDO1 mapping: position value 0x6004")
            self._sdo(0x1A00, 0, "<B", 1, "TPDO1 mapping count")
            self._sdo(0x1800, 2, "<B", 1, "TPDO1 transmission type (synchronous)")
            self._sdo(0x1800, 1, "<I", valid, "TPDO1 COB-ID (enable)")
            self._node.nmt.send_command(0x01)
        self._stop_notifier()  # pump mode: the loop thread reads the bus itself from now on
        self._reset_cyclic()
        self._rebooted = self._link_dead = self._bus_off = False

    def persisting_faults(self) -> tuple[str, ...]:
        """Faults whose cause is present now: link closed, bus-off with nothing heard since, heartbeat still
        missing. Real-time safe."""
        out: list[str] = []
        if self._link_dead:
            out.append("disconnected: CAN link closed")
        if self._bus_off:
            out.append("bus_off: no frame from the encoder since the bus-off error frame")
        if self.cfg.heartbeat_producer_s > 0 and self._hb_age > self._hb_timeout_cycles:
            out.append(f"heartbeat_lost: no encoder heartbeat for {self._hb_age} cycles")
        return tuple(out)

    def _do_fault_reset(self) -> None:
        if self._link_dead:
            raise DriverIOError(f"{self.name}: fault reset: CAN link closed; check the socketcand server / adapter")
        if self._rebooted:
            log.warning("%s: encoder was reset (boot-up seen): configuring it again", self.name)
            self._do_configure()
        self._pending = None
        self._missed = 0
        self._hb_age = 0

    # ------------------------------------------------------------------ cyclic
    def _handle(self, msg: can.Message) -> int | None:
        if msg.is_error_frame:
            kind = FaultKind.BUS_OFF if error_frame_is_bus_off(msg) else FaultKind.BUS_ERROR
            self._bus_off = self._bus_off or kind is FaultKind.BUS_OFF
            self._note(DeviceFault(kind, f"CAN error frame class 0x{msg.arbitration_id:08X}"))
            return None
        if msg.is_extended_id:
            return None
        cid = msg.arbitration_id
        if cid == SYNC_COB_ID:
            if self.cfg.sync_producer:
                self._note(DeviceFault(FaultKind.BUS_ERROR, "second SYNC producer on the bus (COB-ID 0x080)"))
            self._after_sync = True
            return -1
        if cid == self._tpdo_id:
            self._bus_off = False
        if cid == self._tpdo_id and len(msg.data) >= 4:
            return _POS.unpack_from(msg.data)[0] if self._after_sync else None
        if cid == self._emcy_id and len(msg.data) >= 2:
            code = int.from_bytes(bytes(msg.data[:2]), "little")
            if code:
                self._note(DeviceFault(FaultKind.EMCY, "encoder EMCY", code))
        elif cid == self._hb_id:
            self._hb_age = 0
            self._bus_off = False
            if msg.data and msg.data[0] == 0:
                self._rebooted = True
        return None

    def _note(self, fault: DeviceFault) -> None:
        if self._pending is None:
            self._pending = fault

    def sync(self) -> None:
        """With ``sync_producer``: drain stale frames and send SYNC; otherwise nothing. Real-time safe."""
        self._require(DeviceState.CONFIGURED, DeviceState.ENABLED, DeviceState.FAULT)
        if not self.cfg.sync_producer:
            return
        if self._pump is not None:
            self._pump()
        bus = self._bus
        assert bus is not None
        try:
            while (msg := bus.recv(0.0)) is not None:
                self._handle(msg)
            bus.send(self._sync_msg)
            self._after_sync = True  # our own SYNC is not received back: TPDOs from now on are fresh
        except can.CanError as exc:
            raise DriverIOError(f"{self.name}: CAN I/O failed: {exc}") from exc

    def _collect(self) -> int | None:
        bus = self._bus
        assert bus is not None
        got: int | None = None
        if self._link_dead:
            return None

        def take(msg: can.Message) -> None:
            nonlocal got
            r = self._handle(msg)
            if r == -1:
                got = None  # a newer SYNC: only TPDOs after it count
            elif r is not None:
                got = r

        try:
            if self._pump is not None:
                self._pump()
                while (msg := bus.recv(0.0)) is not None:
                    take(msg)
                return got
            # drain everything that has arrived (a backlog, e.g. the drive's enable cycles, ends with the newest
            # SYNC); wait only while no TPDO follows the newest SYNC seen
            deadline = time.monotonic() + self.cfg.rx_timeout_s
            while True:
                msg = bus.recv(0.0)
                if msg is None:
                    left = deadline - time.monotonic()
                    if got is not None or left <= 0 or (msg := bus.recv(left)) is None:
                        break
                take(msg)
            if got is None and link_closed(bus):
                self._link_dead = True  # recv would return at once forever: stop waiting on it
                self._note(DeviceFault(FaultKind.DISCONNECTED, "CAN link closed by the socketcand server"))
        except can.CanError as exc:
            raise DriverIOError(f"{self.name}: CAN receive failed: {exc}") from exc
        return got

    def read(self) -> Measurement:
        """The encoder position sampled at the latest SYNC. Real-time safe (bounded wait)."""
        self._require(DeviceState.CONFIGURED, DeviceState.ENABLED, DeviceState.FAULT)
        got = self._collect()
        self._after_sync = False
        self._hb_age += 1
        fault: DeviceFault | None = None
        if got is not None:
            self._missed = 0
            if self._have:
                counts = unwrap32(self._raw, self._counts, got)
                if abs(counts - self._counts) > self._max_step * (1 + self._skipped):
                    fault = DeviceFault(FaultKind.SENSOR_ERROR, f"encoder position jumped "
                                        f"{abs(counts - self._counts) * self.cfg.resolution_m:.3g} m in one cycle")
            else:
                counts = got - (1 << 32) if got & 0x80000000 else got
                self._have = True
            self._raw, self._counts, self._skipped = got, counts, 0
        else:
            self._missed += 1
            self._skipped += 1
            self.missed_total += 1
            if self._missed >= self.cfg.max_missed:
                fault = DeviceFault(FaultKind.MISSED_FRAME, f"no encoder TPDO after SYNC for {self._missed} cycles")
        if self._pending is not None and (fault is None or fault.kind is FaultKind.MISSED_FRAME):
            fault = self._pending
        self._pending = None
        if fault is None and self.cfg.heartbeat_producer_s > 0 and self._hb_age > self._hb_timeout_cycles:
            fault = DeviceFault(FaultKind.HEARTBEAT_LOST, f"no encoder heartbeat for {self._hb_age} cycles")
        if fault is not None:
            self._latch(fault)
        return Measurement(self._counts * self.cfg.resolution_m, got is not None, self._counts, 0, fault)
