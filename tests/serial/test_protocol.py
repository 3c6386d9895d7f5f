"""Serial interferometer codec: the pure parser on raw bytes, and pyserial's loop:// as transport."""

from __future__ import annotations

import random
import struct

import pytest
import serial
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stagectl.drivers.interferometer_protocol import (
    FRAME_LEN,
    SYNC,
    Frame,
    FrameParser,
    Status,
    crc16,
    encode_frame,
    max_frame_rate_hz,
)


def frames_bytes(n: int, start: int = 0) -> list[bytes]:
    return [encode_frame(start + i, (-1) ** i * (i * 123_456_789), i % 4, 200 + i % 50, 10**9 + i) for i in range(n)]


def test_crc16_is_ccitt_false():
    assert crc16(b"123456789") == 0x29B1


def test_frame_layout_matches_docstring_table():
    b = encode_frame(0x01020304, -2, int(Status.SIGNAL_LOST | Status.ERROR), 77, 0x1122334455667788)
    assert len(b) == FRAME_LEN == 28
    assert b[:2] == SYNC
    assert b[2] == 1 and b[3] == 0x09 and b[4] == 77 and b[5] == 0
    assert struct.unpack_from("<I", b, 6)[0] == 0x01020304
    assert struct.unpack_from("<q", b, 10)[0] == -2
    assert struct.unpack_from("<Q", b, 18)[0] == 0x1122334455667788
    assert struct.unpack_from("<H", b, 26)[0] == crc16(b[2:26])


def test_encode_rejects_out_of_range_fields():
    with pytest.raises(ValueError, match="counts"):
        encode_frame(0, 1 << 63)
    with pytest.raises(ValueError, match="status"):
        encode_frame(0, 0, status=256)
    with pytest.raises(ValueError, match="signal"):
        encode_frame(0, 0, signal=-1)


def test_i64_extremes_and_sequence_wrap_round_trip():
    p = FrameParser()
    out = p.feed(encode_frame(0xFFFFFFFF, -(1 << 63)) + encode_frame(0, (1 << 63) - 1))
    assert [(f.seq, f.counts) for f in out] == [(0xFFFFFFFF, -(1 << 63)), (0, (1 << 63) - 1)]
    assert p.sequence_gaps == 0 and p.sequence_resets == 0


def test_split_at_every_byte_boundary():
    blob = b"".join(frames_bytes(3))
    ref = FrameParser().feed(blob)
    assert len(ref) == 3
    for cut in range(len(blob) + 1):
        p = FrameParser()
        got = p.feed(blob[:cut]) + p.feed(blob[cut:])
        assert got == ref, cut
        assert p.buffered == 0 and p.bytes_discarded == 0


def test_byte_by_byte_feed():
    blob = b"".join(frames_bytes(5))
    p = FrameParser()
    got = [f for i in range(len(blob)) for f in p.feed(blob[i : i + 1])]
    assert [f.seq for f in got] == [0, 1, 2, 3, 4]
    assert p.buffered < FRAME_LEN


def test_garbage_between_frames_is_discarded_and_counted():
    fr = frames_bytes(3)
    junk1, junk2 = b"\x00\x11\x22\xa5", b"\xff" * 9 + b"\xa5"
    p = FrameParser()
    got = p.feed(junk1 + fr[0] + junk2 + fr[1] + fr[2])
    assert [f.seq for f in got] == [0, 1, 2]
    assert p.bytes_discarded == len(junk1) + len(junk2)
    assert p.crc_errors == 0


def test_crc_error_counted_and_frame_not_yielded():
    fr = frames_bytes(3)
    bad = bytearray(fr[1])
    bad[12] ^= 0x10
    p = FrameParser()
    got = p.feed(fr[0] + bytes(bad) + fr[2])
    assert [f.seq for f in got] == [0, 2]
    assert p.crc_errors == 1
    assert p.sequence_gaps == 1 and p.frames_lost == 1
    assert got[1].lost_before == 1


def test_resync_restarts_one_byte_after_a_failed_sync():
    # a false sync word immediately before a real frame: its candidate overlaps the real frame and fails CRC;
    # the parser must restart one byte later and still find the real frame.
    real = encode_frame(7, 42)
    p = FrameParser()
    got = p.feed(b"\xa5\x5a\x01" + real)
    assert [(f.seq, f.counts) for f in got] == [(7, 42)]
    assert p.crc_errors == 1


def test_sequence_gaps_and_resets_counted():
    p = FrameParser()
    seqs = [10, 11, 14, 15, 20, 3, 4]
    got = p.feed(b"".join(encode_frame(s, s) for s in seqs))
    assert [f.seq for f in got] == seqs
    assert p.sequence_gaps == 2 and p.frames_lost == 2 + 4
    assert p.sequence_resets == 1
    assert [f.lost_before for f in got] == [0, 0, 2, 0, 4, 0, 0]


def test_unknown_version_is_skipped():
    body = bytearray(encode_frame(1, 1))
    body[2] = 2
    body[26:28] = struct.pack("<H", crc16(bytes(body[2:26])))
    p = FrameParser()
    assert p.feed(bytes(body) + encode_frame(2, 2)) == [Frame(2, 2, 0, 255, 0, 0)]
    assert p.version_errors == 1


def test_non_bytes_input_is_ignored():
    p = FrameParser()
    assert p.feed("not bytes") == []  # type: ignore[arg-type]
    assert p.feed(5) == []  # type: ignore[arg-type]
    assert p.bytes_in == 0


def test_reset_clears_buffer_and_counters():
    p = FrameParser()
    p.feed(b"\x00" + encode_frame(0, 0)[:10])
    p.reset()
    assert p.buffered == 0 and p.bytes_in == 0 and p.stats().frames == 0


def test_link_budget():
    assert max_frame_rate_hz(921600) == pytest.approx(921600 / 280)


# ------------------------------------------------------------------ property tests
SETTINGS = settings(max_examples=300, deadline=None, derandomize=True, database=None, suppress_health_check=[HealthCheck.too_slow])


@SETTINGS
@given(st.lists(st.binary(max_size=200), max_size=8))
def test_random_bytes_never_raise_never_bad_crc_bounded_memory(chunks):
    p = FrameParser()
    for c in chunks:
        for f in p.feed(c):
            assert encode_frame(f.seq, f.counts, f.status, f.signal, f.timestamp_ns)  # re-encodable
        assert p.buffered < FRAME_LEN
    assert p.bytes_in == sum(map(len, chunks))
    assert p.bytes_discarded <= p.bytes_in


@SETTINGS
@given(
    st.lists(
        st.tuples(
            st.binary(max_size=60),
            st.integers(0, 2**32 - 1),
            st.integers(-(2**63), 2**63 - 1),
            st.integers(0, 255),
            st.integers(0, 255),
            st.integers(0, 2**64 - 1),
        ),
        min_size=1,
        max_size=6,
    ),
    st.binary(max_size=60),
    st.integers(1, 64),
)
def test_every_valid_frame_in_garbage_is_recovered(items, tail, chunk):
    blob = bytearray()
    expected = []
    for junk, seq, counts, status, signal, ts in items:
        blob += junk
        blob += encode_frame(seq, counts, status, signal, ts)
        expected.append((seq, counts, status, signal, ts))
    blob += tail
    p = FrameParser()
    got = []
    for i in range(0, len(blob), chunk):
        got += p.feed(bytes(blob[i : i + chunk]))
    got_t = [(f.seq, f.counts, f.status, f.signal, f.timestamp_ns) for f in got]
    # every embedded frame comes out, in order (garbage can only add frames if it happens to hold a
    # CRC-valid frame itself, which these short random strings essentially never do)
    it = iter(got_t)
    assert all(any(e == g for g in it) for e in expected), (expected, got_t)
    # every yielded frame has a good CRC: re-encoding reproduces bytes present in the stream
    for g in got_t:
        assert encode_frame(*g) in blob


@SETTINGS
@given(st.integers(0, FRAME_LEN * 8 - 1))
def test_any_single_bit_flip_is_never_yielded(bit):
    fr = frames_bytes(3)
    bad = bytearray(fr[1])
    bad[bit // 8] ^= 1 << (bit % 8)
    p = FrameParser()
    got = p.feed(fr[0] + bytes(bad) + fr[2])
    assert [f.seq for f in got] == [0, 2]
    if bit >= 16:  # sync intact: a CRC failure is counted
        assert p.crc_errors >= 1


def test_random_stream_with_corruption_fixed_seed():
    rng = random.Random(1234)
    p = FrameParser()
    sent_ok = 0
    blob = bytearray()
    for seq in range(2000):
        b = bytearray(encode_frame(seq, rng.randrange(-(10**12), 10**12), 0, 255, seq))
        r = rng.random()
        if r < 0.05:
            b[rng.randrange(2, FRAME_LEN)] ^= 1 << rng.randrange(8)
        elif r < 0.1:
            blob += rng.randbytes(rng.randrange(1, 40))
            sent_ok += 1
        else:
            sent_ok += 1
        blob += b
    got = []
    pos = 0
    while pos < len(blob):
        n = rng.randrange(1, 300)
        got += p.feed(bytes(blob[pos : pos + n]))
        pos += n
    assert len(got) == sent_ok
    assert p.crc_errors >= 2000 - sent_ok
    assert p.frames_lost == 2000 - sent_ok


# ------------------------------------------------------------------ pyserial loop:// transport
def test_codec_over_pyserial_loop_url():
    port = serial.serial_for_url("loop://", timeout=0)
    try:
        p = FrameParser()
        sent = frames_bytes(50)
        got: list[Frame] = []
        for i, fr in enumerate(sent):
            port.write(b"\x00\xa5" if i % 7 == 0 else b"")
            port.write(fr)
            got += p.feed(port.read(4096))
        got += p.feed(port.read(4096))
        assert [f.seq for f in got] == list(range(50))
        assert p.crc_errors == 0 and p.sequence_gaps == 0
    finally:
        port.close()


def test_plain_pyserial_client_decodes_with_the_documented_table(tmp_path):
    """A client written from the docstring only: the field table is parsed out of the module docstring, the
    CRC is a bitwise CRC-16/CCITT-FALSE from its stated parameters; frames come from the virtual device over
    a real pty, read with plain pyserial. Checks that the document is right, not just the code."""
    import re
    import select

    from stagectl.drivers import interferometer_protocol as proto
    from stagectl.sim.interferometer import SimInterferometer, SimInterferometerConfig

    types = {"u8[2]": "2s", "u8": "B", "u16": "H", "u32": "I", "i64": "q", "u64": "Q"}
    rows = re.findall(r"^(\d+)\s+(\d+)\s+(u8\[2\]|u8|u16|u32|i64|u64)\s+(\S.*)$", proto.__doc__, re.M)
    fmt, offset, names = "<", 0, []
    for off, size, typ, text in rows:
        assert int(off) == offset and struct.calcsize(types[typ]) == int(size), (off, size, typ)
        fmt += types[typ]
        offset += int(size)
        names.append(text.split()[0])
    assert names[0] == "sync" and names[-1].startswith("CRC") and offset == 28

    def crc(data: bytes) -> int:  # poly 0x1021, init 0xFFFF, no reflection, xorout 0
        r = 0xFFFF
        for b in data:
            r ^= b << 8
            for _ in range(8):
                r = ((r << 1) ^ 0x1021) & 0xFFFF if r & 0x8000 else (r << 1) & 0xFFFF
        return r

    class Plant:
        t_s = 0.0
        x = -1.234567e-3

        def measure(self):
            return self.x

    plant = Plant()
    with SimInterferometer(plant, SimInterferometerConfig(transport="pty", link_path=str(tmp_path / "ifm"),
                                                          resolution_m=1e-9)) as sim:
        port = serial.serial_for_url(sim.url, baudrate=921600, timeout=0)
        try:
            buf = b""
            for k in range(20):
                plant.x += 1e-7 * k
                plant.t_s += 1e-3
                sim.pump()
                select.select([port.fileno()], [], [], 5.0)
                buf += port.read(4096)
                i = buf.find(b"\xa5\x5a")
                assert i >= 0 and len(buf) - i >= 28, k
                frame, buf = buf[i:i + 28], buf[i + 28:]
                fields = struct.unpack(fmt, frame)
                sync, version, status, signal, reserved, seq, counts, ts, crc_field = fields
                assert sync == b"\xa5\x5a" and version == 1 and reserved == 0 and status == 0
                assert crc(frame[2:26]) == crc_field
                assert seq == k and counts == round(plant.x / 1e-9) and ts == round(plant.t_s * 1e9)
                assert signal == sim.cfg.signal
        finally:
            port.close()
