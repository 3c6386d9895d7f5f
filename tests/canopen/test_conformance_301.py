"""CiA 301 conformance of the virtual CiA 402 drive, driven by canopen's stock master (``RemoteNode`` SDO client
plus raw frames), never by our driver. Each table row is a rule of CiA 301 (PDO parameters §7.5.2.35–38, SDO
abort codes §7.2.4.3.17, EMCY §7.2.7, error register §7.5.2.2, SYNC §7.2.5) that docs/canopen.md lists."""

from __future__ import annotations

import logging
import struct

import pytest

from stagectl.sim.cia402_drive import DriveState, error_register_bits

ABORTS = {
    "not mappable": 0x06040041,
    "length": 0x06040042,
    "incompatible": 0x06040043,
    "no object": 0x06020000,
    "access": 0x06010000,
    "invalid value": 0x06090030,
}


def _disable(m, comm, cob):
    assert m.abort_code(comm, 1, "<I", 0x80000000 | cob) is None


# (what, writes before the checked one, (index, sub, fmt, value) checked, expected abort)
PDO_RULES = [
    ("TPDO maps 0x6072 (PDOMapping=0)", "tpdo-off", (0x1A00, 1, "<I", 0x60720010), "not mappable"),
    ("TPDO maps missing 0x2000", "tpdo-off", (0x1A00, 1, "<I", 0x20000010), "no object"),
    ("TPDO maps 0x6064 with 24 bits", "tpdo-off", (0x1A00, 1, "<I", 0x60640018), "incompatible"),
    ("RPDO maps read-only statusword", "rpdo-off", (0x1600, 1, "<I", 0x60410010), "not mappable"),
    ("mapping count 9", "tpdo-off", (0x1A00, 0, "<B", 9), "length"),
    ("mapping count while PDO valid", "", (0x1A00, 0, "<B", 0), "access"),
    ("mapping entry while count != 0", "tpdo-off-only", (0x1A00, 1, "<I", 0x60410010), "access"),
    ("COB-ID change while valid", "", (0x1800, 1, "<I", 0x190), "invalid value"),
    ("29-bit COB-ID", "tpdo-off-only", (0x1800, 1, "<I", 0x20000185), "invalid value"),
    ("COB-ID in the SDO range", "tpdo-off-only", (0x1800, 1, "<I", 0x601), "invalid value"),
    ("reserved transmission type 245", "", (0x1800, 2, "<B", 245), "invalid value"),
    ("RTR-only transmission type 253", "", (0x1800, 2, "<B", 253), "invalid value"),
    ("inhibit time while valid", "", (0x1800, 3, "<H", 10), "invalid value"),
]


@pytest.mark.parametrize("what, prep, write, expect", PDO_RULES, ids=[r[0] for r in PDO_RULES])
def test_pdo_parameter_rules_abort_codes(master, what, prep, write, expect):
    world, m = master()
    if prep.startswith("tpdo-off"):
        _disable(m, 0x1800, 0x181)
        if prep == "tpdo-off":
            assert m.abort_code(0x1A00, 0, "<B", 0) is None
    elif prep == "rpdo-off":
        _disable(m, 0x1400, 0x201)
        assert m.abort_code(0x1600, 0, "<B", 0) is None
    assert m.abort_code(*write) == ABORTS[expect], what


def test_mapping_over_64_bits_refused_at_count(master):
    world, m = master()
    _disable(m, 0x1800, 0x181)
    assert m.abort_code(0x1A00, 0, "<B", 0) is None
    for i in (1, 2, 3):  # three INT32 entries: each alone is fine (step 3), together 96 bits (step 4)
        assert m.abort_code(0x1A00, i, "<I", 0x60640020) is None
    assert m.abort_code(0x1A00, 0, "<B", 3) == ABORTS["length"]
    assert m.abort_code(0x1A00, 0, "<B", 2) is None


def test_pdo_changes_are_live_in_operational(master):
    """Disable / remap a TPDO and disable an RPDO in OPERATIONAL: effective at the next SYNC, no NMT restart."""
    world, m = master()
    m.nmt(0x01)
    m.frames()
    m.sync()
    assert [len(f.data) for f in m.frames(0x181)] == [6]
    _disable(m, 0x1800, 0x181)
    m.frames()
    m.sync(3)
    assert m.frames(0x181) == []  # disabled by bit 31: not sent
    assert m.abort_code(0x1A00, 0, "<B", 0) is None
    assert m.abort_code(0x1A00, 1, "<I", 0x60410010) is None
    assert m.abort_code(0x1A00, 0, "<B", 1) is None
    assert m.abort_code(0x1800, 1, "<I", 0x181) is None
    m.sync()
    got = m.frames(0x181)
    assert [bytes(f.data) for f in got] == [struct.pack("<H", world.drive.statusword)]  # the new layout
    # RPDO disabled: its frames are no longer applied
    _disable(m, 0x1400, 0x201)
    m.send(0x201, struct.pack("<Hh", 0x06, 77))
    m.sync()
    assert world.drive.target_torque == 0 and world.drive.controlword == 0


def _map_tpdo2(m, entries, ttype, event_ms=0, inhibit_100us=0):
    _disable(m, 0x1801, 0x281)
    assert m.abort_code(0x1A01, 0, "<B", 0) is None
    for i, e in enumerate(entries, 1):
        assert m.abort_code(0x1A01, i, "<I", e) is None
    assert m.abort_code(0x1A01, 0, "<B", len(entries)) is None
    assert m.abort_code(0x1801, 2, "<B", ttype) is None
    assert m.abort_code(0x1801, 3, "<H", inhibit_100us) is None
    assert m.abort_code(0x1801, 5, "<H", event_ms) is None
    assert m.abort_code(0x1801, 1, "<I", 0x281) is None


def test_transmission_type_cyclic_every_nth_sync(master):
    world, m = master()
    _map_tpdo2(m, [0x60410010], 3)
    m.nmt(0x01)
    m.frames()
    sent = []
    for k in range(1, 10):
        m.sync()
        if m.frames(0x281):
            sent.append(k)
    assert sent == [3, 6, 9]


def test_transmission_type_0_acyclic_on_change(master):
    """Type 0: sent at a SYNC only when a mapped value changed (here the statusword)."""
    world, m = master()
    _map_tpdo2(m, [0x60410010], 0)
    m.nmt(0x01)
    m.frames()
    m.sync()
    assert len(m.frames(0x281)) == 1  # first SYNC after start: the event "value first available"
    m.sync(3)
    assert m.frames(0x281) == []  # nothing changed
    m.download(0x6040, 0, "<H", 0x06)  # shutdown: statusword changes
    m.sync(2)
    got = m.frames(0x281)
    assert [struct.unpack("<H", bytes(f.data))[0] & 0x6F for f in got] == [0x21]


def test_event_timer_and_inhibit_time(master):
    """Type 255: event timer 10 ms sends every 10 ms of device time without SYNC; a value changing every
    1 ms SYNC with inhibit 5 ms is sent at most every 5 ms."""
    world, m = master()
    _map_tpdo2(m, [0x60410010], 255, event_ms=10)
    m.nmt(0x01)
    m.frames()
    t0 = world.now()
    sent = []
    for _ in range(50):
        world.advance(0.001)
        sent += [round(world.now() - t0, 6)] * len(m.frames(0x281))
    gaps = {round(b - a, 6) for a, b in zip(sent, sent[1:])}
    assert len(sent) >= 5 and gaps == {0.01}, sent  # one frame every 10 ms of device time, no SYNC
    # inhibit: position changes at every SYNC (torque commanded), inhibit 5 ms
    m.nmt(0x80)
    _map_tpdo2(m, [0x60640020], 255, inhibit_100us=50)
    m.nmt(0x01)
    m.download(0x6060, 0, "<b", 10)
    for cw in (0x06, 0x07, 0x0F):
        m.download(0x6040, 0, "<H", cw)
    m.download(0x6071, 0, "<h", 500)
    m.frames()
    n_sync = 40
    stamps = []
    for _ in range(n_sync):
        m.sync()
        if m.frames(0x281):
            stamps.append(world.now())
    assert world.now() - t0 > 0.05
    gaps = [b - a for a, b in zip(stamps, stamps[1:])]
    assert gaps and min(gaps) >= 0.005 - 1e-9, gaps
    assert len(stamps) >= n_sync // 5 - 1  # but sent when allowed: the value keeps changing


def test_rpdo_event_type_applies_at_once(master):
    world, m = master()
    _disable(m, 0x1400, 0x201)
    assert m.abort_code(0x1400, 2, "<B", 255) is None
    assert m.abort_code(0x1400, 1, "<I", 0x201) is None
    m.nmt(0x01)
    m.send(0x201, struct.pack("<Hh", 0x06, 12))  # no SYNC
    assert world.drive.controlword == 0x06 and world.drive.target_torque == 12
    assert world.drive.state is DriveState.READY_TO_SWITCH_ON


def test_tpdo_sends_the_value_sdo_reads(master):
    """A TPDO mapping any object (0x6060, 0x605A) carries what an SDO upload returns, not zeros."""
    world, m = master()
    m.download(0x6060, 0, "<b", 10)
    _map_tpdo2(m, [0x60600008, 0x605A0010], 1)
    m.nmt(0x01)
    m.frames()
    m.sync()
    (f,) = m.frames(0x281)
    assert struct.unpack("<bh", bytes(f.data)) == (m.upload(0x6060, 0, "<b"), m.upload(0x605A, 0, "<h")) == (10, 2)


def test_node_relative_default_cob_ids(master):
    world, m = master(node_id=5)
    assert m.upload(0x1400, 1, "<I") == 0x205
    assert m.upload(0x1401, 1, "<I") == 0x80000305
    assert m.upload(0x1800, 1, "<I") == 0x185
    assert m.upload(0x1801, 1, "<I") == 0x80000285
    assert m.upload(0x1014, 0, "<I") == 0x85


def test_sync_cob_id_0x1005_honoured(master):
    world, m = master()
    m.nmt(0x01)
    assert m.abort_code(0x1005, 0, "<I", 0x090) is None
    m.frames()
    m.sync()  # 0x080: no longer SYNC for this device
    assert m.frames(0x181) == []
    m.sync_id = 0x090
    m.sync()
    assert len(m.frames(0x181)) == 1
    assert m.abort_code(0x1005, 0, "<I", 0x40000080) == ABORTS["invalid value"]  # a consumer cannot produce


def test_emcy_invalid_bit_0x1014(master):
    world, m = master()
    assert m.abort_code(0x1014, 0, "<I", 0x80000081) is None
    world.inject("drive_fault", code=0x2310)
    m.nmt(0x01)
    m.frames()
    m.sync()
    assert m.frames(0x081) == []  # EMCY invalid: no frame
    assert m.upload(0x1001, 0, "<B") == 0x03  # the error register is still kept


@pytest.mark.parametrize("code, register", [(0x2310, 0x03), (0x3210, 0x05), (0x4210, 0x09), (0x8130, 0x11),
                                            (0x5000, 0x01), (0x6100, 0x01), (0xFF01, 0x81)])
def test_error_register_bits_by_class(master, code, register):
    assert error_register_bits(code) == register
    world, m = master()
    world.inject("drive_fault", code=code)
    m.nmt(0x01)
    m.frames()
    m.sync()
    (emcy,) = m.frames(0x081)
    assert struct.unpack("<HB", bytes(emcy.data[:3])) == (code, register)
    assert m.upload(0x1001, 0, "<B") == register


def test_short_rpdo_gives_emcy_8210(master):
    world, m = master()
    m.nmt(0x01)
    m.frames()
    m.send(0x201, b"\x06\x00\x05")  # 3 bytes, mapping needs 4
    m.sync()
    emcy = m.frames(0x081)
    assert [struct.unpack("<HB", bytes(f.data[:3])) for f in emcy] == [(0x8210, 0x11)]
    assert world.drive.controlword == 0  # not applied


def test_29_bit_frames_are_ignored(master):
    world, m = master()
    m.frames()
    req = bytes([0x40, 0x00, 0x10, 0x00, 0, 0, 0, 0])  # SDO upload 0x1000
    m.send(0x00000601, req, extended=True)
    assert m.frames() == [] or all(f.arbitration_id != 0x581 for f in m.frames())
    m.send(0x601, req)
    assert [f.arbitration_id for f in m.frames(0x581)] == [0x581]


def test_internal_error_is_never_silent(master, caplog):
    """A corrupt dictionary entry makes the PDO compile raise: EMCY 0x6100, FAULT, a log line, and the device
    keeps answering."""
    world, m = master()
    world.drive.node.data_store.setdefault(0x1A01, {})[1] = struct.pack("<I", 0x60990020)  # no such object
    world.drive.node.data_store[0x1A01][0] = b"\x01"
    m.frames()
    with caplog.at_level(logging.ERROR, logger="stagectl.sim.cia402_drive"):
        assert m.abort_code(0x1801, 1, "<I", 0x281) is None  # recompiles the bad mapping
    assert any("internal error" in r.getMessage() for r in caplog.records)
    assert [struct.unpack("<H", bytes(f.data[:2]))[0] for f in m.frames(0x081)] == [0x6100]
    assert world.drive.state is DriveState.FAULT
    assert m.upload(0x1000, 0, "<I") & 0xFFFF == 402  # still answers


def test_heartbeat_on_schedule_under_traffic(master):
    """0x1017 = 10 ms with SYNC, RPDO and SDO traffic every 1 ms of device time: a beat every 10 ms."""
    world, m = master()
    m.download(0x1017, 0, "<H", 10)
    m.nmt(0x01)
    m.frames()
    beats = []
    for k in range(300):
        m.sync()
        m.send(0x201, struct.pack("<Hh", 0, 0))
        if any(f.arbitration_id == 0x701 for f in m.frames()):
            beats.append(world.now())
    gaps = [round(b - a, 6) for a, b in zip(beats, beats[1:])]
    assert len(beats) >= 29 and set(gaps) == {0.01}, gaps


SDO_ABORTS = [
    ("write read-only 0x6041", (0x6041, 0, "<H", 1), 0x06010002),
    ("object does not exist", (0x2999, 0, "<H", 1), 0x06020000),
    ("sub-index does not exist", (0x1018, 9, "<I", 1), 0x06090011),
    ("length does not match", (0x6040, 0, "<I", 1), 0x06070010),
    ("mode not implemented", (0x6060, 0, "<b", 1), 0x06090030),
    ("SYNC producer bit on a consumer", (0x1005, 0, "<I", 0x40000080), 0x06090030),
    ("EMCY COB-ID change while valid", (0x1014, 0, "<I", 0x0A0), 0x06090030),
    # CiA 402 option codes: reserved values and manufacturer-specific ones this drive does not implement
    ("quick stop option reserved 9", (0x605A, 0, "<h", 9), 0x06090030),
    ("quick stop option manufacturer -1", (0x605A, 0, "<h", -1), 0x06090030),
    ("fault reaction option reserved 5", (0x605E, 0, "<h", 5), 0x06090030),
    ("abort connection option reserved 4", (0x6007, 0, "<h", 4), 0x06090030),
]


@pytest.mark.parametrize("what, write, code", SDO_ABORTS, ids=[a[0] for a in SDO_ABORTS])
def test_sdo_abort_codes(master, what, write, code):
    world, m = master()
    assert m.abort_code(*write) == code, what
    assert m.upload(0x1000, 0, "<I") & 0xFFFF == 402  # the server goes on answering


@pytest.mark.parametrize(("index", "top"), [(0x605A, 8), (0x605E, 4), (0x6007, 3)])
def test_every_defined_option_code_is_accepted_and_read_back(master, index, top):
    world, m = master()
    for code in range(top + 1):
        assert m.abort_code(index, 0, "<h", code) is None, (hex(index), code)
        assert m.upload(index, 0, "<h") == code


def test_an_sdo_frame_shorter_than_8_bytes_is_ignored(master):
    """CiA 301: every SDO frame has DLC 8. A shorter "request" is no SDO request: no answer (the client's own
    time-out reports it, as with CANopenNode's server), and the next well-formed request is served."""
    world, m = master()
    m.frames()
    upload_0x1000 = bytes([0x40, 0x00, 0x10, 0x00])
    for dlc in (0, 1, 4, 7):
        m.send(0x601, upload_0x1000[:dlc] if dlc <= 4 else upload_0x1000 + bytes(dlc - 4))
        assert m.frames(0x581) == [], dlc
    m.send(0x601, upload_0x1000 + bytes(4))
    (reply,) = m.frames(0x581)
    assert reply.data[0] == 0x43 and struct.unpack_from("<I", reply.data, 4)[0] & 0xFFFF == 402
