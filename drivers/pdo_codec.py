"""Pure, preallocated codec for the cyclic CiA 402 frames (CiA 301 PDO/SYNC layout, little-endian).

The cyclic path of :class:`~stagectl.drivers.cia402.Cia402Drive` sends a SYNC, receives TPDO1 and sends RPDO1
every period. Building a ``can.Message`` and a ``bytes`` object per frame allocates; python-can's in-process
``virtual`` bus then ``deepcopy``-s every sent frame once per listening bus (~6 µs each through the generic
``copy.deepcopy`` machinery). This module keeps one frame object per cyclic COB-ID, packs the payload into its
preallocated ``bytearray`` in place (``struct.pack_into``), and gives the frames a ``__deepcopy__`` that builds
the copy directly (a new message with its own copy of the data, so a receiver never sees a later cycle's
payload). Decoding unpacks from the received buffer without copying.

Layouts. A PDO's payload is its mapped objects in mapping order, each little-endian, at the bit length its
mapping entry (``0xIIIISSLL``: index, sub-index, length in bits) gives; :class:`PdoLayout` turns a mapping as
read back from the device, plus each object's data type from the object dictionary (signedness), into one
``struct.Struct`` (byte-aligned entries only; at most 64 bits). The driver builds its codecs from the mappings
it reads back at start-up (docs/canopen.md)::

    TPDO1  0x180+node  statusword 0x6041 U16 | position actual 0x6064 INT32      6 bytes   "<Hi"
    TPDO2  0x280+node  velocity actual 0x606C INT32                               4 bytes   "<i"
    RPDO1  0x200+node  controlword 0x6040 U16 | target torque 0x6071 INT16       4 bytes   "<Hh"
    SYNC   0x080       no data

canopen's generic PDO machinery (``canopen.pdo``) stays for configuration and tests; the cyclic path packs and
unpacks with these structs (tests/canopen/test_pdo_codec.py checks them against ``canopen.pdo`` for the same
mapping). Pure: no I/O, no clock; the caller sends the returned frame.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import can

from stagectl.drivers.inproc import copy_message

__all__ = ["RPDO1", "RPDO1_MAPPING", "STRUCT_CODES", "TPDO1", "TPDO1_MAPPING", "TPDO2", "TPDO2_MAPPING",
           "CIA402_TYPES", "CyclicFrame", "PdoLayout", "Rpdo1Encoder", "decode_tpdo1", "decode_tpdo2", "frame"]

#: CiA 301 basic data types (the EDS ``DataType`` codes) of byte-aligned PDO entries → (struct code, bits)
STRUCT_CODES: dict[int, tuple[str, int]] = {
    0x01: ("B", 8),    # BOOLEAN, one byte in a byte-aligned entry
    0x02: ("b", 8),    # INTEGER8
    0x03: ("h", 16),   # INTEGER16
    0x04: ("i", 32),   # INTEGER32
    0x05: ("B", 8),    # UNSIGNED8
    0x06: ("H", 16),   # UNSIGNED16
    0x07: ("I", 32),   # UNSIGNED32
    0x08: ("f", 32),   # REAL32
    0x11: ("d", 64),   # REAL64
    0x15: ("q", 64),   # INTEGER64
    0x1B: ("Q", 64),   # UNSIGNED64
}

#: the data types of the CiA 402 objects stagectl maps (CiA 402-2), for a mapping whose device gives none
CIA402_TYPES: dict[tuple[int, int], int] = {
    (0x6040, 0): 0x06,  # controlword UNSIGNED16
    (0x6041, 0): 0x06,  # statusword UNSIGNED16
    (0x6064, 0): 0x04,  # position actual value INTEGER32
    (0x606C, 0): 0x04,  # velocity actual value INTEGER32
    (0x6071, 0): 0x03,  # target torque INTEGER16
}

#: the mappings the CiA 402 driver writes (0xIIIISSLL)
TPDO1_MAPPING = (0x60410010, 0x60640020)
TPDO2_MAPPING = (0x606C0020,)
RPDO1_MAPPING = (0x60400010, 0x60710010)


@dataclass(frozen=True)
class PdoLayout:
    """The byte layout of one PDO: ``entries`` (mapping entries ``0xIIIISSLL`` in order) and the
    ``struct.Struct`` that packs/unpacks its payload, one value per entry (little-endian, no padding)."""

    entries: tuple[int, ...]
    struct: struct.Struct

    @classmethod
    def from_mapping(cls, entries: Sequence[int], data_type: Callable[[int, int], int | None]) -> PdoLayout:
        """The layout of a PDO mapping; ``data_type(index, sub)`` is the object's CiA 301 data type code (from
        the object dictionary; None: unknown, then :data:`CIA402_TYPES`).

        Raises
        ------
        ValueError
            An entry that is not byte-aligned, an unknown or non-basic data type, a data type that differs from
            the one CiA 402 defines for the object, a length that differs from the type's, or more than 64 bits
            in all (one line naming the entry).
        """
        codes = []
        bits = 0
        for e in entries:
            index, sub, length = (e >> 16) & 0xFFFF, (e >> 8) & 0xFF, e & 0xFF
            where = f"mapping entry 0x{e:08X} (0x{index:04X}:{sub:02X}, {length} bits)"
            dt = data_type(index, sub)
            std = CIA402_TYPES.get((index, sub))
            if dt is None:
                dt = std
            elif std is not None and dt != std:
                # e.g. a signed torque declared unsigned: the first negative value would not pack
                raise ValueError(f"{where}: the drive's object dictionary gives data type 0x{dt:02X}, CiA 402 "
                                 f"defines 0x{std:02X} for this object; correct the EDS")
            if dt is None or dt not in STRUCT_CODES:
                raise ValueError(f"{where}: data type {'unknown' if dt is None else f'0x{dt:02X}'} is not a "
                                 f"basic type the cyclic codec packs")
            code, n = STRUCT_CODES[dt]
            if length != n:
                raise ValueError(f"{where}: length differs from its data type's {n} bits (not byte-aligned "
                                 f"or a partial mapping: not supported on the cyclic path)")
            codes.append(code)
            bits += n
        if bits > 64:
            raise ValueError(f"mapping {[f'0x{e:08X}' for e in entries]}: {bits} bits exceed a CAN frame's 64")
        return cls(tuple(int(e) for e in entries), struct.Struct("<" + "".join(codes)))

    @property
    def size(self) -> int:
        """Payload length [bytes]."""
        return self.struct.size


def _no_od(index: int, sub: int) -> int | None:
    return None


TPDO1_LAYOUT = PdoLayout.from_mapping(TPDO1_MAPPING, _no_od)
TPDO2_LAYOUT = PdoLayout.from_mapping(TPDO2_MAPPING, _no_od)
RPDO1_LAYOUT = PdoLayout.from_mapping(RPDO1_MAPPING, _no_od)
TPDO1 = TPDO1_LAYOUT.struct  # "<Hi"
TPDO2 = TPDO2_LAYOUT.struct  # "<i"
RPDO1 = RPDO1_LAYOUT.struct  # "<Hh"


class CyclicFrame(can.Message):
    """A ``can.Message`` reused every cycle; ``deepcopy`` (python-can's virtual bus) copies it cheaply."""

    __slots__ = ()

    def __deepcopy__(self, memo: dict[int, Any] | None = None) -> can.Message:
        return copy_message(self)


def frame(cob_id: int, data: bytes = b"") -> CyclicFrame:
    """A reusable standard-ID frame with a preallocated payload."""
    return CyclicFrame(arbitration_id=cob_id, data=bytearray(data), is_extended_id=False)


class Rpdo1Encoder:
    """RPDO1 (controlword, target torque) packed in place into one preallocated frame, with the layout of the
    mapping (default: :data:`RPDO1_MAPPING`'s, controlword U16 then target torque INT16)."""

    __slots__ = ("msg", "_buf", "_pack")

    def __init__(self, cob_id: int, layout: PdoLayout = RPDO1_LAYOUT) -> None:
        if len(layout.entries) != 2:
            raise ValueError(f"RPDO1 layout: needs two entries (controlword, target torque), got {layout.entries}")
        self.msg = frame(cob_id, bytes(layout.size))
        self._buf: bytearray = self.msg.data
        self._pack = layout.struct.pack_into

    def encode(self, controlword: int, torque: int) -> CyclicFrame:
        """The frame carrying ``controlword`` (U16) and ``torque`` (INT16, 0x6071 units); no allocation."""
        self._pack(self._buf, 0, controlword, torque)
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
