"""SimWorld: the plant plus the virtual devices around it, built from the ``sim:`` config section.

Two ways to run the virtual devices, switchable at any time:

* **thread mode** (``start()``): one background thread receives the device-side bus and serves the devices
  (SDO, NMT, SYNC→TPDO, heartbeats) in real time; device time = wall clock. Used for SDO configuration,
  real-time runs, ``stagectl sim-plant`` and canopen's own master in tests. After a frame the devices
  answered (a SYNC's TPDOs, an SDO response) the thread yields (``os.sched_yield``: it gives up the GIL, and
  on a CPU it shares with the receiver under SCHED_FIFO the CPU too), so the receiver handles the answer
  before the thread's own timers run.
* **lock-step mode** (``pump()``): the caller's thread drains the device-side bus with ``recv(timeout=0)``
  and processes every frame synchronously; device time is simulated: each SYNC advances it by the drive's
  communication cycle period (0x1006), ``advance(dt_s)`` advances it without SYNC (e.g. to let the drive's
  heartbeat consumer expire). The first ``pump()`` while the thread runs stops the thread (the switch is
  seamless: simulated time continues from the wall-clock time reached). Give ``world.pump`` to the
  drivers' ``set_pump`` for deterministic, faster-than-real-time runs.
* **served lock-step** (``start(lockstep=True)``): a background thread serves the devices as frames arrive
  (blocking on the bus, so a client in another process is answered at once), but device time is simulated
  as in ``pump()``: each SYNC advances it by exactly one communication cycle period, and nothing happens
  between frames (no heartbeat, no drive-consumer time-out while the client is silent). A client that waits
  for each SYNC's TPDO (``io.drive.rx_timeout_s`` large, a :class:`~stagectl.clock.SimClock` loop) then runs
  the plant deterministically and as fast as the two processes exchange frames: ``stagectl sim-plant
  --lockstep`` (docs/commissioning.md, "Across processes").

Real-time thread mode over socketcand (``stagectl sim-plant``): the client's frames are served at once in the
server's reader thread that parsed them (``_serve_now``, under the world lock; the world thread then only runs
the timers), so no hand-over between threads delays a SYNC's answer (docs/platform.md §1.3).

Transports: ``virtual`` (python-can in-process bus; channel name unique per world unless given, so
tests are xdist-safe) or ``socketcand`` (a TCP server, :mod:`stagectl.sim.socketcand`, so another
process connects with python-can's stock socketcand client). ``ready_info()`` says where to connect.

The plant is stepped only by the drive: at each SYNC by exactly one nominal period, and on the drive's own
clock while its power stage is on and SYNC is missing (docs/canopen.md §1); SYNC is dispatched
to the drive before the encoder so the encoder samples the stepped plant. The optional serial
interferometer (``stagectl.sim.interferometer.SimInterferometer``) is either triggered by each SYNC right after
the drive stepped the plant (``trigger: sync``, both modes), or streams from its own thread in thread
mode and is pumped at the end of every ``pump()`` in lock-step (configure it with
``lockstep: plant_time`` there, since drivers may pump more than once per cycle); give its driver
``world.serial_pump`` (returns the bytes written as ``LinkBytes``) rather than ``world.pump``.

Example::

    model = load_model_file(models_dir / "kamenar2016_gms.yaml")   # sim.plant.model_file, if any
    world = SimWorld.from_config(SimWorldConfig.from_mapping(yaml_mapping["sim"], plant_model=model))
    world.start()                                   # devices served in real time
    drive = Cia402Drive(Cia402Config(node_id=1, can=world.ready_info()["can"]), Timing(1e-3))
    drive.set_pump(world.pump)                      # optional: lock-step from now on
    with drive: drive.configure(); drive.enable(); ...
    world.stop()
"""

from __future__ import annotations

import itertools
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any

import can

from stagectl.drivers.canbus import close_bus, open_bus
from stagectl.drivers.interferometer_protocol import LinkBytes
from stagectl.errors import ConfigError, short
from stagectl.schema import load
from stagectl.sim.cia402_drive import SimCanopenDevice, SimCia402Drive
from stagectl.sim.cia406_encoder import SimCia406Encoder
from stagectl.sim.faults import FaultSpec, SimFault
from stagectl.sim.interferometer import SimInterferometer
from stagectl.sim.plant import StagePlant
from stagectl.sim.socketcand import SocketcandServer
from stagectl.world_schema import SimTransportConfig as SimTransportConfig
from stagectl.world_schema import SimWorldConfig as SimWorldConfig

log = logging.getLogger(__name__)

_counter = itertools.count(1)
#: thread mode: run the device timers at least this often while frames keep arriving [s]
TICK_EVERY_S = 0.0005


class SimWorld:
    """Plant + virtual CANopen drive (+ optional CiA 406 encoder and serial interferometer).

    Use as a context manager or call :meth:`stop` (idempotent) to release the bus, threads and sockets.
    """

    def __init__(self, cfg: SimWorldConfig, plant: StagePlant | None = None,
                 base_dir: str | Path | None = None) -> None:
        if plant is None:
            plant = StagePlant(cfg.plant)
        self.cfg = cfg
        self.plant = plant
        self.base_dir = Path(base_dir) if base_dir is not None else None
        tr = cfg.transport
        self.channel = tr.channel or f"stagectl-sim-{os.getpid()}-{next(_counter)}-{id(self):x}"
        self._bus: Any = None  # a virtual can.Bus, or the SocketcandServer (same recv/send)
        self._lock = threading.RLock()
        self._thread: threading.Thread | None = None
        self._stop_evt = threading.Event()
        self._sim_t = 0.0
        self._t0 = 0.0
        self._closed = False
        self.drive: SimCia402Drive | None = None
        self.encoder: SimCia406Encoder | None = None
        self._devs_of: tuple[SimCia402Drive | None, SimCia406Encoder | None] = (None, None)
        self._devs: tuple[SimCanopenDevice, ...] = ()
        self.interferometer: SimInterferometer | None = None
        self.server: SocketcandServer | None = None
        self.frames_in = 0
        self.frames_out = 0
        self._serial_bytes = 0  # bytes written by the simulated interferometer in lock-step pumps
        self._ifm_on_sync = False  # interferometer triggered by SYNC (trigger: sync) instead of streaming
        self._thread_error: BaseException | None = None
        self._last_tick = 0.0
        self._lockstep_thread = False  # served lock-step: device time advances by SYNC only

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_config(cls, cfg: SimWorldConfig, base_dir: str | Path | None = None) -> SimWorld:
        """Build the plant (``StagePlant(cfg.plant)``) and the world around it (nothing opened yet)."""
        return cls(cfg, None, base_dir)

    @property
    def devices(self) -> tuple[SimCanopenDevice, ...]:
        """The drive and the encoder present (rebuilt only when either is replaced: read several times a cycle)."""
        d, e = self.drive, self.encoder
        if d is not self._devs_of[0] or e is not self._devs_of[1]:
            self._devs_of = (d, e)
            self._devs = tuple(x for x in (d, e) if x is not None)
        return self._devs

    def open(self) -> None:
        """Open the device-side bus, power the devices on (boot-up frames), start servers. Idempotent."""
        if self._bus is not None:
            return
        if self._closed:
            raise RuntimeError("SimWorld is stopped")
        try:
            if self.cfg.transport.kind == "socketcand":
                tr = self.cfg.transport
                try:
                    self.server = SocketcandServer(self.channel, tr.host, tr.port, tr.can_name)
                except OSError as exc:
                    raise ConfigError(f"sim.transport.port: cannot listen on {tr.host}:{tr.port} "
                                      f"({exc.strerror or exc})") from exc
                self._bus = self.server  # the server is the devices' bus (recv/send)
                self.server.start()
            else:
                self._bus = open_bus({"interface": "virtual", "channel": self.channel}, path="sim.transport")
            send = self._send
            self.drive = SimCia402Drive(self.plant, self.cfg.drive, send, self.base_dir)
            if self.cfg.encoder is not None:
                self.encoder = SimCia406Encoder(self.plant, self.cfg.encoder, send, self.base_dir)
            for spec in self.cfg.faults:
                self.inject(spec)
            if self.cfg.interferometer is not None:
                self.interferometer = SimInterferometer(self.plant, self.cfg.interferometer)
                self._ifm_on_sync = self.cfg.interferometer.trigger == "sync"
            for d in self.devices:
                d.power_on(self.now())
        except BaseException:
            self.stop()
            raise

    def _send(self, msg: can.Message) -> None:
        bus = self._bus
        if bus is not None:
            self.frames_out += 1
            bus.send(msg)

    # ------------------------------------------------------------------ time
    @property
    def running(self) -> bool:
        """True while the background device thread runs (thread mode)."""
        return self._thread is not None

    def now(self) -> float:
        """Device time [s]: wall clock since start in thread mode, simulated time in lock-step."""
        if self._thread is not None and not self._lockstep_thread:
            return time.monotonic() - self._t0
        return self._sim_t

    # ------------------------------------------------------------------ dispatch
    def _dispatch(self, msg: can.Message) -> None:
        self.frames_in += 1
        drive = self.drive
        if (drive is not None and msg.arbitration_id == drive.sync_cob_id and not msg.is_error_frame
                and not msg.is_extended_id and (self._thread is None or self._lockstep_thread)):
            self._sim_t += drive.period_s
        t = self.now()
        for d in self.devices:
            d.on_frame(msg, t)
        ifm = self.interferometer
        if self._ifm_on_sync and ifm is not None and msg.arbitration_id == 0x080 and not msg.is_error_frame:
            self._serial_bytes += int(ifm.trigger())  # after the drive stepped the plant

    def _tick(self) -> None:
        self._last_tick = time.monotonic()
        t = self.now()
        for d in self.devices:
            d.tick(t)

    # ------------------------------------------------------------------ thread mode
    def start(self, lockstep: bool = False) -> None:
        """Serve the devices from a background thread (idempotent): in real time, or with ``lockstep`` in
        simulated time advanced by each SYNC (module docstring, "served lock-step")."""
        self.open()
        if self._thread is not None:
            return
        if lockstep and self.interferometer is not None and not self._ifm_on_sync:
            raise ConfigError("sim.interferometer: served lock-step needs trigger: sync (a streaming "
                              "interferometer follows the wall clock)")
        with self._lock:
            self._t0 = time.monotonic() - self._sim_t
            self._stop_evt.clear()
            for d in self.devices:
                d.threaded = not lockstep  # lock-step: the devices' time is the SYNC count, never the wall clock
            self._lockstep_thread = lockstep
            self._thread = threading.Thread(target=self._run_lockstep if lockstep else self._run,
                                            name="sim-world", daemon=True)
            self._thread.start()
            if not lockstep and self.server is not None:
                self.server.on_receive = self._serve_now  # answer in the socketcand reader thread
        if self.interferometer is not None and not self._ifm_on_sync:
            self.interferometer.start()

    def _serve_now(self, msg: can.Message) -> bool:
        """Real-time thread mode over socketcand: handle one client frame in the reader thread that received
        it (a SYNC is answered at once: drive TPDO, triggered interferometer frame). Returns False (the frame
        is queued for the world thread instead) once the thread is being stopped.

        Why not the world thread: its ``queue.get`` wake-up after the reader's ``put`` needs the OS to run a
        second thread and hand it the GIL; on a loaded 2-core machine that was measured to hold SYNCs for
        53–69 ms while the reader thread kept running, so the interferometer fell silent for 50 loop cycles
        (MISSED_FRAME) although the process had the CPU (docs/platform.md §1.3).
        """
        try:
            with self._lock:
                if self._stop_evt.is_set() or self._thread is None or self._lockstep_thread:
                    return False
                self._dispatch(msg)
                if time.monotonic() - self._last_tick >= TICK_EVERY_S:
                    self._tick()
        except Exception as exc:  # noqa: BLE001 - reported by pump()/stop(), as a world-thread failure
            self._thread_error = exc
            log.exception("sim world: serving a frame failed")
        return True

    def _run_lockstep(self) -> None:
        """Served lock-step: block for the next frame, then handle it and everything queued behind it as
        :meth:`pump` does (device time advances by SYNC only)."""
        bus = self._bus
        assert bus is not None
        try:
            while not self._stop_evt.is_set():
                msg = bus.recv(0.05)
                if msg is None:
                    continue
                with self._lock:
                    for d in self.devices:
                        d.release_late()
                    while msg is not None:
                        self._dispatch(msg)
                        self._tick()
                        msg = bus.recv(0.0)
                    self._tick()
        except Exception as exc:  # noqa: BLE001 - reported by pump()/stop()
            self._thread_error = exc
            log.exception("sim world thread failed")

    def _run(self) -> None:
        bus = self._bus
        assert bus is not None
        try:
            while not self._stop_evt.is_set():
                msg = bus.recv(0.002)
                with self._lock:
                    while msg is not None:
                        out = self.frames_out
                        self._dispatch(msg)
                        if self.frames_out != out:  # answered: let the receiver run first (we give up the
                            os.sched_yield()  # GIL and, on one CPU under FIFO, the CPU) before our timers
                        if time.monotonic() - self._last_tick >= TICK_EVERY_S:  # steady traffic must not
                            self._tick()  # starve the timers (heartbeat) while frames keep coming
                        msg = bus.recv(0.0)
                    self._tick()
        except Exception as exc:  # noqa: BLE001 - reported by pump()/stop()
            self._thread_error = exc
            log.exception("sim world thread failed")

    def _halt_thread(self) -> None:
        t = self._thread
        if t is None:
            return
        if self.server is not None:
            self.server.on_receive = None  # from now on frames are queued for pump()
        self._stop_evt.set()
        t.join(5.0)
        if not self._lockstep_thread:
            self._sim_t = time.monotonic() - self._t0
        self._thread = None
        for d in self.devices:
            d.threaded = False
        self._lockstep_thread = False
        if self.interferometer is not None:
            self.interferometer.stop()

    # ------------------------------------------------------------------ lock-step mode
    def pump(self) -> int:
        """Process every pending frame synchronously (lock-step); returns the number of frames handled.

        Stops the background thread first if it runs. Never blocks, never sleeps.
        """
        if self._thread is not None:
            self._halt_thread()
        if self._thread_error is not None:
            raise RuntimeError(f"sim world thread failed: {self._thread_error}") from self._thread_error
        self.open()
        bus = self._bus
        assert bus is not None
        n = 0
        with self._lock:
            msg = bus.recv(0.0)
            if msg is not None:
                # lock-step late TPDO: it arrives once the controller has moved on (its RPDO or the next SYNC
                # is on the bus), not at a sensor's own pump in the same cycle
                for d in self.devices:
                    d.release_late()
            while msg is not None:
                self._dispatch(msg)
                self._tick()
                n += 1
                msg = bus.recv(0.0)
            self._tick()
        if self.interferometer is not None and not self._ifm_on_sync:
            self._serial_bytes += int(self.interferometer.pump())
        return n

    def serial_pump(self) -> LinkBytes:
        """Lock-step pump for the serial interferometer's driver: :meth:`pump`, then the bytes the simulated
        interferometer wrote to its link during this call, as :class:`LinkBytes`. The driver waits for exactly
        those bytes, so a dropped or stopped frame costs no waiting (with :meth:`pump`, whose count is of CAN
        frames, it would wait for one new frame up to its ``lockstep_timeout_s``)."""
        before = self._serial_bytes
        self.pump()
        return LinkBytes(self._serial_bytes - before)

    def advance(self, dt_s: float) -> None:
        """Lock-step: advance device time by ``dt_s`` [s] without SYNC, running the timers (heartbeats)."""
        if self._thread is not None:
            raise RuntimeError("SimWorld.advance(): only in lock-step mode (the device thread is running)")
        self.pump()
        self._sim_t += float(dt_s)
        with self._lock:
            self._tick()
        self.pump()

    # ------------------------------------------------------------------ faults
    def inject(self, spec: FaultSpec | SimFault | str, **kw: Any) -> FaultSpec:
        """Schedule a fault (a :class:`FaultSpec`, or a kind plus FaultSpec fields)."""
        if not isinstance(spec, FaultSpec):
            spec = FaultSpec(kind=SimFault(spec) if isinstance(spec, str) else spec, **kw)
        dev = self.drive if spec.device == "drive" else self.encoder
        if dev is None:
            if self._bus is None:
                raise RuntimeError("SimWorld.inject(): open() or start() the world first")
            raise ConfigError(f"sim.faults: device {short(spec.device)} is not configured")
        with self._lock:
            dev.add_fault(spec)
        return spec

    def inject_fault(self, kind: str, **kw: Any) -> dict[str, Any]:
        """Control-socket form of :meth:`inject`: returns the scheduled fault as a plain dict."""
        spec = load(FaultSpec, {"kind": kind, **kw}, "fault")
        self.inject(spec)
        return {"kind": spec.kind.value, "device": spec.device, "at_cycle": spec.at_cycle,
                "at_time_s": spec.at_time_s, "cycles": spec.cycles}

    def clear_faults(self) -> None:
        with self._lock:
            for d in self.devices:
                d.faults.clear()

    # ------------------------------------------------------------------ info / shutdown
    def ready_info(self) -> dict[str, Any]:
        """Where clients connect: the ``can:`` mapping for the drivers, node ids, serial URL."""
        self.open()
        tr = self.cfg.transport
        info: dict[str, Any] = {"transport": tr.kind}
        if tr.kind == "socketcand" and self.server is not None:
            info["can"] = {"interface": "socketcand", "host": self.server.host, "port": self.server.port,
                           "channel": tr.can_name}
        else:
            info["can"] = {"interface": "virtual", "channel": self.channel}
        info["drive_node_id"] = self.cfg.drive.node_id
        if self.cfg.encoder is not None:
            info["encoder_node_id"] = self.cfg.encoder.node_id
        if self.interferometer is not None:
            info["interferometer_url"] = self.interferometer.url
        return info

    def stop(self) -> None:
        """Stop the thread, close the servers and the bus. Idempotent."""
        self._halt_thread()
        self._closed = True
        if self.interferometer is not None:
            try:
                self.interferometer.close()
            except Exception:  # noqa: BLE001
                log.debug("interferometer close failed", exc_info=True)
        if self.server is not None:
            self.server.stop()
            self.server = None
        else:
            close_bus(self._bus)
        self._bus = None

    close = stop

    def __enter__(self) -> SimWorld:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
