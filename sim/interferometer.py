"""Virtual serial interferometer: streams :mod:`stagectl.drivers.interferometer_protocol` frames of a plant's
position over a real pty or a loopback TCP server, with scriptable fault injection.

Usage (lock-step, deterministic; the driver calls ``pump`` through ``set_pump``)::

    sim = SimInterferometer(plant, SimInterferometerConfig(transport="pty", link_path=str(tmp / "ifm")))
    drv = SerialInterferometer(InterferometerConfig(url=sim.url, resolution_m=1e-9))
    drv.set_pump(sim.pump)
    ...
    sim.close()

Real time: ``sim.start()`` streams from a thread at ``rate_hz`` (absolute deadlines), ``sim.stop()`` ends it.
Triggered (``trigger: sync``): ``trigger()`` emits one frame now; :class:`~stagectl.sim.world.SimWorld` calls it
on every SYNC right after the drive stepped the plant, in thread and lock-step mode. Use it across processes
(``stagectl sim-plant``): the simulated plant moves only at SYNC, so a free-running stream samples it at a
random phase and adds up to one period of extra, jittering delay that a real (continuous) stage does not have.

Stable API (used by ``SimWorld``): ``SimInterferometer(plant, cfg)``, ``.url``, ``start()``, ``stop()``,
``pump() -> LinkBytes`` (an int: bytes written), ``inject(kind, ...)``, ``disconnect()``, ``close()`` (idempotent; also a context manager).

Plant interface (duck-typed, see ``sim/plant.py``): ``plant.measure() -> float`` position [m] as seen by the
sensor model (noise, delay), and ``plant.t_s`` plant time [s]. Each frame carries
``counts = round(plant.measure() / resolution_m)``; the frame timestamp is ``time.monotonic_ns()`` at send
(streaming) or ``round(plant.t_s · 1e9)`` (lock-step).

Transports:

* ``pty``: ``os.openpty()``, both ends in raw mode before anyone opens the slave, the slave fd kept open by
  the sim (so the master never sees EIO when a client closes), and a symlink ``link_path`` → ``/dev/pts/N``.
  ``url`` is the symlink path.
* ``tcp``: a listening socket on ``host:port`` (port 0 = ephemeral), one client at a time (a new connection
  replaces the old), TCP_NODELAY. ``url`` is ``socket://host:port``.

Optional baud pacing (``baudrate``): each frame reaches the wire no earlier than ``10·len/baudrate`` s after
the previous one ended (8N1), and it is written when its last byte would arrive; frames that would queue more
than 4 frame-times are dropped (counted in ``frames_overrun``; the sequence counter still advances, as on a
device whose UART FIFO overflows). Without pacing the device keeps no backlog either: while the link has not
taken the previous frame completely (a pty or socket nobody reads), new frames are dropped and counted in
``frames_overrun``, so a client that opens late and flushes its input reads current, contiguous frames.

Fault kinds (``SerialFaultKind``), each from sample slot ``at_frame`` for ``count`` slots:
``corrupt`` (one bit flipped → CRC error), ``drop`` (frame not sent, sequence advances → gap),
``garbage`` (``garbage_bytes`` seeded random bytes before the frame), ``signal_lost`` (status bit 0,
signal 0), ``laser_unlocked`` (status bit 2), ``glitch`` (position jumps by ``glitch_m``; status bit 1 unless
``flag`` is false), ``low_signal`` (signal strength byte = ``signal``), ``stop`` (device silent, sequence
does not advance), ``disconnect`` (the sim closes the link: TCP connection or pty master; permanent).
"""

from __future__ import annotations

import enum
import os
import random
import select
import socket
import tempfile
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol

from stagectl.drivers.interferometer_protocol import LinkBytes, Status, encode_frame
from stagectl.errors import ConfigError
from stagectl.schema import param

__all__ = [
    "SerialFaultKind",
    "SimInterferometer",
    "SimInterferometerConfig",
    "SimInterferometerFault",
]


class PlantLike(Protocol):
    t_s: float

    def measure(self) -> float: ...


class SerialFaultKind(enum.Enum):
    CORRUPT = "corrupt"
    DROP = "drop"
    GARBAGE = "garbage"
    SIGNAL_LOST = "signal_lost"
    LASER_UNLOCKED = "laser_unlocked"
    GLITCH = "glitch"
    LOW_SIGNAL = "low_signal"
    STOP = "stop"
    DISCONNECT = "disconnect"


@dataclass(frozen=True)
class SimInterferometerFault:
    """One scripted fault: ``kind`` on ``count`` sample slots starting at slot ``at_frame``."""

    kind: SerialFaultKind = param(desc="fault kind: corrupt, drop, garbage, signal_lost, laser_unlocked, "
                                  "glitch, low_signal, stop, disconnect")
    at_frame: int = param(0, desc="first sample slot (frame index since start) affected", ge=0)
    count: int = param(1, desc="number of consecutive sample slots affected", ge=1)
    garbage_bytes: int = param(16, unit="B", desc="garbage: bytes inserted before each affected frame", ge=1)
    glitch_m: float = param(1e-6, unit="m", desc="glitch: position jump added to affected frames")
    flag: bool = param(True, desc="glitch: also set the GLITCH status bit")
    signal: int = param(10, desc="low_signal: signal strength byte sent (0..255)", ge=0, le=255)


@dataclass(frozen=True)
class SimInterferometerConfig:
    """Virtual interferometer settings (YAML block ``interferometer_sim`` or built in tests)."""

    transport: str = param("pty", desc="pty (a pseudo-terminal with a symlink) or tcp (loopback server)",
                           choices=("pty", "tcp"))
    link_path: str | None = param(None, desc="pty: symlink path published to clients (None: unique temp path)")
    host: str = param("127.0.0.1", desc="tcp: listen address")
    port: int = param(0, desc="tcp: listen port (0: ephemeral, see .url)", ge=0, le=65535)
    rate_hz: float = param(1000.0, unit="Hz", desc="streaming rate (start()) and lock-step plant_time rate", gt=0)
    resolution_m: float = param(1e-9, unit="m", desc="position resolution per count", ge=1e-15)
    signal: int = param(230, desc="signal strength byte sent when healthy (0..255)", ge=0, le=255)
    baudrate: int | None = param(None, unit="bit/s", desc="pace frames as on an 8N1 line (None: unpaced)", gt=0)
    lockstep: str = param("per_pump", desc="pump(): per_pump = one frame per call; plant_time = one frame "
                          "per elapsed 1/rate_hz of plant time", choices=("per_pump", "plant_time"))
    trigger: str = param("rate", desc="rate = free-running at rate_hz; sync = one frame per CANopen SYNC, sampled "
                         "right after the drive stepped the plant (external trigger input; SimWorld only)",
                         choices=("rate", "sync"))
    seed: int = param(0, desc="seed of the garbage generator", ge=0)
    faults: tuple[SimInterferometerFault, ...] = param((), desc="scripted faults")


class SimInterferometer:
    """Virtual interferometer reading ``plant`` (see module docstring). Not real-time safe itself; run it in
    its own thread (``start``) or call ``pump`` from the test/loop thread (lock-step)."""

    #: lock-step failure guard [s]: longest wait for written pty bytes to become readable
    lockstep_guard_s = 1.0

    def __init__(self, plant: Any, cfg: SimInterferometerConfig | None = None) -> None:
        self.plant = plant
        self.cfg = cfg = cfg or SimInterferometerConfig()
        self._faults: list[SimInterferometerFault] = list(cfg.faults)
        self._rng = random.Random(cfg.seed)
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop_evt = threading.Event()
        self._pending = bytearray()
        self._closed = False
        self._disconnected = False
        #: next sample slot index (schedule clock for faults)
        self.slot = 0
        #: next sequence number to send
        self.seq = 0
        self.frames_sent = 0
        self.frames_dropped = 0
        self.frames_overrun = 0
        self.bytes_sent = 0
        #: the last frame's intended content (before corruption): counts, status, signal, position [m]
        self.last_counts = 0
        self.last_status = 0
        self.last_position_m = 0.0
        self._link_free_ns = 0
        self._plant_slots = 0
        self._master = self._slave = -1
        self._link: Path | None = None
        self._tmpdir: str | None = None
        self._server: socket.socket | None = None
        self._client: socket.socket | None = None
        if cfg.transport == "pty":
            self._open_pty()
        else:
            self._open_tcp()

    # ------------------------------------------------------------------ transport
    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        if self.cfg.link_path is None:
            self._tmpdir = tempfile.mkdtemp(prefix="stagectl-ifm-")
            link = Path(self._tmpdir) / "interferometer"
        else:
            link = Path(self.cfg.link_path)
        try:
            if link.is_symlink():
                link.unlink()
            link.symlink_to(os.ttyname(slave))
        except OSError as exc:
            self.close()
            raise ConfigError(f"link_path: cannot create symlink {link} ({exc.strerror or exc})") from exc
        self._link = link

    def _open_tcp(self) -> None:
        srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            srv.bind((self.cfg.host, self.cfg.port))
        except OSError as exc:
            srv.close()
            raise ConfigError(f"host/port: cannot listen on {self.cfg.host}:{self.cfg.port} "
                              f"({exc.strerror or exc})") from exc
        srv.listen(4)
        srv.setblocking(False)
        self._server = srv

    @property
    def url(self) -> str:
        """Where a client connects: the pty symlink path or ``socket://host:port``."""
        if self._link is not None:
            return str(self._link)
        if self._server is not None:
            host, port = self._server.getsockname()[:2]
            return f"socket://{host}:{port}"
        raise RuntimeError("SimInterferometer is closed")

    @property
    def connected(self) -> bool:
        """tcp: a client is connected; pty: the link is up."""
        if self.cfg.transport == "pty":
            return self._master >= 0
        return self._client is not None

    def _accept(self) -> None:
        srv = self._server
        if srv is None:
            return
        while True:
            try:
                conn, _ = srv.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.setblocking(False)
            if self._client is not None:
                self._client.close()
            self._client = conn
            self._pending.clear()

    def _write(self, data: bytes) -> int:
        """Queue ``data`` and write as much as the link takes now. Returns bytes written now."""
        if self._disconnected:
            return 0
        if self.cfg.transport == "tcp":
            if self._client is None:
                self._accept()
                if self._client is None:
                    return 0
        elif self._master < 0:
            return 0
        n = self._flush() if self._pending else 0
        if self._pending:
            # the link has not taken the previous frame yet (nobody reads): a UART keeps no backlog, the
            # bytes are lost, so a reader that flushes its input starts on current, contiguous frames
            if data:
                self.frames_overrun += 1
            return n
        self._pending += data
        return n + (self._flush() if data else 0)

    def _flush(self) -> int:
        """Write as much of the pending bytes as the link takes now; returns the bytes written."""
        try:
            client = self._client
            if client is not None:
                n = client.send(self._pending)
            else:
                n = os.write(self._master, self._pending)
        except (BlockingIOError, InterruptedError):
            return 0
        except OSError:
            if self.cfg.transport == "tcp" and self._client is not None:
                self._client.close()
                self._client = None
            self._pending.clear()
            return 0
        del self._pending[:n]
        self.bytes_sent += n
        return n

    def disconnect(self) -> None:
        """Close the link as a device that is unplugged would (tcp: the connection; pty: the master)."""
        self._disconnected = True
        if self._client is not None:
            try:
                self._client.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self._client.close()
            self._client = None
        if self._master >= 0:
            os.close(self._master)
            self._master = -1

    # ------------------------------------------------------------------ faults
    def inject(
        self,
        kind: SerialFaultKind | str,
        *,
        count: int = 1,
        at_frame: int | None = None,
        **params: Any,
    ) -> SimInterferometerFault:
        """Schedule a fault on ``count`` slots starting at ``at_frame`` (default: the next frame).

        ``params``: ``garbage_bytes``, ``glitch_m``, ``flag``, ``signal`` (see :class:`SimInterferometerFault`).
        Thread-safe.
        """
        k = kind if isinstance(kind, SerialFaultKind) else SerialFaultKind(kind)
        with self._lock:
            f = SimInterferometerFault(kind=k, at_frame=self.slot if at_frame is None else at_frame,
                                       count=count, **params)
            self._faults.append(f)
        return f

    def clear_faults(self) -> None:
        with self._lock:
            self._faults.clear()

    def _active(self, slot: int) -> list[SimInterferometerFault]:
        with self._lock:
            self._faults = [f for f in self._faults if f.at_frame + f.count > slot]
            return [f for f in self._faults if f.at_frame <= slot]

    # ------------------------------------------------------------------ frames
    def _make(self, timestamp_ns: int) -> tuple[bytes, bool]:
        """Build the bytes for the current slot. Returns (bytes, advances_sequence)."""
        slot = self.slot
        self.slot += 1
        faults = self._active(slot)
        kinds = {f.kind for f in faults}
        if SerialFaultKind.DISCONNECT in kinds:
            self.disconnect()
            return b"", False
        if SerialFaultKind.STOP in kinds:
            return b"", False
        res = self.cfg.resolution_m
        pos = float(self.plant.measure())
        counts = round(pos / res)
        status = 0
        signal = self.cfg.signal
        prefix = b""
        corrupt = False
        drop = False
        for f in faults:
            k = f.kind
            if k is SerialFaultKind.SIGNAL_LOST:
                status |= Status.SIGNAL_LOST
                signal = 0
            elif k is SerialFaultKind.LASER_UNLOCKED:
                status |= Status.LASER_UNLOCKED
            elif k is SerialFaultKind.GLITCH:
                counts += round(f.glitch_m / res)
                if f.flag:
                    status |= Status.GLITCH
            elif k is SerialFaultKind.LOW_SIGNAL:
                signal = f.signal
            elif k is SerialFaultKind.GARBAGE:
                prefix += self._rng.randbytes(f.garbage_bytes)
            elif k is SerialFaultKind.CORRUPT:
                corrupt = True
            elif k is SerialFaultKind.DROP:
                drop = True
        seq = self.seq
        self.seq = (seq + 1) & 0xFFFFFFFF
        self.last_counts, self.last_status, self.last_position_m = counts, int(status), pos
        if drop:
            self.frames_dropped += 1
            return prefix, True
        frame = encode_frame(seq, counts, int(status), signal, timestamp_ns)
        if corrupt:
            b = bytearray(frame)
            b[10 + (slot % 8)] ^= 1 << (slot % 8)  # one bit of the position field
            frame = bytes(b)
        self.frames_sent += 1
        return prefix + frame, True

    def pump(self) -> LinkBytes:
        """Lock-step: emit the frame(s) due now and return the number of bytes written to the link.

        ``per_pump``: exactly one sample slot per call. ``plant_time``: one slot per elapsed ``1/rate_hz`` of
        ``plant.t_s`` since the first call (possibly none). Synchronous, never sleeps. pty: returns only once
        the bytes are readable on the slave side (the kernel moves pty data through a work queue), so a client
        that polls after ``pump()`` finds them; ``lockstep_guard_s`` bounds that wait as a failure guard.
        """
        if self._thread is not None:
            raise RuntimeError("SimInterferometer.pump(): streaming thread is running (call stop() first)")
        if self._closed:
            return LinkBytes(0)
        ts = round(float(self.plant.t_s) * 1e9)
        if self.cfg.lockstep == "per_pump":
            due = 1
        else:
            target = int(float(self.plant.t_s) * self.cfg.rate_hz + 1e-9) + 1
            due = max(0, target - self._plant_slots)
            self._plant_slots += due
        n = 0
        if self.cfg.transport == "tcp":
            self._accept()
        for _ in range(due):
            data, _adv = self._make(ts)
            n += self._write(data)
        if n and self._slave >= 0:
            select.select([self._slave], [], [], self.lockstep_guard_s)
        return LinkBytes(n)

    def trigger(self) -> LinkBytes:
        """External trigger (``trigger: sync``; SimWorld calls it on each SYNC, after the drive stepped the
        plant): emit one frame sampled now, stamped with plant time. Returns the bytes written. No baud pacing."""
        if self._thread is not None:
            raise RuntimeError("SimInterferometer.trigger(): streaming thread is running (call stop() first)")
        if self._closed:
            return LinkBytes(0)
        if self.cfg.transport == "tcp":
            self._accept()
        data, _adv = self._make(round(float(self.plant.t_s) * 1e9))
        n = self._write(data)
        if n and self._slave >= 0:
            select.select([self._slave], [], [], self.lockstep_guard_s)
        return LinkBytes(n)

    # ------------------------------------------------------------------ streaming thread
    def start(self) -> None:
        """Stream in real time from a daemon thread at ``rate_hz`` (absolute deadlines)."""
        if self._thread is not None:
            return
        if self._closed:
            raise RuntimeError("SimInterferometer is closed")
        self._stop_evt.clear()
        self._thread = threading.Thread(target=self._run, name="sim-interferometer", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the streaming thread (idempotent)."""
        t = self._thread
        if t is None:
            return
        self._stop_evt.set()
        t.join(timeout=5.0)
        self._thread = None

    def _sleep_until(self, t_ns: int) -> None:
        while True:
            dt = t_ns - time.monotonic_ns()
            if dt <= 0 or self._stop_evt.is_set():
                return
            time.sleep(dt * 1e-9)

    def _run(self) -> None:
        period_ns = round(1e9 / self.cfg.rate_hz)
        next_ns = time.monotonic_ns()
        baud = self.cfg.baudrate
        while not self._stop_evt.is_set():
            self._sleep_until(next_ns)
            if self._stop_evt.is_set():
                break
            now = time.monotonic_ns()
            data, _ = self._make(now)
            if baud and data:
                tx_ns = round(len(data) * 10 * 1e9 / baud)
                # the line is judged against the sampling schedule (next_ns), not against ``now``: a device
                # samples at rate_hz whatever its UART does, so a link too slow for the rate drops frames
                start = max(next_ns, self._link_free_ns)
                end = start + tx_ns
                if end - next_ns > 4 * tx_ns:
                    self.frames_overrun += 1
                    data = b""
                else:
                    self._link_free_ns = end
                    self._sleep_until(end)
            self._write(data)
            next_ns += period_ns
            late = time.monotonic_ns() - next_ns
            if late > 100 * period_ns:  # stalled for long: skip missed deadlines instead of bursting
                next_ns += (late // period_ns) * period_ns

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        """Stop streaming and release the pty/sockets/symlink. Idempotent."""
        self.stop()
        self._closed = True
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._server is not None:
            self._server.close()
            self._server = None
        for fd in (self._master, self._slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = -1
        if self._link is not None:
            try:
                if self._link.is_symlink():
                    self._link.unlink()
            except OSError:
                pass
            self._link = None
        if self._tmpdir is not None:
            try:
                os.rmdir(self._tmpdir)
            except OSError:
                pass
            self._tmpdir = None

    def __enter__(self) -> SimInterferometer:
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        self.close()

    def __del__(self) -> None:  # last resort; close() is the API
        try:
            if not self._closed:
                self.close()
        except Exception:
            pass
