"""Serial interferometer streaming protocol: frame encoder and incremental byte-level parser (pure, no I/O).

The interferometer streams one fixed-size binary frame per sample, unsolicited, at its output rate.
All multi-byte fields are **little-endian**. One frame is :data:`FRAME_LEN` = 28 bytes:

====== ==== ======= ====================================================================================
offset size type    field
====== ==== ======= ====================================================================================
0      2    u8[2]   sync word ``A5 5A``
2      1    u8      protocol version, :data:`VERSION` = 1
3      1    u8      status flags (:class:`Status`, bit set = condition present)
4      1    u8      signal strength, 0 (no beam) … 255 (full scale)
5      1    u8      reserved, sent as 0, ignored by receivers
6      4    u32     sequence counter, +1 per frame, wraps 2**32 → 0
10     8    i64     position in counts (two's complement); position_m = counts × resolution_m
18     8    u64     sample timestamp [ns] on the device clock (the sim uses its ``time.monotonic_ns()``
                    at send time, or plant time in lock-step), wraps 2**64
26     2    u16     CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0) over bytes
                    2..25 (everything after the sync word, before the CRC); ``binascii.crc_hqx(b, 0xFFFF)``
====== ==== ======= ====================================================================================

Why a signed 64-bit position: at a resolution of 1 pm per count it spans ±9.2·10⁶ m; at 1 nm, ±9.2·10⁹ m.
A 32-bit counter would wrap after ±2.1 m at 1 nm (±2.1 mm at 1 pm), so real travel could wrap it; 64 bits
never wrap for any stage, so the receiver needs no unwrapping and a lost frame cannot cause a wrap error.

Status bits (:class:`Status`): bit 0 ``SIGNAL_LOST`` (beam interrupted / too weak to count), bit 1
``GLITCH`` (the device saw a position glitch, e.g. fringe count error), bit 2 ``LASER_UNLOCKED`` (laser
not frequency-locked / warming up), bit 3 ``ERROR`` (other device error), bit 4 ``OVERSPEED`` (velocity above
the counting limit), bits 5–7 reserved.

Link budget: 8N1 carries baud/10 bytes/s, so 28-byte frames top out at baud / 280 frames/s
(3291 Hz at 921 600 baud, 7142 Hz at 2 Mbaud).

Parser rules (:class:`FrameParser`): it searches for the sync word; a candidate frame whose CRC fails is
counted in ``crc_errors`` and the search restarts **one byte after** the failed sync word (so a real frame
that starts inside a corrupt or garbage region is still found); bytes skipped are counted in
``bytes_discarded``; a CRC-valid frame with an unknown version is skipped and counted in
``version_errors``. Sequence discontinuities are counted in ``sequence_gaps`` (events) and
``frames_lost`` (missing sequence numbers); a step backwards (reset, duplicate) is counted in
``sequence_resets``. ``feed`` never raises, never blocks and keeps at most ``FRAME_LEN - 1`` bytes between
calls.
"""

from __future__ import annotations

import binascii
import enum
import struct
from dataclasses import dataclass

__all__ = [
    "FRAME_LEN",
    "SYNC",
    "VERSION",
    "Frame",
    "FrameParser",
    "LinkBytes",
    "ParserStats",
    "Status",
    "crc16",
    "encode_frame",
    "max_frame_rate_hz",
]

SYNC = b"\xa5\x5a"
VERSION = 1
_BODY = struct.Struct("<BBBBIqQ")  # version, status, strength, reserved, seq, counts, timestamp
_CRC = struct.Struct("<H")
FRAME_LEN = len(SYNC) + _BODY.size + _CRC.size  # 28
_CRC_OFF = len(SYNC) + _BODY.size  # 26
_SEQ_MOD = 1 << 32
_TS_MOD = 1 << 64
_I64_MIN = -(1 << 63)
_I64_MAX = (1 << 63) - 1


class Status(enum.IntFlag):
    """Status flag bits of byte 3. Any of them set means the position is not trustworthy."""

    SIGNAL_LOST = 0x01
    GLITCH = 0x02
    LASER_UNLOCKED = 0x04
    ERROR = 0x08
    OVERSPEED = 0x10


class LinkBytes(int):
    """Return type of a simulated device's lock-step ``pump()``: the number of bytes it has just written to
    the link. A driver whose pump returns a ``LinkBytes`` waits for exactly that many bytes (0: none), so frames
    that a fault suppressed cost no waiting; any other return value (e.g. ``SimWorld.pump``'s message count)
    means "unknown", and the driver waits for one new frame instead."""

    __slots__ = ()


def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (check value of ``b"123456789"`` is 0x29B1)."""
    return binascii.crc_hqx(data, 0xFFFF)


def max_frame_rate_hz(baudrate: int) -> float:
    """Highest frame rate an 8N1 link of ``baudrate`` [bit/s] can carry: baud / (10 · FRAME_LEN) [Hz]."""
    return baudrate / (10.0 * FRAME_LEN)


@dataclass(frozen=True, slots=True)
class Frame:
    """One decoded, CRC-valid frame.

    Attributes
    ----------
    seq : int
        Sequence counter (u32).
    counts : int
        Position [counts]; multiply by the resolution [m/count] for metres.
    status : int
        Status flags (:class:`Status` bits).
    signal : int
        Signal strength 0–255.
    timestamp_ns : int
        Sample timestamp [ns] on the device clock.
    lost_before : int
        Frames missing between the previous frame and this one (0 if contiguous or first).
    """

    seq: int
    counts: int
    status: int = 0
    signal: int = 255
    timestamp_ns: int = 0
    lost_before: int = 0


def encode_frame(seq: int, counts: int, status: int = 0, signal: int = 255, timestamp_ns: int = 0) -> bytes:
    """Encode one frame (see the module table).

    ``seq`` wraps modulo 2**32 and ``timestamp_ns`` modulo 2**64.

    Raises
    ------
    ValueError
        ``counts`` outside the signed 64-bit range, ``status`` or ``signal`` outside 0–255.
    """
    if not _I64_MIN <= counts <= _I64_MAX:
        raise ValueError(f"counts: {counts} outside the signed 64-bit range")
    if not 0 <= status <= 0xFF:
        raise ValueError(f"status: {status} outside 0..255")
    if not 0 <= signal <= 0xFF:
        raise ValueError(f"signal: {signal} outside 0..255")
    body = _BODY.pack(VERSION, status, signal, 0, seq % _SEQ_MOD, counts, timestamp_ns % _TS_MOD)
    return SYNC + body + _CRC.pack(binascii.crc_hqx(body, 0xFFFF))


@dataclass(frozen=True, slots=True)
class ParserStats:
    """Snapshot of the parser counters (all cumulative since construction or :meth:`FrameParser.reset`)."""

    frames: int
    crc_errors: int
    version_errors: int
    sequence_gaps: int
    frames_lost: int
    sequence_resets: int
    bytes_in: int
    bytes_discarded: int


class FrameParser:
    """Incremental parser: ``feed(bytes) -> list[Frame]``. Pure: no I/O, no clock, never raises on data."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.reset()

    def reset(self) -> None:
        """Drop buffered bytes and zero the counters."""
        self._buf.clear()
        self._last_seq: int | None = None
        self.frames = 0
        self.crc_errors = 0
        self.version_errors = 0
        self.sequence_gaps = 0
        self.frames_lost = 0
        self.sequence_resets = 0
        self.bytes_in = 0
        self.bytes_discarded = 0

    @property
    def buffered(self) -> int:
        """Bytes held for the next call (always < FRAME_LEN)."""
        return len(self._buf)

    def stats(self) -> ParserStats:
        return ParserStats(
            self.frames, self.crc_errors, self.version_errors, self.sequence_gaps, self.frames_lost,
            self.sequence_resets, self.bytes_in, self.bytes_discarded,
        )

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        """Consume ``data`` and return the CRC-valid frames completed by it, oldest first.

        Real-time safe: O(len(data)), no allocation beyond the returned frames and one buffer copy.
        """
        out: list[Frame] = []
        if not isinstance(data, (bytes, bytearray, memoryview)):  # not bytes-like: nothing to parse
            return out
        chunk = bytes(data)
        self.bytes_in += len(chunk)
        buf = self._buf
        buf += chunk
        n = len(buf)
        pos = 0
        find = buf.find
        while True:
            i = find(SYNC, pos)
            if i < 0:
                # keep a trailing first sync byte: it may start a frame completed by the next call
                keep = 1 if n > pos and buf[n - 1] == SYNC[0] else 0
                self.bytes_discarded += n - pos - keep
                pos = n - keep
                break
            self.bytes_discarded += i - pos
            if n - i < FRAME_LEN:
                pos = i
                break
            body = buf[i + 2 : i + _CRC_OFF]
            (crc,) = _CRC.unpack_from(buf, i + _CRC_OFF)
            if binascii.crc_hqx(body, 0xFFFF) != crc:
                self.crc_errors += 1
                self.bytes_discarded += 1
                pos = i + 1
                continue
            version, status, signal, _res, seq, counts, ts = _BODY.unpack(body)
            if version != VERSION:
                self.version_errors += 1
                self.bytes_discarded += FRAME_LEN
                pos = i + FRAME_LEN
                continue
            lost = 0
            last = self._last_seq
            if last is not None:
                d = (seq - last - 1) % _SEQ_MOD
                if d:
                    if d < _SEQ_MOD // 2:
                        self.sequence_gaps += 1
                        self.frames_lost += d
                        lost = d
                    else:
                        self.sequence_resets += 1
            self._last_seq = seq
            self.frames += 1
            out.append(Frame(seq, counts, status, signal, ts, lost))
            pos = i + FRAME_LEN
        if pos:
            del buf[:pos]
        return out
