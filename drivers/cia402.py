"""CiA 402 servo drive over CANopen, cyclic synchronous torque (CST), with the loop as SYNC producer.

Start-up (``configure``, SDO only, canopen's Notifier running): NMT pre-operational, check device type
0x1000 (profile 402) and supported modes 0x6502 (CST bit 9), write the communication cycle period
0x1006 (= loop ``period_s``), the drive's heartbeat producer 0x1017, the drive's heartbeat consumer 0x1016
(watching *our* heartbeat, so the drive stops by itself if the controller dies), the PDO mapping
(TPDO1 = statusword 0x6041 + position actual 0x6064, optional TPDO2 = velocity actual 0x606C;
RPDO1 = controlword 0x6040 + target torque 0x6071; all synchronous, transmission type 1; each PDO read back
and compared), max torque 0x6072 read (if present) into the force clamp, mode of operation 0x6060 = 10 (CST)
confirmed by polling 0x6061 for up to ``mode_switch_timeout_s``; then NMT start and the Notifier is stopped
("pump mode", docs/platform.md §0.2): during cyclic operation the loop thread reads the bus itself. 0x1006 is
optional (a drive that only consumes SYNC); every start-up failure is one line naming the object, the SDO
abort code with its CiA 301 meaning and what to check (:func:`explain_sdo_error`). docs/canopen.md §4.

Cyclic exchange, each period (all real-time safe; hot path packed with :mod:`struct`)::

    drive.sync()    # drain stale frames, send SYNC (0x080), every N cycles our heartbeat (0x700+ctrl)
    drive.read()    # wait for the TPDO sent after this SYNC; unwrap position; detect faults. If it does not
                    # come in time, the newest late answer to the previous SYNC (drained by sync()) is
                    # returned as a fresh sample with age_cycles = 1 (a loaded machine answering late)
    drive.write(f)  # RPDO1 (controlword, target torque); the drive applies it at the next SYNC

Sample age (``Measurement.age_cycles``, sync producer). A TPDO carries no SYNC number, and the SYNC counter of
CiA 301 (0x1019 overflow value 2..240, one counter byte in the SYNC) does not help: it tells the *drive* which
SYNC it received (for TPDO SYNC start value 0x18xx:06), nothing in the TPDO returns it. So the driver ties
each TPDO1 to its SYNC from two facts of its own: arrival (a TPDO drained before SYNC n was sent answers SYNC
n−1 or older: age ≥ 1; one that arrives in read()'s wait after SYNC n: age ≥ 0) and counting (transmission
type 1: the drive answers every SYNC once, in order, so the j-th TPDO1 answers the j-th SYNC, less the
answers lost: a drive working off a backlog after its process was held off the CPU sends answers that arrive
"on time" yet are b SYNCs old). age = arrival bound + backlog b, b = (n − j) − L, L the lost answers
(:meth:`Cia402Drive._count_tpdo`: the smallest n − j seen). A drive works off a backlog faster than SYNC
comes, so its answers come in bursts (two or more TPDO1s between two reads) and b shrinks; lost answers
(dropped frames) leave b standing with one TPDO1 per cycle: b > 0 with a single TPDO1 since the last read
raises L by b at once (age 0 or 1 by arrival), as does a b that did not shrink over ``LOST_AFTER_TPDOS``
TPDO1s in a row -- for b > ``MAX_LOST_ANSWERS`` (10) only if the drive's heartbeat kept coming meanwhile. A
drive that stays behind by a constant b, one answer per SYNC, is indistinguishable by counting from one that
lost b answers; but frames lost on the way leave its heartbeat running, while a drive process held off the CPU
falls silent altogether. So a longer b behind a heartbeat silent for 1.5 producer periods is a backlog (the
HIL's sim-plant held off the CPU for 0.3 s, then answering about one SYNC per cycle: taken for lost answers,
0.3 s old samples were used as fresh, the controller wound up to -3 N against a stage that seemed not to move,
and the queued commands ran the stage 9.5 mm): its samples stay stale (the loop's stale limits fault) until it
is worked off, or until it stood unchanged over ``LOST_BLOCK_AFTER_TPDOS`` TPDO1s. A b taken for lost answers
that stands is aged by arrival only. So is a sample whose count says one period more than
its arrival (one period in all) unless the previous read's backlog was 2: a lost answer followed by a late
one looks the same, and a wrong age 1 costs an extrapolation by v̂·T, a wrong age 2 only a predicted step.
Motion tells the two apart where counting cannot: before a count gap of b answers is taken for lost ones, the
TPDO1's position is compared with the last two fresh samples extrapolated to the newest SYNC (lost answers) and
to the SYNC b earlier (backlog); nearer the older one, it stays a backlog (``_looks_old``; only when the two lie
``AGE_EVIDENCE_COUNTS`` apart). Where nothing tells (the stage slower than that, its velocity not steady, or
the evidence used up) a single answer after a gap of b ≥ 2 is still counted as lost answers (the next one is on
time), but that one sample is reported b periods old, the age it has if it is a backlog: the loop holds on it
(stale) instead of stepping on a position that may be b periods old. A wrong guess costs one held cycle; the
other costs an observer kick (the HIL demo at load 9-12: a 17-periods-old sample at a move's start taken for
this SYNC's, the next one 2 µm further, the observer's -1.9 N held blind through the next gap, the stage stuck
and ``following_error``). A drive process held off the CPU for 5-40 ms, heartbeat still running, that
then works off its backlog at about one SYNC per cycle was taken for lost answers: its 2-30 periods old samples
were stepped on as age 1, and the observer answered the apparent stop and jump of the stage with ±1 N spikes
(the HIL demo's following-error episodes). The loop steps on samples of age 0 and 1 (age 1 extrapolated by v̂·T) and treats age ≥ 2
as stale (``loop.STALE_AGE_CYCLES``).

Force scaling. 0x6071 is INT16 in per-mille of the drive's rated torque (CiA 402); for a linear motor
``rated force F_r`` [N] one unit is ``F_r / 1000`` newtons, so ``force_per_unit_n = F_r / 1000``::

    target_torque [units] = round(force_n / force_per_unit_n),  clamped to ±min(32767, max_force_n / force_per_unit_n)

Position: ``position_m = counts × resolution_m`` where ``counts`` is 0x6064 (INT32) unwrapped across
the 32-bit wrap: ``counts_k = counts_{k-1} + ((raw_k − raw_{k−1} + 2³¹) mod 2³² − 2³¹)``.

Faults (``Measurement.fault``, latched in ``drive.fault``): statusword fault bit → ``DRIVE_FAULT`` (code of
the last EMCY); EMCY → ``EMCY``; drive heartbeat older than ``heartbeat_timeout_s`` → ``HEARTBEAT_LOST``;
error frame → ``BUS_ERROR`` or ``BUS_OFF``; ``max_missed`` consecutive cycles without a fresh TPDO →
``MISSED_FRAME``; a position step faster than ``max_speed_m_s`` → ``SENSOR_ERROR``. Time-outs that are
counted per cycle (heartbeat age) use ``cycles × period_s``, so they hold in lock-step simulated time too.
Once a fault is latched, ``write()`` sends quick stop (controlword 0x0002) with zero torque.

Lock-step: with ``set_pump(pump)``, waiting for the TPDO is ``pump()`` followed by non-blocking polls;
during ``configure`` (SDO) the SDO client's waiting thread pumps and reads the answer itself
(:func:`~stagectl.drivers.canbus.lockstep_sdo_reader`: no wall-clock time-out race on a loaded machine) when the
pump was set before ``open``; set later, a helper thread keeps pumping while canopen's Notifier receives.
"""

from __future__ import annotations

import enum
import logging
import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from stagectl.clock import Timing
from stagectl.drivers import pdo_codec
from stagectl.drivers.base import (
    DeviceFault,
    DeviceState,
    FaultKind,
    ForceActuator,
    Measurement,
    PositionSensor,
    SyncProducer,
)
from stagectl.drivers.canbus import CanopenNode, error_frame_is_bus_off, link_closed, pumping
from stagectl.errors import ConfigError, DriveFault, DriverError, DriverInitError, DriverIOError, DriverTimeoutError
from stagectl.resources import EDS_DIR
from stagectl.schema import param

log = logging.getLogger(__name__)

DEFAULT_EDS = EDS_DIR / "stagectl_cia402.eds"

SYNC_COB_ID = 0x080
#: motion evidence on a count gap (Cia402Drive._looks_old) only when the two hypotheses lie this many counts apart
AGE_EVIDENCE_COUNTS = 20
#: ... and for at most this many verdicts since the last answer without a gap (a standing backlog is then
#: taken for lost answers by the counting rule, as before: holding its samples stale faulted stale_position)
AGE_EVIDENCE_RUNS = 10
#: TPDO1s in a row whose backlog age did not shrink before it is taken for lost answers (module docstring)
LOST_AFTER_TPDOS = 3
#: at most this many answers in a row are always taken for lost frames (a lag this short, misjudged, costs at
#: most this many periods of feedback delay); a longer gap in the count while the drive's heartbeat was silent
#: too (its process held off the CPU, not frames lost on the way) is a backlog: its samples keep their age ...
MAX_LOST_ANSWERS = 10
#: ... unless it stood unchanged over this many TPDO1s in a row (answers really lost, e.g. a dropped block)
LOST_BLOCK_AFTER_TPDOS = 1000
#: CiA 402 "cyclic synchronous torque" mode of operation (0x6060)
MODE_CST = 10
#: 0x6502 bit for CST support
SUPPORTED_CST_BIT = 1 << 9
PDO_DISABLED = 0x80000000
PDO_NO_RTR = 0x40000000  # PDO COB-ID bit 30: no RTR allowed on this PDO



def cob_id_writes(current: int, cob_id: int) -> tuple[list[tuple[int, str]], int]:
    """The PDO COB-ID writes (value, what) that make a PDO now at ``current`` invalid on 11-bit ``cob_id``
    before its mapping is changed, and the value that validates it afterwards.

    CiA 301 §7.5.2.35: bits 0-29 may change only while the PDO is invalid (bit 31), so it is invalidated on the
    COB-ID it has (a drive may have stored another one), then given ours; bit 30 (RTR not allowed, fixed at 1
    on many drives) is kept as the drive has it."""
    keep = current & PDO_NO_RTR
    writes = []
    if not current & PDO_DISABLED:
        writes.append((current | PDO_DISABLED, "COB-ID (disable)"))
    if current & ~PDO_DISABLED & 0xFFFFFFFF != keep | cob_id:  # bits 0-30: ours (bit 30 as the drive has it)
        writes.append((PDO_DISABLED | keep | cob_id, "COB-ID (set while disabled)"))
    return writes, keep | cob_id


_RPDO1 = pdo_codec.RPDO1  # controlword 0x6040 (U16), target torque 0x6071 (INT16)
_EMCY = struct.Struct("<HB5s")


class State402(enum.Enum):
    """CiA 402 power state machine states, decoded from the statusword."""

    NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
    SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
    READY_TO_SWITCH_ON = "READY TO SWITCH ON"
    SWITCHED_ON = "SWITCHED ON"
    OPERATION_ENABLED = "OPERATION ENABLED"
    QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
    FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
    FAULT = "FAULT"

    @classmethod
    def from_statusword(cls, sw: int) -> State402:
        """Decode bits 0–3, 5, 6 of the statusword (CiA 402 table of state coding)."""
        low = sw & 0x4F
        if low == 0x00:
            return cls.NOT_READY_TO_SWITCH_ON
        if low == 0x40:
            return cls.SWITCH_ON_DISABLED
        if low == 0x0F:
            return cls.FAULT_REACTION_ACTIVE
        if low == 0x08:
            return cls.FAULT
        mid = sw & 0x6F
        if mid == 0x21:
            return cls.READY_TO_SWITCH_ON
        if mid == 0x23:
            return cls.SWITCHED_ON
        if mid == 0x27:
            return cls.OPERATION_ENABLED
        if mid == 0x07:
            return cls.QUICK_STOP_ACTIVE
        return cls.NOT_READY_TO_SWITCH_ON


class Controlword(enum.IntEnum):
    """CiA 402 controlword commands (bits: 0 switch on, 1 enable voltage, 2 quick stop (low active),
    3 enable operation, 7 fault reset)."""

    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007
    ENABLE_OPERATION = 0x000F
    FAULT_RESET = 0x0080


#: next controlword on the way to OPERATION ENABLED
_TOWARDS_ENABLED = {
    State402.NOT_READY_TO_SWITCH_ON: Controlword.DISABLE_VOLTAGE,
    State402.SWITCH_ON_DISABLED: Controlword.SHUTDOWN,
    State402.READY_TO_SWITCH_ON: Controlword.SWITCH_ON,
    State402.SWITCHED_ON: Controlword.ENABLE_OPERATION,
    State402.OPERATION_ENABLED: Controlword.ENABLE_OPERATION,
    State402.QUICK_STOP_ACTIVE: Controlword.DISABLE_VOLTAGE,
}

STATUSWORD_FAULT = 1 << 3


def _default_can() -> dict[str, Any]:
    return {"interface": "socketcan", "channel": "can0", "bitrate": 1000000}


@dataclass(frozen=True)
class Cia402Config:
    """Configuration of a CiA 402 drive in cyclic synchronous torque mode (YAML ``drive:`` section)."""

    node_id: int = param(desc="CANopen node id of the drive", ge=1, le=127)
    can: dict[str, Any] = param(
        desc="mapping passed to can.Bus (interface, channel, bitrate, host/port for socketcand, ...)",
        default_factory=_default_can,
    )
    resolution_m: float = param(1e-9, unit="m", desc="position per count of 0x6064 (metres per count)", gt=0)
    force_per_unit_n: float = param(
        0.01,
        unit="N",
        desc="newtons per unit of target torque 0x6071 (INT16, per-mille of rated torque: rated force / 1000)",
        gt=0,
    )
    max_force_n: float = param(
        math.inf, unit="N", desc="clamp on the commanded force (inf = only the INT16 range)", gt=0, allow_inf=True
    )
    velocity: bool = param(False, desc="also map velocity actual 0x606C into TPDO2")
    velocity_resolution_m_s: float = param(1e-6, unit="m/s", desc="velocity per unit of 0x606C", gt=0)
    heartbeat_producer_s: float = param(
        0.05, unit="s", desc="drive heartbeat producer period written to 0x1017 (0 = off)", ge=0, le=65.535
    )
    heartbeat_timeout_s: float = param(
        0.2, unit="s", desc="drive heartbeat older than this -> HEARTBEAT_LOST", gt=0
    )
    controller_node_id: int = param(
        127, desc="node id under which the controller sends its heartbeat (0x700 + id)", ge=1, le=127
    )
    controller_heartbeat_s: float = param(0.02, unit="s", desc="period of the controller's heartbeat", gt=0)
    drive_consumer_timeout_s: float = param(
        0.1,
        unit="s",
        desc="drive's heartbeat consumer time (0x1016): it stops itself if our heartbeat is older",
        gt=0,
        le=65.535,
    )
    rx_timeout_s: float = param(
        0.0008, unit="s", desc="how long read() waits for the TPDO after SYNC (real-time mode)", gt=0
    )
    max_missed: int = param(3, desc="consecutive cycles without a fresh TPDO before MISSED_FRAME", ge=1)
    max_late_cycles: int = param(
        50, unit="cycles", desc="consecutive cycles without an on-time TPDO (late answers to the previous SYNC "
        "used, one period old) before MISSED_FRAME: a lasting extra period of delay eats the loop's phase margin",
        ge=1)
    max_speed_m_s: float = param(
        2.0, unit="m/s", desc="position steps faster than this are a sensor glitch (SENSOR_ERROR)", gt=0
    )
    sdo_timeout_s: float = param(0.5, unit="s", desc="SDO response timeout during configure", gt=0)
    state_timeout_s: float = param(
        0.5, unit="s", desc="time allowed for enable/disable/fault reset state changes", gt=0
    )
    mode_switch_timeout_s: float = param(
        0.5, unit="s", desc="configure: how long to wait for 0x6061 to show CST after 0x6060 = 10 (real drives "
        "switch modes in milliseconds)", gt=0)
    sync_producer: bool = param(
        True, desc="the loop sends SYNC (0x080); false = another node produces SYNC and the loop follows its TPDOs")
    no_answer_timeout_s: float = param(
        0.05, unit="s", desc="enable/disable/fault reset give up after this long without any TPDO (drive not "
        "answering: bus-off, unpowered) instead of waiting state_timeout_s", gt=0)
    eds_file: str = param("", desc="EDS of the drive (empty = stagectl's config/eds/stagectl_cia402.eds)")
    quick_stop_option_code: int | None = param(
        3, desc="quick stop option code written to 0x605A at configure: 3/7 (4/8) = the drive brakes the stage "
        "on its current (voltage) limit by itself, even when the controller is starved; then the loop releases "
        "to it at once. A drive that refuses it keeps its own code and the loop brakes over the bus. null = "
        "leave the drive's code", ge=-1, le=8)

    def __post_init__(self) -> None:
        if self.heartbeat_producer_s > 0 and self.heartbeat_timeout_s <= self.heartbeat_producer_s:
            raise ConfigError(
                f"heartbeat_timeout_s: must be > heartbeat_producer_s ({self.heartbeat_timeout_s:g} s "
                f"<= {self.heartbeat_producer_s:g} s)"
            )
        if self.drive_consumer_timeout_s <= self.controller_heartbeat_s:
            raise ConfigError(
                f"drive_consumer_timeout_s: must be > controller_heartbeat_s ({self.drive_consumer_timeout_s:g} s "
                f"<= {self.controller_heartbeat_s:g} s)"
            )


#: CiA 301 SDO abort codes: meaning and what to check on the drive
ABORT_HINTS: dict[int, tuple[str, str]] = {
    0x05040000: ("SDO protocol timed out", "the drive's power, node id and bit rate, and the bus wiring"),
    0x06010000: ("unsupported access to an object", "that the PDO is disabled (COB-ID bit 31) before remapping"),
    0x06010001: ("attempt to read a write-only object", "the drive's EDS"),
    0x06010002: ("attempt to write a read-only object", "the drive's EDS / manual for this object"),
    0x06020000: ("object does not exist in the object dictionary", "the drive's EDS: this drive lacks the object"),
    0x06040041: ("object cannot be mapped to the PDO", "the drive manual's list of mappable objects"),
    0x06040042: ("number and length of mapped objects exceed the PDO length",
                 "the number of objects per PDO the drive supports (at most 8 bytes)"),
    0x06040043: ("general parameter incompatibility", "the mapping entry's bit length against the object's type"),
    0x06040047: ("general internal incompatibility in the device", "the drive's state and firmware"),
    0x06060000: ("access failed due to a hardware error", "the drive's hardware status"),
    0x06070010: ("data type does not match, length of service parameter does not match", "the drive's EDS"),
    0x06090011: ("sub-index does not exist", "the drive's EDS"),
    0x06090030: ("invalid value for parameter", "the value range in the drive manual"),
    0x06090031: ("value of parameter written too high", "the value range in the drive manual"),
    0x06090032: ("value of parameter written too low", "the value range in the drive manual"),
    0x08000000: ("general error", "the drive's error log"),
    0x08000020: ("data cannot be transferred or stored to the application", "the drive's state (e.g. enabled)"),
    0x08000021: ("data cannot be transferred because of local control", "the drive's local/remote setting"),
    0x08000022: ("data cannot be transferred because of the present device state",
                 "the drive's NMT / CiA 402 state (PRE-OPERATIONAL, not enabled)"),
}


def explain_sdo_error(exc: BaseException, timeout_s: float | None = None, option: str = "sdo_timeout_s") -> str:
    """One line for an SDO failure: ``abort 0x06020000 (meaning); check …`` or the exception text; a missing
    answer names the time waited (``timeout_s``) and the ``option`` that sets it."""
    code = getattr(exc, "code", None)
    if isinstance(code, int):
        meaning, check = ABORT_HINTS.get(code, ("abort code not in CiA 301", "the drive manual"))
        return f"abort 0x{code:08X} ({meaning}); check {check}"
    text = " ".join(str(exc).split())
    if "timeout" in text.lower() or "no sdo response" in text.lower():
        within = f" within {option} {timeout_s:g} s" if timeout_s is not None else ""
        slow = f", or raise {option} for a drive that answers slowly" if timeout_s is not None else ""
        return (f"no SDO answer{within} ({text}); check the drive's power, node id and bit rate, and the bus "
                f"wiring{slow}")
    return text


def unwrap32(prev_raw: int, prev_counts: int, raw: int) -> int:
    """Unwrapped counts from a wrapping 32-bit reading: prev + signed 32-bit difference."""
    return prev_counts + (((raw - prev_raw + 0x80000000) & 0xFFFFFFFF) - 0x80000000)


class Cia402Drive(CanopenNode, PositionSensor, ForceActuator, SyncProducer):
    """CiA 402 drive in CST mode: position sensor, force actuator and SYNC producer of the loop.

    Parameters
    ----------
    cfg : Cia402Config
    timing : Timing or float
        The loop's timing (or its period [s]); the period is written to 0x1006 at ``configure`` and the
        per-cycle time-outs are derived from it.
    """

    name = "cia402"

    def __init__(self, cfg: Cia402Config, timing: Timing | float) -> None:
        super().__init__()
        self.cfg = cfg
        self.name = f"cia402[node {cfg.node_id}]"
        self.resolution_m = cfg.resolution_m
        self._period_s = 0.0
        self.set_period(timing)
        nid = cfg.node_id
        self._tpdo1_id = 0x180 + nid
        self._tpdo2_id = 0x280 + nid
        self._rpdo1_id = 0x200 + nid
        self._emcy_id = 0x080 + nid
        self._hb_id = 0x700 + nid
        # cyclic frames preallocated once, payloads packed in place (drivers/pdo_codec.py)
        self._sync_msg = pdo_codec.frame(SYNC_COB_ID)
        self._hb_msg = pdo_codec.frame(0x700 + cfg.controller_node_id, b"\x05")
        self._use_layouts(pdo_codec.TPDO1_LAYOUT, pdo_codec.TPDO2_LAYOUT, pdo_codec.RPDO1_LAYOUT)
        self._max_units = self._config_units()
        self._reset_cyclic()
        #: statusword and state of the last fresh TPDO
        self.statusword = 0
        self.velocity_m_s = 0.0
        #: the drive's max torque 0x6072 read at configure (None: the drive has no 0x6072)
        self.drive_max_units: int | None = None
        #: the drive brakes the stage itself on a quick stop (0x605A 3, 4, 7, 8 accepted at configure)
        self.brakes_itself = False
        self._rebooted = False
        self._link_dead = False
        self._bus_off = False
        self._stuck_in_fault = False
        #: NMT state from the drive's last heartbeat (None: none seen yet)
        self.drive_nmt_state: int | None = None

    # ------------------------------------------------------------------ config helpers
    def set_period(self, timing: Timing | float) -> None:
        """Set the loop timing (or its period [s]) before ``configure``; re-derives the cycle counts.

        Raises
        ------
        ConfigError
            A period that is not a finite number > 0.
        """
        t = Timing.of(timing)
        self.timing = t
        self._period_s = t.period_s
        self._hb_every = t.every(self.cfg.controller_heartbeat_s)
        self._hb_timeout_cycles = t.cycles(self.cfg.heartbeat_timeout_s)
        # the drive's heartbeat missing this long (1.5 producer periods): its process was held off the CPU
        hb = self.cfg.heartbeat_producer_s
        self._hb_silent_cycles = t.cycles(1.5 * hb) + 2 if hb > 0 else 0
        self._max_step_counts = t.per_cycle(self.cfg.max_speed_m_s) / self.cfg.resolution_m
        # following an external SYNC producer, the TPDO may come at any time within the period
        self._rx_wait_s = self.cfg.rx_timeout_s if self.cfg.sync_producer else max(
            self.cfg.rx_timeout_s, 0.9 * t.period_s)

    @property
    def period_s(self) -> float:
        return self._period_s

    @property
    def drive_state(self) -> State402:
        """CiA 402 state decoded from the last statusword received."""
        return State402.from_statusword(self.statusword)

    def _reset_cyclic(self) -> None:
        self._held: tuple[int, int] | None = None
        self._late: tuple[int, int] | None = None  # the newest late answer to an earlier SYNC (sync producer)
        self._late_excess = 0  # its backlog age beyond the arrival bound (see _count_tpdo)
        # which SYNC a TPDO1 answers (sync producer): SYNCs sent, TPDO1s received, the count offset (lost
        # answers), the backlog age of the newest TPDO1 and how many in a row did not shrink it
        self._n_sync = 0
        self._n_rx = 0
        self._lost: int | None = None
        self._rx_excess = 0
        self._excess_run = 0
        self._rx_burst = 0  # TPDO1s received since the last read()
        self._prev_excess = 0  # the backlog age of the sample the last read() returned
        self._hb_silent_in_gap = False  # the drive's heartbeat fell silent since its answers were last on time
        # motion evidence for a count gap (_looks_old): the last fresh sample's SYNC number and counts, the
        # velocity between the last two [counts per period], the raw position of the TPDO1 being counted, and
        # how many gaps in a row the evidence kept as a backlog
        self._ref_idx: int | None = None
        self._ref_counts = 0
        self._v_cpp: float | None = None
        self._v_last: float | None = None
        self._rx_raw = 0
        self._old_run = 0
        self._cycle = 0
        # device-time pacing (behind()): TPDO1 drained while the loop waited, wall slots waited since the last
        # TPDO1, a drive heartbeat seen meanwhile
        self._paced_got: tuple[int, int] | None = None
        self._wait_slots = 0
        self._hb_in_wait = False
        self._cw = int(Controlword.SHUTDOWN)
        self._synced = False
        self._unread = False
        self._missed = 0
        self._late_run = 0
        self._hb_age = 0
        self._hb_seen = False
        self._pending: DeviceFault | None = None
        self._last_emcy = 0
        self._have_pos = False
        self._raw = 0
        self._counts = 0
        self._skipped_since_good = 0
        self.statusword = 0
        self.cycles = 0
        self.missed_total = 0

    # ------------------------------------------------------------------ lifecycle hooks
    def _do_open(self) -> None:
        eds = Path(self.cfg.eds_file) if self.cfg.eds_file else DEFAULT_EDS
        self._open_canopen(self.cfg.can, "drive.can", self.cfg.node_id, eds, self.cfg.sdo_timeout_s)

    def _do_close(self) -> None:
        if self._bus is not None and self._state is DeviceState.ENABLED:
            try:  # best effort: leave the drive switched off
                self._bus.send(can.Message(arbitration_id=self._rpdo1_id, data=_RPDO1.pack(Controlword.SHUTDOWN, 0),
                                           is_extended_id=False))
            except (can.CanError, OSError):
                pass
        self._teardown()

    # ------------------------------------------------------------------ configure (SDO)
    def _sdo_write(self, index: int, sub: int, fmt: str, value: int, what: str) -> None:
        from canopen.sdo.exceptions import SdoError

        try:
            self._node.sdo.download(index, sub, struct.pack(fmt, value))
        except SdoError as exc:
            raise DriverInitError(
                f"{self.name}: configure: writing {what} 0x{index:04X}:{sub:02X} = 0x{value & 0xFFFFFFFF:X} failed: "
                f"{explain_sdo_error(exc, self.cfg.sdo_timeout_s, 'drive.sdo_timeout_s')}"
            ) from exc
        except (can.CanError, OSError) as exc:
            raise DriverInitError(f"{self.name}: configure: CAN error writing {what} 0x{index:04X}:{sub:02X}: "
                                  f"{' '.join(str(exc).split())}; check the CAN interface") from exc

    def _sdo_read(self, index: int, sub: int, fmt: str, what: str) -> int:
        from canopen.sdo.exceptions import SdoError

        try:
            data = self._node.sdo.upload(index, sub)
            return int(struct.unpack_from(fmt, data)[0])
        except SdoError as exc:
            raise DriverInitError(f"{self.name}: configure: reading {what} 0x{index:04X}:{sub:02X} failed: "
                                  f"{explain_sdo_error(exc, self.cfg.sdo_timeout_s, 'drive.sdo_timeout_s')}") from exc
        except struct.error as exc:
            raise DriverInitError(f"{self.name}: configure: reading {what} 0x{index:04X}:{sub:02X}: answer too "
                                  f"short for its data type; check the drive's EDS") from exc
        except (can.CanError, OSError) as exc:
            raise DriverInitError(f"{self.name}: configure: CAN error reading {what} 0x{index:04X}:{sub:02X}: "
                                  f"{' '.join(str(exc).split())}; check the CAN interface") from exc

    def _sdo_read_optional(self, index: int, sub: int, fmt: str, what: str) -> int | None:
        """Like :meth:`_sdo_read`, None when the drive does not have the object (abort 0x06020000/0x06090011)."""
        from canopen.sdo.exceptions import SdoAbortedError

        try:
            data = self._node.sdo.upload(index, sub)
            return int(struct.unpack_from(fmt, data)[0])
        except SdoAbortedError as exc:
            if exc.code in (0x06020000, 0x06090011):
                return None
            raise DriverInitError(f"{self.name}: configure: reading {what} 0x{index:04X}:{sub:02X} failed: "
                                  f"{explain_sdo_error(exc, self.cfg.sdo_timeout_s, 'drive.sdo_timeout_s')}") from exc
        except struct.error:
            return None

    def _map_pdo(self, comm: int, mapping: int, cob_id: int, entries: list[int], what: str) -> pdo_codec.PdoLayout:
        """Write one PDO's mapping and communication parameters, read them back and compare; the layout of
        the cyclic codec comes from the mapping as read back (and the object dictionary's data types)."""
        writes, valid = cob_id_writes(self._sdo_read(comm, 1, "<I", f"{what} COB-ID"), cob_id)
        for value, step in writes:
            self._sdo_write(comm, 1, "<I", value, f"{what} {step}")
        self._sdo_write(mapping, 0, "<B", 0, f"{what} mapping count")
        for i, entry in enumerate(entries, 1):
            self._sdo_write(mapping, i, "<I", entry, f"{what} mapping entry {i}")
        self._sdo_write(mapping, 0, "<B", len(entries), f"{what} mapping count")
        self._sdo_write(comm, 2, "<B", 1, f"{what} transmission type (synchronous)")
        self._sdo_write(comm, 1, "<I", valid, f"{what} COB-ID (enable)")
        # read back: a drive may accept a download and keep another value (or map a different length)
        got = [self._sdo_read(mapping, i, "<I", f"{what} mapping entry {i}") for i in range(1, len(entries) + 1)]
        n = self._sdo_read(mapping, 0, "<B", f"{what} mapping count")
        cob = self._sdo_read(comm, 1, "<I", f"{what} COB-ID")
        tt = self._sdo_read(comm, 2, "<B", f"{what} transmission type")
        want = ([f"0x{e:08X}" for e in entries], len(entries), cob_id, 1)
        if (got, n, cob & 0x9FFFFFFF, tt) != (entries, len(entries), cob_id, 1):
            raise DriverInitError(
                f"{self.name}: configure: {what} read back differs from what was written: mapping "
                f"{[f'0x{e:08X}' for e in got]} count {n} COB-ID 0x{cob:08X} type {tt}, wrote {want[0]} count "
                f"{want[1]} COB-ID 0x{cob_id:08X} type 1; check the drive's PDO mapping rules in its manual"
            )
        try:
            return pdo_codec.PdoLayout.from_mapping(got, self._od_type)
        except ValueError as exc:
            raise DriverInitError(f"{self.name}: configure: {what} {exc}") from exc

    def _od_type(self, index: int, sub: int) -> int | None:
        """CiA 301 data type of object ``index:sub`` in the drive's EDS (None: not there)."""
        var = self._node.object_dictionary.get_variable(index, sub) if self._node is not None else None
        dt = getattr(var, "data_type", None)
        return int(dt) if isinstance(dt, int) else None

    def _disable_pdo(self, comm: int, what: str) -> None:
        """Invalidate a PDO we do not use, on the COB-ID the drive has for it (bits 0-29 must not change while
        it is valid). Not on the drive: nothing to do. An RPDO the drive refuses to invalidate is a start-up
        failure (another node's frame on its COB-ID would command the drive); a TPDO only costs bus load."""
        if self._node is None or comm not in self._node.object_dictionary:
            return
        cur = self._sdo_read_optional(comm, 1, "<I", f"{what} COB-ID")
        if cur is None or cur & PDO_DISABLED:
            return
        try:
            self._sdo_write(comm, 1, "<I", cur | PDO_DISABLED, f"{what} COB-ID (disable unused PDO)")
        except DriverInitError as exc:
            if comm < 0x1800:
                raise
            log.warning("%s (it keeps sending)", exc)

    def _do_configure(self) -> None:
        self._start_notifier()
        nid = self.cfg.node_id
        with pumping(None if self._sdo_lockstep else self._pump, self.name):
            self._node.nmt.send_command(0x80)  # enter PRE-OPERATIONAL (PDOs off while remapping)
            dtype = self._sdo_read(0x1000, 0, "<I", "device type")
            if dtype & 0xFFFF != 402:
                raise DriverInitError(
                    f"{self.name}: device type 0x1000 = 0x{dtype:08X} is not a CiA 402 drive (profile {dtype & 0xFFFF})"
                )
            modes = self._sdo_read(0x6502, 0, "<I", "supported drive modes")
            if not modes & SUPPORTED_CST_BIT:
                raise DriverInitError(
                    f"{self.name}: drive does not support cyclic synchronous torque (0x6502 = 0x{modes:08X})"
                )
            self._write_cycle_period()
            self._sdo_write(0x1017, 0, "<H", round(self.cfg.heartbeat_producer_s * 1000), "producer heartbeat [ms]")
            consumer = (self.cfg.controller_node_id << 16) | round(self.cfg.drive_consumer_timeout_s * 1000)
            self._sdo_write(0x1016, 1, "<I", consumer, "consumer heartbeat time")
            tpdo1 = self._map_pdo(0x1800, 0x1A00, 0x180 + nid, list(pdo_codec.TPDO1_MAPPING), "TPDO1")
            tpdo2 = pdo_codec.TPDO2_LAYOUT
            if self.cfg.velocity:
                tpdo2 = self._map_pdo(0x1801, 0x1A01, 0x280 + nid, list(pdo_codec.TPDO2_MAPPING), "TPDO2")
            else:
                self._disable_pdo(0x1801, "TPDO2")
            for n in (2, 3):
                self._disable_pdo(0x1800 + n, f"TPDO{n + 1}")
            rpdo1 = self._map_pdo(0x1400, 0x1600, 0x200 + nid, list(pdo_codec.RPDO1_MAPPING), "RPDO1")
            self._use_layouts(tpdo1, tpdo2, rpdo1)
            for n in (1, 2, 3):
                self._disable_pdo(0x1400 + n, f"RPDO{n + 1}")
            self._read_max_torque()
            self._select_quick_stop()
            self._sdo_write(0x6060, 0, "<b", MODE_CST, "mode of operation (CST)")
            self._wait_mode(MODE_CST)
            self._node.nmt.send_command(0x01)  # NMT start: OPERATIONAL, PDOs run
        self._stop_notifier()  # pump mode: the loop thread reads the bus itself from now on
        self._reset_cyclic()
        self._rebooted = False
        self._link_dead = False
        self.drive_nmt_state = None  # the next heartbeat tells (PRE-OPERATIONAL ones came during configure)

    def _use_layouts(self, tpdo1: pdo_codec.PdoLayout, tpdo2: pdo_codec.PdoLayout,
                     rpdo1: pdo_codec.PdoLayout) -> None:
        """The cyclic codec from the layouts read back at configure (preallocated RPDO1 frame, unpackers)."""
        self._tpdo1_unpack = tpdo1.struct.unpack_from
        self._tpdo1_size = tpdo1.size
        self._tpdo2_unpack = tpdo2.struct.unpack_from
        self._tpdo2_size = tpdo2.size
        self._rpdo1 = pdo_codec.Rpdo1Encoder(self._rpdo1_id, rpdo1)

    def _write_cycle_period(self) -> None:
        """0x1006 = loop period; optional on a drive that only consumes SYNC (abort 0x06020000 → skipped)."""
        from canopen.sdo.exceptions import SdoAbortedError

        us = round(self._period_s * 1e6)
        try:
            self._node.sdo.download(0x1006, 0, struct.pack("<I", us))
        except SdoAbortedError as exc:
            if exc.code not in (0x06020000, 0x06090011):
                raise DriverInitError(f"{self.name}: configure: writing communication cycle period 0x1006:00 = "
                                      f"{us} µs failed: {explain_sdo_error(exc, self.cfg.sdo_timeout_s, 'drive.sdo_timeout_s')}") from exc
            log.info("%s: drive has no 0x1006 (communication cycle period): it follows SYNC only", self.name)
        except (can.CanError, OSError) as exc:
            raise DriverInitError(f"{self.name}: configure: CAN error writing 0x1006:00: "
                                  f"{' '.join(str(exc).split())}; check the CAN interface") from exc

    def _config_units(self) -> int:
        """``max_force_n`` in 0x6071 units (floor, within INT16; a float ratio such as 10 / 0.001 =
        9999.999… counts as 10000)."""
        units = self.cfg.max_force_n / self.cfg.force_per_unit_n
        return int(min(32767.0, units * (1.0 + 1e-12))) if math.isfinite(units) else 32767

    def _read_max_torque(self) -> None:
        """Honour the drive's max torque 0x6072 (optional object): the command clamp is the smaller limit.

        The master never writes 0x6072: it is the drive's current limit as its integrator set it (a master
        raising it would drive the motor beyond what the drive was set up for). The loop hands the resulting
        :attr:`force_limit_n` to the controller and to safety and warns when it is below their ``max_force_n``."""
        self._max_units = self._config_units()
        limit = self._sdo_read_optional(0x6072, 0, "<H", "max torque")
        self.drive_max_units = limit
        if limit is not None and limit < self._max_units:
            log.info("%s: drive max torque 0x6072 = %d (%.4g N) limits the command (max_force_n %.4g N)",
                     self.name, limit, limit * self.cfg.force_per_unit_n, self.cfg.max_force_n)
            self._max_units = limit

    def _select_quick_stop(self) -> None:
        """Write ``quick_stop_option_code`` to 0x605A (optional object). The fault reaction 0x605E is left to
        the drive: after a drive fault the loop releases at once (its power stage may be what failed).

        ``brakes_itself`` is True when the drive took a braking code (3, 4, 7, 8: slow down on the current /
        voltage limit, CiA 402 / IEC 61800-7-201), so the loop's fault reaction is the drive's quick stop at
        once; a drive without the object or refusing the value (any SDO abort) keeps its codes and
        ``brakes_itself`` False (the loop brakes over the bus)."""
        from canopen.sdo.exceptions import SdoAbortedError

        self.brakes_itself = False
        opt = self.cfg.quick_stop_option_code
        if opt is None:
            return
        try:
            self._node.sdo.download(0x605A, 0, struct.pack("<h", opt))
        except SdoAbortedError as exc:
            log.info("%s: quick stop option code 0x605A = %d refused (%s): the loop brakes over the bus",
                     self.name, opt, explain_sdo_error(exc))
            return
        self.brakes_itself = opt in (3, 4, 7, 8)

    def _wait_mode(self, mode: int) -> None:
        """Poll 0x6061 until it shows ``mode``, for at most ``mode_switch_timeout_s`` (wall clock: SDO time)."""
        deadline = time.monotonic() + self.cfg.mode_switch_timeout_s
        while True:
            shown = self._sdo_read(0x6061, 0, "<b", "mode of operation display")
            if shown == mode:
                return
            if time.monotonic() >= deadline:
                raise DriverInitError(
                    f"{self.name}: configure: modes of operation display 0x6061:00 = {shown} still not {mode} (CST) "
                    f"{self.cfg.mode_switch_timeout_s:g} s after 0x6060 = {mode}; check that the drive allows "
                    f"CST in its present state, or raise drive.mode_switch_timeout_s"
                )
            time.sleep(0.002)

    # ------------------------------------------------------------------ frame handling
    def _handle(self, msg: can.Message) -> tuple[int, int] | None:
        """Process one received frame; return (statusword, raw position) for TPDO1."""
        if msg.is_error_frame:
            if error_frame_is_bus_off(msg):
                self._bus_off = True
                self._note(DeviceFault(FaultKind.BUS_OFF, "CAN controller reports bus-off"))
            else:
                self._note(DeviceFault(FaultKind.BUS_ERROR, f"CAN error frame class 0x{msg.arbitration_id:08X}"))
            return None
        cid = msg.arbitration_id
        if msg.is_extended_id:
            return None  # CANopen CC uses 11-bit ids: a 29-bit frame is never one of ours
        if cid == self._tpdo1_id:
            self._bus_off = False
            data = msg.data
            if len(data) >= self._tpdo1_size:
                got = self._tpdo1_unpack(data)  # (statusword, raw position)
                self._rx_raw = got[1]
                self._count_tpdo()
                self._wait_slots = 0
                return got
            self._note(DeviceFault(FaultKind.BUS_ERROR, f"TPDO1 too short ({len(data)} bytes, need "
                                                        f"{self._tpdo1_size})"))
        elif cid == self._tpdo2_id and len(msg.data) >= self._tpdo2_size:
            self.velocity_m_s = self._tpdo2_unpack(msg.data)[0] * self.cfg.velocity_resolution_m_s
        elif cid == self._emcy_id and len(msg.data) >= 3:
            code, reg, _ = _EMCY.unpack(bytes(msg.data[:8]).ljust(8, b"\0"))
            if code != 0:
                self._last_emcy = code
                self._note(DeviceFault(FaultKind.EMCY, f"EMCY error register 0x{reg:02X}", code))
        elif cid == self._hb_id and msg.data:
            self._hb_age = 0
            self._hb_in_wait = self._wait_slots > 0
            self._hb_seen = True
            self._bus_off = False
            nmt = msg.data[0] & 0x7F
            self.drive_nmt_state = nmt
            if nmt == 0:
                self._rebooted = True  # boot-up: default PDOs, PRE-OPERATIONAL; fault_reset() re-configures
                if self._state is DeviceState.ENABLED:
                    self._note(DeviceFault(FaultKind.HEARTBEAT_LOST, "drive sent boot-up (it was reset)"))
            elif nmt != 5 and self._state is DeviceState.ENABLED:
                self._note(DeviceFault(FaultKind.HEARTBEAT_LOST, f"drive left OPERATIONAL (NMT state {nmt})"))
        elif cid == self._rpdo1_id:
            # we never receive our own frames: another node sends our RPDO (a second master or a spoofed frame)
            self._note(DeviceFault(FaultKind.BUS_ERROR, f"second sender of our RPDO1 COB-ID 0x{cid:03X} on the bus "
                                                        f"(another master or a foreign frame)"))
        elif cid == SYNC_COB_ID and self.cfg.sync_producer:
            self._note(DeviceFault(FaultKind.BUS_ERROR, "second SYNC producer on the bus (COB-ID 0x080): "
                                                        "set drive.sync_producer false if another node produces SYNC"))
        return None

    def _count_tpdo(self) -> None:
        """Tie a received TPDO1 to the SYNC it answers (sync producer; module docstring, "Sample age").

        The j-th TPDO1 (transmission type 1: one per SYNC, in order) answers the j-th SYNC, less the answers
        lost on the way: ``c = n − j`` (n = SYNCs sent when it arrived) is its age at arrival plus the lost
        ones. The lost count ``L`` is the smallest ``c`` seen, raised to ``c`` when ``c − L`` > 0 did not shrink
        over ``LOST_AFTER_TPDOS`` TPDOs in a row (a drive working off a backlog answers faster than SYNC comes,
        so its ``c`` falls; a lost answer leaves it standing). ``_rx_excess = c − L`` is the backlog age.
        """
        self._n_rx += 1
        self._rx_burst += 1
        c = self._n_sync - self._n_rx
        lost = self._lost
        if lost is None or c <= lost:
            self._lost, e, self._excess_run = c, 0, 0
            self._hb_silent_in_gap = False
            self._old_run = 0
        else:
            e = c - lost
            self._excess_run = self._excess_run + 1 if e >= self._rx_excess else 0
            if (self._excess_run >= (LOST_AFTER_TPDOS if self._may_be_lost(e) else LOST_BLOCK_AFTER_TPDOS)
                    and not self._looks_old(self._rx_raw, e, self._n_sync)):
                # answers lost (or a lasting lag: then arrival time only)
                self._lost, e, self._excess_run = c, 0, 0
        self._rx_excess = e

    def _looks_old(self, raw: int, b: int, now: int) -> bool | None:
        """Motion evidence on a count gap of ``b`` answers (module docstring, "Sample age"): True when the TPDO1's
        position ``raw`` is nearer where the stage was b SYNCs before SYNC number ``now`` (the newest it can answer
        by its arrival) than where it was at ``now``, extrapolated from the
        last fresh samples at their SYNC numbers; False when the stage is too slow to tell (|v|·b below
        ``AGE_EVIDENCE_COUNTS``), when its velocity is not steady (the last two intervals disagree by more than
        20 %: a glitch, a break-away, a reversal), or after ``AGE_EVIDENCE_RUNS`` such verdicts since
        the last answer without a gap (then the counting rule decides: a stage that stopped dead must not look
        old for ever). None (falsy) in those cases: no evidence either way."""
        v, ref = self._v_cpp, self._ref_idx
        if (v is None or ref is None or b <= 0 or abs(v) * b < AGE_EVIDENCE_COUNTS
                or self._old_run >= AGE_EVIDENCE_RUNS):
            return None
        counts = self._counts + (((raw - self._raw + 0x80000000) & 0xFFFFFFFF) - 0x80000000)
        p_now = self._ref_counts + v * (now - ref)
        old = abs(counts - (p_now - v * b)) < abs(counts - p_now)
        self._old_run = self._old_run + 1 if old else 0
        return old

    def _may_be_lost(self, b: int) -> bool:
        """Whether a count gap of ``b`` answers may be taken for lost frames (module docstring, "Sample age")."""
        return b <= MAX_LOST_ANSWERS or not self._hb_silent_in_gap

    def _note(self, fault: DeviceFault) -> None:
        if self._pending is None:
            self._pending = fault

    def _drain(self) -> tuple[int, int] | None:
        """Handle every frame that has arrived; return the newest TPDO1 among them (None if none)."""
        bus = self._bus
        assert bus is not None
        got: tuple[int, int] | None = None
        if self._link_dead:
            return None
        while True:
            try:
                msg = bus.recv(0.0)
            except can.CanError as exc:
                raise DriverIOError(f"{self.name}: CAN receive failed: {exc}") from exc
            if msg is None:
                return got
            got = self._handle(msg) or got

    def _send(self, msg: can.Message) -> None:
        try:
            self._bus.send(msg)  # type: ignore[union-attr]
        except (can.CanError, OSError) as exc:
            self._note(DeviceFault(FaultKind.BUS_ERROR, f"transmit failed: {exc}"))

    # ------------------------------------------------------------------ cyclic API
    def sync(self) -> None:
        """Drain stale frames, send SYNC and (every N cycles) the controller heartbeat. Real-time safe."""
        if self._state is not DeviceState.ENABLED:  # (the cycle's usual state, checked first)
            self._require(DeviceState.CONFIGURED, DeviceState.ENABLED, DeviceState.FAULT)
        if self._pump is not None:
            self._pump()
        got = self._drain()  # TPDOs that answered an earlier SYNC: stale for read() ...
        if self._paced_got is not None:  # (one drained while the loop waited for it: behind())
            got = got or self._paced_got
            self._paced_got = None
        self._late = None
        self._late_excess = self._rx_excess
        if not self.cfg.sync_producer:
            self._held = got  # ... unless another node produces SYNC: its newest answer may already be here
        if self._unread:  # ... but the answer to the previous SYNC when only write() ran in that cycle
            self._unread = False
            self._rx_burst = 0
            self._evaluate(got)
        elif self.cfg.sync_producer:
            self._late = got  # ... kept as a late sample (age 1) in case this SYNC's answer is late too
        if self._cycle % self._hb_every == 0:
            self._send(self._hb_msg)
        if self.cfg.sync_producer:
            self._send(self._sync_msg)
            self._n_sync += 1
        self._cycle += 1
        self._hb_age += 1
        if self._hb_silent_cycles and self._hb_age > self._hb_silent_cycles:
            self._hb_silent_in_gap = True
        self._synced = True

    def behind(self, unanswered: int, slots: int) -> bool:
        """Device-time pacing (``loop.pace_cycles``): True when ``unanswered`` or more of our SYNCs have no answer
        yet, so the loop should not start a cycle (no SYNC, no RPDO) in this slot. Real-time safe.

        For a drive whose plant advances one period per SYNC (the HIL's ``stagectl sim-plant``, ``loop.device_time``):
        a drive process held off the CPU then neither answers nor moves its plant, and the loop's time waits with it
        instead of sending SYNCs (and forces) it cannot see answered: each of those is one period of the plant run
        blind once the drive works them off. Meanwhile this drains the bus (an answer arriving is kept for the next
        :meth:`sync` as its late sample), sends the controller heartbeat on its wall-clock schedule and ages the
        drive's heartbeat by ``slots`` (wall slots since the last call: 1 + skipped). It stops waiting (False) when
        the drive's heartbeat came during the wait (the drive runs: answers were lost, not delayed; the loop's
        stale limits judge them as usual), at once when a fault was noted meanwhile (bus error, EMCY, a closed
        socketcand link: the next :meth:`read` latches it) and, with a ``MISSED_FRAME`` fault for the next :meth:`read`, after
        ``max_missed`` wall slots without any answer (a dead drive process).
        """
        if self._state is not DeviceState.ENABLED or not self.cfg.sync_producer or unanswered <= 0:
            return False
        if self._pump is not None:
            self._pump()
        got = self._drain()
        if got is not None:
            self._paced_got = got
        lost = self._lost or 0
        if self._n_sync - self._n_rx - lost < unanswered:
            self._wait_slots = 0
            self._hb_in_wait = False
            return False
        if self._pending is None and not self._link_dead and link_closed(self._bus):  # type: ignore[arg-type]
            self._link_dead = True  # the socketcand server went away while we waited: nothing will answer
            self._note(DeviceFault(FaultKind.DISCONNECTED, "CAN link closed by the socketcand server"))
        if self._pending is not None:  # a fault came (or the link died) during the wait: the next cycle's
            return False  # read() latches it now, not after max_missed wall slots
        if self._hb_in_wait:  # the drive's process runs: its answers were lost, stop waiting for them (the
            self._hb_in_wait = False  # wall slots waited still count towards max_missed until an answer comes)
            return False
        for _ in range(slots):
            if self._cycle % self._hb_every == 0:
                self._send(self._hb_msg)
            self._cycle += 1
        self._hb_age += slots
        self._wait_slots += slots
        if self._wait_slots >= self.cfg.max_missed:
            self._note(DeviceFault(FaultKind.MISSED_FRAME, f"no TPDO for {self._wait_slots} cycles while the loop "
                                                           f"waited for the drive (device time)"))
            self._wait_slots = 0
            return False
        return True

    def _wait_tpdo(self) -> tuple[int, int] | None:
        bus = self._bus
        assert bus is not None
        got: tuple[int, int] | None = None
        if self._link_dead:
            return None
        try:
            if self._pump is not None:
                self._pump()
                while (msg := bus.recv(0.0)) is not None:
                    r = self._handle(msg)
                    if r is not None:
                        got = r
                return got
            deadline = time.monotonic() + self._rx_wait_s
            while got is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                msg = bus.recv(left)
                if msg is None:
                    break
                got = self._handle(msg) or got
            while (msg := bus.recv(0.0)) is not None:  # newest wins (a late frame may precede it)
                got = self._handle(msg) or got
            if got is None and link_closed(bus):
                self._link_dead = True  # a closed socketcand link: recv would return at once forever (busy spin)
                self._note(DeviceFault(FaultKind.DISCONNECTED, "CAN link closed by the socketcand server"))
        except can.CanError as exc:
            raise DriverIOError(f"{self.name}: CAN receive failed: {exc}") from exc
        return got

    def read(self) -> Measurement:
        """Measurement sampled at this cycle's SYNC (``fresh=False`` if the TPDO missed). Real-time safe."""
        if self._state is not DeviceState.ENABLED:  # (the cycle's usual state, checked first)
            self._require(DeviceState.CONFIGURED, DeviceState.ENABLED, DeviceState.FAULT)
        if not self._synced:
            raise DriverError(f"{self.name}: read() before sync() in this cycle")
        self._synced = False
        got = self._wait_tpdo()
        age, excess = 0, self._rx_excess
        if got is None and self._held is not None:
            got = self._held
        elif got is None and self._late is not None:
            got, age = self._late, 1  # arrived before this SYNC was sent: one period old or more ...
            excess = self._late_excess
        unsure = False
        if got is not None and self.cfg.sync_producer and excess > 0:  # ... plus the backlog counted
            verdict: bool | None = True
            if (self._rx_burst == 1 and self._may_be_lost(excess)  # one answer in the cycle: answers were lost
                    and not (verdict := self._looks_old(got[1], excess, self._n_sync - age))):
                # (a backlog comes in bursts; a long one behind a silent heartbeat stays a backlog)
                assert self._lost is not None
                self._lost += excess
                self._rx_excess = self._late_excess = self._excess_run = 0
                if verdict is None and excess >= 2:  # nothing tells lost from old: this one as old as a backlog
                    age += excess  # would make it (>= 2: the loop holds on it); the next answer counts as on time
                    unsure = True
            elif age + excess >= 2 or self._prev_excess == excess + 1:  # ≥ 2 old, or a backlog shrinking
                age += excess
            else:  # 1 period old, or on time after lost answers and a late one: not told apart, arrival only
                excess = 0
        self._prev_excess = excess if got is not None else 0
        self._rx_burst = 0
        self._held = self._late = None
        m = self._evaluate(got, age)
        if got is not None and self.cfg.sync_producer and not unsure:  # the motion evidence's reference
            idx = self._n_sync - age
            if self._ref_idx is not None and idx > self._ref_idx:
                # the velocity counts as evidence only when two intervals in a row agree (a position glitch,
                # a break-away or a reversal leaves it out)
                v = (self._counts - self._ref_counts) / (idx - self._ref_idx)
                vp = self._v_last
                self._v_cpp = v if vp is not None and abs(v - vp) <= max(AGE_EVIDENCE_COUNTS, 0.2 * abs(v)) \
                    and v * vp > 0 else None
                self._v_last = v
            if self._ref_idx is None or idx > self._ref_idx:
                self._ref_idx, self._ref_counts = idx, self._counts
        return m

    def _evaluate(self, got: tuple[int, int] | None, age: int = 0) -> Measurement:
        self.cycles += 1
        fault: DeviceFault | None = None
        fresh = got is not None
        if got is not None and age == 0:
            self._late_run = 0
        else:
            self._late_run += 1
        if got is not None:
            sw, raw = got
            self.statusword = sw
            self._missed = 0
            if self._have_pos:
                counts = self._counts + (((raw - self._raw + 0x80000000) & 0xFFFFFFFF) - 0x80000000)  # unwrap32
                step = abs(counts - self._counts)
                if step > self._max_step_counts * (1 + self._skipped_since_good):
                    fault = DeviceFault(
                        FaultKind.SENSOR_ERROR,
                        f"position jumped {step * self.cfg.resolution_m:.3g} m in one cycle "
                        f"(> max_speed_m_s {self.cfg.max_speed_m_s:g} m/s)",
                    )
            else:
                counts = raw
                self._have_pos = True
            self._raw, self._counts = raw, counts
            self._skipped_since_good = 0
            if sw & STATUSWORD_FAULT:
                fault = DeviceFault(FaultKind.DRIVE_FAULT, f"drive in {self.drive_state.value}", self._last_emcy)
        else:
            self._missed += 1
            self.missed_total += 1
            self._skipped_since_good += 1
            if self._missed >= self.cfg.max_missed:
                fault = DeviceFault(
                    FaultKind.MISSED_FRAME,
                    f"no TPDO after SYNC for {self._missed} consecutive cycles",
                )
        if fault is None and self._late_run >= self.cfg.max_late_cycles:
            fault = DeviceFault(
                FaultKind.MISSED_FRAME,
                f"no TPDO in time after SYNC for {self._late_run} consecutive cycles "
                f"(max_late_cycles; late ones used)",
            )
        if self._pending is not None and (fault is None or fault.kind is FaultKind.MISSED_FRAME):
            fault = self._pending
        self._pending = None
        if fault is None and self.cfg.heartbeat_producer_s > 0 and self._hb_age > self._hb_timeout_cycles:
            fault = DeviceFault(
                FaultKind.HEARTBEAT_LOST,
                f"no drive heartbeat for {self._hb_age} cycles ({self._hb_age * self._period_s:.3g} s)",
            )
        if fault is not None and self._state is not DeviceState.CONFIGURED:
            self._latch(fault)
        # position_m, fresh, counts, status, fault, age_cycles
        return Measurement(self._counts * self.resolution_m, fresh, self._counts, self.statusword, fault, age)

    @property
    def force_limit_n(self) -> float:
        """The largest force the drive is commanded [N]: ``max_force_n`` and the drive's max torque 0x6072."""
        return self._max_units * self.cfg.force_per_unit_n

    @property
    def force_limit_source(self) -> str:
        """What sets :attr:`force_limit_n`, for the loop's start-up warning."""
        lim = self.drive_max_units
        if lim is not None and lim == self._max_units:
            return (f"the drive's max torque 0x6072 = {lim} units x force_per_unit_n "
                    f"{self.cfg.force_per_unit_n:g} N")
        if self._max_units == 32767:
            return f"the drive's torque range 32767 units x force_per_unit_n {self.cfg.force_per_unit_n:g} N"
        return "io.drive.max_force_n"

    def torque_units(self, force_n: float) -> int:
        """Force [N] → 0x6071 units: ``round(force_n / force_per_unit_n)``, clamped (NaN → 0)."""
        if force_n != force_n:
            return 0
        u = round(force_n / self.cfg.force_per_unit_n) if math.isfinite(force_n) else (
            self._max_units if force_n > 0 else -self._max_units
        )
        return max(-self._max_units, min(self._max_units, u))

    def write(self, force_n: float) -> None:
        """Send RPDO1 (controlword, target torque) for the next period. Real-time safe.

        After a latched fault or ``quick_stop()`` the RPDO carries quick stop and zero torque. If ``read()``
        was not called in this cycle (another device is the position sensor), the drive's answer to this
        SYNC is evaluated at the next ``sync()`` (whatever arrived within the period, no waiting here), so
        drive faults (statusword, EMCY, heartbeat, missed TPDOs) are still latched, one cycle later.
        """
        if self._synced and self._state in (DeviceState.ENABLED, DeviceState.FAULT):
            self._synced = False
            self._unread = True
        if self._state is DeviceState.ENABLED and self._cw == Controlword.ENABLE_OPERATION:
            self._send_rpdo(self._cw, self.torque_units(force_n))
        elif self._state is DeviceState.FAULT:
            self._send_rpdo(Controlword.QUICK_STOP, 0)
        elif self._state in (DeviceState.ENABLED, DeviceState.CONFIGURED):
            self._send_rpdo(self._cw, 0)
        else:
            raise DriverError(f"{self.name}: write() needs an open, configured drive (state {self._state.value})")

    def _send_rpdo(self, cw: int, torque: int) -> None:
        self._send(self._rpdo1.encode(cw, torque))

    def quick_stop(self) -> None:
        """Controlword QUICK STOP with zero torque, now and in every following ``write``. Real-time safe."""
        self._cw = int(Controlword.QUICK_STOP)
        if self._bus is not None:
            self._send_rpdo(self._cw, 0)

    def persisting_faults(self) -> tuple[str, ...]:
        """Faults whose cause is present now: link closed, bus-off with nothing heard since, drive heartbeat
        still missing, drive still in FAULT after a fault reset (docs/canopen.md). Real-time safe: it first
        handles the frames that have arrived (non-blocking), so a heartbeat that came back counts; call it from
        the thread that cycles the drive."""
        if self._bus is not None and not self._link_dead and self._state is not DeviceState.OPEN:
            try:
                self._drain()
            except DriverIOError:
                pass
        out: list[str] = []
        if self._link_dead:
            out.append("disconnected: CAN link closed")
        if self._bus_off:
            out.append("bus_off: no frame from the drive since the bus-off error frame")
        if self.cfg.heartbeat_producer_s > 0 and self._hb_age > self._hb_timeout_cycles:
            out.append(f"heartbeat_lost: no drive heartbeat for {self._hb_age * self._period_s:.3g} s")
        if self._stuck_in_fault and self.statusword & STATUSWORD_FAULT:
            out.append("drive_fault: drive stays in FAULT after fault reset (cause still present)")
        return tuple(out)

    # ------------------------------------------------------------------ state machine (cycles)
    def _step_cycles(self, choose: Callable[[State402 | None], int | None], what: str) -> State402:
        """Run SYNC/TPDO/RPDO cycles, sending ``choose(state)`` until it returns None."""
        n_max = max(8, self.timing.cycles(self.cfg.state_timeout_s))
        self._unread = False  # state changes read the statusword themselves
        next_t = time.monotonic()
        state: State402 | None = None
        silent = 0
        for _ in range(n_max):
            if self._link_dead:
                raise DriverIOError(f"{self.name}: {what}: CAN link closed; check the socketcand server / adapter")
            self.sync()
            got = self._wait_tpdo()
            self._synced = False
            silent = 0 if got is not None else silent + 1
            if silent >= max(2, self.timing.cycles(self.cfg.no_answer_timeout_s)):
                raise DriverTimeoutError(
                    f"{self.name}: {what}: drive not answering (no TPDO for {silent} cycles); check its power, "
                    f"the bus (bus-off?) and that it is OPERATIONAL"
                )
            if got is not None:
                self.statusword = got[0]
                state = State402.from_statusword(got[0])
                if not self._have_pos:
                    self._raw = self._counts = got[1]
                    self._have_pos = True
                else:
                    self._counts = unwrap32(self._raw, self._counts, got[1])
                    self._raw = got[1]
            cw = choose(state)
            if cw is None:
                return state  # type: ignore[return-value]
            self._cw = cw
            self._send_rpdo(cw, 0)
            if self._pump is None:
                next_t += self._period_s
                delay = next_t - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                else:
                    next_t = time.monotonic()
        raise DriverTimeoutError(
            f"{self.name}: {what} not reached within {self.cfg.state_timeout_s:g} s "
            f"(drive state {state.value if state else 'unknown: no TPDO'})"
        )

    def _do_enable(self) -> None:
        self._drain()
        self._pending = None
        self._last_emcy = 0

        def choose(state: State402 | None) -> int | None:
            if state is State402.OPERATION_ENABLED:
                return None
            if state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
                raise DriveFault(f"{self.name}: drive is in FAULT; call fault_reset()", self._last_emcy)
            if state is None:
                return int(Controlword.SHUTDOWN)
            return int(_TOWARDS_ENABLED[state])

        self._step_cycles(choose, "OPERATION ENABLED")
        self._cw = int(Controlword.ENABLE_OPERATION)
        self._missed = 0  # an EMCY that came while enabling stays pending: the first read() reports it

    def _do_disable(self) -> None:
        if self._bus is None:
            return

        def choose(state: State402 | None) -> int | None:
            if state in (State402.READY_TO_SWITCH_ON, State402.SWITCH_ON_DISABLED, State402.FAULT):
                return None
            return int(Controlword.SHUTDOWN)

        try:
            self._step_cycles(choose, "READY TO SWITCH ON")
        finally:
            self._cw = int(Controlword.SHUTDOWN)

    def _do_fault_reset(self) -> None:
        if self._link_dead:
            raise DriverIOError(f"{self.name}: fault reset: CAN link closed; check the socketcand server / adapter")
        self._drain()
        for attempt in (1, 2):
            if self._rebooted or (self.drive_nmt_state is not None and self.drive_nmt_state != 5):
                log.warning("%s: drive was reset (boot-up or NMT state %s): configuring it again", self.name,
                            self.drive_nmt_state)
                self._do_configure()
            self._pending = None
            self._missed = 0
            self._late_run = 0
            self._hb_age = 0
            sent_low = [False]

            def choose(state: State402 | None) -> int | None:
                if state is None:
                    return int(Controlword.DISABLE_VOLTAGE)
                if state not in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
                    return None
                if not sent_low[0]:  # fault reset acts on the rising edge of bit 7
                    sent_low[0] = True
                    return int(Controlword.DISABLE_VOLTAGE)
                sent_low[0] = False
                return int(Controlword.FAULT_RESET)

            try:
                self._step_cycles(choose, "fault reset (leave FAULT)")
                break
            except DriverTimeoutError:
                # another node stopped the drive (NMT) just before: the fault came from the missing TPDOs and
                # the heartbeat saying so arrived only while we waited for them; configure it again, once
                if attempt == 1 and (self._rebooted or self.drive_nmt_state not in (None, 5)):
                    continue
                self._stuck_in_fault = bool(self.statusword & STATUSWORD_FAULT)
                raise
        self._stuck_in_fault = False
        self._cw = int(Controlword.SHUTDOWN)
        self._pending = None
        self._last_emcy = 0
        self._missed = 0
        self._late_run = 0
