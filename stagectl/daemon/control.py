"""Control socket: a Unix-domain stream socket speaking JSON lines (no network listener).

Protocol: one JSON object per line in each direction. A request names its kind in ``"request"`` and may carry
an ``"id"`` (a string of at most 256 characters or a number) that is echoed in the reply::

    -> {"request": "move", "target_m": 0.001, "id": 7}
    <- {"ok": true, "id": 7, ...}
    -> {"request": "move", "target_m": "far"}
    <- {"ok": false, "error": "target_m: expected a number in m, got 'far'", "field": "target_m"}

Replies on one connection come in request order. Errors never close the connection; the client may go on.

Bounds (nothing a client does can block or crash the loop; the loop never touches this thread):

* one selector thread at normal priority serves every client with non-blocking sockets;
* at most ``max_clients`` connections; a new client when all are taken **evicts** the connection that has been
  quiet longest (no request awaiting the loop preferred; it gets an error line), so 32 half-open
  connections cannot lock ``stop`` out: a newcomer always gets in;
* at most ``lines_per_round`` requests per connection per serving round, and a connection's socket is not
  read again while complete lines of it wait: a flooding client gets back-pressure, and every other
  client's request (``stop``) is served within one round (at most ``max_clients × lines_per_round``
  requests);
* error texts are bounded (:data:`MAX_ERROR_CHARS`), and a reply larger than ``max_out_bytes`` is replaced by
  an error reply instead of disconnecting the client;
* a line longer than ``max_line_bytes`` gets an error reply (field ``line``) and is discarded;
* a client that does not read its replies is disconnected once ``max_out_bytes`` are queued for it;
* a connection idle for ``idle_timeout_s`` (half-open, stalled mid-line) is closed;
* JSON nested too deeply is a ``json`` error; an internal error while serving one connection closes that
  connection only (logged), never the serving thread;
* a request whose answer needs the loop (move, stop, reset) is answered when the loop has applied it, or
  with a timeout error after ``reply_timeout_s``; meanwhile that connection's further requests wait, others
  are served.

The socket file is created with mode ``0660`` (owner and group only); the group is the daemon's group (the
unit's ``Group=``) unless ``group`` names another.
"""

from __future__ import annotations

import concurrent.futures
import errno
import grp
import json
import logging
import math
import os
import selectors
import socket
import stat
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from stagectl.daemon._sched import demote_to_normal_priority
from stagectl.config.daemon import DaemonConfig
from stagectl.outputs import plain
from stagectl.runtime.requests import RequestError

__all__ = ["ControlClient", "ControlServer", "RequestError", "encode", "error_reply"]

log = logging.getLogger("stagectl.control")

Reply = dict[str, Any]
#: handler(request) -> reply dict, or a Future resolving to one; raises RequestError/ValueError for bad input
Handler = Callable[[dict[str, Any]], "Reply | concurrent.futures.Future[Reply]"]


#: longest error text in a reply [characters]; the rest is cut and its length said
MAX_ERROR_CHARS = 1000


def bound_text(text: str, limit: int = MAX_ERROR_CHARS) -> str:
    """``text`` cut to at most ``limit`` characters plus a note of how many were left out."""
    if len(text) <= limit:
        return text
    return f"{text[:limit]}... ({len(text) - limit} more characters)"


def error_reply(exc: BaseException) -> Reply:
    """Turn an exception into ``{"ok": false, "error": ..., "field": ...}``; the text is bounded
    (:data:`MAX_ERROR_CHARS`).

    ``ValueError("target_m: ...")`` (the loop's convention) gives ``field = "target_m"``.
    """
    msg = bound_text(str(exc) or type(exc).__name__)
    field = exc.field if isinstance(exc, RequestError) else None
    if field is None and isinstance(exc, ValueError):
        head, sep, _ = msg.partition(":")
        if sep and head and " " not in head.strip() and len(head) < 64:
            field = head.strip()
    out: Reply = {"ok": False, "error": msg}
    if field:
        out["field"] = field
    return out


def encode(reply: Reply) -> bytes:
    """One JSON line: NaN/inf as null, dataclasses and enums as plain data, anything else as its text."""
    return (json.dumps(plain(reply, json=True), allow_nan=False, default=str, separators=(",", ":")) + "\n").encode()


#: longest request ``id`` string echoed back [characters]
MAX_ID_CHARS = 256


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object whose keys are all different: ``{"request": "status", "request": "stop"}`` was read as
    its last value (a stop), not what the line seemed to ask first; a key given twice is refused."""
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise RequestError(key, "given twice in one request (which one is meant?)")
        out[key] = value
    return out


def _check_id(rid: Any) -> Any:
    """A request ``id`` is echoed in the reply, so only a short scalar is accepted (never a deep structure)."""
    if rid is None or isinstance(rid, bool):
        return rid
    if isinstance(rid, int) and -(2**63) <= rid < 2**63:
        return rid
    if isinstance(rid, float) and math.isfinite(rid):
        return rid
    if isinstance(rid, str) and len(rid) <= MAX_ID_CHARS:
        return rid
    raise RequestError("id", f"must be a string of at most {MAX_ID_CHARS} characters or a 64-bit/finite number")


class _Conn:
    __slots__ = ("sock", "rbuf", "wbuf", "discarding", "pending", "last_active", "closed", "peer")

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.rbuf = bytearray()
        self.wbuf = bytearray()
        self.discarding = False
        self.pending: tuple[concurrent.futures.Future[Reply], Any, float] | None = None
        self.last_active = time.monotonic()
        self.closed = False
        self.peer = ""


class ControlServer:
    """JSON-lines server on a Unix socket, served by one background thread (see module docstring)."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        handler: Handler,
        *,
        mode: int = 0o660,
        group: str | int | None = None,
        max_clients: int = 32,
        max_line_bytes: int = 65536,
        max_out_bytes: int = 1 << 20,
        idle_timeout_s: float = 600.0,
        reply_timeout_s: float = 5.0,
    ) -> None:
        self.path = Path(path)
        self.handler = handler
        self.mode = mode
        self.group = group
        self.max_clients = max_clients
        self.max_line_bytes = max_line_bytes
        self.max_out_bytes = max_out_bytes
        self.idle_timeout_s = idle_timeout_s
        self.reply_timeout_s = reply_timeout_s
        self._sel = selectors.DefaultSelector()
        self._listen: socket.socket | None = None
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._conns: dict[int, _Conn] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.lines_per_round = 4
        self._backlog: dict[int, _Conn] = {}  # connections with complete lines waiting (served each round)
        self.stats = {"accepted": 0, "rejected": 0, "evicted": 0, "requests": 0, "errors": 0, "kicked_slow": 0,
                      "kicked_idle": 0, "long_lines": 0, "internal_errors": 0, "oversized_replies": 0}

    @classmethod
    def from_config(cls, path: Path, handler: Handler, c: DaemonConfig) -> ControlServer:
        """A server with the ``daemon:`` section's bounds."""
        return cls(path, handler, group=c.socket_group, max_clients=c.max_clients, max_line_bytes=c.max_line_bytes,
                   max_out_bytes=c.max_out_bytes, idle_timeout_s=c.client_idle_timeout_s,
                   reply_timeout_s=c.reply_timeout_s)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Bind (replacing a stale socket file), set mode/group, start serving in a thread."""
        if len(os.fsencode(self.path)) > 107:  # sun_path is 108 bytes including the NUL
            raise OSError(errno.ENAMETOOLONG, f"{self.path}: a Unix socket path must be at most 107 bytes; "
                                              "use a shorter runtime directory")
        self.path.parent.mkdir(parents=True, mode=0o750, exist_ok=True)
        if self.path.exists() or self.path.is_symlink():
            st = self.path.lstat()
            if not stat.S_ISSOCK(st.st_mode):
                raise OSError(errno.EEXIST, f"{self.path} exists and is not a socket")
            probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                probe.settimeout(0.5)
                probe.connect(str(self.path))
            except OSError:
                self.path.unlink()  # stale socket from a previous run
            else:
                raise OSError(errno.EADDRINUSE, f"{self.path}: another daemon is serving this socket")
            finally:
                probe.close()
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        old_umask = os.umask(0o177)  # no window in which the socket is world-accessible
        try:
            s.bind(str(self.path))
        finally:
            os.umask(old_umask)
        if self.group is not None:
            gid = self.group if isinstance(self.group, int) else grp.getgrnam(self.group).gr_gid
            os.chown(self.path, -1, gid)
        os.chmod(self.path, self.mode)
        s.listen(64)
        s.setblocking(False)
        self._listen = s
        self._sel.register(s, selectors.EVENT_READ, "listen")
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._thread = threading.Thread(target=self._run, name="stagectl-control", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Stop serving, close every connection and remove the socket file."""
        self._stop.set()
        self._wakeup()
        if self._thread is not None:
            self._thread.join(timeout)
        try:
            if self.path.exists() and stat.S_ISSOCK(self.path.lstat().st_mode):
                self.path.unlink()
        except OSError:
            pass

    def _wakeup(self) -> None:
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass  # buffer full: a wake-up is already pending

    @property
    def clients(self) -> int:
        return len(self._conns)

    @property
    def alive(self) -> bool:
        """The serving thread is running (False before ``start`` and after ``stop`` or a crash)."""
        return self._thread is not None and self._thread.is_alive()

    # ------------------------------------------------------------------ thread
    def _run(self) -> None:
        demote_to_normal_priority()
        try:
            while not self._stop.is_set():
                timeout = 0.0 if self._backlog else self._next_timeout()
                for key, events in self._sel.select(timeout=timeout):
                    tag = key.data
                    if tag == "listen":
                        self._accept()
                    elif tag == "wake":
                        try:
                            while self._wake_r.recv(4096):
                                pass
                        except BlockingIOError:
                            pass
                    else:
                        conn: _Conn = tag
                        if conn.closed:
                            continue
                        try:
                            if events & selectors.EVENT_WRITE:
                                self._flush(conn)
                            if events & selectors.EVENT_READ and not conn.closed:
                                self._read(conn)
                        except Exception:  # a bug triggered by one client costs that connection only
                            self.stats["internal_errors"] += 1
                            log.exception("control: connection dropped after an internal error")
                            self._close(conn)
                for conn in list(self._backlog.values()):  # the rest of a flooding client's lines, budgeted
                    if not conn.closed:
                        self._process_lines(conn)
                self._check_pending()
                self._check_idle()
        except Exception:  # pragma: no cover - keep the loop alive; the daemon reports control as down
            log.exception("control socket thread crashed")
        finally:
            for conn in list(self._conns.values()):
                self._close(conn)
            for s in (self._listen, self._wake_r, self._wake_w):
                if s is not None:
                    try:
                        s.close()
                    except OSError:
                        pass
            self._sel.close()

    def _next_timeout(self) -> float:
        t = 1.0
        now = time.monotonic()
        for conn in self._conns.values():
            if conn.pending is not None:
                t = min(t, max(conn.pending[2] - now, 0.0))
            else:
                t = min(t, max(conn.last_active + self.idle_timeout_s - now, 0.0) + 1e-3)
        return t

    def _accept(self) -> None:
        assert self._listen is not None
        while True:
            try:
                sock, _ = self._listen.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # EMFILE etc.: keep serving the others
                log.warning("control: accept failed: %s", exc)
                return
            sock.setblocking(False)
            if len(self._conns) >= self.max_clients:
                self._evict_one()
            if len(self._conns) >= self.max_clients:
                self.stats["rejected"] += 1
                try:
                    sock.send(encode({"ok": False, "error": f"too many clients (max {self.max_clients})",
                                      "field": "connection"}))
                except OSError:
                    pass
                sock.close()
                continue
            conn = _Conn(sock)
            self._conns[sock.fileno()] = conn
            self._sel.register(sock, selectors.EVENT_READ, conn)
            self.stats["accepted"] += 1

    def _evict_one(self) -> None:
        """Make room for a new client: close the connection quiet longest, preferring one that waits for no
        reply from the loop (half-open and idle clients go first)."""
        conns = list(self._conns.values())
        if not conns:
            return
        free = [c for c in conns if c.pending is None]
        victim = min(free or conns, key=lambda c: c.last_active)
        self.stats["evicted"] += 1
        try:
            victim.sock.send(encode({"ok": False, "field": "connection",
                                     "error": f"connection: closed to make room for a new client (all "
                                              f"{self.max_clients} taken; this one was quiet longest)"}))
        except OSError:
            pass
        self._close(victim)

    def _read(self, conn: _Conn) -> None:
        try:
            data = conn.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._close(conn)
            return
        if not data:
            self._close(conn)
            return
        conn.last_active = time.monotonic()
        conn.rbuf += data
        self._process_lines(conn)

    def _process_lines(self, conn: _Conn) -> None:
        budget = self.lines_per_round
        while conn.pending is None and not conn.closed:
            nl = conn.rbuf.find(b"\n")
            if nl >= 0 and budget <= 0:
                self._backlog[id(conn)] = conn  # served next round, after every other client
                self._update_interest(conn)
                return
            if nl < 0:
                if len(conn.rbuf) > self.max_line_bytes:
                    if not conn.discarding:
                        self.stats["long_lines"] += 1
                        self._send(conn, {"ok": False, "field": "line",
                                          "error": f"line: longer than {self.max_line_bytes} bytes; discarded"})
                    conn.discarding = True
                    conn.rbuf.clear()
                break  # no complete line left: read the socket again
            line = bytes(conn.rbuf[:nl])
            del conn.rbuf[: nl + 1]
            if conn.discarding:  # the tail of an over-long line
                conn.discarding = False
                continue
            if len(line) > self.max_line_bytes:
                self.stats["long_lines"] += 1
                self._send(conn, {"ok": False, "field": "line",
                                  "error": f"line: longer than {self.max_line_bytes} bytes; discarded"})
                continue
            if line.strip():
                budget -= 1
                self._handle_line(conn, line)
        self._backlog.pop(id(conn), None)
        self._update_interest(conn)

    def _handle_line(self, conn: _Conn, line: bytes) -> None:
        self.stats["requests"] += 1
        rid: Any = None
        try:
            try:
                text = line.decode("utf-8")
            except UnicodeDecodeError as exc:
                raise RequestError("json", f"not UTF-8 text (byte 0x{line[exc.start]:02x} at offset {exc.start})"
                                   ) from None
            try:
                req = json.loads(text, object_pairs_hook=_unique_keys)
            except RequestError:
                raise
            except ValueError as exc:
                raise RequestError("json", f"not valid JSON ({exc})") from None
            except RecursionError:
                raise RequestError("json", "nested too deeply") from None
            if not isinstance(req, dict):
                raise RequestError("request", "each line must be a JSON object like {\"request\": \"status\"}")
            rid = _check_id(req.get("id"))
            result = self.handler(req)
        except Exception as exc:  # noqa: BLE001 - every error becomes a reply, never a crash
            self.stats["errors"] += 1
            if not isinstance(exc, ValueError):
                log.exception("control: request failed")
            self._send(conn, error_reply(exc), rid)
            return
        if isinstance(result, concurrent.futures.Future):
            conn.pending = (result, rid, time.monotonic() + self.reply_timeout_s)
            result.add_done_callback(lambda _f: self._wakeup())
            return
        self._send(conn, result, rid)

    def _check_pending(self) -> None:
        now = time.monotonic()
        for conn in list(self._conns.values()):
            p = conn.pending
            if p is None:
                continue
            fut, rid, deadline = p
            if fut.done():
                conn.pending = None
                try:
                    reply = fut.result()
                    if not isinstance(reply, dict):
                        reply = {"ok": True, "result": reply}
                except Exception as exc:  # noqa: BLE001
                    self.stats["errors"] += 1
                    reply = error_reply(exc)
                self._send(conn, reply, rid)
            elif now >= deadline:
                conn.pending = None
                fut.cancel()
                self.stats["errors"] += 1
                self._send(conn, {"ok": False, "field": "request",
                                  "error": f"request: not applied by the loop within {self.reply_timeout_s:g} s"},
                           rid)
            else:
                continue
            if not conn.closed:
                self._process_lines(conn)  # requests that queued up behind this one

    def _check_idle(self) -> None:
        now = time.monotonic()
        for conn in list(self._conns.values()):
            if conn.pending is None and now - conn.last_active > self.idle_timeout_s:
                self.stats["kicked_idle"] += 1
                self._close(conn)

    def _send(self, conn: _Conn, reply: Reply, rid: Any = None) -> None:
        if conn.closed:
            return
        if "ok" not in reply:
            reply = {"ok": True, **reply}
        if rid is not None:
            reply = {**reply, "id": rid}
        try:
            data = encode(reply)
        except Exception as exc:  # noqa: BLE001 - TypeError, ValueError, RecursionError: a bug, not the client's
            log.error("control: reply not serialisable: %s: %s", type(exc).__name__, exc)
            data = encode({"ok": False, "error": f"reply not serialisable: {type(exc).__name__}"})
        if len(data) > self.max_out_bytes:  # never disconnect a client for a reply we made too big
            self.stats["oversized_replies"] += 1
            log.error("control: a %d-byte reply exceeds max_out_bytes %d; replaced by an error", len(data),
                      self.max_out_bytes)
            err: Reply = {"ok": False, "field": "reply",
                          "error": f"reply: {len(data)} bytes, more than max_out_bytes {self.max_out_bytes}"}
            data = encode(err if rid is None else {**err, "id": rid})
        conn.wbuf += data
        if len(conn.wbuf) > self.max_out_bytes:
            self.stats["kicked_slow"] += 1
            log.warning("control: client does not read its replies (%d bytes queued); disconnected",
                        len(conn.wbuf))
            self._close(conn)
            return
        self._flush(conn)

    def _flush(self, conn: _Conn) -> None:
        while conn.wbuf:
            try:
                n = conn.sock.send(conn.wbuf)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self._close(conn)
                return
            del conn.wbuf[:n]
            conn.last_active = time.monotonic()
        self._update_interest(conn)

    def _update_interest(self, conn: _Conn) -> None:
        """Read only when no reply is pending (keeps replies in order); write while output is queued."""
        if conn.closed:
            return
        reading = conn.pending is None and id(conn) not in self._backlog
        ev = (selectors.EVENT_READ if reading else 0) | (selectors.EVENT_WRITE if conn.wbuf else 0)
        try:
            key = self._sel.get_key(conn.sock)
        except (KeyError, ValueError):
            key = None
        try:
            if ev == 0:
                if key is not None:
                    self._sel.unregister(conn.sock)
            elif key is None:
                self._sel.register(conn.sock, ev, conn)
            elif key.events != ev:
                self._sel.modify(conn.sock, ev, conn)
        except (KeyError, ValueError, OSError):
            self._close(conn)

    def _close(self, conn: _Conn) -> None:
        if conn.closed:
            return
        conn.closed = True
        self._backlog.pop(id(conn), None)
        if conn.pending is not None:
            conn.pending = None
        try:
            self._sel.unregister(conn.sock)
        except (KeyError, ValueError):
            pass
        self._conns.pop(conn.sock.fileno(), None)
        try:
            conn.sock.close()
        except OSError:
            pass


class ControlClient:
    """Blocking JSON-lines client for the CLI and tests: ``request({"request": "status"}) -> dict``."""

    def __init__(self, path: str | os.PathLike[str], timeout_s: float = 10.0) -> None:
        self.path = Path(path)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        self.sock.settimeout(timeout_s)
        self.sock.connect(str(self.path))
        self._buf = bytearray()

    def send_raw(self, data: bytes) -> None:
        self.sock.sendall(data)

    def read_reply(self) -> Reply:
        while True:
            nl = self._buf.find(b"\n")
            if nl >= 0:
                line = bytes(self._buf[:nl])
                del self._buf[: nl + 1]
                out = json.loads(line)
                if not isinstance(out, dict):
                    raise ConnectionError(f"{self.path}: unexpected reply {line[:200]!r}")
                return out
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError(f"{self.path}: the daemon closed the connection")
            self._buf += chunk

    def request(self, req: dict[str, Any]) -> Reply:
        self.send_raw(encode(req))
        return self.read_reply()

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass

    def __enter__(self) -> ControlClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
