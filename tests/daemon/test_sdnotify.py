"""sd_notify against a real AF_UNIX datagram socket (path and abstract namespace)."""

from __future__ import annotations

import os
import socket
import uuid

import pytest

from stagectl.daemon.sdnotify import SdNotifier, watchdog_interval_s


def _recv(sock: socket.socket) -> set[str]:
    sock.settimeout(5.0)  # failure guard only; the datagram is already queued
    return set(sock.recv(4096).decode().split("\n"))


@pytest.fixture
def path_socket(tmp_path):
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    addr = str(tmp_path / "notify.sock")
    s.bind(addr)
    yield addr, s
    s.close()


def test_path_socket_ready_status_watchdog_stopping(path_socket):
    addr, s = path_socket
    dut = SdNotifier(environ={"NOTIFY_SOCKET": addr})
    assert dut.enabled
    assert dut.ready("cycles 10")
    assert _recv(s) == {"READY=1", f"MAINPID={os.getpid()}", "STATUS=cycles 10"}
    assert dut.status("line1\nline2")
    assert _recv(s) == {"STATUS=line1 line2"}  # a newline would inject a bogus assignment
    assert dut.watchdog()
    assert _recv(s) == {"WATCHDOG=1"}
    assert dut.watchdog_trigger()
    assert _recv(s) == {"WATCHDOG=trigger"}
    assert dut.stopping("bye")
    assert _recv(s) == {"STOPPING=1", "STATUS=bye"}
    dut.close()


def test_abstract_namespace_socket():
    name = f"stagectl-test-{uuid.uuid4().hex}"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind("\0" + name)
    try:
        dut = SdNotifier(environ={"NOTIFY_SOCKET": "@" + name})
        assert dut.watchdog()
        assert _recv(s) == {"WATCHDOG=1"}
    finally:
        s.close()


def test_noop_without_notify_socket_and_never_raises(tmp_path):
    dut = SdNotifier(environ={})
    assert not dut.enabled
    assert dut.ready() is False and dut.watchdog() is False
    gone = SdNotifier(environ={"NOTIFY_SOCKET": str(tmp_path / "missing.sock")})
    assert gone.ready() is False  # ENOENT: counted, not raised
    assert gone.errors == 1 and "FileNotFoundError" in gone.last_error


@pytest.mark.parametrize(
    "env,expected",
    [
        ({"WATCHDOG_USEC": "2000000"}, 2.0),
        ({"WATCHDOG_USEC": "500000", "WATCHDOG_PID": str(os.getpid())}, 0.5),
        ({"WATCHDOG_USEC": "500000", "WATCHDOG_PID": "1"}, None),  # meant for another process
        ({"WATCHDOG_USEC": "abc"}, None),
        ({"WATCHDOG_USEC": "0"}, None),
        ({}, None),
    ],
)
def test_watchdog_usec_parsing(env, expected):
    assert watchdog_interval_s(env) == expected
    assert SdNotifier(environ=env).watchdog_s == expected


def test_never_blocks_when_the_receiver_does_not_read(path_socket):
    addr, s = path_socket  # bound, never read: its datagram queue fills up
    dut = SdNotifier(environ={"NOTIFY_SOCKET": addr})
    results = [dut.status("x" * 200) for _ in range(2000)]  # would hang forever with a blocking socket
    assert results[0] is True and results[-1] is False
    assert dut.errors > 0 and "BlockingIOError" in dut.last_error
