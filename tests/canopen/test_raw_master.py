"""The virtual CiA 402 drive against a master written here from CiA 301/402 with nothing but raw python-can
frames: its own SDO client (expedited and segmented, both directions, toggle bit), NMT, SYNC, its own heartbeat,
PDO mapping through 0x1600/0x1A00 and their communication parameters, the controlword sequence, EMCY. No canopen
client and none of our driver's code: every reply is checked against the standard's frame layouts.
(test_conformance_301/402 cover the PDO parameter rules and the power state machine through canopen's client.)
"""

from __future__ import annotations

import struct

import can
import pytest

from stagectl.drivers import canbus

NODE = 1
CTRL = 0x7F  # our heartbeat node id
# CiA 301 SDO abort codes (§7.2.4.3.17)
TOGGLE, COMMAND, READ_ONLY, NO_OBJECT, LENGTH, NO_SUB, RANGE = (
    0x05030000, 0x05040001, 0x06010002, 0x06020000, 0x06070010, 0x06090011, 0x06090030)
# CiA 402 statusword (mask, value)
SOD, RTSO, SO, OE, FAULT = (0x4F, 0x40), (0x6F, 0x21), (0x6F, 0x23), (0x6F, 0x27), (0x4F, 0x08)


class RawMaster:
    """A CiA 301 master made of raw frames on its own bus, pumping a lock-step world after each frame."""

    def __init__(self, world):
        world.pump()
        self.world = world
        self.bus = canbus.open_bus({"interface": "virtual", "channel": world.channel})
        self.other: list[can.Message] = []  # frames other than TPDO1 seen by cycle()

    def close(self):
        canbus.close_bus(self.bus)

    def send(self, cid, data=b""):
        self.bus.send(can.Message(arbitration_id=cid, data=bytes(data), is_extended_id=False))
        self.world.pump()

    def frames(self, cid=None):
        self.world.pump()
        out = []
        while (m := self.bus.recv(0.0)) is not None:
            if cid is None or m.arbitration_id == cid:
                out.append(m)
        return out

    # ------------------------------------------------------------------ SDO client (CiA 301 §7.2.4.3)
    def sdo(self, req):
        """One request, exactly one 8-byte answer on 0x580+id."""
        self.frames()
        self.send(0x600 + NODE, bytes(req).ljust(8, b"\0"))
        got = self.frames(0x580 + NODE)
        assert len(got) == 1 and len(got[0].data) == 8, got
        return bytes(got[0].data)

    @staticmethod
    def aborted(reply, index, sub):
        """The abort code of an abort frame for ``index:sub`` (None if not an abort)."""
        if reply[0] != 0x80:
            return None
        assert struct.unpack_from("<HB", reply, 1) == (index, sub), f"abort names another object: {reply.hex()}"
        return struct.unpack_from("<I", reply, 4)[0]

    def upload(self, index, sub):
        """Expedited or segmented upload: bytes (or the abort code as an int)."""
        r = self.sdo(struct.pack("<BHB", 0x40, index, sub))
        if (code := self.aborted(r, index, sub)) is not None:
            return code
        assert r[0] >> 5 == 2 and struct.unpack_from("<HB", r, 1) == (index, sub), r.hex()
        if r[0] & 0x02:  # expedited: e=1, s=1, n in bits 2-3
            assert r[0] & 0x01, "expedited upload without size indicated"
            return r[4:8 - ((r[0] >> 2) & 3)]
        assert r[0] & 0x01, "segmented upload without size"
        size = struct.unpack_from("<I", r, 4)[0]
        out, toggle = b"", 0
        while True:
            s = self.sdo(bytes([0x60 | toggle << 4]))
            assert s[0] >> 5 == 0 and (s[0] >> 4) & 1 == toggle, f"toggle bit not alternated: {s.hex()}"
            out += s[1:8 - ((s[0] >> 1) & 7)]
            toggle ^= 1
            if s[0] & 0x01:
                break
        assert len(out) == size, f"segmented upload sent {len(out)} bytes, indicated {size}"
        return out

    def download(self, index, sub, data, segmented=False):
        """Expedited (≤ 4 bytes) or segmented download: None, or the abort code."""
        if not segmented:
            r = self.sdo(struct.pack("<BHB", 0x23 | (4 - len(data)) << 2, index, sub) + bytes(data))
            return self.aborted(r, index, sub) if r[0] != 0x60 else None
        r = self.sdo(struct.pack("<BHBI", 0x21, index, sub, len(data)))
        if r[0] != 0x60:
            return self.aborted(r, index, sub)
        toggle = 0
        for i in range(0, len(data), 7):
            chunk = data[i:i + 7]
            last = i + 7 >= len(data)
            s = self.sdo(bytes([toggle << 4 | (7 - len(chunk)) << 1 | last]) + chunk)
            if s[0] == 0x80:
                return self.aborted(s, index, sub)
            assert s[0] == 0x20 | toggle << 4, f"segment answer {s.hex()}"
            toggle ^= 1
        return None

    def write(self, index, sub, fmt, value):
        code = self.download(index, sub, struct.pack(fmt, value))
        assert code is None, f"0x{index:04X}:{sub} = {value}: abort 0x{code:08X}"

    def read(self, index, sub, fmt):
        return struct.unpack(fmt, self.upload(index, sub))[0]

    # ------------------------------------------------------------------ NMT, SYNC, heartbeat, PDOs
    def nmt(self, cmd):
        self.send(0x000, bytes([cmd, NODE]))

    def map_pdo(self, comm, mapping, cob, entries):
        """CiA 301 §7.5.2.36/38 sequence: invalidate, count 0, entries, count, type 1 (every SYNC), validate."""
        self.write(comm, 1, "<I", 0x80000000 | cob)
        self.write(mapping, 0, "<B", 0)
        for i, e in enumerate(entries, 1):
            self.write(mapping, i, "<I", e)
        self.write(mapping, 0, "<B", len(entries))
        self.write(comm, 2, "<B", 1)
        self.write(comm, 1, "<I", cob)

    def cycle(self, cw, torque=0, beat=True):
        """Our heartbeat, RPDO1 (controlword, target torque), SYNC; the (statusword, position) of TPDO1s."""
        if beat:
            self.send(0x700 + CTRL, b"\x05")
        self.send(0x200 + NODE, struct.pack("<Hh", cw, torque))
        self.send(0x080)
        got = self.frames()
        self.other += [f for f in got if f.arbitration_id != 0x180 + NODE]
        return [struct.unpack_from("<Hi", f.data) for f in got if f.arbitration_id == 0x180 + NODE]


@pytest.fixture
def raw(make_world):
    made = []

    def make(**sim):
        w = make_world(**sim)
        m = RawMaster(w)
        made.append(m)
        return w, m

    yield make
    for m in made:
        m.close()


def _is(sw, state):
    return sw & state[0] == state[1]


def test_sdo_transfers_and_abort_codes(raw):
    _, m = raw()
    assert m.read(0x1000, 0, "<I") & 0xFFFF == 402
    name = m.upload(0x1008, 0)  # VISIBLE_STRING longer than 4 bytes: segmented, toggle alternating
    assert isinstance(name, bytes) and len(name) > 7 and name.isascii()
    assert m.download(0x1017, 0, struct.pack("<H", 100), segmented=True) is None  # segmented download
    assert m.read(0x1017, 0, "<H") == 100
    assert m.upload(0x2222, 0) == NO_OBJECT
    assert m.upload(0x1018, 9) == NO_SUB
    assert m.download(0x6041, 0, b"\1\0") == READ_ONLY
    assert m.download(0x1000, 0, b"\1\0\0\0") == READ_ONLY
    assert m.download(0x6040, 0, b"\6\0\0\0") == LENGTH
    assert m.download(0x6060, 0, b"\3") == RANGE  # profile position: not supported by this drive
    assert m.download(0x1017, 0, b"\1\0\0\0\0\0\0\0\0", segmented=True) == LENGTH
    assert m.aborted(m.sdo(b"\xe0\x00\x10\x00"), 0x1000, 0) == COMMAND  # ccs 7 does not exist
    # toggle bit: the first upload segment must carry toggle 0
    assert m.sdo(struct.pack("<BHB", 0x40, 0x1008, 0))[0] == 0x41
    assert m.aborted(m.sdo(b"\x70"), 0x1008, 0) == TOGGLE


def test_segments_outside_a_transfer_are_refused(raw):
    """A segment request belongs to the segmented transfer its initiate opened (CiA 301 §7.2.4.3.4-7): outside
    one it is aborted 0x05040001, never served from the last transfer's leftovers."""
    _, m = raw()
    m.write(0x6040, 0, "<H", 0x06)  # READY TO SWITCH ON
    # a client starts a segmented download of the controlword and aborts it (ccs 4) ...
    assert m.sdo(struct.pack("<BHBI", 0x21, 0x6040, 0, 2))[0] == 0x60
    m.send(0x600 + NODE, struct.pack("<BHBI", 0x80, 0x6040, 0, 0x08000000))
    assert m.frames(0x580 + NODE) == []  # an abort is not answered
    # ... a stray last segment [0x000F = enable operation] must not reach the controlword
    assert m.aborted(m.sdo(bytes([0x0B, 0x0F, 0x00])), 0x6040, 0) == COMMAND
    assert _is(m.read(0x6041, 0, "<H"), RTSO) and m.read(0x6040, 0, "<H") == 0x06
    # an upload segment with no upload in progress; a segmented download delivering more than it indicated
    assert m.aborted(m.sdo(b"\x60"), 0x6040, 0) == COMMAND
    assert m.sdo(struct.pack("<BHBI", 0x21, 0x6040, 0, 2))[0] == 0x60
    assert m.aborted(m.sdo(bytes([0x09, 0x0F, 0x00, 0x00])), 0x6040, 0) == LENGTH  # 3 bytes of 2
    assert m.read(0x6040, 0, "<H") == 0x06
    # block upload is not offered (the client gave no protocol switch threshold): abort, not a normal upload
    assert m.aborted(m.sdo(struct.pack("<BHBBB", 0xA4, 0x1008, 0, 0x7F, 0)), 0x1008, 0) == COMMAND


def test_nmt_states_heartbeat_and_boot_up(raw):
    _, m = raw()
    m.write(0x1017, 0, "<H", 1)  # heartbeat every 1 ms = every SYNC in lock-step

    def beats(n=3):
        got = []
        for _ in range(n):
            m.send(0x080)
            got += [bytes(f.data) for f in m.frames(0x700 + NODE)]
        return got

    assert set(beats()) == {b"\x7f"}  # PRE-OPERATIONAL
    m.nmt(0x01)
    assert set(beats()) == {b"\x05"}
    m.nmt(0x02)
    assert set(beats()) == {b"\x04"}
    m.send(0x600 + NODE, struct.pack("<BHB4x", 0x40, 0x1000, 0))
    assert m.frames(0x580 + NODE) == []  # no SDO in STOPPED
    for cmd in (0x81, 0x82):  # reset node / reset communication: boot-up [00], then PRE-OPERATIONAL
        m.nmt(cmd)
        assert [bytes(f.data) for f in m.frames(0x700 + NODE)] == [b"\x00"]
        assert m.read(0x1017, 0, "<H") == 0  # the EDS value again
        m.write(0x1017, 0, "<H", 1)
        assert set(beats()) == {b"\x7f"}


def _enabled_by_pdo(m, consumer_ms=0):
    """Map TPDO1 = (statusword, position actual), RPDO1 = (controlword, target torque), CST, NMT start,
    shutdown -> switch on -> enable operation, each statusword checked; returns the last TPDO."""
    m.map_pdo(0x1800, 0x1A00, 0x180 + NODE, [0x60410010, 0x60640020])
    m.map_pdo(0x1400, 0x1600, 0x200 + NODE, [0x60400010, 0x60710010])
    m.write(0x6060, 0, "<b", 10)
    assert m.read(0x6061, 0, "<b") == 10
    if consumer_ms:
        m.write(0x1016, 1, "<I", CTRL << 16 | consumer_ms)
    m.nmt(0x01)
    for cw, state in [(0x00, SOD), (0x06, RTSO), (0x07, SO), (0x0F, OE)]:
        (sw, _), = m.cycle(cw)
        assert _is(sw, state), f"controlword 0x{cw:04X}: statusword 0x{sw:04X}"
        assert sw & 0x0200  # remote
    assert sw & 0x1000  # CST: target torque followed
    return sw


def test_pdo_session_torque_moves_the_stage_and_quick_stop(raw):
    _, m = raw()
    _enabled_by_pdo(m)
    first = m.cycle(0x0F, 300)[0][1]
    for _ in range(20):
        (sw, pos), = m.cycle(0x0F, 300)  # 3 N > 1.5 N static friction
    assert _is(sw, OE) and pos > first + 1000, (first, pos)  # 1 nm counts: it moved
    (sw, _), = m.cycle(0x02, 300)  # quick stop (transition 11)
    for _ in range(400):
        (sw, _), = m.cycle(0x02, 300)
        if _is(sw, SOD):
            break
    assert _is(sw, SOD), f"quick stop (0x605A default) ends in SWITCH ON DISABLED: 0x{sw:04X}"
    assert m.read(0x6077, 0, "<h") == 0


def test_heartbeat_loss_one_emcy_fault_and_reset(raw):
    _, m = raw()
    _enabled_by_pdo(m, consumer_ms=20)
    m.frames()
    tpdos = []
    m.other.clear()
    for _ in range(40):  # our heartbeat stops: > 20 ms of SYNCs without it
        tpdos += m.cycle(0x0F, 0, beat=False)
    emcys = [bytes(f.data) for f in m.other if f.arbitration_id == 0x080 + NODE]
    code, reg = struct.unpack_from("<HB", emcys[0])
    assert len(emcys[0]) == 8 and (code, reg & 0x11) == (0x8130, 0x11)  # generic + communication bits
    assert emcys == [emcys[0]], f"one EMCY per error, got {[e.hex() for e in emcys]}"
    assert _is(tpdos[-1][0], FAULT) and m.read(0x603F, 0, "<H") == 0x8130
    assert m.read(0x1001, 0, "<B") == reg
    # fault reset: rising edge of bit 7 -> SWITCH ON DISABLED, EMCY "error reset" with register 0
    m.cycle(0x00)
    m.other.clear()
    (sw, _), = m.cycle(0x80)
    assert _is(sw, SOD)
    assert [bytes(f.data) for f in m.other if f.arbitration_id == 0x080 + NODE] == [bytes(8)]
    assert m.read(0x1001, 0, "<B") == 0


@pytest.mark.parametrize("cmd", [0x02, 0x82], ids=["stop", "reset communication"])
def test_leaving_operational_takes_the_abort_connection_reaction(raw, cmd):
    """CiA 402 0x6007 (abort connection option code) covers NMT STOPPED and reset communication as well as
    heartbeat loss: once no RPDO can reach the drive it must not keep the last torque (default 1: fault)."""
    _, m = raw()
    _enabled_by_pdo(m)
    for _ in range(3):
        m.cycle(0x0F, 100)  # 1 N: below break-away, the stage stays put under it
    m.frames()
    m.nmt(cmd)
    stray = [f for f in m.frames(0x080 + NODE)]
    assert all(cmd == 0x82 for _ in stray)  # no EMCY in STOPPED (CiA 301 §7.3.2.2)
    for _ in range(5):
        m.send(0x080)
    m.nmt(0x80)  # PRE-OPERATIONAL: SDO again
    sw = m.read(0x6041, 0, "<H")
    assert _is(sw, FAULT), f"statusword 0x{sw:04X} after NMT 0x{cmd:02X}"
    assert m.read(0x6077, 0, "<h") == 0 and m.read(0x603F, 0, "<H") == 0x8100


def test_abort_connection_option_2_disables_voltage(raw):
    _, m = raw()
    m.write(0x6007, 0, "<h", 2)
    _enabled_by_pdo(m)
    m.cycle(0x0F, 100)
    m.nmt(0x02)
    m.send(0x080)
    m.nmt(0x80)
    assert _is(m.read(0x6041, 0, "<H"), SOD) and m.read(0x6077, 0, "<h") == 0
