"""Control socket protocol: errors name the field, the connection stays usable, bounds hold."""

from __future__ import annotations

import concurrent.futures
import json
import os
import socket
import stat
import threading

import pytest

from stagectl.daemon.control import ControlClient, ControlServer, RequestError


class _Handler:
    """A small real request handler: status, move with a range check, and a deferred 'slow' request."""

    def __init__(self) -> None:
        self.calls = 0
        self.deferred: list[concurrent.futures.Future] = []
        self.deferred_event = threading.Event()

    def __call__(self, req):
        self.calls += 1
        kind = req.get("request")
        if kind == "status":
            return {"state": "active", "calls": self.calls, "nan": float("nan")}
        if kind == "move":
            x = req.get("target_m")
            if not isinstance(x, (int, float)) or not -0.01 <= x <= 0.01:
                raise ValueError(f"target_m: must be within [-0.01, 0.01] m (got {x!r})")
            return {"target_m": x}
        if kind == "later":
            fut: concurrent.futures.Future = concurrent.futures.Future()
            self.deferred.append(fut)
            self.deferred_event.set()
            return fut
        raise RequestError("request", f"unknown request {kind!r}")


@pytest.fixture
def server(tmp_path):
    h = _Handler()
    dut = ControlServer(tmp_path / "run" / "control.sock", h, max_clients=8, max_line_bytes=1024,
                        max_out_bytes=64 * 1024, reply_timeout_s=0.5)
    dut.start()
    yield dut, h
    dut.stop()


def test_socket_is_unix_and_mode_0660(server):
    dut, _ = server
    st = os.stat(dut.path)
    assert stat.S_ISSOCK(st.st_mode)
    assert stat.S_IMODE(st.st_mode) == 0o660


def test_errors_name_the_field_and_connection_stays_usable(server):
    dut, _ = server
    with ControlClient(dut.path) as c:
        c.send_raw(b"{not json\n")
        r = c.read_reply()
        assert r["ok"] is False and r["field"] == "json"
        r = c.request({"request": "fly", "id": 3})
        assert r == {"ok": False, "error": "request: unknown request 'fly'", "field": "request", "id": 3}
        c.send_raw(b"[1, 2]\n")
        assert c.read_reply()["field"] == "request"
        r = c.request({"request": "move", "target_m": 5.0})
        assert r["ok"] is False and r["field"] == "target_m" and "m" in r["error"]
        r = c.request({"request": "move", "target_m": 0.002, "id": "a"})
        assert r == {"ok": True, "target_m": 0.002, "id": "a"}
        r = c.request({"request": "status"})
        assert r["ok"] is True and r["state"] == "active" and r["nan"] is None  # NaN is not JSON


def test_a_key_given_twice_is_refused_and_bytes_not_utf8_are_named(server):
    """{"request": "status", "request": "stop"} was read as its last value: a stop the line did not seem to
    ask for first. A key twice is refused, naming it, and the handler is not called (audit16)."""
    dut, h = server
    with ControlClient(dut.path) as c:
        c.send_raw(b'{"request": "status", "request": "move", "target_m": 0.001}\n')
        r = c.read_reply()
        assert r == {"ok": False, "field": "request",
                     "error": "request: given twice in one request (which one is meant?)"}, r
        c.send_raw(b'{"request": "move", "target_m": 0.001, "target_m": 0.002}\n')
        assert c.read_reply()["field"] == "target_m"
        assert h.calls == 0
        c.send_raw(b'\xff\xfe{"request": "status"}\n')
        r = c.read_reply()
        assert r["field"] == "json" and r["error"] == "json: not UTF-8 text (byte 0xff at offset 0)", r
        assert c.request({"request": "status"})["ok"] is True


def test_pipelined_requests_answered_in_order(server):
    dut, _ = server
    with ControlClient(dut.path) as c:
        c.send_raw(b"".join(json.dumps({"request": "status", "id": i}).encode() + b"\n" for i in range(50)))
        assert [c.read_reply()["id"] for _ in range(50)] == list(range(50))


def test_huge_line_rejected_then_usable(server):
    dut, _ = server
    with ControlClient(dut.path) as c:
        c.send_raw(b'{"request": "status", "pad": "' + b"x" * 100_000 + b'"}\n')
        r = c.read_reply()
        assert r["ok"] is False and r["field"] == "line"
        assert c.request({"request": "status", "id": 1})["ok"] is True
    assert dut.stats["long_lines"] == 1


def test_many_clients_at_once(server):
    dut, _ = server
    errors: list[str] = []

    def worker(k: int) -> None:
        try:
            with ControlClient(dut.path) as c:
                for i in range(25):
                    r = c.request({"request": "move", "target_m": 1e-4 * k, "id": i})
                    if r != {"ok": True, "target_m": 1e-4 * k, "id": i}:
                        errors.append(repr(r))
        except Exception as exc:  # noqa: BLE001
            errors.append(repr(exc))

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert errors == []


def test_a_new_client_evicts_the_quietest_when_all_slots_are_taken(server):
    """All 8 slots held: the 9th client is served, and the connection quiet longest gets an error line."""
    dut, _ = server
    held = [ControlClient(dut.path) for _ in range(8)]
    try:
        for c in held:  # make sure all 8 are accepted (held[0] is then the one quiet longest)
            assert c.request({"request": "status"})["ok"]
        with ControlClient(dut.path) as extra:
            assert extra.request({"request": "status"})["ok"]
        r = held[0].read_reply()
        assert r["ok"] is False and r["field"] == "connection" and "make room" in r["error"]
        assert held[1].request({"request": "status"})["ok"]  # the others keep their connection
        assert dut.stats["evicted"] == 1
    finally:
        for c in held:
            c.close()


def test_error_text_is_bounded_and_an_oversized_reply_is_an_error_not_a_disconnect(tmp_path):
    huge = "x" * 100_000

    def handler(req):
        if req.get("request") == "big":
            return {"blob": huge}
        raise ValueError(f"value: {huge}")

    dut = ControlServer(tmp_path / "c.sock", handler, max_out_bytes=8192)
    dut.start()
    try:
        with ControlClient(dut.path) as c:
            r = c.request({"request": "bad"})
            assert r["ok"] is False and r["field"] == "value"
            assert len(r["error"]) < 1100 and "more characters" in r["error"]
            r = c.request({"request": "big", "id": 3})
            assert r["ok"] is False and r["field"] == "reply" and r["id"] == 3
            assert c.request({"request": "bad"})["ok"] is False  # still connected
    finally:
        dut.stop()


def test_client_that_never_reads_is_disconnected_others_unaffected(server):
    dut, _ = server
    hog = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    hog.connect(str(dut.path))
    hog.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    hog.settimeout(10)
    line = json.dumps({"request": "status"}).encode() + b"\n"
    try:
        with ControlClient(dut.path) as good:
            sent = 0
            with pytest.raises(OSError):  # the server hangs up on the hog once its queue passes the bound
                for _ in range(200_000):
                    hog.sendall(line * 64)
                    sent += 1
            assert good.request({"request": "status"})["ok"]  # served throughout
        assert dut.stats["kicked_slow"] >= 1
    finally:
        hog.close()


def test_deferred_reply_and_timeout(server):
    dut, h = server
    with ControlClient(dut.path) as c:
        c.send_raw(b'{"request": "later", "id": 1}\n{"request": "status", "id": 2}\n')
        # wait until the server has taken the deferred request, then complete it from this thread
        assert h.deferred_event.wait(10)  # failure guard only
        h.deferred[0].set_result({"done": True})
        assert c.read_reply() == {"ok": True, "done": True, "id": 1}
        assert c.read_reply()["id"] == 2  # the queued request is served after it, in order
        r = c.request({"request": "later", "id": 3})  # never completed: timeout error, connection usable
        assert r["ok"] is False and r["field"] == "request" and r["id"] == 3
        fut = h.deferred[1]
        assert fut.cancelled()
        h_err = c.request({"request": "status"})
        assert h_err["ok"]


def test_stale_socket_file_is_replaced(tmp_path):
    path = tmp_path / "c.sock"
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(path))
    stale.close()  # file left behind, nobody listening
    dut = ControlServer(path, _Handler())
    dut.start()
    try:
        with ControlClient(path) as c:
            assert c.request({"request": "status"})["ok"]
        with pytest.raises(OSError, match="another daemon"):
            ControlServer(path, _Handler()).start()
    finally:
        dut.stop()
    assert not path.exists()


def test_stalled_half_line_connection_is_closed_after_idle_timeout(tmp_path):
    dut = ControlServer(tmp_path / "c.sock", _Handler(), idle_timeout_s=0.2)
    dut.start()
    try:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.connect(str(dut.path))
        s.sendall(b'{"request": "sta')  # never finished: a stuck or half-open client
        s.settimeout(20)  # failure guard; the server closes after 0.2 s idle
        assert s.recv(100) == b""
        s.close()
        assert dut.stats["kicked_idle"] == 1
        with ControlClient(dut.path) as c:  # the server is fine
            assert c.request({"request": "status"})["ok"]
    finally:
        dut.stop()


def test_too_long_socket_path_is_a_clear_error(tmp_path):
    with pytest.raises(OSError, match="at most 107 bytes"):
        ControlServer(tmp_path / ("d" * 120) / "control.sock", _Handler()).start()


def test_hostile_lines_get_field_errors_and_the_server_survives(tmp_path, caplog):
    """Found by the issue-5 audit: a deeply nested `id` (echoed in the reply) crashed the serving thread, and
    deeply nested JSON produced a traceback. Each must be a plain error naming the field."""
    dut = ControlServer(tmp_path / "c.sock", _Handler())  # default 64 KiB lines: room for deep nesting
    dut.start()
    try:
        _hostile_lines(dut, caplog)
    finally:
        dut.stop()


def _hostile_lines(dut: ControlServer, caplog) -> None:
    with ControlClient(dut.path) as c:
        for line, field in [
            (b'{"request": "status", "id": ' + b"[" * 900 + b"]" * 900 + b"}\n", "id"),
            (b'{"request": "status", "id": {"a": 1}}\n', "id"),
            (b'{"request": "status", "id": "' + b"i" * 300 + b'"}\n', "id"),
            (b"[" * 1000 + b"\n", "json"),  # RecursionError inside the decoder
            (b"\xff\xfe\xfd\n", "json"),  # not UTF-8
            (b"\x00\x01garbage\n", "json"),
            (b"42\n", "request"),
            (b"NaN\n", "request"),
        ]:
            c.send_raw(line)
            r = c.read_reply()
            assert r["ok"] is False and r["field"] == field and "id" not in r, (line[:40], r)
        assert c.request({"request": "status", "id": 2**62})["id"] == 2**62  # scalars are still echoed
        assert c.request({"request": "status", "id": "tag-1"})["id"] == "tag-1"
    assert dut.alive and dut.stats["internal_errors"] == 0
    assert "Traceback" not in caplog.text and not any(r.exc_info for r in caplog.records)
