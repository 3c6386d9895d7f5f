"""The cyclic PDO codec against the CiA 301 byte layout (little-endian, mapping order), and frame reuse."""

from __future__ import annotations

import copy

import can
import pytest
from stagectl.drivers import pdo_codec


def test_rpdo1_layout_controlword_then_torque_little_endian():
    enc = pdo_codec.Rpdo1Encoder(0x201)
    msg = enc.encode(0x000F, -2)
    assert msg.arbitration_id == 0x201 and not msg.is_extended_id and msg.dlc == 4
    assert bytes(msg.data) == bytes([0x0F, 0x00, 0xFE, 0xFF])  # U16 0x000F, INT16 -2 (two's complement)
    again = enc.encode(0x0002, 300)
    assert again is msg  # the same preallocated frame, repacked in place
    assert bytes(msg.data) == bytes([0x02, 0x00, 0x2C, 0x01])


def test_rpdo1_refuses_out_of_range_values():
    enc = pdo_codec.Rpdo1Encoder(0x201)
    with pytest.raises(Exception):
        enc.encode(0x0F, 40000)  # INT16 range


def test_tpdo_decoding_follows_the_mapping():
    data = bytes([0x37, 0x02]) + (-123456).to_bytes(4, "little", signed=True)
    assert pdo_codec.decode_tpdo1(data) == (0x0237, -123456)
    assert pdo_codec.decode_tpdo1(data[:5]) is None
    assert pdo_codec.decode_tpdo2((-7).to_bytes(4, "little", signed=True)) == -7
    assert pdo_codec.decode_tpdo2(b"\x00") is None


def test_a_deep_copy_is_an_independent_plain_message():
    enc = pdo_codec.Rpdo1Encoder(0x201)
    sent = copy.deepcopy(enc.encode(0x0F, 5))
    enc.encode(0x0F, 6)  # the next cycle reuses the frame
    assert type(sent) is can.Message
    assert bytes(sent.data) == bytes([0x0F, 0x00, 0x05, 0x00])
    assert sent.arbitration_id == 0x201 and sent.dlc == 4 and not sent.is_extended_id


def test_frames_travel_over_the_virtual_bus_unchanged():
    a = can.Bus(interface="virtual", channel="pdo_codec_test")
    b = can.Bus(interface="virtual", channel="pdo_codec_test")
    try:
        enc = pdo_codec.Rpdo1Encoder(0x205)
        a.send(enc.encode(0x0F, 1))
        a.send(enc.encode(0x0F, 2))
        a.send(pdo_codec.frame(0x80))
        got = [b.recv(1.0) for _ in range(3)]
        assert [bytes(m.data) for m in got] == [b"\x0f\x00\x01\x00", b"\x0f\x00\x02\x00", b""]
        assert [m.arbitration_id for m in got] == [0x205, 0x205, 0x80]
    finally:
        a.shutdown()
        b.shutdown()
