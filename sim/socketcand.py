"""A socketcand-protocol TCP server: the virtual devices' CAN bus, seen from other processes.

A stock python-can ``socketcand`` client (``can.Bus(interface="socketcand", host=..., port=...,
channel="can0", tcp_tune=True)``) connects to it as to a real socketcand daemon in raw mode. The server is
the CAN "port" of a :class:`~stagectl.sim.world.SimWorld` (``recv``/``send``, like a bus): the world
receives every client frame and its devices' frames go to every client; client frames are also forwarded
to the other clients, so two drivers (drive + encoder) see each other's SYNC as on a real bus.

Protocol (rawmode subset; docs/platform.md §1.2 lists the client's parsing rules we must honour)::

    server: < hi >                       client: < open can0 >
    server: < ok >                       client: < rawmode >
    server: < ok >
    client -> server:  < send 601 8 40 0 10 0 0 0 0 0 >        (hex id, hex length, one hex token per byte)
    server -> client:  < frame 581 1700000000.123456 4300100092010200 >   (contiguous hex data)
                       < frame 080 1700000000.123456  >        (0-byte frame: keep the trailing space)
                       < error 00000040 1700000000.123456 >    (error frame; id = SocketCAN error class)

Rules: standard ids are exactly 3 hex digits (the client decides "extended" from the length), extended ids 8;
each handshake reply is sent on its own after the client's request (the client compares one ``recv(256)``
exactly, so replies must not be coalesced), and no frame follows the final ``< ok >`` until the client has
sent a frame or ``RAW_SETTLE_S`` (50 ms) has passed (a frame in the same read would fail its handshake on a
busy machine; a pure listener misses the first 50 ms of traffic, as an adapter that just joined the bus);
TCP_NODELAY on every accepted socket.
"""

from __future__ import annotations

import logging
import queue
import socket
import threading
import time

import can

log = logging.getLogger(__name__)

#: after the rawmode "< ok >", a client that has not sent anything yet gets no frames for this long [s]
RAW_SETTLE_S = 0.05


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
        self.raw = False
        self.lock = threading.Lock()
        self.alive = True
        #: frames are held back until the client has surely read the final "< ok >" (see ``send``)
        self.quiet_until: float | None = None

    def send(self, data: bytes) -> None:
        if not (self.raw and self.alive):
            return
        if self.quiet_until is not None:
            # python-can's client reads the rawmode "< ok >" with one recv(256) and compares it exactly: a
            # frame in the same read fails its handshake. So nothing is sent until the client has sent its
            # first frame (it has read the ok by then) or RAW_SETTLE_S has passed (a pure listener).
            if time.monotonic() < self.quiet_until:
                return
            self.quiet_until = None
        try:
            with self.lock:
                self.sock.sendall(data)
        except OSError:
            self.alive = False  # the reader notices the closed socket and cleans up

    def run(self) -> None:
        sock = self.sock
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.settimeout(0.2)
            sock.sendall(b"< hi >")
            buf = b""
            opened = False
            while self.alive:
                while b">" in buf:
                    line, buf = buf.split(b">", 1)
                    text = line.decode("ascii", "replace")
                    if self.raw:
                        msg = parse_send(text)
                        self.quiet_until = None
                        if msg is not None:
                            msg.timestamp = time.time()
                            self.server.from_client(msg, self)
                        continue
                    cmd = text.strip("< \r\n")  # handshake: one reply per request, never coalesced
                    if cmd.startswith("open "):
                        opened = True
                        sock.sendall(b"< ok >")
                    elif cmd == "rawmode" and opened:
                        self.quiet_until = time.monotonic() + RAW_SETTLE_S
                        sock.sendall(b"< ok >")
                        self.raw = True
                    else:
                        sock.sendall(b"< error unknown command >")
                chunk = self._recv()
                if chunk is None:
                    continue
                if not chunk:
                    return
                buf += chunk
        except OSError:
            pass
        except Exception:  # noqa: BLE001 - a server bug must be visible
            log.exception("socketcand client handler failed")
        finally:
            self.alive = False
            try:
                sock.close()
            except OSError:
                pass

    def _recv(self) -> bytes | None:
        """One socket read; None on time-out (to check for shutdown), b"" at EOF."""
        if self.server.stopping:
            return b""
        try:
            return self.sock.recv(4096)
        except TimeoutError:
            return None


class SocketcandServer:
    """socketcand rawmode server on ``host:port`` (port 0 = ephemeral): the CAN "port" of a SimWorld.

    The world reads what clients send with :meth:`recv` and answers with :meth:`send` (to every client);
    frames from one client are also forwarded to the other clients, as on a shared bus. Threads: one
    accept thread and one reader per client; the world's thread writes to the sockets directly.
    """

    def __init__(self, channel: str = "", host: str = "127.0.0.1", port: int = 0, can_name: str = "can0") -> None:
        self.channel = channel
        self.can_name = can_name
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._sock.bind((host, port))
            self._sock.listen(8)
        except OSError:
            self._sock.close()
            raise
        self._sock.settimeout(0.2)
        self.host, self.port = self._sock.getsockname()[:2]
        self.stopping = False
        self._incoming: queue.Queue[can.Message] = queue.Queue()
        self._clients: list[tuple[_Client, threading.Thread]] = []
        self._clients_lock = threading.Lock()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ bus-like side for the world
    def recv(self, timeout: float | None = None) -> can.Message | None:
        """Next frame sent by a client (None after ``timeout`` [s]; 0 = poll)."""
        try:
            if not timeout:
                return self._incoming.get_nowait()
            return self._incoming.get(timeout=timeout)
        except queue.Empty:
            return None

    def send(self, msg: can.Message) -> None:
        """Send a device frame to every connected client."""
        self._broadcast(format_frame(msg), None)

    def from_client(self, msg: can.Message, origin: _Client) -> None:
        # forward first: the other clients must see a SYNC before the devices' answers to it (on a real bus
        # the SYNC is on the wire before any TPDO it triggers)
        self._broadcast(format_frame(msg, msg.timestamp), origin)
        self._incoming.put(msg)

    def _broadcast(self, data: bytes, exclude: _Client | None) -> None:
        with self._clients_lock:
            clients = [c for c, _ in self._clients if c is not exclude]
        for c in clients:
            c.send(data)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._accept, name="socketcand-accept", daemon=True)
            self._thread.start()

    def _accept(self) -> None:
        while not self.stopping:
            try:
                conn, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            c = _Client(self, conn)
            t = threading.Thread(target=c.run, name="socketcand-client", daemon=True)
            with self._clients_lock:
                self._clients = [(cl, th) for cl, th in self._clients if th.is_alive()]
                self._clients.append((c, t))
            t.start()

    def stop(self) -> None:
        """Close the listening socket and every client connection (idempotent)."""
        self.stopping = True
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        try:
            self._sock.close()
        except OSError:
            pass
        with self._clients_lock:
            clients, self._clients = self._clients, []
        for c, t in clients:
            c.alive = False
            try:
                c.sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            t.join(2.0)

    close = stop
