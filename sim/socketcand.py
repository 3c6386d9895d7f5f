"""A socketcand-protocol TCP server bridging TCP clients to an in-process python-can ``virtual`` bus.

A stock python-can ``socketcand`` client (``can.Bus(interface="socketcand", host=..., port=...,
channel="can0", tcp_tune=True)``) connects to it as to a real socketcand daemon in raw mode. Each client
gets its own ``virtual`` bus instance on ``channel``, so clients see each other's frames and the virtual
devices' frames, as on a real bus.

Protocol (rawmode subset; PLATFORM_NOTES §1.2 lists the client's parsing rules we must honour)::

    server: < hi >                       client: < open can0 >
    server: < ok >                       client: < rawmode >
    server: < ok >
    client -> server:  < send 601 8 40 0 10 0 0 0 0 0 >        (hex id, hex length, one hex token per byte)
    server -> client:  < frame 581 1700000000.123456 4300100092010200 >   (contiguous hex data)
                       < frame 080 1700000000.123456  >        (0-byte frame: keep the trailing space)
                       < error 00000040 1700000000.123456 >    (error frame; id = SocketCAN error class)

Rules: standard ids are exactly 3 hex digits (the client decides "extended" from the length), extended ids 8;
each handshake reply is sent on its own after the client's request (the client compares one ``recv(256)``
exactly, so replies must not be coalesced); TCP_NODELAY on every accepted socket.
"""

from __future__ import annotations

import logging
import socket
import threading
import time

import can

from stagectl.drivers.canbus import close_bus, open_bus

log = logging.getLogger(__name__)


def format_frame(msg: can.Message, ts: float | None = None) -> bytes:
    """One server→client line for ``msg``."""
    t = time.time() if ts is None else ts
    if msg.is_error_frame:
        return f"< error {msg.arbitration_id & 0x1FFFFFFF:08X} {t:.6f} >".encode("ascii")
    cid = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id & 0x7FF:03X}"
    return f"< frame {cid} {t:.6f} {bytes(msg.data).hex().upper()} >".encode("ascii")


def parse_send(text: str) -> can.Message | None:
    """Parse ``< send ID LEN B0 B1 ... >`` (without validation errors escaping: None if malformed)."""
    parts = text.strip("<> \r\n").split()
    if len(parts) < 3 or parts[0] != "send":
        return None
    try:
        cid = int(parts[1], 16)
        n = int(parts[2], 16)
        data = bytes(int(b, 16) for b in parts[3 : 3 + n])
    except ValueError:
        return None
    if len(data) != n or n > 8:
        return None
    return can.Message(arbitration_id=cid, data=data, is_extended_id=len(parts[1]) != 3)


class _Client:
    def __init__(self, server: SocketcandServer, sock: socket.socket) -> None:
        self.server = server
        self.sock = sock
        self.bus: can.BusABC | None = None
        self.stop = threading.Event()
        self.threads: list[threading.Thread] = []

    def run(self) -> None:
        sock = self.sock
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.sendall(b"< hi >")
            buf = b""
            opened = raw = False
            while not raw:
                chunk = sock.recv(256)
                if not chunk:
                    return
                buf += chunk
                while b">" in buf:
                    line, buf = buf.split(b">", 1)
                    cmd = line.decode("ascii", "replace").strip("< \r\n")
                    if cmd.startswith("open "):
                        opened = True
                        sock.sendall(b"< ok >")
                    elif cmd == "rawmode" and opened:
                        raw = True
                        sock.sendall(b"< ok >")
                        break
                    else:
                        sock.sendall(b"< error unknown command >")
            self.bus = open_bus({"interface": "virtual", "channel": self.server.channel}, path="socketcand")
            w = threading.Thread(target=self._writer, name="socketcand-tx", daemon=True)
            w.start()
            self.threads.append(w)
            self._reader(buf)
        except OSError:
            pass
        except Exception:  # noqa: BLE001 - a server bug must be visible
            log.exception("socketcand client handler failed")
        finally:
            self.stop.set()
            for t in self.threads:
                t.join(1.0)
            close_bus(self.bus)
            self.bus = None
            try:
                sock.close()
            except OSError:
                pass

    def _reader(self, buf: bytes) -> None:
        sock, bus = self.sock, self.bus
        assert bus is not None
        sock.settimeout(0.2)
        while not self.stop.is_set():
            while b">" in buf:
                line, buf = buf.split(b">", 1)
                msg = parse_send(line.decode("ascii", "replace"))
                if msg is not None:
                    bus.send(msg)
            try:
                chunk = sock.recv(4096)
            except TimeoutError:
                continue
            if not chunk:
                return
            buf += chunk

    def _writer(self) -> None:
        bus, sock = self.bus, self.sock
        assert bus is not None
        while not self.stop.is_set():
            try:
                msg = bus.recv(0.1)
                if msg is None:
                    continue
                out = [format_frame(msg)]
                while (more := bus.recv(0.0)) is not None:
                    out.append(format_frame(more))
                sock.sendall(b"".join(out))
            except (OSError, can.CanError):
                self.stop.set()
                return


class SocketcandServer:
    """socketcand rawmode server on ``host:port`` (port 0 = ephemeral) for the virtual bus ``channel``."""

    def __init__(self, channel: str, host: str = "127.0.0.1", port: int = 0, can_name: str = "can0") -> None:
        self.channel = channel
        self.can_name = can_name
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._sock.bind((host, port))
        self._sock.listen(8)
        self._sock.settimeout(0.2)
        self.host, self.port = self._sock.getsockname()[:2]
        self._stop = threading.Event()
        self._clients: list[tuple[_Client, threading.Thread]] = []
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._accept, name="socketcand-accept", daemon=True)
            self._thread.start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conn.settimeout(None)
            c = _Client(self, conn)
            t = threading.Thread(target=c.run, name="socketcand-rx", daemon=True)
            self._clients = [(cl, th) for cl, th in self._clients if th.is_alive()]
            self._clients.append((c, t))
            t.start()

    def stop(self) -> None:
        """Close the listening socket and every client connection (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        try:
            self._sock.close()
        except OSError:
            pass
        for c, t in self._clients:
            c.stop.set()
            try:
                c.sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            t.join(2.0)
        self._clients.clear()
