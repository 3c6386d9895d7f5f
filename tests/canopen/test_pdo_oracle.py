"""The cyclic PDO codec against an independent oracle: canopen's own PDO machinery (``canopen.pdo.PdoMap``) for
the same mapping and the same object dictionary (the shipped CiA 402 EDS), encoding and decoding; and the driver's
codec built from the mapping it reads back at configure."""

from __future__ import annotations

import struct

import canopen
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from stagectl.drivers import pdo_codec
from stagectl.drivers.cia402 import DEFAULT_EDS

OD = canopen.import_od(str(DEFAULT_EDS))
#: every PDO-mappable object of the shipped EDS: (index, sub, bits)
MAPPABLE = [(v.index, v.subindex, len(v))
            for obj in OD.values()
            for v in ([obj] if isinstance(obj, canopen.objectdictionary.ODVariable) else list(obj.values()))
            if v.pdo_mappable]
RANGES = {"b": (-(1 << 7), (1 << 7) - 1), "h": (-(1 << 15), (1 << 15) - 1), "i": (-(1 << 31), (1 << 31) - 1),
          "B": (0, (1 << 8) - 1), "H": (0, (1 << 16) - 1), "I": (0, (1 << 32) - 1)}


def od_type(index: int, sub: int) -> int | None:
    var = OD.get_variable(index, sub)
    return None if var is None else int(var.data_type)


def oracle_map(entries):
    """canopen's PdoMap for ``entries`` (0xIIIISSLL), on a node with the same EDS, no network needed."""
    node = canopen.RemoteNode(1, OD)
    m = node.tpdo[1]
    m.clear()
    for e in entries:
        m.add_variable(e >> 16, (e >> 8) & 0xFF, e & 0xFF)
    return m


@st.composite
def mapping_and_values(draw):
    """A mapping of 1..4 distinct mappable objects (≤ 64 bits) in any order, and a value for each."""
    objs = draw(st.lists(st.sampled_from(MAPPABLE), min_size=1, max_size=4, unique=True)
                .filter(lambda xs: sum(b for _, _, b in xs) <= 64))
    entries = [(i << 16) | (s << 8) | b for i, s, b in objs]
    layout = pdo_codec.PdoLayout.from_mapping(entries, od_type)
    values = [draw(st.integers(*RANGES[c])) for c in layout.struct.format.lstrip("<")]
    return entries, values


def test_the_shipped_mappings_have_the_documented_layouts_from_the_eds_types():
    for entries, fmt in ((pdo_codec.TPDO1_MAPPING, "<Hi"), (pdo_codec.TPDO2_MAPPING, "<i"),
                         (pdo_codec.RPDO1_MAPPING, "<Hh")):
        assert pdo_codec.PdoLayout.from_mapping(entries, od_type).struct.format == fmt


@settings(max_examples=150, deadline=None)
@given(mapping_and_values())
def test_encoding_equals_canopens_pdo_encoding(case):
    entries, values = case
    m = oracle_map(entries)
    for var, v in zip(m.map, values):
        var.raw = v
    ours = pdo_codec.PdoLayout.from_mapping(entries, od_type).struct.pack(*values)
    assert ours == bytes(m.data)


@settings(max_examples=150, deadline=None)
@given(mapping_and_values(), st.data())
def test_decoding_equals_canopens_pdo_decoding(case, data):
    entries, _ = case
    layout = pdo_codec.PdoLayout.from_mapping(entries, od_type)
    payload = data.draw(st.binary(min_size=layout.size, max_size=layout.size))
    m = oracle_map(entries)
    m.data = bytearray(payload)
    assert list(layout.struct.unpack_from(payload)) == [var.raw for var in m.map]


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 0xFFFF), st.integers(-(1 << 15), (1 << 15) - 1))
def test_the_preallocated_rpdo1_frame_carries_canopens_bytes(cw, torque):
    layout = pdo_codec.PdoLayout.from_mapping(pdo_codec.RPDO1_MAPPING, od_type)
    msg = pdo_codec.Rpdo1Encoder(0x201, layout).encode(cw, torque)
    m = oracle_map(pdo_codec.RPDO1_MAPPING)
    m["Controlword"].raw = cw
    m["Target torque"].raw = torque
    assert bytes(msg.data) == bytes(m.data) and msg.dlc == 4


def test_tpdo1_decoding_matches_canopen_for_wrapping_positions():
    layout = pdo_codec.PdoLayout.from_mapping(pdo_codec.TPDO1_MAPPING, od_type)
    for sw, pos in ((0x0237, -123456), (0xFFFF, -(1 << 31)), (0x0000, (1 << 31) - 1)):
        payload = struct.pack("<Hi", sw, pos)
        m = oracle_map(pdo_codec.TPDO1_MAPPING)
        m.data = bytearray(payload)
        assert layout.struct.unpack_from(payload) == (m["Statusword"].raw, m["Position actual value"].raw)
        assert pdo_codec.decode_tpdo1(payload) == (sw, pos)


@pytest.mark.parametrize("entries, words", [
    ([0x60410008], "not byte-aligned"),                        # 8 bits of a U16
    ([0x60640020, 0x606C0020, 0x60410010], "exceed"),         # 80 bits
    ([0x20000020], "unknown"),                                 # not in the dictionary, not a known CiA 402 object
])
def test_mappings_the_codec_cannot_pack_are_refused_naming_the_entry(entries, words):
    with pytest.raises(ValueError, match=words):
        pdo_codec.PdoLayout.from_mapping(entries, od_type)


def test_the_driver_builds_its_codec_from_the_mapping_it_read_back(make_world, make_drive, monkeypatch):
    """The layouts come from the entries read back over SDO from the virtual drive (recorded on their way into
    the real ``from_mapping``), with the EDS's data types; the cycle then runs on them."""
    world = make_world()
    drive = make_drive(world.ready_info()["can"], velocity=True)
    drive.set_pump(world.pump)
    seen = []
    real = pdo_codec.PdoLayout.from_mapping.__func__

    def recording(cls, entries, data_type):
        layout = real(cls, entries, data_type)
        seen.append((tuple(entries), layout.struct.format))
        return layout

    monkeypatch.setattr(pdo_codec.PdoLayout, "from_mapping", classmethod(recording))
    drive.open()
    drive.configure()
    assert seen == [(pdo_codec.TPDO1_MAPPING, "<Hi"), (pdo_codec.TPDO2_MAPPING, "<i"),
                    (pdo_codec.RPDO1_MAPPING, "<Hh")]
    drive.enable()
    drive.sync()
    m = drive.read()
    drive.write(0.5)
    assert m.fresh and m.status == drive.statusword and world.drive is not None
    assert abs(m.position_m - world.plant.x_m) < 1e-6  # sensor resolution 1 nm


def test_an_eds_type_that_contradicts_cia402_is_refused_at_configure_time() -> None:
    """An EDS that declares the target torque 0x6071 UNSIGNED16 (CiA 402: INTEGER16) would make the first
    negative torque fail to pack in the cycle (a loop fault); the layout is refused up front, naming it."""
    def unsigned_torque(index: int, sub: int) -> int | None:
        return 0x06 if (index, sub) == (0x6071, 0) else pdo_codec.CIA402_TYPES.get((index, sub))

    with pytest.raises(ValueError, match=r"0x6071:00.*0x06.*CiA 402 defines 0x03"):
        pdo_codec.PdoLayout.from_mapping(pdo_codec.RPDO1_MAPPING, unsigned_torque)
    # the standard's own types pass, and a negative torque packs
    std = pdo_codec.PdoLayout.from_mapping(pdo_codec.RPDO1_MAPPING, lambda i, s: pdo_codec.CIA402_TYPES.get((i, s)))
    std.struct.pack(0x0F, -5)
