"""Simulated CiA 402 drive (and the CANopen device glue shared with the simulated CiA 406 encoder).

canopen's ``LocalNode`` only provides the object dictionary and the SDO server (docs/platform.md §2.2);
:class:`SimCanopenDevice` adds what a CiA 301 device needs (docs/canopen.md lists what is implemented and
what deliberately is not):

* **NMT** (own implementation; NmtSlave does not reboot): boot-up ``0x700+id [00]`` at power-on and after
  reset node / reset communication (which restore the EDS values of all / of the 0x1xxx objects), states
  PRE-OPERATIONAL 127, OPERATIONAL 5, STOPPED 4. PDOs run only in OPERATIONAL. 11-bit frames only: a 29-bit
  frame is ignored whatever its id.
* **Heartbeat producer** (0x1017) and **consumer** (0x1016 sub 1: ``node_id << 16 | time_ms``), both counted
  in the device's own time base ``t_s`` given by :class:`~stagectl.sim.world.SimWorld` (wall clock when the
  world runs in its thread, simulated time in lock-step: each SYNC advances it by the 0x1006 period). The
  consumer is armed by the first heartbeat received (CiA 301); on time-out it sends EMCY 0x8130 and calls
  :meth:`SimCanopenDevice.on_heartbeat_lost`.
* **PDO engine** (CiA 301 §7.2.2, §7.5.2.35–38): communication and mapping parameters are checked on every SDO
  write with the standard abort codes and take effect at once, also in OPERATIONAL:

  ===================================================  ===========
  mapping entry: object missing                         0x06020000
  mapping entry: object not mappable / wrong direction  0x06040041
  mapping sub 0 > 8 entries or > 64 bits                0x06040042
  mapping entry length ≠ the object's size              0x06040043
  mapping written while the PDO is valid, or an entry   0x06010000
  written while sub 0 ≠ 0
  COB-ID bits 0–29 changed while valid, 29-bit COB-ID,  0x06090030
  reserved transmission type, inhibit time while valid
  ===================================================  ===========

  Transmission types: RPDO 0–240 latched and applied at the next SYNC, 254/255 at once; TPDO 0 at a SYNC
  when a mapped value changed, 1–240 on every n-th SYNC, 254/255 on a change of a mapped value and when the
  event timer (sub 5, ms) expires, never closer than the inhibit time (sub 3, 100 µs). A TPDO carries the
  value an SDO upload of the mapped object returns. An RPDO shorter than its mapping is not applied and
  raises EMCY 0x8210; a longer one is applied and raises EMCY 0x8220.
* **SYNC** consumer on the COB-ID of 0x1005, **EMCY** producer on the COB-ID of 0x1014 (bit 31 = no EMCY) and
  the error register 0x1001 with its bits set by error class (:func:`error_register_bits`).
* An internal error while handling a frame or a timer never stops the device silently: a log line, EMCY
  0x6100 and :meth:`SimCanopenDevice.on_internal_error` (the drive faults).
* Fault injection from :mod:`stagectl.sim.faults`.

:class:`SimCia402Drive` adds the CiA 402 power state machine (controlword 0x6040 → statusword 0x6041),
mode 0x6060 (only 0 and 10 = cyclic synchronous torque are accepted), and the plant: at each SYNC ::

    plant.step(F, T)               T = 0x1006 period [s] (nominal: deterministic), F = force of last period
                                   (``wall_clock_plant`` in thread mode: n·T, n = whole periods of wall time
                                   since the last step, at most MAX_CATCH_UP_PERIODS; 0 when SYNCs bunch)
    apply latched RPDO             controlword transition, target torque 0x6071
    F = clamp(0x6071, ±0x6072) × force_per_unit_n   in OPERATION ENABLED + CST; the braking force of the
                                   quick-stop / fault-reaction ramp in QUICK STOP / FAULT REACTION ACTIVE; else 0
    0x6064 = wrap32(round((plant.measure() + jump) / resolution_m))
    send TPDOs

While the power stage is on and SYNC is missing the drive runs the plant on its own clock (periods of 0x1006 in
device time): in QUICK STOP / FAULT REACTION ACTIVE after three silent periods (a ramp completes without SYNC),
in OPERATION ENABLED after half of ``sync_timeout_s`` (the stage keeps moving under the last torque; a merely
late SYNC on a loaded machine does not move it), until SYNC supervision (``sync_timeout_s``) faults the drive
with EMCY 0x8700. In thread mode a timer tick more than ``SELF_STALL_S`` after the previous one means this
process itself was held off the CPU (the HIL's sim-plant on a loaded machine): for ``SELF_STALL_GRACE_S`` the
master's heartbeat and SYNC are not judged missing, since its frames from the stall are still queued (before,
the drive ran the plant on its own clock through the whole stall under the last torque, or faulted 0x8130).

The protocol constants are written out here on purpose, independently of the driver in
:mod:`stagectl.drivers.cia402`, so that the two sides check each other (and canopen's BaseNode402 checks both).
"""

from __future__ import annotations

import enum
import logging
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
from canopen.objectdictionary import ODVariable
from stagectl.sim.faults import FaultSchedule, FaultSpec, SimFault

from stagectl.resources import EDS_DIR
from stagectl.world_schema import SimDriveConfig as SimDriveConfig

log = logging.getLogger(__name__)


NMT_INITIALISING, NMT_STOPPED, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL = 0, 4, 5, 127
#: struct code by CiA 301 data type (BOOLEAN is not mappable here: granularity 8)
_TYPE_FMT = {0x2: "b", 0x3: "h", 0x4: "i", 0x5: "B", 0x6: "H", 0x7: "I", 0x8: "f"}
_FMT = {(8, False): "B", (8, True): "b", (16, False): "H", (16, True): "h", (32, False): "I", (32, True): "i"}
_SIGNED_TYPES = {0x2, 0x3, 0x4}  # INTEGER8/16/32
CAN_ERR_BUSOFF = 0x40
EMCY_HEARTBEAT = 0x8130
EMCY_RESET = 0x0000
EMCY_PDO_LENGTH = 0x8210  # PDO not processed due to length error
EMCY_PDO_LENGTH_EXCEEDED = 0x8220
EMCY_SYNC_LOST = 0x8700  # CiA 402: sync controller
EMCY_COMMUNICATION = 0x8100  # communication, generic: NMT left OPERATIONAL (STOPPED / reset communication)
EMCY_INTERNAL = 0x6100  # internal software
#: thread mode: a timer tick this long after the previous one means this process was held off the CPU ...
SELF_STALL_S = 0.02
#: ... and for this long after it the master's heartbeat and SYNC are not judged missing (its queued frames
#: are worked off first); lock-step (device time) is not affected
SELF_STALL_GRACE_S = 0.05
#: late_tpdo: a held TPDO is due this fraction of a period after its SYNC (after the driver's rx time-out)
LATE_FRACTION = 0.9

# CiA 301 SDO abort codes used by the PDO parameter checks
ABORT_UNSUPPORTED_ACCESS = 0x06010000
ABORT_NO_OBJECT = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_INCOMPATIBLE = 0x06040043
ABORT_INVALID_VALUE = 0x06090030
#: the option codes CiA 402 defines (IEC 61800-7-201): 0x6007 abort connection 0–3, 0x605A quick stop 0–8,
#: 0x605E fault reaction 0–4; larger values are reserved and negative ones manufacturer-specific, so a write of
#: either is refused with "value range of parameter exceeded", as a drive that implements none of them does
_OPTION_RANGE = {0x6007: (0, 3), 0x605A: (0, 8), 0x605E: (0, 4)}
ABORT_COMMAND = 0x05040001  # client/server command specifier not valid or unknown
ABORT_LENGTH = 0x06070010  # data type does not match, length of service parameter does not match
_EPS = 1e-12


def wrap_int32(v: int) -> int:
    return ((v + 0x80000000) & 0xFFFFFFFF) - 0x80000000


def restricted_cob_id(cob: int) -> bool:
    """CiA 301 restricted COB-IDs (NMT, SYNC/EMCY range, TIME.., SDO, LSS, heartbeat): not for a PDO."""
    return (cob <= 0x07F or 0x101 <= cob <= 0x180 or 0x581 <= cob <= 0x5FF or 0x601 <= cob <= 0x67F
            or 0x6E0 <= cob <= 0x6FF or cob >= 0x701)


def error_register_bits(code: int) -> int:
    """Error register 0x1001 bits for an EMCY error code (CiA 301 table 48): bit 0 generic always, plus
    bit 1 current (0x2xxx), bit 2 voltage (0x3xxx), bit 3 temperature (0x4xxx), bit 4 communication (0x8xxx),
    bit 7 manufacturer specific (0xFFxx)."""
    if code == 0:
        return 0
    bits = 0x01
    group = code >> 12
    if group == 0x2:
        bits |= 0x02
    elif group == 0x3:
        bits |= 0x04
    elif group == 0x4:
        bits |= 0x08
    elif group == 0x8:
        bits |= 0x10
    elif code >> 8 == 0xFF:
        bits |= 0x80
    return bits


@dataclass
class _Pdo:
    num: int  # 0..3
    cob_id: int
    trans_type: int
    fmt: struct.Struct
    fields: list[tuple[int, int]]  # (index, subindex), dummies excluded
    inhibit_s: float = 0.0
    event_s: float = 0.0
    last_data: bytes | None = None
    last_sent_t: float = -1e9
    syncs: int = 0
    extra: dict[str, Any] = field(default_factory=dict)


def _u(data: bytes, fmt: str) -> int:
    return int(struct.unpack_from(fmt, data.ljust(4, b"\0"))[0])


def _abort(code: int) -> Exception:
    from canopen.sdo.exceptions import SdoAbortedError

    return SdoAbortedError(code)


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
        self.threaded = False  # set by SimWorld: served by its thread (device time = wall clock)
        self.period_s = 0.001
        self.sync_cob_id = 0x080
        self.emcy_cob_id: int | None = 0x80 + node_id
        self._hb_period_s = 0.0
        self._next_hb_t = 0.0
        self._consumer_node = 0
        self._consumer_timeout_s = 0.0
        self._consumer_last_t = 0.0
        self._consumer_armed = False
        self._tpdos: list[_Pdo] = []
        self._event_tpdos: list[_Pdo] = []
        self._rpdos: dict[int, _Pdo] = {}
        self._latched: list[tuple[int, int, int]] = []
        self._silent = False
        self._hb_stopped = False
        self._late: list[tuple[float, can.Message]] = []
        self._pdo_dirty = False
        self._sdo_seg: str | None = None  # segmented transfer in progress: "up", "down" or None
        self._sdo_mux = b"\0\0\0"  # index and sub-index of that transfer (for the abort frame)
        self._sdo_size: int | None = None  # segmented download: size the client indicated (None: not given)
        self._sdo_got = 0  # segmented download: bytes received so far
        self._sdo_resp = 0  # first byte of the SDO server's last response
        self.last_sync_t = 0.0
        self._tick_t: float | None = None  # device time of the previous timer tick
        self._grace_until = -1.0  # thread mode: no judging of the master's silence before this time (own stall)
        #: False while this process was just held off the CPU (thread mode): the frames the master sent
        #: meanwhile are still queued, so its heartbeat and SYNC are not judged missing yet
        self.judging_silence = True
        self.error_register = 0
        self.emcy_sent: list[int] = []
        self.heartbeat_lost_events = 0
        self.internal_errors = 0

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

    def on_connection_aborted(self) -> None:
        """NMT left OPERATIONAL for STOPPED or a reset communication: the CiA 402 "abort connection" event."""

    def on_internal_error(self) -> None:
        """A handler raised (already logged, EMCY 0x6100 sent): put the application in a safe state."""

    def on_tick(self, t_s: float) -> None:
        """Device-specific timer work at device time ``t_s`` (own clock)."""

    # ------------------------------------------------------------------ frames out
    def send(self, cob_id: int, data: bytes) -> None:
        if self._silent:
            return
        self._send_raw(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    def _send_sdo(self, can_id: int, data: bytes) -> None:
        self._sdo_resp = data[0] if data else 0
        self.send(can_id, bytes(data))

    def _sdo_abort(self, code: int) -> None:
        self._sdo_seg = None
        self._send_sdo(0x580 + self.node_id, b"\x80" + self._sdo_mux + struct.pack("<I", code))

    def _sdo_request(self, cid: int, data: bytes, timestamp: float) -> None:
        """One SDO request, with the transfer state canopen's server does not keep (CiA 301 §7.2.4.3): a
        segment request outside a segmented transfer of its direction is aborted 0x05040001 (not served from
        a stale buffer, which could write a stray segment into the last object addressed), a client's abort
        ends the transfer, a segmented download must deliver the size it indicated (0x06070010), and block
        transfer is not offered (0x05040001; the switch to a normal upload needs the client's protocol switch
        threshold, which this server does not evaluate). A frame that is not 8 bytes long is no SDO request
        (CiA 301 §7.2.4.3: every SDO frame has DLC 8) and is ignored, as CANopenNode's server does: the client's
        own SDO time-out reports it."""
        if len(data) != 8:
            return
        ccs = data[0] >> 5
        if ccs == 4:  # abort transfer (client): no answer
            self._sdo_seg = None
            return
        if ccs in (1, 2, 5, 6, 7):  # initiate (or unknown): a new transfer replaces any unfinished one
            self._sdo_seg = None
            self._sdo_mux = bytes(data[1:4]).ljust(3, b"\0")
        if ccs in (5, 7) or (ccs == 3 and self._sdo_seg != "up") or (ccs == 0 and self._sdo_seg != "down"):
            self._sdo_abort(ABORT_COMMAND)
            return
        if ccs == 0:
            self._sdo_got += 7 - ((data[0] >> 1) & 7)
            if data[0] & 0x01 and self._sdo_size is not None and self._sdo_got != self._sdo_size:
                self._sdo_abort(ABORT_LENGTH)
                return
        self._sdo_resp = 0
        self.node.sdo.on_request(cid, data, timestamp)  # type: ignore[no-untyped-call]
        if self._sdo_resp == 0x80:  # the server aborted
            self._sdo_seg = None
        elif ccs == 2 and self._sdo_resp & 0xE3 == 0x41:  # segmented upload initiated
            self._sdo_seg = "up"
        elif ccs == 1 and not data[0] & 0x02:  # segmented download initiated
            self._sdo_seg = "down"
            self._sdo_size = struct.unpack_from("<I", data, 4)[0] if data[0] & 0x01 and len(data) >= 8 else None
            self._sdo_got = 0
        elif ccs == 3 and self._sdo_resp & 0x01 or ccs == 0 and data[0] & 0x01:  # last segment
            self._sdo_seg = None

    def send_emcy(self, code: int, register_bits: int | None = None) -> None:
        """Raise (``code`` ≠ 0) or clear (0) an error: error register 0x1001 and, unless 0x1014 bit 31 is
        set, the EMCY frame ``[code lo, code hi, 0x1001, 0, 0, 0, 0, 0]``."""
        if code:
            self.error_register |= error_register_bits(code) if register_bits is None else register_bits
        else:
            self.error_register = 0
        self.emcy_sent.append(code)
        # CiA 301 §7.3.2.2 (services per NMT state): no EMCY in STOPPED or INITIALISING (register still kept)
        if self.emcy_cob_id is not None and self.nmt_state in (NMT_PRE_OPERATIONAL, NMT_OPERATIONAL):
            self.send(self.emcy_cob_id, struct.pack("<HB5s", code, self.error_register, b""))

    def _internal_error(self, where: str) -> None:
        self.internal_errors += 1
        log.exception("%s (node %d): internal error in %s: EMCY 0x%04X, device faulted",
                      self.name, self.node_id, where, EMCY_INTERNAL)
        try:
            self.send_emcy(EMCY_INTERNAL)
            self.on_internal_error()
        except Exception:  # noqa: BLE001 - the safe-state path itself failed: logged, never silent
            log.exception("%s: safe-state reaction after an internal error failed", self.name)

    # ------------------------------------------------------------------ power-on / NMT
    def power_on(self, t_s: float) -> None:
        """Boot: load the EDS values, send boot-up, enter PRE-OPERATIONAL."""
        self.t_s = t_s
        self._load_comm()
        self.nmt_state = NMT_PRE_OPERATIONAL
        self.send(0x700 + self.node_id, b"\x00")
        self._next_hb_t = t_s + self._hb_period_s

    def _stored(self, index: int, sub: int, fmt: str, default: int) -> int:
        try:
            return _u(self.node.get_data(index, sub), fmt)
        except Exception:  # noqa: BLE001 - object not in this device's dictionary
            return default

    def _load_comm(self) -> None:
        self.period_s = (self._stored(0x1006, 0, "<I", 1000) * 1e-6) or 0.001
        self._hb_period_s = self._stored(0x1017, 0, "<H", 0) * 1e-3
        self._set_consumer(self._stored(0x1016, 1, "<I", 0))
        self.sync_cob_id = self._stored(0x1005, 0, "<I", 0x80) & 0x7FF
        emcy = self._stored(0x1014, 0, "<I", 0x80 + self.node_id)
        self.emcy_cob_id = None if emcy & 0x80000000 else emcy & 0x7FF
        self._compile_pdos()

    def _set_consumer(self, value: int) -> None:
        self._consumer_node = (value >> 16) & 0x7F
        self._consumer_timeout_s = (value & 0xFFFF) * 1e-3
        self._consumer_armed = False

    def _nmt(self, data: bytes) -> None:
        if len(data) < 2 or data[1] not in (0, self.node_id):
            return
        cmd = data[0]
        was_operational = self.nmt_state == NMT_OPERATIONAL
        if cmd == 0x01:
            if self.nmt_state != NMT_OPERATIONAL:
                for p in self._tpdos:
                    p.syncs, p.last_data = 0, None
            self.nmt_state = NMT_OPERATIONAL
        elif cmd == 0x02:
            self.nmt_state = NMT_STOPPED
            if was_operational:
                self.on_connection_aborted()  # no RPDO can reach it any more
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
            if cmd == 0x82 and was_operational:
                self.on_connection_aborted()  # the application kept running: its master connection is gone

    # ------------------------------------------------------------------ PDO parameters
    def _pdo_of(self, index: int) -> tuple[bool, bool, int] | None:
        """(is_tpdo, is_mapping, number 0..3) for a PDO parameter index, else None."""
        for base, tx, mapping in ((0x1400, False, False), (0x1600, False, True),
                                  (0x1800, True, False), (0x1A00, True, True)):
            if base <= index < base + 4:
                return tx, mapping, index - base
        return None

    def _pdo_valid(self, tx: bool, num: int) -> bool:
        comm = (0x1800 if tx else 0x1400) + num
        return not self._stored(comm, 1, "<I", 0x80000000) & 0x80000000

    def _entry_bits(self, tx: bool, entry: int) -> int:
        """Bits of one mapping entry ``index << 16 | sub << 8 | bits``, checked (raises the abort)."""
        index, sub, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
        if 0x0001 <= index <= 0x0007 and not tx:  # dummy entry (RPDO only): a data type's size
            size = {0x2: 8, 0x3: 16, 0x4: 32, 0x5: 8, 0x6: 16, 0x7: 32}.get(index)
            if size is None:
                raise _abort(ABORT_NOT_MAPPABLE)
            if bits != size:
                raise _abort(ABORT_INCOMPATIBLE)
            return bits
        od = self.node.object_dictionary
        if index not in od:
            raise _abort(ABORT_NO_OBJECT)
        obj = od[index]
        if not hasattr(obj, "data_type"):
            if sub not in obj:
                raise _abort(ABORT_NO_OBJECT)
            obj = obj[sub]
        elif sub != 0:
            raise _abort(ABORT_NO_OBJECT)
        assert isinstance(obj, ODVariable)
        access = str(obj.access_type)
        readable, writable = "r" in access or access == "const", "w" in access
        if not obj.pdo_mappable or obj.data_type not in _TYPE_FMT or (readable if tx else writable) is False:
            raise _abort(ABORT_NOT_MAPPABLE)
        if bits != 8 * struct.calcsize(_TYPE_FMT[int(obj.data_type or 0)]):
            raise _abort(ABORT_INCOMPATIBLE)
        return bits

    def _check_pdo_write(self, index: int, sub: int, data: bytes) -> None:
        """CiA 301 PDO parameter rules for an SDO download (raises SdoAbortedError)."""
        what = self._pdo_of(index)
        if what is None:
            return
        tx, mapping, num = what
        valid = self._pdo_valid(tx, num)
        if mapping:
            if valid:
                raise _abort(ABORT_UNSUPPORTED_ACCESS)
            if sub == 0:
                n = _u(data, "<B")
                if n > 8:
                    raise _abort(ABORT_PDO_LENGTH)
                total = sum(self._entry_bits(tx, self._stored(index, i, "<I", 0)) for i in range(1, n + 1))
                if total > 64:
                    raise _abort(ABORT_PDO_LENGTH)
            else:
                if self._stored(index, 0, "<B", 0) != 0:
                    raise _abort(ABORT_UNSUPPORTED_ACCESS)
                entry = _u(data, "<I")
                if entry:
                    self._entry_bits(tx, entry)
        else:
            if sub == 1:
                new = _u(data, "<I")
                old = self._stored(index, 1, "<I", 0x80000000)
                if new & 0x20000000:
                    raise _abort(ABORT_INVALID_VALUE)  # 29-bit COB-IDs: not supported (11-bit device)
                if valid and not new & 0x80000000 and (new ^ old) & 0x1FFFFFFF:
                    raise _abort(ABORT_INVALID_VALUE)
                if not new & 0x80000000 and restricted_cob_id(new & 0x7FF):
                    raise _abort(ABORT_INVALID_VALUE)
            elif sub == 2:
                tt = _u(data, "<B")
                if not (tt <= 240 or tt >= 254):
                    raise _abort(ABORT_INVALID_VALUE)  # 241–251 reserved, 252/253 RTR-only: not supported
            elif sub == 3 and valid:
                raise _abort(ABORT_INVALID_VALUE)  # inhibit time only while the PDO does not exist
        self._pdo_dirty = True

    # ------------------------------------------------------------------ PDO engine
    def _compile_pdos(self) -> None:
        od = self.node.object_dictionary
        old = {(True, p.num): p for p in self._tpdos}
        tpdos: list[_Pdo] = []
        rpdos: dict[int, _Pdo] = {}
        for comm_base, map_base, out in ((0x1800, 0x1A00, True), (0x1400, 0x1600, False)):
            for n in range(4):
                comm, mapping = comm_base + n, map_base + n
                if comm not in od or mapping not in od:
                    continue
                cob = self._stored(comm, 1, "<I", 0x80000000)
                if cob & 0x80000000:
                    continue
                ttype = self._stored(comm, 2, "<B", 1)
                count = self._stored(mapping, 0, "<B", 0)
                fmt, fields = "<", []
                for i in range(1, count + 1):
                    entry = self._stored(mapping, i, "<I", 0)
                    index, sub, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
                    if index <= 0x0007:
                        fmt += f"{bits // 8}x"
                        continue
                    obj = od[index]
                    if not hasattr(obj, "data_type"):
                        obj = obj[sub]
                    assert isinstance(obj, ODVariable)
                    fmt += _TYPE_FMT[int(obj.data_type or 0)]
                    fields.append((index, sub))
                pdo = _Pdo(n, cob & 0x7FF, ttype, struct.Struct(fmt), fields,
                           inhibit_s=self._stored(comm, 3, "<H", 0) * 1e-4,
                           event_s=self._stored(comm, 5, "<H", 0) * 1e-3)
                if out:
                    prev = old.get((True, n))
                    if prev is not None and prev.fmt.format == pdo.fmt.format and prev.fields == pdo.fields:
                        pdo.syncs, pdo.last_data, pdo.last_sent_t = prev.syncs, prev.last_data, prev.last_sent_t
                    tpdos.append(pdo)
                else:
                    rpdos[pdo.cob_id] = pdo
        self._tpdos, self._rpdos = tpdos, rpdos
        self._event_tpdos = [p for p in tpdos if p.trans_type >= 254]
        self._pdo_dirty = False

    def value(self, index: int, sub: int) -> int | float:
        """The value an SDO upload of ``index:sub`` returns (live value, else the stored one), for TPDOs."""
        v = self.live_value(index, sub)
        if v is not None:
            return v
        obj = self.node.object_dictionary[index]
        if not hasattr(obj, "data_type"):
            obj = obj[sub]
        assert isinstance(obj, ODVariable)
        raw = obj.decode_raw(self.node.get_data(index, sub))
        return raw if isinstance(raw, (int, float)) else 0

    def _rpdo(self, pdo: _Pdo, data: bytes) -> None:
        if len(data) < pdo.fmt.size:
            log.warning("%s: RPDO 0x%03X too short (%d < %d bytes): EMCY 0x8210", self.name, pdo.cob_id,
                        len(data), pdo.fmt.size)
            self.send_emcy(EMCY_PDO_LENGTH)
            return
        if len(data) > pdo.fmt.size:
            self.send_emcy(EMCY_PDO_LENGTH_EXCEEDED)
        values = pdo.fmt.unpack_from(data)
        if pdo.trans_type <= 240:
            self._latched.extend((i, s, int(v)) for (i, s), v in zip(pdo.fields, values))
        else:
            for (i, s), v in zip(pdo.fields, values):
                self.apply_value(i, s, int(v))

    def _pack(self, pdo: _Pdo) -> bytes:
        return pdo.fmt.pack(*[self.value(i, s) for i, s in pdo.fields])

    def _emit(self, pdo: _Pdo, data: bytes, late: bool = False) -> None:
        pdo.last_data, pdo.last_sent_t = data, self.t_s
        msg = can.Message(arbitration_id=pdo.cob_id, data=data, is_extended_id=False)
        if late:
            self._late.append((self.t_s + LATE_FRACTION * self.period_s, msg))
        elif not self._silent:
            self._send_raw(msg)

    def _send_tpdos(self, active: set[SimFault]) -> None:
        if self.nmt_state != NMT_OPERATIONAL:
            return
        drop = SimFault.DROP_TPDO in active
        late = SimFault.LATE_TPDO in active
        for pdo in self._tpdos:
            tt = pdo.trans_type
            if tt > 240:
                continue
            pdo.syncs += 1
            if tt == 0:
                data = self._pack(pdo)
                if data == pdo.last_data:
                    continue
            elif pdo.syncs % tt:
                continue
            else:
                data = self._pack(pdo)
            if drop:
                pdo.last_data = data
                continue
            self._emit(pdo, data, late)

    def _send_event_tpdos(self) -> None:
        """Event-driven TPDOs (254/255): on a change of a mapped value or the event timer, after inhibit."""
        if self.nmt_state != NMT_OPERATIONAL:
            return
        t = self.t_s
        for pdo in self._event_tpdos:
            if t - pdo.last_sent_t + _EPS < pdo.inhibit_s:
                continue
            data = self._pack(pdo)
            timer = pdo.event_s > 0 and t - pdo.last_sent_t + _EPS >= pdo.event_s
            if data != pdo.last_data or timer:
                self._emit(pdo, data)

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
        data = bytes(data)
        if 0x1400 <= index <= 0x1BFF:
            self._check_pdo_write(index, subindex, data)
        elif index == 0x1017:
            self._hb_period_s = _u(data, "<H") * 1e-3
            self._next_hb_t = self.t_s + self._hb_period_s
        elif index == 0x1016 and subindex == 1:
            self._set_consumer(_u(data, "<I"))
        elif index == 0x1006:
            self.period_s = (_u(data, "<I") * 1e-6) or 0.001
        elif index == 0x1005:
            v = _u(data, "<I")
            if v & 0x60000000:
                raise _abort(ABORT_INVALID_VALUE)  # 29-bit id or "generate SYNC": a SYNC consumer only
            self.sync_cob_id = v & 0x7FF
        elif index == 0x1014:
            v = _u(data, "<I")
            if v & 0x20000000:
                raise _abort(ABORT_INVALID_VALUE)
            cur = self.emcy_cob_id
            if cur is not None and not v & 0x80000000 and (v & 0x7FF) != cur:
                raise _abort(ABORT_INVALID_VALUE)  # change the id only while EMCY is invalid (bit 31)
            self.emcy_cob_id = None if v & 0x80000000 else v & 0x7FF
        elif 0x2000 <= index:
            fmt = _FMT.get((len(od) if hasattr(od, "__len__") else 8 * len(data), od.data_type in _SIGNED_TYPES))
            if fmt is not None:
                self.apply_value(index, subindex, _u(data, "<" + fmt))

    # ------------------------------------------------------------------ entry points (called by SimWorld)
    def add_fault(self, spec: FaultSpec) -> None:
        self.faults.add(spec, self.sync_count + 1)

    def on_frame(self, msg: can.Message, t_s: float) -> None:
        """Handle one received frame at device time ``t_s`` (never raises: see :meth:`_internal_error`)."""
        self.t_s = t_s
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return  # 11-bit device: a 29-bit frame is not for it whatever its id
        try:
            self._on_frame(msg, t_s)
        except Exception:  # noqa: BLE001 - logged, EMCY, fault: never a dead device
            self._internal_error(f"frame 0x{msg.arbitration_id:03X}")

    def _on_frame(self, msg: can.Message, t_s: float) -> None:
        cid = msg.arbitration_id
        data = bytes(msg.data)
        if cid == self.sync_cob_id:
            self.sync(t_s)
        elif cid == 0x000:
            if not self._silent:
                self._nmt(data)
        elif cid in self._rpdos:
            if self.nmt_state == NMT_OPERATIONAL:
                self._rpdo(self._rpdos[cid], data)
                if self._event_tpdos:
                    self._send_event_tpdos()
        elif cid == 0x600 + self.node_id:
            if not self._silent and self.nmt_state in (NMT_PRE_OPERATIONAL, NMT_OPERATIONAL):
                try:
                    self._sdo_request(cid, data, msg.timestamp)
                finally:
                    if self._pdo_dirty:
                        self._compile_pdos()  # PDO parameters take effect at once (also in OPERATIONAL)
                if self._event_tpdos:
                    self._send_event_tpdos()
        elif self._consumer_node and cid == 0x700 + self._consumer_node:
            self._consumer_last_t = t_s
            self._consumer_armed = self._consumer_timeout_s > 0

    def sync(self, t_s: float) -> None:
        self.t_s = t_s
        self.last_sync_t = t_s
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
        finally:
            self._send_tpdos(active)
            if self._event_tpdos:
                self._send_event_tpdos()

    def tick(self, t_s: float) -> None:
        """Timers: heartbeat producer and consumer, event TPDOs, late TPDOs, own clock, at device time ``t_s``."""
        self.t_s = t_s
        try:
            self._tick(t_s)
        except Exception:  # noqa: BLE001 - logged, EMCY, fault: never a dead device
            self._internal_error("timer")

    def _tick(self, t_s: float) -> None:
        prev, self._tick_t = self._tick_t, t_s
        if self.threaded and prev is not None and t_s - prev > SELF_STALL_S:
            # this process (the HIL's sim-plant) was held off the CPU: what the master sent meanwhile is still
            # queued behind this tick; judging its heartbeat or SYNC missing now would fault (EMCY 0x8130 /
            # 0x8700) or run the plant on the drive's own clock for the whole stall under the last torque
            self._grace_until = t_s + SELF_STALL_GRACE_S
        self.judging_silence = not self.threaded or t_s >= self._grace_until
        if self._late:
            self.release_late(t_s)
        if self.nmt_state == NMT_INITIALISING:
            return
        if self._hb_period_s > 0 and t_s + 1e-12 >= self._next_hb_t:
            if not self._hb_stopped:
                self.send(0x700 + self.node_id, bytes([self.nmt_state]))
            # on schedule: a late tick sends one beat now and keeps the grid (no burst, no drift)
            self._next_hb_t += self._hb_period_s
            if self._next_hb_t <= t_s:
                self._next_hb_t = t_s + self._hb_period_s
        if (self._consumer_armed and self.judging_silence
                and t_s - self._consumer_last_t > self._consumer_timeout_s + 1e-12):
            self._consumer_armed = False
            self.heartbeat_lost_events += 1
            self.send_emcy(EMCY_HEARTBEAT)
            self.on_heartbeat_lost()
        self.on_tick(t_s)
        if self._event_tpdos:
            self._send_event_tpdos()


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
    FAULT_REACTION_ACTIVE = 0x001F
    FAULT = 0x0008


_S = DriveState
#: states in which the power stage is on (the drive runs the plant on its own clock when SYNC is missing)
_POWERED = (_S.OPERATION_ENABLED, _S.QUICK_STOP_ACTIVE, _S.FAULT_REACTION_ACTIVE)
#: SYNC missing for this many periods: the drive steps the plant on its own clock
OWN_CLOCK_PERIODS = 3
#: wall_clock_plant: most periods one SYNC steps the plant by: a skipped controller slot or two are physical, a
#: longer gap is mostly this process held off the CPU (its SYNCs then arrive bunched) and is lost, as without
MAX_CATCH_UP_PERIODS = 5
#: quick-stop / fault-reaction option codes that brake on the current (3, 7) or voltage (4, 8) limit
BRAKE_OPTIONS = frozenset({3, 4, 7, 8})
#: the braking slow-down ends once |v| stays below this [m/s] ...
BRAKE_STANDSTILL_M_S = 1e-5
#: ... for this many periods
BRAKE_STILL_PERIODS = 5
#: the braking slow-down gives up after this long [s] (power off / FAULT, as at the end of a ramp)
BRAKE_MAX_S = 2.0
#: statusword bit 12 in CST: the drive follows the target torque
SW_CST_FOLLOWING = 0x1000


class SimCia402Drive(SimCanopenDevice):
    """Simulated CiA 402 drive in cyclic synchronous torque mode driving ``plant`` (see module docstring).

    Quick stop (0x605A) and fault reaction (0x605E) in a torque mode: option 0 switches the power stage off at
    once; the others ramp the torque down to zero with the torque slope 0x6087 [‰ of rated torque per s],
    one period at a time on the drive's own clock::

        F_k+1 = sign(F_k) · max(0, |F_k| − 0x6087 · force_per_unit_n · T)

    When it reaches 0: 0x605A 1–4 → SWITCH ON DISABLED, 5–8 stay in QUICK STOP ACTIVE (transition 16 to
    OPERATION ENABLED allowed from then on); a fault reaction ends in FAULT.

    In a torque mode the slow-down and quick-stop *ramps* (options 1, 2, 5, 6) are torque ramps: they only take
    the force away, and a moving stage coasts on against its friction. Options 3, 4, 7, 8 ("slow down on current
    limit / voltage limit", CiA 402 / IEC 61800-7-201 0x605A; 0x605E 3, 4) brake the motor: the drive closes its
    own velocity loop on its encoder at the torque limit, every period, on its own clock when SYNC is missing (a
    starved master cannot let the stage coast)::

        F = clamp(−k_v·v, ±F_lim),   k_v = m / (2·T)   (half the dead-beat gain: no overshoot per period)

    F_lim = 0x6072 max torque × force_per_unit_n (the current limit), m the plant's moving mass (the drive's
    velocity loop is tuned to its load). The slow-down ends when |v| < ``BRAKE_STANDSTILL_M_S`` for
    ``BRAKE_STILL_PERIODS`` periods (or after ``BRAKE_MAX_S``): then as for the ramps above (3, 4 → SWITCH ON
    DISABLED, 7, 8 stay in QUICK STOP ACTIVE at zero force, fault reaction → FAULT).
    """

    def __init__(self, plant: Any, cfg: SimDriveConfig, send: Callable[[can.Message], None],
                 base_dir: Path | None = None) -> None:
        eds = Path(cfg.eds_file) if cfg.eds_file else EDS_DIR / "stagectl_cia402.eds"
        if base_dir is not None and not eds.is_absolute():
            eds = base_dir / eds
        super().__init__(cfg.node_id, eds, send, "drive")
        self.plant = plant
        self.cfg = cfg
        self._store_current_limit()
        self.on_reset()

    def _store_current_limit(self) -> None:
        """The drive's current limit as its integrator stored it (a DCF ParameterValue, kept across NMT resets):
        0x6072 = floor(F_lim / force_per_unit_n), F_lim = ``sim.drive.max_force_n`` or else the simulated
        actuator's ``max_force_n`` (the force the twin's actuator really gives), within UNSIGNED16. An infinite
        F_lim or an EDS without 0x6072 keeps the EDS default (or no object)."""
        f_lim = self.cfg.max_force_n
        if f_lim is None:
            act = getattr(getattr(getattr(self.plant, "cfg", None), "actuator", None), "max_force_n", None)
            f_lim = float(act) if isinstance(act, (int, float)) else None
        if f_lim is None or not math.isfinite(f_lim) or 0x6072 not in self.node.object_dictionary:
            return
        obj = self.node.object_dictionary[0x6072]
        if isinstance(obj, ODVariable):
            obj.value = max(1, min(0xFFFF, int(f_lim / self.cfg.force_per_unit_n * (1.0 + 1e-12))))

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
        self._plant_t = self.t_s
        self._sync_seen = False
        self._own_steps = 0  # plant periods stepped on the drive's own clock since the last SYNC
        self._max_torque: int | None = None
        self._ramp: float | None = None  # torque slope [N/s] while a quick-stop / fault-reaction ramp runs
        self._braking = False  # a current-limit slow-down (options 3, 4, 7, 8) runs (with _ramp = inf)
        self._brake_still = 0
        self._brake_t = 0.0
        self.brake_periods = 0  # periods of the last braking slow-down (diagnostics, tests)

    # ------------------------------------------------------------------ process values
    @property
    def statusword(self) -> int:
        sw = self.state.value | 0x0200
        if self.state is _S.OPERATION_ENABLED and self.mode == 10:
            sw |= SW_CST_FOLLOWING
        return sw

    @property
    def max_torque_units(self) -> int:
        """0x6072 max torque [per mille of rated torque] (cached; updated on every write of 0x6072)."""
        if self._max_torque is None:
            self._max_torque = self._stored(0x6072, 0, "<H", 0x7FFF)
        return self._max_torque

    @property
    def torque_units(self) -> int:
        """0x6077 torque actual value: the force applied this period in 0x6071 units."""
        return max(-32768, min(32767, round(self.force_n / self.cfg.force_per_unit_n)))

    def live_value(self, index: int, sub: int) -> int | None:
        if index == 0x6041:
            return self.statusword
        if index == 0x6064:
            return self.position_counts
        if index == 0x606C:
            return self.velocity_units
        if index == 0x6061 or index == 0x6060:
            return self.mode
        if index == 0x603F:
            return self.error_code
        if index == 0x6077:
            return self.torque_units
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
            self.mode = value if value in (0, 10) else self.mode

    def _on_sdo_write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        if index == 0x6060:
            mode = struct.unpack_from("<b", bytes(data))[0]
            if mode not in (0, 10):
                raise _abort(ABORT_INVALID_VALUE)  # value range: only CST (10) is implemented
            self.mode = mode
        elif index == 0x6040:
            self.apply_controlword(_u(bytes(data), "<H"))
        elif index == 0x6071:
            self.target_torque = struct.unpack_from("<h", bytes(data))[0]
        elif index == 0x6072:
            self._max_torque = _u(bytes(data), "<H")
        elif index in _OPTION_RANGE and subindex == 0 and len(data) == 2:
            code = struct.unpack_from("<h", bytes(data))[0]
            lo, hi = _OPTION_RANGE[index]
            if not lo <= code <= hi:  # reserved (above hi) or manufacturer-specific (< 0): none is implemented
                raise _abort(ABORT_INVALID_VALUE)
            super()._on_sdo_write(index, subindex, od, data)
        else:
            super()._on_sdo_write(index, subindex, od, data)

    # ------------------------------------------------------------------ 402 state machine
    def apply_controlword(self, cw: int) -> None:
        rising_reset = bool(cw & 0x80) and not (self.controlword & 0x80)
        self.controlword = cw
        st = self.state
        if st in (_S.FAULT, _S.FAULT_REACTION_ACTIVE):
            if rising_reset and st is _S.FAULT:  # transition 15
                self.state = _S.SWITCH_ON_DISABLED
                self.error_code = 0
                self.send_emcy(EMCY_RESET)
            return
        if cw & 0x80:
            return
        if not cw & 0x02:  # disable voltage (7, 9, 10, 12)
            self.state = _S.SWITCH_ON_DISABLED
            self._ramp = None
            self._braking = False
        elif cw & 0x06 == 0x02:  # quick stop (7, 10, 11)
            if st is _S.OPERATION_ENABLED:
                self.state = _S.QUICK_STOP_ACTIVE
                self._start_ramp(self._option(0x605A, 2))
            elif st is not _S.QUICK_STOP_ACTIVE:
                self.state = _S.SWITCH_ON_DISABLED
        elif st is _S.QUICK_STOP_ACTIVE:
            if cw & 0x0F == 0x0F and self._option(0x605A, 2) >= 5 and self._ramp is None:
                self.state = _S.OPERATION_ENABLED  # 16: only after the ramp, for options 5..8
        elif cw & 0x07 == 0x06:  # shutdown (2, 6, 8)
            if st in (_S.SWITCH_ON_DISABLED, _S.SWITCHED_ON, _S.OPERATION_ENABLED):
                self.state = _S.READY_TO_SWITCH_ON
        elif cw & 0x0F == 0x07:  # switch on (3) / disable operation (5)
            if st in (_S.READY_TO_SWITCH_ON, _S.OPERATION_ENABLED):
                self.state = _S.SWITCHED_ON
        elif cw & 0x0F == 0x0F:  # enable operation (4, also 3+4 from READY TO SWITCH ON)
            if st in (_S.SWITCHED_ON, _S.READY_TO_SWITCH_ON):
                self.state = _S.OPERATION_ENABLED
        if self.state is _S.OPERATION_ENABLED and st is not _S.OPERATION_ENABLED:
            self._plant_t = self.t_s

    def _option(self, index: int, default: int) -> int:
        """An INTEGER16 option code (0x605A, 0x605E, 0x6007), ``default`` if the object is missing."""
        raw = self._stored(index, 0, "<H", default & 0xFFFF)
        return raw - 0x10000 if raw & 0x8000 else raw

    def _start_ramp(self, option: int) -> None:
        """Begin a quick-stop / fault-reaction torque ramp (option 0: power stage off at once)."""
        self._braking = False
        if option <= 0:
            self._ramp = None
            self.force_n = 0.0
            return
        if option in BRAKE_OPTIONS:  # brake on the current limit (class docstring)
            self._braking = True
            self._ramp = float("inf")
            self._brake_still = 0
            self._brake_t = 0.0
            self.brake_periods = 0
            self.force_n = self._brake_force()
            return
        self._ramp = max(1, self._stored(0x6087, 0, "<I", 1_000_000)) * self.cfg.force_per_unit_n

    def _brake_force(self) -> float:
        """The current-limit slow-down's force [N]: clamp(−m/(2T)·v, ±0x6072·force_per_unit_n)."""
        v = float(getattr(self.plant, "v_m_s", 0.0))
        mass = getattr(getattr(self.plant, "cfg", None), "mass_kg", None)
        m = float(mass) if isinstance(mass, (int, float)) and mass > 0 else 1.0
        lim = self.max_torque_units * self.cfg.force_per_unit_n
        f = -m / (2.0 * self.period_s) * v
        return lim if f > lim else -lim if f < -lim else f

    def _advance_ramp(self) -> None:
        """After one period: the next force on the ramp; at zero the ramp ends (see class docstring)."""
        if self._ramp is None:
            return
        if self._braking:
            self.brake_periods += 1
            self._brake_t += self.period_s
            v = float(getattr(self.plant, "v_m_s", 0.0))
            self._brake_still = self._brake_still + 1 if abs(v) < BRAKE_STANDSTILL_M_S else 0
            if self._brake_still < BRAKE_STILL_PERIODS and self._brake_t < BRAKE_MAX_S:
                self.force_n = self._brake_force()
                return
            if self.state is _S.QUICK_STOP_ACTIVE and self._option(0x605A, 2) >= 5:
                self._ramp = None  # 7, 8: stay in QUICK STOP ACTIVE, the velocity loop holds the stage
                self._braking = False
                self.force_n = 0.0
                return
            self._braking = False
        else:
            left = abs(self.force_n) - self._ramp * self.period_s
            if left > 1e-12:
                self.force_n = left if self.force_n > 0 else -left
                return
        self._ramp = None
        self.force_n = 0.0
        if self.state is _S.FAULT_REACTION_ACTIVE:
            self.state = _S.FAULT
        elif self.state is _S.QUICK_STOP_ACTIVE and self._option(0x605A, 2) <= 4:
            self.state = _S.SWITCH_ON_DISABLED

    def enter_fault(self, code: int, emcy_sent: bool = False) -> None:
        """A fault: EMCY ``code`` (once: not again if the caller already sent it), FAULT REACTION ACTIVE (0x605E
        ramp or power off), then FAULT."""
        if self.state in (_S.FAULT, _S.FAULT_REACTION_ACTIVE):
            if code and code != self.error_code and not emcy_sent:
                self.send_emcy(code)
            return
        was_powered = self.state in _POWERED
        self.state = _S.FAULT_REACTION_ACTIVE
        self.error_code = code
        if not emcy_sent:
            self.send_emcy(code)
        self._start_ramp(self._option(0x605E, 0) if was_powered else 0)

    def on_internal_error(self) -> None:
        self.force_n = 0.0
        self._ramp = None
        self._braking = False
        self.state = _S.FAULT
        self.error_code = EMCY_INTERNAL

    def on_heartbeat_lost(self) -> None:
        self._abort_connection(EMCY_HEARTBEAT, emcy_sent=True)  # the consumer already sent EMCY 0x8130

    def on_connection_aborted(self) -> None:
        self._abort_connection(EMCY_COMMUNICATION, emcy_sent=False)

    def _abort_connection(self, code: int, emcy_sent: bool) -> None:
        """CiA 402 abort connection option code 0x6007 (heartbeat loss, NMT STOPPED, reset communication):
        1 fault, 2 disable voltage, 3 quick stop; only while the power stage is on."""
        if self.state in (_S.FAULT, _S.FAULT_REACTION_ACTIVE):
            self.error_code = code  # 0x603F shows the last error
            return
        if self.state not in (_S.OPERATION_ENABLED, _S.QUICK_STOP_ACTIVE):
            return
        action = self._option(0x6007, 1)
        if action == 1:
            self.enter_fault(code, emcy_sent=emcy_sent)
        elif action == 2:
            self.state = _S.SWITCH_ON_DISABLED
            self._ramp = None
            self._braking = False
            self.force_n = 0.0
        elif action == 3 and self.state is _S.OPERATION_ENABLED:
            self.state = _S.QUICK_STOP_ACTIVE
            self._start_ramp(self._option(0x605A, 2))

    # ------------------------------------------------------------------ SYNC and own clock
    def _sample(self) -> int:
        x = float(self.plant.measure()) + self.jump_m
        return wrap_int32(round(x / self.cfg.resolution_m))

    def _step_period(self) -> None:
        """One period of the drive: the plant under the force of the last period, then the new force."""
        self.plant.step(self.force_n, self.period_s)
        self._plant_t += self.period_s
        if self.state is _S.FAULT_REACTION_ACTIVE and self._ramp is None:
            self.state = _S.FAULT  # reaction "power off": done after one period
            self.force_n = 0.0
        elif self.state in (_S.QUICK_STOP_ACTIVE, _S.FAULT_REACTION_ACTIVE):
            self._advance_ramp()
        elif self.state is _S.OPERATION_ENABLED and self.mode == 10:
            lim = self.max_torque_units
            self.force_n = max(-lim, min(lim, self.target_torque)) * self.cfg.force_per_unit_n
        else:
            self.force_n = 0.0
        self.position_counts = self._sample()
        v = getattr(self.plant, "v_m_s", 0.0)
        self.velocity_units = max(-(2**31), min(2**31 - 1, round(float(v) / self.cfg.velocity_resolution_m_s)))

    def on_sync(self, active: set[SimFault]) -> None:
        self._sync_seen = True
        self.jump_m = self.faults.jump_m(active)
        if self._own_steps:  # the own clock already ran up to now: this SYNC only samples
            self._own_steps = 0
            self.position_counts = self._sample()
        elif self.cfg.wall_clock_plant and self.threaded:
            T = self.period_s
            n = min(MAX_CATCH_UP_PERIODS, round((self.t_s - self._plant_t) / T))
            if n <= 0:  # SYNCs bunched (this process was held off the CPU): the plant is up to date
                self.position_counts = self._sample()
            else:
                if self.state is _S.OPERATION_ENABLED:
                    for _ in range(n - 1):  # the periods without SYNC: the torque of the last one is held
                        self.plant.step(self.force_n, T)
                    self._plant_t = self.t_s - T
                else:
                    self._plant_t = self.t_s - n * T
                    for _ in range(n - 1):
                        self._step_period()
                self._step_period()
                self._plant_t = self.t_s
        else:
            self._plant_t = self.t_s - self.period_s
            self._step_period()
        if SimFault.DRIVE_FAULT in active:  # FAULT REACTION ACTIVE for (at least) this period, then FAULT
            spec = self.faults.spec_of(SimFault.DRIVE_FAULT)
            self.enter_fault(spec.code if spec else 0x2310)

    def on_tick(self, t_s: float) -> None:
        if not self.judging_silence:  # right after this process's own stall: the SYNCs may still be queued
            return
        T = self.period_s
        silent_s = t_s - self.last_sync_t
        if (self._sync_seen and self.cfg.sync_timeout_s > 0 and self.state is _S.OPERATION_ENABLED
                and self.mode == 10 and self.nmt_state == NMT_OPERATIONAL
                and silent_s > self.cfg.sync_timeout_s + _EPS):
            log.warning("%s: no SYNC for %.3g s (> sync_timeout_s %.3g s): EMCY 0x%04X, fault", self.name,
                        silent_s, self.cfg.sync_timeout_s, EMCY_SYNC_LOST)
            self.enter_fault(EMCY_SYNC_LOST)
        if self.state is _S.OPERATION_ENABLED:
            # the controller may only be late (thread mode on a loaded machine): take over when it is surely gone
            take_over_s = 0.5 * self.cfg.sync_timeout_s if self.cfg.sync_timeout_s > 0 else 0.05
        else:
            take_over_s = OWN_CLOCK_PERIODS * T  # a quick stop / fault reaction completes without SYNC
        if self.state in _POWERED and silent_s > take_over_s + _EPS:
            n = 0
            while t_s - self._plant_t >= T - _EPS and n < 10_000 and self.state in _POWERED:
                self._step_period()
                n += 1
            self._own_steps += n
