"""The virtual bus's socketcand server against the daemon's protocol (linux-can/socketcand doc/protocol.md and
its C source): every command gets the daemon's reply, never silence. Raw TCP clients on loopback."""

from __future__ import annotations

import re
import socket

import can
import pytest

from stagectl.sim.socketcand import SocketcandServer, format_frame, parse_send, split_commands, timestamp


@pytest.fixture
def server():
    srv = SocketcandServer(can_name="can0")
    srv.start()
    yield srv
    srv.stop()


class Client:
    def __init__(self, srv):
        self.s = socket.create_connection((srv.host, srv.port), timeout=5.0)  # failure guard only
        self.buf = b""

    def element(self):
        """The next ``< … >`` element from the server (b"" at EOF)."""
        while True:
            cmds, rest = split_commands(self.buf)
            if cmds:
                first = cmds[0].encode()
                self.buf = self.buf[self.buf.index(first) + len(first):]
                return first
            chunk = self.s.recv(4096)
            if not chunk:
                return b""
            self.buf += chunk

    def ask(self, cmd):
        self.s.sendall(cmd)
        return self.element()

    def close(self):
        self.s.close()


@pytest.fixture
def client(server):
    made = []

    def make(raw=True):
        c = Client(server)
        made.append(c)
        assert c.element() == b"< hi >"
        if raw:
            assert c.ask(b"< open can0 >") == b"< ok >"
            assert c.ask(b"< rawmode >") == b"< ok >"
        return c

    yield make
    for c in made:
        c.close()


def test_open_of_a_bus_not_served_is_refused_and_closed(client):
    c = client(raw=False)
    assert c.ask(b"< open vcan7 >") == b"< error could not open bus >"
    assert c.element() == b""  # connection closed, as the daemon does


@pytest.mark.parametrize("stage, cmd, reply", [
    ("nobus", b"< rawmode >", b"< error unknown command >"),
    ("nobus", b"< echo >", b"< error unknown command >"),
    ("bcm", b"< echo >", b"< echo >"),
    ("bcm", b"< bcmmode >", b"< error unknown command >"),
    ("bcm", b"< isotpmode >", b"< error unknown command >"),
    ("bcm", b"< controlmode >", b"< error unknown command >"),
    ("bcm", b"< subscribe 0 0 123 >", b"< error unknown command >"),
    ("raw", b"< echo >", b"< echo >"),
    ("raw", b"< bcmmode >", b"< error unknown command >"),
    ("raw", b"< isotpmode >", b"< error unknown command >"),
    ("raw", b"< controlmode >", b"< error unknown command >"),
    ("raw", b"< frobnicate >", b"< error unknown command >"),
])
def test_every_command_is_answered(client, stage, cmd, reply):
    c = client(raw=stage == "raw")
    if stage == "bcm":
        assert c.ask(b"< open can0 >") == b"< ok >"
    assert c.ask(cmd) == reply
    assert c.ask(b"< echo >") in (b"< echo >", b"< error unknown command >")  # still talking


def test_garbage_before_a_command_is_skipped_and_ids_follow_the_daemon(server, client):
    c = client()
    c.s.sendall(b"xx junk < send 123 1 aa >\r\nnoise< send 1 0 >< send 00000001 2 1 f1 >")
    got = []
    while len(got) < 3:
        m = server.recv(5.0)  # failure guard
        assert m is not None
        got.append((m.arbitration_id, m.is_extended_id, bytes(m.data)))
    assert got == [(0x123, False, b"\xaa"), (0x001, False, b""), (0x001, True, b"\x01\xf1")]


def test_parse_send_rules():
    assert parse_send("< send 7FF 0 >").arbitration_id == 0x7FF
    assert parse_send("< send 800 0 >") is None  # 3 digits but beyond 11 bits
    assert parse_send("< send 123 2 1 >") is None  # length does not match
    assert parse_send("< send 123 9 1 2 3 4 5 6 7 8 9 >") is None


def test_no_frame_lost_right_after_rawmode_ok(server, client):
    c = client()  # ok read: the settle window is running and this client has not sent anything
    for k in range(5):
        server.send(can.Message(arbitration_id=0x180 + k, data=bytes([k]), is_extended_id=False))
    got = [c.element() for _ in range(5)]
    assert [int(g.split()[2], 16) for g in got] == [0x180 + k for k in range(5)]


def test_error_frame_and_timestamp_format():
    line = format_frame(can.Message(arbitration_id=0x40, is_error_frame=True, is_extended_id=True), 12.5)
    assert line == b"< error 040 12.500000 >"
    assert format_frame(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False), 3.0) == \
        b"< frame 080 3.000000  >"
    assert format_frame(can.Message(arbitration_id=0x1AAAAAAA, data=b"\x01", is_extended_id=True), 3.0) == \
        b"< frame 1AAAAAAA 3.000000 01 >"
    stamps = [timestamp() for _ in range(2000)]
    assert all(b >= a for a, b in zip(stamps, stamps[1:]))
    assert re.fullmatch(rb"< frame 080 \d+\.\d{6}  >", format_frame(can.Message(arbitration_id=0x80, is_extended_id=False)))


def test_on_receive_serves_a_frame_in_the_reader_thread(server, client):
    """With ``on_receive`` set, a client frame is handled in the reader thread that parsed it (the world answers a
    SYNC there, with no hand-over to its own thread); a frame the handler declines is queued for recv()."""
    import threading

    seen = []

    def handler(msg):
        seen.append((msg.arbitration_id, threading.current_thread().name))
        return msg.arbitration_id == 0x080

    server.on_receive = handler
    c = client()
    c.s.sendall(b"< send 080 0 >< send 201 2 0f 00 >")
    queued = server.recv(5.0)  # failure guard only
    assert queued is not None and queued.arbitration_id == 0x201 and bytes(queued.data) == b"\x0f\x00"
    assert seen == [(0x080, "socketcand-client"), (0x201, "socketcand-client")]
    assert server.served_in_reader == 1 and server.recv(0) is None  # the SYNC was not queued
