"""Our driver against an independent minimal CiA 402 slave, written here from CiA 301/402 on canopen's
``LocalNode`` with its own EDS (tests/canopen/data/minimal402.eds) and real-drive habits: the mode display 0x6061
follows 0x6060 only 20 ms (wall clock) later, there is no 0x1006 (a SYNC consumer only) and no 0x6072, the TPDO
defaults are event-driven, and a quick stop ramps for 30 ms of the slave's own clock before SWITCH ON DISABLED.
It shares no code with stagectl's virtual drive. The slave is pumped (lock-step): its clock advances 1 ms per SYNC.
"""

from __future__ import annotations

import struct
import threading
import time
from pathlib import Path

import can
import canopen
import pytest
from canopen.sdo.exceptions import SdoAbortedError

from stagectl.drivers import canbus
from stagectl.drivers.base import DeviceState, FaultKind
from stagectl.drivers.cia402 import Cia402Config, Cia402Drive
from stagectl.errors import DriverInitError

EDS = Path(__file__).parent / "data" / "minimal402.eds"
PERIOD_S = 0.001
_TYPES = {0x2: "b", 0x3: "h", 0x4: "i", 0x5: "B", 0x6: "H", 0x7: "I"}

# CiA 402 statusword coding of the states this slave uses
SOD, RTSO, SO, OE, QSA, FAULT = 0x0250, 0x0231, 0x0233, 0x0237, 0x0217, 0x0208


class MinimalSlave:
    """A minimal CiA 402 drive: NMT, SDO (LocalNode), SYNC-triggered TPDOs built from its mapping objects,
    RPDOs latched to the next SYNC, heartbeat producer on its own clock, EMCY, the power state machine."""

    def __init__(self, channel, node_id=1, mode_delay_s=0.02, ramp_s=0.03, refuse_map=None, misreport=None):
        self.id = node_id
        self.bus = canbus.open_bus({"interface": "virtual", "channel": channel})
        self.node = canopen.LocalNode(node_id, str(EDS))
        self.node._write_callbacks.remove(self.node.nmt.on_write)  # heartbeat on our own clock, not a thread
        self.node.add_write_callback(self._on_write)
        self.node.add_read_callback(self._on_read)
        self.node.sdo.network = self  # the SDO server answers through send_message
        self.lock = threading.Lock()
        self.mode_delay_s, self.ramp_s = mode_delay_s, ramp_s
        self.refuse_map, self.misreport = refuse_map, misreport
        self.nmt = 127
        self.clock_s = 0.0
        self.sw = SOD
        self.cw = 0
        self.mode, self.mode_shown, self.mode_at = 8, 8, 0.0
        self.torque = 0
        self.position = 0
        self.ramp_end = None
        self.latched = []
        self.mode_reads = 0
        self.next_hb = 0.0
        self.heartbeat = True
        self.syncs = 0
        self.error = 0
        self.send_message(0x700 + node_id, b"\x00")  # boot-up

    def close(self):
        canbus.close_bus(self.bus)

    def send_message(self, cid, data):
        self.bus.send(can.Message(arbitration_id=cid, data=bytes(data), is_extended_id=False))

    # ---------------------------------------------------------------- object dictionary hooks
    def _on_read(self, index, subindex, od):
        if index == 0x6061:
            self.mode_reads += 1
            if time.monotonic() - self.mode_at >= self.mode_delay_s:
                self.mode_shown = self.mode
            return self.mode_shown
        if index == 0x6041:
            return self.sw
        if index == 0x603F:
            return self.error
        if self.misreport and (index, subindex) == self.misreport[0]:
            return self.misreport[1]
        return None

    def _on_write(self, index, subindex, od, data):
        if index == 0x6060:
            self.mode, self.mode_at = struct.unpack("<b", data)[0], time.monotonic()
        elif index == 0x6040:
            self.controlword(struct.unpack("<H", data)[0])
        elif 0x1A00 <= index <= 0x1A01 and subindex >= 1 and self.refuse_map:
            if struct.unpack("<I", data)[0] >> 16 == self.refuse_map:
                raise SdoAbortedError(0x06040041)

    def _u(self, index, sub, fmt):
        return struct.unpack(fmt, self.node.get_data(index, sub))[0]

    # ---------------------------------------------------------------- CiA 402 state machine
    def controlword(self, cw):
        rising = cw & 0x80 and not self.cw & 0x80
        self.cw = cw
        st = self.sw
        if st == FAULT:
            if rising:
                self.sw, self.error = SOD, 0
                self.send_message(0x80 + self.id, struct.pack("<HB5x", 0, 0))
            return
        if st == QSA:
            if not cw & 0x02:
                self.sw = SOD
            return  # the ramp runs to its end (0x605A = 2)
        if not cw & 0x02:
            self.sw = SOD
        elif cw & 0x06 == 0x02:
            if st == OE:
                self.sw, self.ramp_end = QSA, self.clock_s + self.ramp_s
            else:
                self.sw = SOD
        elif cw & 0x87 == 0x06 and st in (SOD, SO, OE):
            self.sw = RTSO
        elif cw & 0x8F == 0x07 and st in (RTSO, OE):
            self.sw = SO
        elif cw & 0x8F == 0x0F and st in (SO, RTSO):
            self.sw = OE

    def fault(self, code):
        self.sw, self.error = FAULT, code
        self.send_message(0x80 + self.id, struct.pack("<HB5x", code, 0x03))

    # ---------------------------------------------------------------- frames
    def _pdo(self, comm, mapping):
        cob = self._u(comm, 1, "<I")
        if cob & 0x80000000:
            return None
        fields = []
        for i in range(1, self._u(mapping, 0, "<B") + 1):
            e = self._u(mapping, i, "<I")
            fields.append((e >> 16, (e >> 8) & 0xFF, _TYPES[self.node.object_dictionary[e >> 16].data_type]))
        return cob & 0x7FF, self._u(comm, 2, "<B"), fields

    def _value(self, index):
        return {0x6041: self.sw, 0x6064: self.position, 0x6061: self.mode_shown, 0x603F: self.error,
                0x606C: 0}.get(index, 0)

    def pump(self):
        with self.lock:
            while (msg := self.bus.recv(0.0)) is not None:
                self._frame(msg)
        return 0

    def _frame(self, msg):
        cid, data = msg.arbitration_id, bytes(msg.data)
        if msg.is_extended_id:
            return
        if cid == 0 and data[1] in (0, self.id):
            self.nmt = {1: 5, 2: 4, 0x80: 127}.get(data[0], self.nmt)
        elif cid == 0x600 + self.id:
            self.node.sdo.on_request(cid, data, 0.0)
        elif cid == 0x80:
            self._sync()
        elif self.nmt == 5:
            r = self._pdo(0x1400, 0x1600)
            if r and cid == r[0]:
                values = struct.unpack("<" + "".join(f for _, _, f in r[2]), data)
                self.latched = list(zip([i for i, _, _ in r[2]], values))

    def _sync(self):
        self.syncs += 1
        self.clock_s += PERIOD_S
        for index, value in self.latched:
            if index == 0x6040:
                self.controlword(value)
            elif index == 0x6071:
                self.torque = value
        self.latched = []
        if self.sw == QSA and self.clock_s >= self.ramp_end - 1e-9:
            self.sw = SOD
        if self.sw == OE:
            self.position += self.torque
        hb = self._u(0x1017, 0, "<H") * 1e-3
        if hb and self.heartbeat and self.clock_s >= self.next_hb - 1e-9:
            self.send_message(0x700 + self.id, bytes([self.nmt]))
            self.next_hb = self.clock_s + hb
        if self.nmt != 5:
            return
        for comm, mapping in ((0x1800, 0x1A00), (0x1801, 0x1A01)):
            r = self._pdo(comm, mapping)
            if r and 1 <= r[1] <= 240 and self.syncs % r[1] == 0:
                self.send_message(r[0], struct.pack("<" + "".join(f for _, _, f in r[2]),
                                                    *[self._value(i) for i, _, _ in r[2]]))


@pytest.fixture
def slave_and_driver(make_drive):
    made = []

    def make(**slave_kw):
        channel = f"stagectl-slave-{id(made):x}-{len(made)}"
        slave = MinimalSlave(channel, **slave_kw)
        made.append(slave)
        dut = make_drive({"interface": "virtual", "channel": channel}, period_s=PERIOD_S, eds_file=str(EDS),
                         heartbeat_producer_s=0.05, heartbeat_timeout_s=0.2)
        dut.set_pump(slave.pump)
        dut.open()
        return slave, dut

    yield make
    for s in made:
        s.close()


def test_configure_waits_for_mode_and_skips_missing_0x1006(slave_and_driver):
    slave, dut = slave_and_driver()
    dut.configure()
    assert slave.mode_shown == 10 and slave.mode_reads >= 2  # 0x6061 polled until the slow switch showed CST
    assert 0x1006 not in slave.node.object_dictionary
    assert slave._u(0x1800, 2, "<B") == 1 and slave._u(0x1A00, 2, "<I") == 0x60640020  # mapped, read back
    assert dut.drive_max_units is None  # no 0x6072: only max_force_n limits
    assert dut.force_limit_n == pytest.approx(32767 * dut.cfg.force_per_unit_n)  # (max_force_n inf: INT16 range)
    assert "torque range" in dut.force_limit_source
    slave.pump()
    assert slave.nmt == 5


def test_cyclic_operation_quick_stop_ramp_fault_reset_heartbeat(slave_and_driver):
    slave, dut = slave_and_driver()
    dut.configure()
    dut.enable()
    assert slave.sw == OE
    for _ in range(500):
        dut.sync()
        m = dut.read()
        assert m.fault is None and m.fresh
        dut.write(1.0)  # 100 units
    assert slave.torque == 100 and m.counts == slave.position == 499 * 100  # TPDO of this SYNC; last RPDO latched
    # quick stop: the slave ramps for 30 ms of its own clock; disable() waits it out
    dut.quick_stop()
    s0 = slave.syncs
    dut.disable()
    assert slave.sw in (SOD, RTSO) and slave.syncs - s0 >= 30
    dut.enable()
    slave.fault(0x2310)
    dut.sync()
    m = dut.read()
    assert m.fault.kind in (FaultKind.EMCY, FaultKind.DRIVE_FAULT) and dut.state is DeviceState.FAULT
    dut.fault_reset()
    assert slave.sw == SOD and dut.fault is None
    dut.enable()
    slave.heartbeat = False
    for k in range(400):
        dut.sync()
        m = dut.read()
        dut.write(0.0)
        if m.fault is not None:
            break
    assert m.fault.kind is FaultKind.HEARTBEAT_LOST
    assert any(p.startswith("heartbeat_lost") for p in dut.persisting_faults())


def test_mode_never_confirmed_is_one_clear_line(slave_and_driver):
    slave, dut = slave_and_driver(mode_delay_s=60.0)
    dut.cfg = dut.cfg.__class__(**{**dut.cfg.__dict__, "mode_switch_timeout_s": 0.05})
    with pytest.raises(DriverInitError) as ei:
        dut.configure()
    msg = str(ei.value)
    assert "\n" not in msg and "0x6061" in msg and "mode_switch_timeout_s" in msg and "0.05 s" in msg


def test_refused_mapping_is_one_clear_line(slave_and_driver):
    slave, dut = slave_and_driver(refuse_map=0x6064)
    with pytest.raises(DriverInitError) as ei:
        dut.configure()
    msg = str(ei.value)
    assert "\n" not in msg
    assert "0x1A00:02" in msg and "abort 0x06040041 (object cannot be mapped to the PDO)" in msg and "check" in msg


def test_mapping_read_back_mismatch_is_refused(slave_and_driver):
    slave, dut = slave_and_driver(misreport=((0x1A00, 2), 0x60630020))
    with pytest.raises(DriverInitError, match=r"TPDO1 read back differs .*0x60630020"):
        dut.configure()


def test_a_backlog_of_syncs_is_aged_by_the_independent_slave(slave_and_driver):
    """The slave's process held off for 4 SYNCs, then answering 2 queued SYNCs per cycle (its TPDOs arrive
    "on time" but answer older SYNCs): the driver's age of each sample equals the age the slave's own position
    tells (it moves 100 counts per SYNC it handles, so counts/100 numbers the SYNC a TPDO answers)."""
    from collections import deque

    slave, dut = slave_and_driver()
    dut.cfg = dut.cfg.__class__(**{**dut.cfg.__dict__, "max_missed": 10})
    dut.configure()
    dut.enable()
    queue: deque = deque()
    budget = [None]

    def throttled_pump():
        with slave.lock:
            while (msg := slave.bus.recv(0.0)) is not None:
                queue.append(msg)
            while queue:
                if queue[0].arbitration_id == 0x80 and budget[0] is not None:
                    if budget[0] <= 0:
                        break
                    budget[0] -= 1
                slave._frame(queue.popleft())
        return 0

    dut.set_pump(throttled_pump)
    ages, truth = [], []
    for k in range(40):
        budget[0] = 0 if 20 <= k < 24 else (2 if 24 <= k < 32 else None)
        dut.sync()
        m = dut.read()
        dut.write(1.0)  # 100 units: the slave moves 100 counts per SYNC it handles
        assert m.fault is None
        if m.fresh and k >= 5:
            ages.append(m.age_cycles)
            truth.append(k - m.counts // 100)
    offset = truth[0]  # (SYNCs before the torque reached the slave)
    truth = [t - offset for t in truth]
    assert max(truth) == 3  # the slave really answered 3-periods-old SYNCs
    assert ages == truth, (ages, truth)
