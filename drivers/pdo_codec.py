"""Pure, preallocated codec for the cyclic CiA 402 frames (CiA 301 PDO/SYNC layout, little-endian).

The cyclic path of :class:`~stagectl.drivers.cia402.Cia402Drive` sends a SYNC, receives TPDO1 and sends RPDO1
every period. Building a ``can.Message`` and a ``bytes`` object per frame allocates; python-can's in-process
``virtual`` bus then ``deepcopy``-s every sent frame once per listening bus (~6 µs each through the generic
``copy.deepcopy`` machinery). This module keeps one frame object per cyclic COB-ID, packs the payload into its
preallocated ``bytearray`` in place (``struct.pack_into``), and gives the frames a ``__deepcopy__`` that builds
the copy directly (a new message with its own copy of the data, so a receiver never sees a later cycle's
payload). Decoding unpacks from the received buffer without copying.

Layouts (the mapping the driver configures, docs/canopen.md)::

    TPDO1  0x180+node  statusword 0x6041 U16 | position actual 0x6064 INT32      6 bytes
    TPDO2  0x280+node  velocity actual 0x606C INT32                               4 bytes
    RPDO1  0x200+node  controlword 0x6040 U16 | target torque 0x6071 INT16       4 bytes
    SYNC   0x080       no data

Pure: no I/O, no clock; the caller sends the returned frame.
"""

from __future__ import annotations

import struct
from typing import Any

import can

TPDO1 = struct.Struct("<Hi")
TPDO2 = struct.Struct("<i")
RPDO1 = struct.Struct("<Hh")

__all__ = ["RPDO1", "TPDO1", "TPDO2", "CyclicFrame", "Rpdo1Encoder", "decode_tpdo1", "decode_tpdo2"]


class CyclicFrame(can.Message):
    """A ``can.Message`` reused every cycle; ``deepcopy`` (python-can's virtual bus) copies it cheaply."""

    __slots__ = ()

    def __deepcopy__(self, memo: dict[int, Any] | None = None) -> can.Message:
        return can.Message(timestamp=self.timestamp, arbitration_id=self.arbitration_id,
                           is_extended_id=self.is_extended_id, is_remote_frame=self.is_remote_frame,
                           is_error_frame=self.is_error_frame, channel=self.channel, dlc=self.dlc,
                           data=bytearray(self.data), is_fd=self.is_fd, is_rx=self.is_rx,
                           bitrate_switch=self.bitrate_switch, error_state_indicator=self.error_state_indicator,
                           check=False)


def frame(cob_id: int, data: bytes = b"") -> CyclicFrame:
    """A reusable standard-ID frame with a preallocated payload."""
    return CyclicFrame(arbitration_id=cob_id, data=bytearray(data), is_extended_id=False)


class Rpdo1Encoder:
    """RPDO1 (controlword, target torque) packed in place into one preallocated frame."""

    __slots__ = ("msg", "_buf")

    def __init__(self, cob_id: int) -> None:
        self.msg = frame(cob_id, bytes(RPDO1.size))
        self._buf: bytearray = self.msg.data

    def encode(self, controlword: int, torque: int) -> CyclicFrame:
        """The frame carrying ``controlword`` (U16) and ``torque`` (INT16, 0x6071 units); no allocation."""
        RPDO1.pack_into(self._buf, 0, controlword, torque)
        return self.msg


def decode_tpdo1(data: bytes | bytearray) -> tuple[int, int] | None:
    """(statusword, raw position counts) of a TPDO1 payload, None if shorter than 6 bytes."""
    if len(data) < TPDO1.size:
        return None
    sw, raw = TPDO1.unpack_from(data)
    return int(sw), int(raw)


def decode_tpdo2(data: bytes | bytearray) -> int | None:
    """Raw velocity (0x606C units) of a TPDO2 payload, None if shorter than 4 bytes."""
    if len(data) < TPDO2.size:
        return None
    return int(TPDO2.unpack_from(data)[0])
