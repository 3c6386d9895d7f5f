"""Serial interferometer driver: :class:`SerialInterferometer` (a :class:`PositionSensor`).

The port is opened with ``serial.serial_for_url(url, baudrate=..., timeout=0)``, so ``url`` may be a device
(``/dev/ttyUSB0``), a pty symlink (the virtual interferometer) or ``socket://host:port`` (TCP_NODELAY is set on
the socket). Bytes are read with ``select()`` on the port's file descriptor and non-blocking ``read(4096)``
(pyserial's ``in_waiting`` is only 0/1 on ``socket://``), then decoded by the pure
:class:`~stagectl.drivers.interferometer_protocol.FrameParser` (frame format in that module).

``read()`` (real-time safe: never blocks in streaming mode, or at most ``rx_timeout_s`` when no new frame has
arrived yet, for a device triggered by the loop's SYNC) drains what has arrived and returns the
**newest** valid frame's position, ``position_m = counts × resolution_m``, ``fresh = True`` if a frame newer
than the previous read arrived. Faults (reported in ``Measurement.fault`` and latched in ``fault``):

=================  =========================================================================================
FaultKind          condition
=================  =========================================================================================
SENSOR_ERROR       a frame has any status bit set (signal lost, glitch, laser unlocked, error, overspeed),
                   signal strength < ``min_signal``, or a jump > ``max_step_m`` per frame between frames
CRC_ERRORS         ≥ ``max_crc_errors`` CRC failures within the last ``crc_window_cycles`` reads
SEQUENCE_GAP       a frame arrives with more than ``max_sequence_gap`` frames missing before it
MISSED_FRAME       ``stale_cycles`` consecutive reads without a new frame (reads, not wall time: a loop held off
                   the CPU reads once after the stall and finds the frames that arrived meanwhile, so its own
                   lateness never counts as the device's silence)
DISCONNECTED       the port reports EOF or an I/O error (device unplugged, socket closed)
=================  =========================================================================================

All of them are detected in the read that sees the cause, so within 3 cycles when ``stale_cycles ≤ 3``.

Lock-step (``set_pump(pump)``): ``read()`` calls ``pump()`` first. If ``pump()`` returns a
:class:`~stagectl.drivers.interferometer_protocol.LinkBytes` (as ``SimInterferometer.pump`` does), that is the
number of bytes the simulated device wrote, and ``read()`` waits (``select``) until that many more bytes have
arrived (none for 0: a dropped or suppressed frame costs no wait); for any other return value it waits for
one new frame. ``lockstep_timeout_s`` bounds the wait as a
failure guard only; the simulated device writes synchronously inside ``pump()``, so a healthy run never
reaches it and is deterministic.
"""

from __future__ import annotations

import collections
import select
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from stagectl.drivers.base import DeviceFault, DeviceState, FaultKind, Measurement, PositionSensor
from stagectl.drivers.interferometer_protocol import Frame, FrameParser, LinkBytes, ParserStats, Status
from stagectl.errors import DriverInitError, DriverIOError
from stagectl.schema import param

__all__ = ["InterferometerConfig", "SerialInterferometer"]

_READ_CHUNK = 4096


@dataclass(frozen=True)
class InterferometerConfig:
    """Serial interferometer link (YAML block ``serial:``)."""

    url: str = param(desc="port: device path, pty symlink or socket://host:port")
    baudrate: int = param(921600, unit="bit/s", desc="line rate (ignored by pty and socket://)", gt=0)
    resolution_m: float = param(1e-9, unit="m", desc="position per count", gt=0)
    max_crc_errors: int = param(3, desc="CRC failures within the window that raise CRC_ERRORS", ge=1)
    crc_window_cycles: int = param(1000, desc="window of reads over which CRC failures are counted", ge=1)
    max_sequence_gap: int = param(0, desc="frames that may be missing in one gap before SEQUENCE_GAP", ge=0)
    stale_cycles: int = param(3, desc="consecutive reads without a new frame that raise MISSED_FRAME", ge=1)
    min_signal: int = param(0, desc="lowest acceptable signal strength byte (0..255)", ge=0, le=255)
    max_step_m: float | None = param(None, unit="m", desc="largest plausible position change per frame "
                                     "(None: not checked)", gt=0)
    rx_timeout_s: float = param(0.0, unit="s", desc="real time: how long read() waits for a new frame when none "
                                "has arrived (0 = never wait; e.g. 0.0008 for a device triggered by the SYNC)", ge=0)
    lockstep_timeout_s: float = param(2.0, unit="s", desc="lock-step failure guard: longest wait for the "
                                      "simulated device's bytes", gt=0)


class SerialInterferometer(PositionSensor):
    """Streaming serial interferometer (see module docstring)."""

    name = "interferometer"

    def __init__(self, cfg: InterferometerConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.resolution_m = cfg.resolution_m
        self.parser = FrameParser()
        self._ser: Any = None
        self._fd = -1
        self._crc_window: collections.deque[int] = collections.deque(maxlen=cfg.crc_window_cycles)
        self._crc_sum = 0
        self._crc_seen = 0
        self._stale = 0
        self._last: Frame | None = None
        self._last_read_seq: int | None = None
        #: the port reported EOF or an I/O error: permanent for this open port (a reset cannot bring it back)
        self._link_dead = False
        self._bytes_rx = 0
        #: monotonic time [ns] at which the newest chunk of bytes was read
        self.last_rx_ns = 0

    # ------------------------------------------------------------------ lifecycle hooks
    def _do_open(self) -> None:
        import serial  # vendor import at the boundary

        url = self.cfg.url
        try:
            ser = serial.serial_for_url(url, baudrate=self.cfg.baudrate, timeout=0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DriverInitError(f"{self.name}: cannot open {url!r}: {exc}") from exc
        try:
            sock = getattr(ser, "_socket", None)
            if isinstance(sock, socket.socket):
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self._fd = sock.fileno()
            else:
                self._fd = ser.fileno()
        except (OSError, AttributeError, serial.SerialException) as exc:
            ser.close()
            raise DriverInitError(f"{self.name}: {url!r} has no selectable file descriptor: {exc}") from exc
        self._ser = ser
        self._link_dead = False

    def _do_configure(self) -> None:
        """Discard stale input and reset the parser and fault counters."""
        import serial

        try:
            self._ser.reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            raise DriverInitError(f"{self.name}: cannot flush {self.cfg.url!r}: {exc}") from exc
        self.parser.reset()
        self._reset_monitors()

    def _reset_monitors(self) -> None:
        self._crc_window.clear()
        self._crc_sum = 0
        self._crc_seen = self.parser.crc_errors
        self._stale = 0

    def _do_fault_reset(self) -> None:
        self._reset_monitors()

    def persisting_faults(self) -> tuple[str, ...]:
        """A port that reported EOF or an I/O error stays dead (an unplugged adapter comes back as a new device,
        a closed pty or TCP peer never returns): reported until the port is opened again (daemon restart)."""
        if self._link_dead:
            return (f"disconnected: port {self.cfg.url} closed or failing; restart the daemon once the "
                    f"interferometer is connected again",)
        return ()

    def _do_close(self) -> None:
        ser, self._ser = self._ser, None
        self._fd = -1
        if ser is not None:
            try:
                sock = getattr(ser, "_socket", None)
                if isinstance(sock, socket.socket):
                    # pyserial's socket:// close() sleeps 0.3 s "for quick reconnects"; close the socket
                    # ourselves so that close() never blocks the caller.
                    try:
                        sock.shutdown(socket.SHUT_RDWR)
                    except OSError:
                        pass
                    sock.close()
                    ser._socket = None
                    ser.is_open = False
                    return
                ser.close()
            except Exception:  # closing a dead port must not raise (close is idempotent)
                pass

    # ------------------------------------------------------------------ I/O
    @property
    def stats(self) -> ParserStats:
        """Parser counters: frames, CRC errors, sequence gaps, frames lost, bytes discarded."""
        return self.parser.stats()

    @property
    def last_frame(self) -> Frame | None:
        """The newest valid frame received (None before the first)."""
        return self._last

    def _recv(self, timeout_s: float) -> list[Frame]:
        """Wait up to ``timeout_s`` for readability, then drain everything available. Returns new frames.

        Raises DriverIOError when the port reports EOF or an I/O error.
        """
        import serial

        ser = self._ser
        if ser is None:
            raise DriverIOError(f"{self.name}: port {self.cfg.url!r} is not open")
        frames: list[Frame] = []
        try:
            r, _, _ = select.select([self._fd], [], [], timeout_s)
            while r:
                data = ser.read(_READ_CHUNK)
                if not data:
                    break
                self.last_rx_ns = time.monotonic_ns()
                self._bytes_rx += len(data)
                frames.extend(self.parser.feed(data))
                if len(data) < _READ_CHUNK:
                    break
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DriverIOError(f"{self.name}: {self.cfg.url!r}: {exc}") from exc
        return frames

    def read_frames(self, timeout_s: float = 0.0) -> list[Frame]:
        """Wait up to ``timeout_s`` [s] for data and return all frames decoded (for streaming consumers and
        benchmarks; bypasses the fault monitors). Not real-time safe if ``timeout_s > 0``."""
        self._require(DeviceState.OPEN, DeviceState.CONFIGURED, DeviceState.ENABLED, DeviceState.FAULT)
        frames = self._recv(timeout_s)
        if frames:
            self._last = frames[-1]
        return frames

    def _lockstep_recv(self, pump: Callable[[], object]) -> list[Frame]:
        before = self._bytes_rx
        expected = pump()
        deadline = time.monotonic() + self.cfg.lockstep_timeout_s
        frames: list[Frame] = []
        if isinstance(expected, LinkBytes):
            if expected <= 0:
                return self._recv(0.0)
            while self._bytes_rx - before < expected:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                frames.extend(self._recv(left))
            return frames
        while not frames:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            frames.extend(self._recv(left))
        return frames

    def read(self) -> Measurement:
        """Newest position (see module docstring). Real-time safe in streaming mode (no blocking)."""
        self._require(DeviceState.CONFIGURED, DeviceState.ENABLED, DeviceState.FAULT)
        fault: DeviceFault | None = None
        cfg = self.cfg
        try:
            pump = self._pump
            frames = self._lockstep_recv(pump) if pump is not None else self._recv(0.0)
            if not frames and pump is None and cfg.rx_timeout_s > 0:
                deadline = time.monotonic() + cfg.rx_timeout_s
                while not frames and (left := deadline - time.monotonic()) > 0:
                    frames = self._recv(left)
        except DriverIOError as exc:
            frames = []
            fault = DeviceFault(FaultKind.DISCONNECTED, str(exc))
            self._link_dead = True
        # CRC errors in the window
        crc_now = self.parser.crc_errors
        new_crc = crc_now - self._crc_seen
        self._crc_seen = crc_now
        if len(self._crc_window) == self._crc_window.maxlen:
            self._crc_sum -= self._crc_window[0]
        self._crc_window.append(new_crc)
        self._crc_sum += new_crc
        if fault is None and self._crc_sum >= cfg.max_crc_errors:
            fault = DeviceFault(FaultKind.CRC_ERRORS, f"{self._crc_sum} CRC errors in the last "
                                f"{len(self._crc_window)} cycles on {cfg.url}")
        prev = self._last
        for fr in frames:
            if fault is None:
                fault = self._check_frame(fr, prev)
            prev = fr
        if frames:
            self._last = frames[-1]
            self._stale = 0
        else:
            self._stale += 1
            if fault is None and self._stale >= cfg.stale_cycles:
                # real time: also the wall time since the last bytes (reads, not time, are counted: a loop held
                # off the CPU reads once after its stall and finds the frames that came meanwhile)
                ago = (f" (last bytes {(time.monotonic_ns() - self.last_rx_ns) * 1e-6:.1f} ms ago)"
                       if self._pump is None and self.last_rx_ns else "")
                fault = DeviceFault(FaultKind.MISSED_FRAME, f"no frame for {self._stale} cycles{ago} on {cfg.url}")
        if fault is not None:
            self._latch(fault)
        last = self._last
        if last is None:
            return Measurement(0.0, False, 0, 0, self._fault)
        fresh = bool(frames)
        return Measurement(last.counts * self.resolution_m, fresh, last.counts, last.status, self._fault)

    def _check_frame(self, fr: Frame, prev: Frame | None) -> DeviceFault | None:
        cfg = self.cfg
        if fr.lost_before > cfg.max_sequence_gap:
            return DeviceFault(FaultKind.SEQUENCE_GAP, f"{fr.lost_before} frames missing before seq {fr.seq}")
        if fr.status:
            names = ", ".join(s.name or "" for s in Status if fr.status & s) or f"0x{fr.status:02X}"
            return DeviceFault(FaultKind.SENSOR_ERROR, f"status {names} (signal {fr.signal}/255)", code=fr.status)
        if fr.signal < cfg.min_signal:
            return DeviceFault(FaultKind.SENSOR_ERROR, f"signal strength {fr.signal}/255 below {cfg.min_signal}")
        if cfg.max_step_m is not None and prev is not None:
            step_m = abs(fr.counts - prev.counts) * self.resolution_m
            n = 1 + fr.lost_before if ((fr.seq - prev.seq) & 0xFFFFFFFF) == 1 + fr.lost_before else 1
            if step_m > cfg.max_step_m * n:
                return DeviceFault(FaultKind.SENSOR_ERROR, f"position jump {step_m:.3e} m in {n} frame(s) "
                                   f"> max_step_m {cfg.max_step_m:g} m")
        return None
