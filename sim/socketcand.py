"""A socketcand-protocol TCP server: the virtual devices' CAN bus, seen from other processes.

A stock python-can ``socketcand`` client (``can.Bus(interface="socketcand", host=..., port=...,
channel="can0", tcp_tune=True)``) connects to it as to a real socketcand daemon in raw mode. The server is
the CAN "port" of a :class:`~stagectl.sim.world.SimWorld` (``recv``/``send``, like a bus): the world
receives every client frame and its devices' frames go to every client; client frames are also forwarded
to the other clients, so two drivers (drive + encoder) see each other's SYNC as on a real bus.

Protocol (the daemon's ``doc/protocol.md``; replies as its C source gives them)::

    server: < hi >                       client: < open can0 >
    server: < ok >                       client: < rawmode >
    server: < ok >
    client -> server:  < send 601 8 40 0 10 0 0 0 0 0 >        (hex id, hex length, one hex token per byte)
    server -> client:  < frame 581 1700000000.123456 4300100092010200 >   (contiguous hex data)
                       < frame 080 1700000000.123456  >        (0-byte frame: keep the trailing space)
                       < error 040 1700000000.123456 >         (error frame: SocketCAN error class, %03X)

* NO_BUS: ``< open X >`` for a bus this server does not serve → ``< error could not open bus >`` and the
  connection is closed (as the daemon); any other command → ``< error unknown command >``.
* After ``open`` (the daemon's BCM mode): ``< rawmode >`` → ``< ok >``; ``< echo >`` is echoed; the BCM, ISO-TP
  and CONTROL commands (``add``, ``subscribe``, ``bcmmode`` … ``isotpmode``, ``controlmode``) are not implemented
  here → ``< error unknown command >`` (never silence).
* RAW: ``< send … >``; ``< echo >`` echoed; a malformed ``send`` is dropped without reply (as the daemon, which
  only logs it); anything else → ``< error unknown command >``.
* Ids: an id written with exactly 8 hex digits is extended, any other length standard (``< send 1 0 >`` is the
  standard id 0x001), as the daemon's ``element_length(buf, 2) == 8``.
* Bytes before a ``<`` are skipped (the daemon's ``receive_command``).
* Timestamps: wall-clock seconds, taken from a monotonic clock anchored once at start (never going back).

Rules for python-can's client (docs/platform.md §1.2): each handshake reply is sent on its own (the client
compares one ``recv(256)`` exactly), so frames that arrive within ``RAW_SETTLE_S`` (50 ms) after the final
``< ok >`` are *queued*, not dropped, and sent once the client has sent a frame or the window has passed;
TCP_NODELAY on every accepted socket.
"""

from __future__ import annotations

import logging
import queue
import socket
import threading
import time
from collections.abc import Callable

import can

log = logging.getLogger(__name__)

#: after the rawmode "< ok >", frames for a client that has not sent anything yet are queued this long [s]
RAW_SETTLE_S = 0.05
#: frames queued per client during the settle window (beyond this the oldest are dropped and counted)
SETTLE_QUEUE = 65536
_WALL0 = time.time()
_MONO0 = time.monotonic()
CAN_EFF_MASK = 0x1FFFFFFF
UNKNOWN = b"< error unknown command >"


def timestamp() -> float:
    """Wall-clock seconds that never go back: ``time.time()`` at import + monotonic time since."""
    return _WALL0 + (time.monotonic() - _MONO0)


def _stamp(t: float) -> str:
    sec = int(t)
    return f"{sec}.{min(999999, int(round((t - sec) * 1e6))):06d}"


def format_frame(msg: can.Message, ts: float | None = None) -> bytes:
    """One server→client line for ``msg``, as the daemon's ``state_raw.c`` prints it."""
    t = timestamp() if ts is None else ts
    if msg.is_error_frame:
        return f"< error {msg.arbitration_id & CAN_EFF_MASK:03X} {_stamp(t)} >".encode("ascii")
    cid = f"{msg.arbitration_id & CAN_EFF_MASK:08X}" if msg.is_extended_id else f"{msg.arbitration_id & 0x7FF:03X}"
    return f"< frame {cid} {_stamp(t)} {bytes(msg.data).hex().upper()} >".encode("ascii")


def parse_send(text: str) -> can.Message | None:
    """Parse ``< send ID LEN B0 B1 ... >`` as the daemon does (None if malformed: dropped without reply).

    The id is extended when written with exactly 8 hex digits; LEN is read as hex (``%hhu`` in the daemon reads
    decimal, identical for 0–8) and must match the number of data bytes."""
    parts = text.strip("<> \r\n").split()
    if len(parts) < 3 or parts[0] != "send":
        return None
    try:
        cid = int(parts[1], 16)
        n = int(parts[2], 16)
        data = bytes(int(b, 16) for b in parts[3:])
    except ValueError:
        return None
    if len(data) != n or n > 8:
        return None
    extended = len(parts[1]) == 8
    if cid > (CAN_EFF_MASK if extended else 0x7FF):
        return None
    return can.Message(arbitration_id=cid, data=data, is_extended_id=extended)


def split_commands(buf: bytes) -> tuple[list[str], bytes]:
    """Complete ``< … >`` elements in ``buf`` and the rest to keep; bytes before a ``<`` are skipped."""
    out: list[str] = []
    while True:
        start = buf.find(b"<")
        if start < 0:
            return out, b""
        stop = buf.find(b">", start + 1)
        if stop < 0:
            return out, buf[start:]
        out.append(buf[start : stop + 1].decode("ascii", "replace"))
        buf = buf[stop + 1 :]


class _Client:
    def __init__(self, server: SocketcandServer, sock: socket.socket) -> None:
        self.server = server
        self.sock = sock
        self.raw = False
        self.lock = threading.Lock()
        self.alive = True
        #: while set: frames are queued until the client has surely read the final "< ok >" (see ``send``)
        self.quiet_until: float | None = None
        self.queued: list[bytes] = []
        self.dropped = 0

    def _reply(self, data: bytes) -> None:
        with self.lock:
            self.sock.sendall(data)

    def send(self, data: bytes) -> None:
        if not (self.raw and self.alive):
            return
        with self.lock:
            if self.quiet_until is not None:
                # python-can's client reads the rawmode "< ok >" with one recv(256) and compares it exactly: a
                # frame in the same read fails its handshake. Frames wait in a queue until the client has sent
                # its first frame (it has read the ok by then) or RAW_SETTLE_S has passed; none is lost.
                if time.monotonic() < self.quiet_until:
                    if len(self.queued) >= SETTLE_QUEUE:
                        self.queued.pop(0)
                        self.dropped += 1
                    self.queued.append(data)
                    return
                self._flush_locked()
            try:
                self.sock.sendall(data)
            except OSError:
                self.alive = False  # the reader notices the closed socket and cleans up

    def _flush_locked(self) -> None:
        self.quiet_until = None
        queued, self.queued = self.queued, []
        try:
            if queued:
                self.sock.sendall(b"".join(queued))
        except OSError:
            self.alive = False

    def flush(self) -> None:
        with self.lock:
            if self.quiet_until is not None:
                self._flush_locked()

    def _command(self, cmd: str, opened: bool) -> bool:
        """Handle one command element; returns the new "bus opened" flag. Replies as the daemon does."""
        text = " ".join(cmd.strip("<>").split())
        if self.raw:
            if text.startswith("send "):
                msg = parse_send(cmd)
                self.flush()
                if msg is not None:
                    msg.timestamp = timestamp()
                    self.server.from_client(msg, self)
            elif text == "echo":
                self._reply(b"< echo >")
            else:
                self._reply(UNKNOWN)
            return opened
        if not opened:
            if text.startswith("open "):
                if text.split()[1] != self.server.can_name:
                    self._reply(b"< error could not open bus >")
                    self.alive = False  # the daemon closes the connection
                    return False
                self._reply(b"< ok >")
                return True
            self._reply(UNKNOWN)
            return False
        if text == "rawmode":
            with self.lock:
                self.quiet_until = time.monotonic() + RAW_SETTLE_S
                self.raw = True
                self.sock.sendall(b"< ok >")
        elif text == "echo":
            self._reply(b"< echo >")
        else:  # BCM commands, bcmmode, isotpmode, controlmode: not implemented by this server
            self._reply(UNKNOWN)
        return True

    def run(self) -> None:
        sock = self.sock
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.settimeout(0.02)
            sock.sendall(b"< hi >")
            buf = b""
            opened = False
            while self.alive:
                cmds, buf = split_commands(buf)
                for cmd in cmds:  # one reply per request, each sent on its own
                    opened = self._command(cmd, opened)
                    if not self.alive:
                        return
                if self.quiet_until is not None and time.monotonic() >= self.quiet_until:
                    self.flush()
                chunk = self._recv()
                if chunk is None:
                    continue
                if not chunk:
                    return
                buf += chunk
                if len(buf) > 65536:  # a client that never closes an element
                    buf = buf[-4096:]
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

    ``on_receive`` (optional, set by the world in real-time thread mode): called with each client frame in
    the reader thread that parsed it; when it returns True the frame is handled and not queued for
    :meth:`recv`. The devices then answer a SYNC in the thread that received it, with no hand-over to a
    second thread: on a loaded machine that hand-over (a ``queue.get`` woken by the reader, then the GIL)
    was measured to hold SYNCs for 53–69 ms while the reader kept parsing (docs/platform.md §1.3).
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
        #: see the class docstring; None: every client frame is queued for :meth:`recv`
        self.on_receive: Callable[[can.Message], bool] | None = None
        #: client frames handled by ``on_receive`` in a reader thread (not queued)
        self.served_in_reader = 0

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
        self._broadcast(format_frame(msg, timestamp()), None)

    def from_client(self, msg: can.Message, origin: _Client) -> None:
        # forward first: the other clients must see a SYNC before the devices' answers to it (on a real bus
        # the SYNC is on the wire before any TPDO it triggers)
        self._broadcast(format_frame(msg, msg.timestamp), origin)
        handler = self.on_receive
        if handler is not None and handler(msg):
            self.served_in_reader += 1
        else:
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
