"""Simulated CiA 402 drive (and the CANopen device glue shared with the simulated CiA 406 encoder).

canopen's ``LocalNode`` only provides the object dictionary and the SDO server (docs/platform.md §2.2);
:class:`SimCanopenDevice` adds what a device needs:

* **NMT** (own implementation; NmtSlave does not reboot): boot-up ``0x700+id [00]`` at power-on and after
  reset node / reset communication (which restore the EDS values of all / of the 0x1xxx objects), states
  PRE-OPERATIONAL 127, OPERATIONAL 5, STOPPED 4. PDOs run only in OPERATIONAL.
* **Heartbeat producer** (0x1017) and **consumer** (0x1016 sub 1: ``node_id << 16 | time_ms``), both counted
  in the device's own time base ``t_s`` given by :class:`~stagectl.sim.world.SimWorld` (wall clock when the
  world runs in its thread, simulated time in lock-step: each SYNC advances it by the 0x1006 period). The
  consumer is armed by the first heartbeat received (CiA 301); on time-out it sends EMCY 0x8130 and calls
  :meth:`SimCanopenDevice.on_heartbeat_lost`.
* **PDO engine**: the PDO communication/mapping objects (0x1400/0x1600, 0x1800/0x1A00 ...) are compiled
  into :mod:`struct` formats on NMT start; synchronous RPDOs (transmission type 0–240) are latched and
  applied at the next SYNC, event-driven ones (254/255) at once; TPDOs with type n (1–240) are sent on
  every n-th SYNC.
* **EMCY** producer (0x80+id) and error register 0x1001.
* Fault injection from :mod:`stagectl.sim.faults`.

:class:`SimCia402Drive` adds the CiA 402 power state machine (controlword 0x6040 → statusword 0x6041),
mode 0x6060 (only 0 and 10 = cyclic synchronous torque are accepted), and the plant: at each SYNC ::

    plant.step(F, T)               T = 0x1006 period [s] (nominal: deterministic), F = force of last period
    apply latched RPDO             controlword transition, target torque 0x6071
    F = 0x6071 × force_per_unit_n  if OPERATION ENABLED in CST, else 0
    0x6064 = wrap32(round((plant.measure() + jump) / resolution_m))
    send TPDOs

The protocol constants are written out here on purpose, independently of the driver in
:mod:`stagectl.drivers.cia402`, so that the two sides check each other (and canopen's BaseNode402 checks both).
"""

from __future__ import annotations

import enum
import logging
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from stagectl.resources import EDS_DIR
from stagectl.schema import param
from stagectl.sim.faults import FaultSchedule, FaultSpec, SimFault

log = logging.getLogger(__name__)


NMT_INITIALISING, NMT_STOPPED, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL = 0, 4, 5, 127
_FMT = {(8, False): "B", (8, True): "b", (16, False): "H", (16, True): "h", (32, False): "I", (32, True): "i"}
_SIGNED_TYPES = {0x2, 0x3, 0x4}  # INTEGER8/16/32
CAN_ERR_BUSOFF = 0x40
EMCY_HEARTBEAT = 0x8130
EMCY_RESET = 0x0000
#: late_tpdo: a held TPDO is due this fraction of a period after its SYNC (after the driver's rx time-out)
LATE_FRACTION = 0.9


def wrap_int32(v: int) -> int:
    return ((v + 0x80000000) & 0xFFFFFFFF) - 0x80000000


@dataclass
class _Pdo:
    cob_id: int
    trans_type: int
    fmt: struct.Struct
    fields: list[tuple[int, int]]  # (index, subindex)


def _u(data: bytes, fmt: str) -> int:
    return int(struct.unpack_from(fmt, data.ljust(4, b"\0"))[0])


class SimCanopenDevice:
    """A CANopen device on top of canopen's LocalNode (see module docstring).

    Parameters
    ----------
    node_id : int
    eds : Path
    send : callable
        ``send(msg)`` puts a frame on the bus.
    name : str
        ``drive`` or ``encoder`` (fault schedule key).
    """

    def __init__(self, node_id: int, eds: Path, send: Callable[[can.Message], None], name: str) -> None:
        import canopen

        self.node_id = node_id
        self.name = name
        self._send_raw = send
        self.node = canopen.LocalNode(node_id, str(eds))
        # NmtSlave is not used (it cannot reboot and its heartbeat runs on a wall-clock thread)
        self.node._write_callbacks.remove(self.node.nmt.on_write)
        self.node.add_read_callback(self._on_sdo_read)  # type: ignore[no-untyped-call]  # canopen untyped
        self.node.add_write_callback(self._on_sdo_write)  # type: ignore[no-untyped-call]
        # the SDO server answers through node.sdo.network.send_message
        self.node.sdo.network = _SendOnly(self._send_sdo)  # type: ignore[assignment]  # duck-typed send
        self.faults = FaultSchedule(name)
        self.nmt_state = NMT_INITIALISING
        self.sync_count = 0
        self.t_s = 0.0
        self.period_s = 0.001
        self._hb_period_s = 0.0
        self._next_hb_t = 0.0
        self._consumer_node = 0
        self._consumer_timeout_s = 0.0
        self._consumer_last_t = 0.0
        self._consumer_armed = False
        self._tpdos: list[_Pdo] = []
        self._rpdos: dict[int, _Pdo] = {}
        self._latched: list[tuple[int, int, int]] = []
        self._silent = False
        self._hb_stopped = False
        self._late: list[tuple[float, can.Message]] = []
        self.error_register = 0
        self.emcy_sent: list[int] = []
        self.heartbeat_lost_events = 0

    # ------------------------------------------------------------------ values (override)
    def live_value(self, index: int, sub: int) -> int | None:
        """Current value of a process object (for TPDOs and SDO reads), None if not live."""
        if index == 0x1001:
            return self.error_register
        return None

    def apply_value(self, index: int, sub: int, value: int) -> None:
        """An RPDO (or SDO) wrote ``value`` to a process object."""

    def on_sync(self, active: set[SimFault]) -> None:
        """Device-specific SYNC work, before the TPDOs are sent."""

    def on_heartbeat_lost(self) -> None:
        """The controller's heartbeat timed out (EMCY 0x8130 already sent)."""

    def on_reset(self) -> None:
        """NMT reset node: restore the application state."""

    # ------------------------------------------------------------------ frames out
    def send(self, cob_id: int, data: bytes) -> None:
        if self._silent:
            return
        self._send_raw(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    def _send_sdo(self, can_id: int, data: bytes) -> None:
        self.send(can_id, bytes(data))

    def send_emcy(self, code: int, register_bits: int = 0x01) -> None:
        if code:
            self.error_register |= register_bits
        else:
            self.error_register = 0
        self.emcy_sent.append(code)
        self.send(0x80 + self.node_id, struct.pack("<HB5s", code, self.error_register, b""))

    # ------------------------------------------------------------------ power-on / NMT
    def power_on(self, t_s: float) -> None:
        """Boot: load the EDS values, send boot-up, enter PRE-OPERATIONAL."""
        self.t_s = t_s
        self._load_comm()
        self.nmt_state = NMT_PRE_OPERATIONAL
        self.send(0x700 + self.node_id, b"\x00")
        self._next_hb_t = t_s + self._hb_period_s

    def _load_comm(self) -> None:
        self.period_s = (_u(self.node.get_data(0x1006, 0), "<I") * 1e-6) or 0.001
        self._hb_period_s = _u(self.node.get_data(0x1017, 0), "<H") * 1e-3
        try:
            cons = _u(self.node.get_data(0x1016, 1), "<I")
        except Exception:  # noqa: BLE001 - no consumer object
            cons = 0
        self._set_consumer(cons)
        self._compile_pdos()

    def _set_consumer(self, value: int) -> None:
        self._consumer_node = (value >> 16) & 0x7F
        self._consumer_timeout_s = (value & 0xFFFF) * 1e-3
        self._consumer_armed = False

    def _nmt(self, data: bytes) -> None:
        if len(data) < 2 or data[1] not in (0, self.node_id):
            return
        cmd = data[0]
        if cmd == 0x01:
            self._compile_pdos()
            self.nmt_state = NMT_OPERATIONAL
        elif cmd == 0x02:
            self.nmt_state = NMT_STOPPED
        elif cmd == 0x80:
            self.nmt_state = NMT_PRE_OPERATIONAL
        elif cmd in (0x81, 0x82):
            if cmd == 0x81:
                self.node.data_store.clear()
                self.on_reset()
            else:
                for idx in [i for i in self.node.data_store if 0x1000 <= i <= 0x1FFF]:
                    del self.node.data_store[idx]
            self._latched.clear()
            self._late.clear()
            self.power_on(self.t_s)

    # ------------------------------------------------------------------ PDO engine
    def _compile_pdos(self) -> None:
        od = self.node.object_dictionary
        tpdos: list[_Pdo] = []
        rpdos: dict[int, _Pdo] = {}
        for comm_base, map_base, out in ((0x1800, 0x1A00, True), (0x1400, 0x1600, False)):
            for n in range(4):
                comm, mapping = comm_base + n, map_base + n
                if comm not in od or mapping not in od:
                    continue
                cob = _u(self.node.get_data(comm, 1), "<I")
                if cob & 0x80000000:
                    continue
                ttype = _u(self.node.get_data(comm, 2), "<B")
                count = _u(self.node.get_data(mapping, 0), "<B")
                fmt, fields = "<", []
                for i in range(1, count + 1):
                    entry = _u(self.node.get_data(mapping, i), "<I")
                    index, sub, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
                    obj = od[index]
                    if not hasattr(obj, "data_type"):
                        obj = obj[sub]
                    fmt += _FMT[(bits, obj.data_type in _SIGNED_TYPES)]
                    fields.append((index, sub))
                pdo = _Pdo(cob & 0x7FF, ttype, struct.Struct(fmt), fields)
                if out:
                    tpdos.append(pdo)
                else:
                    rpdos[pdo.cob_id] = pdo
        self._tpdos, self._rpdos = tpdos, rpdos

    def _rpdo(self, pdo: _Pdo, data: bytes) -> None:
        if len(data) < pdo.fmt.size:
            log.warning("%s: RPDO 0x%03X too short (%d < %d bytes)", self.name, pdo.cob_id, len(data), pdo.fmt.size)
            return
        values = pdo.fmt.unpack_from(data)
        if pdo.trans_type <= 240:
            self._latched.extend((i, s, v) for (i, s), v in zip(pdo.fields, values))
        else:
            for (i, s), v in zip(pdo.fields, values):
                self.apply_value(i, s, v)

    def _send_tpdos(self, active: set[SimFault]) -> None:
        if self.nmt_state != NMT_OPERATIONAL:
            return
        if SimFault.DROP_TPDO in active:
            return
        late = SimFault.LATE_TPDO in active
        for pdo in self._tpdos:
            if not 1 <= pdo.trans_type <= 240 or self.sync_count % pdo.trans_type:
                continue
            vals = [self.live_value(i, s) or 0 for i, s in pdo.fields]
            msg = can.Message(arbitration_id=pdo.cob_id, data=pdo.fmt.pack(*vals), is_extended_id=False)
            if late:
                self._late.append((self.t_s + LATE_FRACTION * self.period_s, msg))
            elif not self._silent:
                self._send_raw(msg)

    def release_late(self, t_s: float | None = None) -> None:
        """Send the TPDOs held by ``late_tpdo`` that are due at ``t_s`` (all of them if None)."""
        if not self._late:
            return
        keep = []
        for due, msg in self._late:
            if t_s is None or t_s + 1e-12 >= due:
                if not self._silent:
                    self._send_raw(msg)
            else:
                keep.append((due, msg))
        self._late = keep

    # ------------------------------------------------------------------ SDO callbacks
    def _on_sdo_read(self, index: int, subindex: int, od: Any) -> int | None:
        return self.live_value(index, subindex)

    def _on_sdo_write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        if index == 0x1017:
            self._hb_period_s = _u(bytes(data), "<H") * 1e-3
            self._next_hb_t = self.t_s + self._hb_period_s
        elif index == 0x1016 and subindex == 1:
            self._set_consumer(_u(bytes(data), "<I"))
        elif index == 0x1006:
            self.period_s = (_u(bytes(data), "<I") * 1e-6) or 0.001
        elif 0x2000 <= index:
            fmt = _FMT.get((len(od) if hasattr(od, "__len__") else 8 * len(data), od.data_type in _SIGNED_TYPES))
            if fmt is not None:
                self.apply_value(index, subindex, _u(bytes(data), "<" + fmt))

    # ------------------------------------------------------------------ entry points (called by SimWorld)
    def add_fault(self, spec: FaultSpec) -> None:
        self.faults.add(spec, self.sync_count + 1)

    def on_frame(self, msg: can.Message, t_s: float) -> None:
        """Handle one received frame at device time ``t_s``."""
        self.t_s = t_s
        if msg.is_error_frame or msg.is_remote_frame:
            return
        cid = msg.arbitration_id
        data = bytes(msg.data)
        if cid == 0x080:
            self.sync(t_s)
        elif cid == 0x000:
            if not self._silent:
                self._nmt(data)
        elif cid in self._rpdos:
            if self.nmt_state == NMT_OPERATIONAL:
                self._rpdo(self._rpdos[cid], data)
        elif cid == 0x600 + self.node_id:
            if not self._silent and self.nmt_state in (NMT_PRE_OPERATIONAL, NMT_OPERATIONAL):
                try:
                    self.node.sdo.on_request(cid, data, msg.timestamp)  # type: ignore[no-untyped-call]
                except Exception:  # noqa: BLE001 - canopen only logs str(e); keep the traceback
                    log.exception("%s: SDO request failed", self.name)
        elif self._consumer_node and cid == 0x700 + self._consumer_node:
            self._consumer_last_t = t_s
            self._consumer_armed = self._consumer_timeout_s > 0

    def sync(self, t_s: float) -> None:
        self.t_s = t_s
        self.sync_count += 1
        active = self.faults.at_sync(self.sync_count, t_s)
        self._hb_stopped = SimFault.HEARTBEAT_STOP in active
        if SimFault.BUS_OFF in active:
            if not self._silent:
                self._send_raw(can.Message(arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True, is_extended_id=True,
                                           data=b"\0" * 8))
            self._silent = True
        else:
            self._silent = False
        latched, self._latched = self._latched, []
        for i, s, v in latched:
            self.apply_value(i, s, v)
        try:
            self.on_sync(active)
        except Exception:  # noqa: BLE001 - a sim bug must be visible, not swallowed by a listener
            log.exception("%s: SYNC handler failed", self.name)
            raise
        self._send_tpdos(active)

    def tick(self, t_s: float) -> None:
        """Timers: heartbeat producer and consumer, late TPDOs, at device time ``t_s``."""
        self.t_s = t_s
        if self._late:
            self.release_late(t_s)
        if self.nmt_state == NMT_INITIALISING:
            return
        if self._hb_period_s > 0 and t_s + 1e-12 >= self._next_hb_t:
            if not self._hb_stopped:
                self.send(0x700 + self.node_id, bytes([self.nmt_state]))
            self._next_hb_t = max(self._next_hb_t + self._hb_period_s, t_s)
        if self._consumer_armed and t_s - self._consumer_last_t > self._consumer_timeout_s + 1e-12:
            self._consumer_armed = False
            self.heartbeat_lost_events += 1
            self.send_emcy(EMCY_HEARTBEAT, 0x11)
            self.on_heartbeat_lost()


class _SendOnly:
    """The bit of canopen's Network the SDO server uses: ``send_message``."""

    def __init__(self, fn: Callable[[int, bytes], None]) -> None:
        self.send_message = fn


class DriveState(enum.Enum):
    """CiA 402 power states with their statusword coding (bit 4 voltage enabled, bit 9 remote added)."""

    NOT_READY_TO_SWITCH_ON = 0x0000
    SWITCH_ON_DISABLED = 0x0040
    READY_TO_SWITCH_ON = 0x0031
    SWITCHED_ON = 0x0033
    OPERATION_ENABLED = 0x0037
    QUICK_STOP_ACTIVE = 0x0017
    FAULT_REACTION_ACTIVE = 0x000F
    FAULT = 0x0008


_S = DriveState


@dataclass(frozen=True)
class SimDriveConfig:
    """The simulated drive (YAML ``sim.drive``)."""

    node_id: int = param(1, desc="CANopen node id", ge=1, le=127)
    resolution_m: float = param(1e-9, unit="m", desc="position per count of 0x6064", gt=0)
    force_per_unit_n: float = param(0.01, unit="N", desc="newtons per unit of target torque 0x6071", gt=0)
    velocity_resolution_m_s: float = param(1e-6, unit="m/s", desc="velocity per unit of 0x606C", gt=0)
    eds_file: str = param("", desc="EDS (empty = config/eds/stagectl_cia402.eds)")


class SimCia402Drive(SimCanopenDevice):
    """Simulated CiA 402 drive in cyclic synchronous torque mode driving ``plant`` (see module docstring)."""

    def __init__(self, plant: Any, cfg: SimDriveConfig, send: Callable[[can.Message], None],
                 base_dir: Path | None = None) -> None:
        eds = Path(cfg.eds_file) if cfg.eds_file else EDS_DIR / "stagectl_cia402.eds"
        if base_dir is not None and not eds.is_absolute():
            eds = base_dir / eds
        super().__init__(cfg.node_id, eds, send, "drive")
        self.plant = plant
        self.cfg = cfg
        self.on_reset()

    def on_reset(self) -> None:
        self.state = _S.SWITCH_ON_DISABLED
        self.controlword = 0
        self.target_torque = 0
        self.mode = 0
        self.error_code = 0
        self.force_n = 0.0
        self.jump_m = 0.0
        self.position_counts = self._sample()
        self.velocity_units = 0

    # ------------------------------------------------------------------ process values
    @property
    def statusword(self) -> int:
        return self.state.value | 0x0200

    def live_value(self, index: int, sub: int) -> int | None:
        if index == 0x6041:
            return self.statusword
        if index == 0x6064:
            return self.position_counts
        if index == 0x606C:
            return self.velocity_units
        if index == 0x6061:
            return self.mode
        if index == 0x603F:
            return self.error_code
        if index == 0x6077:
            return max(-32768, min(32767, round(self.force_n / self.cfg.force_per_unit_n)))
        if index == 0x6040:
            return self.controlword
        if index == 0x6071:
            return self.target_torque
        return super().live_value(index, sub)

    def apply_value(self, index: int, sub: int, value: int) -> None:
        if index == 0x6040:
            self.apply_controlword(value)
        elif index == 0x6071:
            self.target_torque = value
        elif index == 0x6060:
            self.mode = value

    def _on_sdo_write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        from canopen.sdo.exceptions import SdoAbortedError

        if index == 0x6060:
            mode = struct.unpack_from("<b", bytes(data))[0]
            if mode not in (0, 10):
                raise SdoAbortedError(0x06090030)  # value range exceeded: only CST (10) is implemented
            self.mode = mode
        elif index == 0x6040:
            self.apply_controlword(_u(bytes(data), "<H"))
        elif index == 0x6071:
            self.target_torque = struct.unpack_from("<h", bytes(data))[0]
        else:
            super()._on_sdo_write(index, subindex, od, data)

    # ------------------------------------------------------------------ 402 state machine
    def apply_controlword(self, cw: int) -> None:
        rising_reset = bool(cw & 0x80) and not (self.controlword & 0x80)
        self.controlword = cw
        st = self.state
        if st in (_S.FAULT, _S.FAULT_REACTION_ACTIVE):
            if rising_reset and st is _S.FAULT:
                self.state = _S.SWITCH_ON_DISABLED
                self.error_code = 0
                self.send_emcy(EMCY_RESET)
            return
        if cw & 0x80:
            return
        if not cw & 0x02:  # disable voltage
            self.state = _S.SWITCH_ON_DISABLED
        elif cw & 0x06 == 0x02:  # quick stop
            self.state = _S.QUICK_STOP_ACTIVE if st is _S.OPERATION_ENABLED else (
                _S.SWITCH_ON_DISABLED if st is not _S.QUICK_STOP_ACTIVE else st)
        elif cw & 0x07 == 0x06:  # shutdown
            if st in (_S.SWITCH_ON_DISABLED, _S.SWITCHED_ON, _S.OPERATION_ENABLED):
                self.state = _S.READY_TO_SWITCH_ON
        elif cw & 0x0F == 0x07:  # switch on / disable operation
            if st in (_S.READY_TO_SWITCH_ON, _S.OPERATION_ENABLED):
                self.state = _S.SWITCHED_ON
        elif cw & 0x0F == 0x0F:  # enable operation (also 3+4 from READY TO SWITCH ON)
            if st in (_S.SWITCHED_ON, _S.READY_TO_SWITCH_ON):
                self.state = _S.OPERATION_ENABLED
            elif st is _S.QUICK_STOP_ACTIVE and self._quick_stop_option() >= 5:
                self.state = _S.OPERATION_ENABLED

    def _quick_stop_option(self) -> int:
        try:
            return int(struct.unpack_from("<h", self.node.get_data(0x605A, 0))[0])
        except Exception:  # noqa: BLE001
            return 2

    def enter_fault(self, code: int) -> None:
        self.state = _S.FAULT
        self.error_code = code
        self.force_n = 0.0
        self.send_emcy(code)

    def on_heartbeat_lost(self) -> None:
        if self.state not in (_S.OPERATION_ENABLED, _S.QUICK_STOP_ACTIVE):
            return
        try:
            action = int(struct.unpack_from("<h", self.node.get_data(0x6007, 0))[0])
        except Exception:  # noqa: BLE001
            action = 1
        if action == 1:
            self.state = _S.FAULT
            self.error_code = EMCY_HEARTBEAT
        elif action == 2:
            self.state = _S.SWITCH_ON_DISABLED
        elif action == 3:
            self.state = _S.QUICK_STOP_ACTIVE
        if self.state is not _S.OPERATION_ENABLED:
            self.force_n = 0.0

    # ------------------------------------------------------------------ SYNC
    def _sample(self) -> int:
        x = float(self.plant.measure()) + self.jump_m
        return wrap_int32(round(x / self.cfg.resolution_m))

    def on_sync(self, active: set[SimFault]) -> None:
        self.plant.step(self.force_n, self.period_s)
        if SimFault.DRIVE_FAULT in active:
            spec = self.faults.spec_of(SimFault.DRIVE_FAULT)
            self.enter_fault(spec.code if spec else 0x2310)
        if self.state is _S.QUICK_STOP_ACTIVE and self._quick_stop_option() < 5:
            self.state = _S.SWITCH_ON_DISABLED  # torque mode: stopped at once, then 605A 0..4 -> disabled
        if self.state is _S.OPERATION_ENABLED and self.mode == 10:
            self.force_n = self.target_torque * self.cfg.force_per_unit_n
        else:
            self.force_n = 0.0
        self.jump_m = self.faults.jump_m(active)
        self.position_counts = self._sample()
        v = getattr(self.plant, "v_m_s", 0.0)
        self.velocity_units = max(-(2**31), min(2**31 - 1, round(float(v) / self.cfg.velocity_resolution_m_s)))
