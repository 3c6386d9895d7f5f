"""Our driver against a strict CiA 402 slave written here from CiA 301/402 with raw frames only (no canopen, no
stagectl code): its own object dictionary and SDO server, and the habits of strict real drives:

* PDO mapping (0x16xx/0x1Axx) writable only in NMT PRE-OPERATIONAL and while the PDO is invalid (COB-ID bit
  31), entries only after sub-index 0 was written 0; transmission type only while invalid; COB-ID bits 0-29
  only while invalid; TPDO COB-ID bit 30 (no RTR) is fixed at 1;
* PDOs as stored by an earlier tool: TPDO1 valid on a non-default COB-ID, RPDO2 valid and mapping the
  controlword on 0x310;
* SDO answers 5 ms late (wall clock), aborts for missing objects/sub-indices, read-only objects, wrong sizes;
  no 0x605A, 0x6072 or 0x1006;
* boot-up frame, heartbeat producer on its own clock (1 ms per SYNC), EMCY on every fault, a drive that powers
  up in SWITCH ON DISABLED or in FAULT; 0x6007 = 1: NMT STOPPED while the power stage is on faults it.
"""

from __future__ import annotations

import struct
import threading
import time

import can
import pytest
from stagectl.drivers import canbus
from stagectl.drivers.base import DeviceState, FaultKind
from support import cycle_drive

from stagectl.errors import DriveFault, DriverInitError

NID = 3
PERIOD_S = 0.001
SOD, RTSO, SO, OE, QSA, FAULT = 0x0250, 0x0231, 0x0233, 0x0237, 0x0217, 0x0218
RO, RW, CONST = "ro", "rw", "const"
# mappable objects: (index, bits) -> direction
TX_MAPPABLE = {(0x6041, 16), (0x6064, 32), (0x606C, 32), (0x603F, 16), (0x6061, 8)}
RX_MAPPABLE = {(0x6040, 16), (0x6071, 16), (0x6060, 8)}


class StrictSlave:
    def __init__(self, channel, power_up_fault=0, sdo_delay_s=0.005):
        self.channel = channel
        self.bus = canbus.open_bus({"interface": "virtual", "channel": channel})
        self.lock = threading.Lock()
        self.sdo_delay_s = sdo_delay_s
        self.power_up_fault = power_up_fault
        self.log: list[tuple[str, int, int, int]] = []  # (what, index, sub, abort code) of refused writes
        self.power_on()

    def close(self):
        canbus.close_bus(self.bus)

    # ---------------------------------------------------------------- object dictionary
    def power_on(self):
        od = {(0x1000, 0): ["I", RO, 0x00020192], (0x1001, 0): ["B", RO, 0], (0x1017, 0): ["H", RW, 0],
              (0x1016, 0): ["B", CONST, 1], (0x1016, 1): ["I", RW, 0], (0x6502, 0): ["I", RO, 1 << 9],
              (0x6040, 0): ["H", RW, 0], (0x6041, 0): ["H", RO, SOD], (0x6060, 0): ["b", RW, 0],
              (0x6061, 0): ["b", RO, 0], (0x6064, 0): ["i", RO, 0], (0x606C, 0): ["i", RO, 0],
              (0x6071, 0): ["h", RW, 0], (0x603F, 0): ["H", RO, 0], (0x6007, 0): ["h", RW, 1]}
        stored = {0x1800: 0x40000190, 0x1801: 0xC0000280 + NID, 0x1802: 0xC0000380 + NID, 0x1803: 0xC0000480 + NID,
                  0x1400: 0x200 + NID, 0x1401: 0x310, 0x1402: 0x80000400 + NID, 0x1403: 0x80000500 + NID}
        maps = {0x1A00: [0x60410010], 0x1600: [0x60400010], 0x1601: [0x60400010]}  # by mapping index
        for comm, cob in stored.items():
            od[(comm, 0)] = ["B", CONST, 2]
            od[(comm, 1)] = ["I", RW, cob]
            od[(comm, 2)] = ["B", RW, 255 if comm >= 0x1800 else 254]
            entries = maps.get(comm + 0x200, [])
            od[(comm + 0x200, 0)] = ["B", RW, len(entries)]
            for i in range(1, 9):
                od[(comm + 0x200, i)] = ["I", RW, entries[i - 1] if i <= len(entries) else 0]
        self.od = od
        self.nmt = 127
        self.cw = 0
        self.syncs = 0
        self.next_hb = 0
        self.latched = None
        self.pending: list[tuple[float, bytes]] = []
        self.send(0x700 + NID, b"\x00")  # boot-up
        if self.power_up_fault:
            self.fault(self.power_up_fault)

    def get(self, index, sub=0):
        return self.od[(index, sub)][2]

    def set(self, index, sub, value):
        self.od[(index, sub)][2] = value

    # ---------------------------------------------------------------- frames out
    def send(self, cid, data):
        self.bus.send(can.Message(arbitration_id=cid, data=bytes(data), is_extended_id=False))

    def emcy(self, code, reg):
        self.set(0x1001, 0, reg)
        if self.nmt in (127, 5):  # no EMCY in STOPPED (CiA 301)
            self.send(0x80 + NID, struct.pack("<HB5x", code, reg))

    def fault(self, code):
        self.set(0x6041, 0, FAULT)
        self.set(0x603F, 0, code)
        self.emcy(code, 0x01 | (0x02 if code >> 12 == 2 else 0x10 if code >> 12 == 8 else 0))

    # ---------------------------------------------------------------- SDO server (expedited)
    def sdo(self, data):
        cs, index, sub = struct.unpack_from("<BHB", data)
        mux = data[1:4]

        def abort(code, what="write"):
            if what == "write":
                self.log.append((what, index, sub, code))
            return b"\x80" + mux + struct.pack("<I", code)

        if (index, sub) not in self.od:
            code = 0x06090011 if any(i == index for i, _ in self.od) else 0x06020000
            return abort(code, "read" if cs >> 5 == 2 else "write")
        fmt, access, value = self.od[(index, sub)]
        if cs >> 5 == 2:  # upload
            raw = struct.pack("<" + fmt, value)
            return bytes([0x43 | (4 - len(raw)) << 2]) + mux + raw.ljust(4, b"\0")
        if cs >> 5 != 1 or not cs & 0x02:
            return abort(0x05040001)  # only expedited downloads
        n = 4 - ((cs >> 2) & 3) if cs & 0x01 else 4
        if access != RW:
            return abort(0x06010002)
        if n != struct.calcsize(fmt):
            return abort(0x06070010)
        new = struct.unpack_from("<" + fmt, data, 4)[0]
        code = self.check(index, sub, new)
        if code:
            return abort(code)
        self.set(index, sub, new)
        if index == 0x6060:
            self.set(0x6061, 0, new)
        elif index == 0x6040:
            self.controlword(new)
        return b"\x60" + mux + b"\0\0\0\0"

    def check(self, index, sub, new):
        """The strict drive's PDO parameter rules: an abort code, or 0."""
        if 0x1600 <= index <= 0x1603 or 0x1A00 <= index <= 0x1A03:
            comm = index - 0x200
            if self.nmt != 127:
                return 0x08000022  # data cannot be transferred because of the present device state
            if not self.get(comm, 1) & 0x80000000:
                return 0x06010000  # PDO valid
            if sub and self.get(index, 0):
                return 0x06010000  # sub-index 0 must be 0 first
            if sub:
                mappable = TX_MAPPABLE if index >= 0x1A00 else RX_MAPPABLE
                if ((new >> 16), new & 0xFF) not in mappable:
                    return 0x06040041
            elif new > 8 or sum(self.get(index, i) & 0xFF for i in range(1, new + 1)) > 64:
                return 0x06040042
        elif 0x1400 <= index <= 0x1403 or 0x1800 <= index <= 0x1803:
            cur = self.get(index, 1)
            if sub == 1:
                if not cur & 0x80000000 and (new ^ cur) & 0x3FFFFFFF:
                    return 0x06090030  # id or bit 30 changed while valid
                if index >= 0x1800 and not new & 0x40000000:
                    return 0x06090030  # no RTR: bit 30 is fixed at 1
            elif sub == 2 and not cur & 0x80000000:
                return 0x06090030
        return 0

    # ---------------------------------------------------------------- CiA 402
    def controlword(self, cw):
        st = self.get(0x6041)
        prev, self.cw = self.cw, cw
        if st == FAULT:
            if cw & 0x80 and not prev & 0x80:
                self.set(0x6041, 0, SOD)
                self.set(0x603F, 0, 0)
                self.emcy(0, 0)
            return
        if cw & 0x80:
            return
        if not cw & 0x02:
            new = SOD
        elif cw & 0x06 == 0x02:
            new = SOD  # quick stop: option 2 without a ramp (torque off at once)
        elif cw & 0x0F == 0x06:
            new = RTSO if st in (SOD, SO, OE) else st
        elif cw & 0x0F == 0x07:
            new = SO if st in (RTSO, OE) else st
        elif cw & 0x0F == 0x0F:
            new = OE if st in (SO, RTSO) else st
        else:
            new = st
        self.set(0x6041, 0, new)

    # ---------------------------------------------------------------- PDOs, SYNC, NMT
    def mapping(self, index):
        return [self.get(index, i) for i in range(1, self.get(index, 0) + 1)]

    @staticmethod
    def fmt(entry):
        idx = entry >> 16
        return {0x6041: "H", 0x6064: "i", 0x606C: "i", 0x603F: "H", 0x6061: "b", 0x6040: "H", 0x6071: "h",
                0x6060: "b"}[idx]

    def on_sync(self):
        self.syncs += 1
        if self.latched:
            for entry, value in self.latched:
                if entry >> 16 == 0x6040:
                    self.controlword(value)
                elif entry >> 16 == 0x6071:
                    self.set(0x6071, 0, value)
            self.latched = None
        if self.get(0x6041) == OE:
            self.set(0x6064, 0, self.get(0x6064) + self.get(0x6071))
        hb = self.get(0x1017)
        if hb and self.syncs >= self.next_hb:
            self.send(0x700 + NID, bytes([self.nmt]))
            self.next_hb = self.syncs + hb
        if self.nmt != 5:
            return
        for comm in range(0x1800, 0x1804):
            cob = self.get(comm, 1)
            if cob & 0x80000000 or not 1 <= self.get(comm, 2) <= 240 or self.syncs % self.get(comm, 2):
                continue
            entries = self.mapping(comm + 0x200)
            self.send(cob & 0x7FF, struct.pack("<" + "".join(self.fmt(e) for e in entries),
                                               *[self.get(e >> 16) for e in entries]))

    def on_frame(self, msg, now):
        cid, data = msg.arbitration_id, bytes(msg.data)
        if msg.is_extended_id or msg.is_error_frame:
            return
        if cid == 0 and len(data) == 2 and data[1] in (0, NID):
            if data[0] in (0x81, 0x82):
                self.power_on()
                return
            was = self.nmt
            self.nmt = {0x01: 5, 0x02: 4, 0x80: 127}.get(data[0], self.nmt)
            if was == 5 and self.nmt == 4 and self.get(0x6041) in (OE, QSA) and self.get(0x6007) == 1:
                self.fault(0x8100)  # 0x6007 = 1: abort connection -> fault
        elif cid == 0x080:
            self.on_sync()
        elif cid == 0x600 + NID and len(data) == 8 and self.nmt in (127, 5):
            self.pending.append((now + self.sdo_delay_s, self.sdo(data)))
        elif self.nmt == 5:
            for comm in range(0x1400, 0x1404):
                cob = self.get(comm, 1)
                if not cob & 0x80000000 and cid == cob & 0x7FF:
                    entries = self.mapping(comm + 0x200)
                    f = "<" + "".join(self.fmt(e) for e in entries)
                    if len(data) >= struct.calcsize(f):
                        self.latched = list(zip(entries, struct.unpack_from(f, data)))

    def pump(self):
        with self.lock:
            now = time.monotonic()
            while (msg := self.bus.recv(0.0)) is not None:
                self.on_frame(msg, now)
            due = [r for t, r in self.pending if t <= now]
            self.pending = [(t, r) for t, r in self.pending if t > now]
            for r in due:
                self.send(0x580 + NID, r)
        return 0


@pytest.fixture
def strict(make_drive):
    made = []

    def make(**kw):
        channel = f"stagectl-strict-{id(made):x}-{len(made)}"
        slave = StrictSlave(channel, **kw)
        made.append(slave)
        dut = make_drive({"interface": "virtual", "channel": channel}, period_s=PERIOD_S, node_id=NID,
                         heartbeat_producer_s=0.05, heartbeat_timeout_s=0.2)
        dut.set_pump(slave.pump)
        dut.open()
        return slave, dut

    yield make
    for s in made:
        s.close()


def _run(dut, n, force=0.0):
    return cycle_drive(dut, n, force)


def test_configure_by_the_rules_enable_cycle_fault_and_disable(strict):
    slave, dut = strict()
    dut.configure()
    assert slave.log == [(w, i, s, c) for w, i, s, c in slave.log if i in (0x605A, 0x6072, 0x1006)], slave.log
    slave.pump()
    assert slave.nmt == 5
    assert slave.get(0x1800, 1) == 0x40000180 + NID and slave.mapping(0x1A00) == [0x60410010, 0x60640020]
    assert slave.get(0x1400, 1) == 0x200 + NID and slave.mapping(0x1600) == [0x60400010, 0x60710010]
    for comm in (0x1401, 0x1402, 0x1403, 0x1801, 0x1802, 0x1803):  # every PDO we do not use is invalid
        assert slave.get(comm, 1) & 0x80000000, f"0x{comm:04X} still valid: 0x{slave.get(comm, 1):08X}"
    assert slave.get(0x6061) == 10
    dut.enable()
    assert slave.get(0x6041) == OE
    m = _run(dut, 100, force=1.0)  # 100 units of 0.01 N: the slave integrates 100 counts per SYNC
    assert m.fault is None and m.fresh and slave.get(0x6064) > 9000 and m.counts == slave.get(0x6064)
    slave.fault(0x2310)
    m = _run(dut, 3)
    assert m.fault is not None and m.fault.kind in (FaultKind.EMCY, FaultKind.DRIVE_FAULT)
    assert dut.state is DeviceState.FAULT and slave.get(0x603F) == 0x2310
    dut.fault_reset()
    assert slave.get(0x6041) == SOD and slave.get(0x1001) == 0
    dut.enable()
    assert _run(dut, 5, force=0.5).fault is None
    dut.disable()
    assert slave.get(0x6041) in (RTSO, SOD)


def test_a_drive_that_powers_up_in_fault(strict):
    slave, dut = strict(power_up_fault=0x3210)
    dut.configure()
    with pytest.raises(DriveFault) as ei:
        dut.enable()
    assert "\n" not in str(ei.value) and "fault_reset" in str(ei.value)
    dut.fault_reset()
    dut.enable()
    assert slave.get(0x6041) == OE and _run(dut, 5).fault is None


def test_nmt_stop_by_another_node_faults_both_sides(strict):
    slave, dut = strict()
    dut.configure()
    dut.enable()
    _run(dut, 5)
    other = canbus.open_bus({"interface": "virtual", "channel": slave.channel})
    try:  # another node on the bus: NMT stop all
        other.send(can.Message(arbitration_id=0, data=b"\x02\x00", is_extended_id=False))
    finally:
        canbus.close_bus(other)
    m = _run(dut, 120)
    assert m.fault is not None and slave.get(0x6041) == FAULT
    assert m.fault.kind is FaultKind.MISSED_FRAME  # its TPDOs stop before its next heartbeat says STOPPED
    assert dut.drive_nmt_state == 5
    # one reset: the heartbeat that shows STOPPED comes while it waits for TPDOs: configure again, then reset
    dut.fault_reset()
    slave.pump()
    assert slave.nmt == 5 and slave.get(0x6041) == SOD
    dut.enable()
    assert slave.nmt == 5 and slave.get(0x6041) == OE


def test_sdo_answers_slower_than_the_timeout_are_one_line_naming_it(make_drive):
    slave = StrictSlave(f"stagectl-strict-slow-{id(make_drive):x}", sdo_delay_s=0.2)
    try:
        dut = make_drive({"interface": "virtual", "channel": slave.channel}, period_s=PERIOD_S, node_id=NID,
                         sdo_timeout_s=0.05)
        dut.set_pump(slave.pump)
        dut.open()
        with pytest.raises(DriverInitError) as ei:
            dut.configure()
        msg = str(ei.value)
        assert "\n" not in msg and "0x1000:00" in msg
        assert "no SDO answer within drive.sdo_timeout_s 0.05 s" in msg and "raise drive.sdo_timeout_s" in msg
    finally:
        slave.close()
