"""The stagectl service: lifecycle, signals, systemd notification, control requests, telemetry.

Lifecycle (``status()["state"]``)::

    unconfigured --config valid, devices opened+configured--> configured
    configured --loop running, drive enabled, loop healthy--> active      (READY=1 sent here, not before)
    active <--loop latches a fault / `reset` clears it--> fault
    any --SIGTERM/SIGINT--> stopping --> stopped                          (STOPPING=1)
    unclean end of the previous run --> fault (latched ``unclean_shutdown``, drive NOT enabled; READY=1)

Unclean-end latch (:class:`RunMarker`, file ``stagectl.running`` in the state directory: ``--state-dir`` /
``$STATE_DIRECTORY``, else the runtime directory): written (fsynced) before the loop thread may enable the
drive, removed on a clean stop (SIGTERM/SIGINT) once the drive is disabled and telemetry flushed, and after a
start-up failure that left the drive disabled; kept after a failure while running (the loop died). If it exists
at start, the previous run ended abnormally (SIGKILL, watchdog SIGABRT, crash, power loss) and systemd's
``Restart=on-failure`` restarted us: the loop starts latched in fault ``unclean_shutdown``
(:meth:`ControlLoop.latch_fault`), READY=1 is still sent (the service answers), and only an explicit ``reset``
request enables the drive, as for any latched fault. The marker (with the old run's pid and start time) is kept
until that reset, so a stop or a start-up failure before it does not lose the latch.

Threads: the **loop thread** runs :meth:`ControlLoop.run` (real-time settings applied inside it); the
**main thread** is the supervisor (signals, watchdog, STATUS=, fault → telemetry flush) and starts a short-lived
**reload thread** per SIGHUP (YAML + design may take longer than the watchdog interval);
the control socket, telemetry writer and log listener each have one normal-priority thread. None of them
takes a lock the loop takes; they talk to the loop only through ``loop.request`` (a queue served at the
cycle boundary), ``loop.status()`` (a snapshot) and the telemetry ring (lock-free).

Watchdog (docs/platform.md section 5): ``WATCHDOG=1`` is sent from the supervisor's check, never from a
free-running thread, and only if since the previous check the loop's cycle counter advanced and the overrun
fraction over the last 10 s (:class:`HealthWindow`) is at or below ``loop.healthy_overrun_fraction``. A latched *fault* does not stop the pings:
the loop is still cycling and holding the stage safely; restarting the process would only lose the latch.
A hung or dead loop stops the pings, and systemd kills and restarts the service (``Restart=on-failure``);
the drive's own heartbeat consumer stops the stage if the process dies.

Signals: SIGTERM/SIGINT → stop motion (decelerate, bounded wait), stop the loop (it writes zero force and
disables the drive), flush and close telemetry, exit 0. SIGHUP → reload the ``controller`` section with the
full ``check-config`` validation; apply it through ``loop.request("retune")`` at a cycle boundary, or reject
it (reason logged and shown in ``status()["reload"]``) and keep the old tuning.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import datetime
import enum
import json
import logging
import math
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from stagectl.config.daemon import DaemonConfig
from stagectl.daemon._sched import demote_to_normal_priority
from stagectl.daemon.control import ControlServer, RequestError, to_json
from stagectl.daemon.sdnotify import SdNotifier
from stagectl.daemon.telemetry import TelemetryRing, TelemetryWriter, WriterSettings
from stagectl.errors import ConfigError, StageError

log = logging.getLogger("stagectl.daemon")


class Lifecycle(enum.Enum):
    UNCONFIGURED = "unconfigured"
    CONFIGURED = "configured"
    ACTIVE = "active"
    FAULT = "fault"
    STOPPING = "stopping"
    STOPPED = "stopped"


class HealthWindow:
    """Loop health as the supervisor sees it, over a sliding time window.

    Samples ``(t, cycle, overruns)`` from ``loop.status()``; the overrun fraction over the window is

        f = Δoverruns / (Δcycles + Δoverruns)        (skipped slots / all slots in the last ``window_s``)

    A time window (not "since start") keeps one start-up stall (JIT compile, first GC) from making a young
    process look unhealthy for minutes, and keeps a long-running one sensitive to a new problem.
    """

    def __init__(self, window_s: float = 10.0) -> None:
        self.window_s = window_s
        self.samples: deque[tuple[float, int, int]] = deque()

    def add(self, t_s: float, cycle: int, overruns: int) -> None:
        self.samples.append((t_s, int(cycle), int(overruns)))
        while len(self.samples) > 2 and self.samples[1][0] <= t_s - self.window_s:
            self.samples.popleft()

    def advancing(self) -> bool:
        """The cycle counter increased between the last two samples."""
        return len(self.samples) >= 2 and self.samples[-1][1] > self.samples[-2][1]

    def overrun_fraction(self) -> float:
        if len(self.samples) < 2:
            return 0.0
        _, c0, o0 = self.samples[0]
        _, c1, o1 = self.samples[-1]
        slots = (c1 - c0) + (o1 - o0)
        return (o1 - o0) / slots if slots > 0 else 0.0


UNCLEAN_FAULT = "unclean_shutdown"


class RunMarker:
    """``<dir>/stagectl.running``: present while a run may have the drive enabled (see the module docstring).

    Content: one JSON object ``{"pid", "started_utc", "config"}``. Written atomically (temporary file, fsync,
    rename, fsync of the directory) so that it survives a power loss; removal is not fsynced (a marker that
    reappears after a power loss only latches once more: the safe side).
    """

    NAME = "stagectl.running"

    def __init__(self, directory: Path) -> None:
        self.path = Path(directory) / self.NAME

    def read(self) -> dict[str, Any] | None:
        """The marker's content, None if there is no marker. An unreadable or garbled marker still counts."""
        try:
            text = self.path.read_text(encoding="utf-8", errors="replace")
        except FileNotFoundError:
            return None
        except OSError as exc:
            return {"unreadable": f"{exc.strerror or exc}"}
        try:
            data = json.loads(text)
        except ValueError:
            data = None
        return data if isinstance(data, dict) else {"content": text[:200]}

    def write(self, config_path: Path) -> None:
        """Record this run (raises OSError: start-up must not go on without the marker)."""
        info = {"pid": os.getpid(), "started_utc": _utc_now(), "config": str(config_path)}
        self.path.parent.mkdir(parents=True, mode=0o750, exist_ok=True)
        tmp = self.path.with_name(self.NAME + ".tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o640)
        try:
            os.write(fd, (json.dumps(info) + "\n").encode())
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, self.path)
        dfd = os.open(self.path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)


def _utc_now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def _unclean_cause(info: dict[str, Any]) -> str:
    who = f"pid {info.get('pid', '?')}, started {info.get('started_utc', '?')}"
    if "pid" not in info:
        who = f"marker {json.dumps(info)}"
    return (f"the previous run ({who}) did not stop cleanly (killed, crashed, watchdog abort or power loss); "
            f"detected at start {_utc_now()}; check the stage, then `stagectl reset` to enable the drive")


@dataclass
class Assembly:
    """What the service needs from the assembled application (built by :mod:`stagectl.app`).

    ``loop`` is the :class:`stagectl.loop.ControlLoop`; ``close()`` releases devices and buses (idempotent);
    ``controller_config`` is the tuning in force; ``inject_fault(kind, **kw)`` exists only for simulated
    plants (the ``fault`` debug request); ``simulated`` says the plant is simulated.
    """

    loop: Any
    close: Callable[[], None]
    controller_config: Any = None
    simulated: bool = False
    inject_fault: Callable[..., Any] | None = None
    describe: dict[str, Any] = field(default_factory=dict)


#: config_path -> (app config, daemon config); raises ConfigError (the check-config validation)
ConfigLoader = Callable[[Path], tuple[Any, DaemonConfig]]
#: app config -> Assembly (opens and configures the devices)
Builder = Callable[[Any], Assembly]

_MOVE_KEYS = {"request", "id", "target_m", "relative_m", "max_velocity_m_s"}
_PLAIN_KEYS = {"request", "id"}


class StageService:
    """The daemon. ``run()`` blocks in the calling (main) thread and returns the process exit code."""

    def __init__(
        self,
        config_path: str | os.PathLike[str],
        runtime_dir: str | os.PathLike[str],
        *,
        load_config: ConfigLoader,
        build: Builder,
        notifier: SdNotifier | None = None,
        state_dir: str | os.PathLike[str] | None = None,
    ) -> None:
        self.config_path = Path(config_path)
        self.runtime_dir = Path(runtime_dir)
        self.state_dir = Path(state_dir) if state_dir else None
        self._load_config = load_config
        self._build = build
        self.notify = notifier if notifier is not None else SdNotifier()
        self.state = Lifecycle.UNCONFIGURED
        self.app_cfg: Any = None
        self.cfg = DaemonConfig()
        self.asm: Assembly | None = None
        self.ring: TelemetryRing | None = None
        self.writer: TelemetryWriter | None = None
        self.server: ControlServer | None = None
        self._loop_thread: threading.Thread | None = None
        self._loop_stop = threading.Event()
        self._loop_result: Any = None
        self._loop_error: BaseException | None = None
        self._wake = threading.Event()
        self._term_signal: int | None = None
        self._hup_pending = 0
        self._reload_thread: threading.Thread | None = None
        self._started_mono = time.monotonic()
        self.reload_status: dict[str, Any] | None = None
        self.fault_flushes = 0
        self.health = HealthWindow()
        self._watchdog_pings = 0
        self._watchdog_withheld = 0
        self._watchdog_reason = ""
        self._control_down = False
        self.socket_path: Path | None = None
        self._status_lock = threading.Lock()
        self._status_cache: tuple[float, dict[str, Any]] | None = None
        self.marker = RunMarker(self._state_directory())
        self._unclean: dict[str, Any] | None = None  # the previous run's marker, until `reset` acknowledges it
        self._unclean_latched = False
        self._ready = False  # READY=1 sent (start-up finished)

    # ================================================================== main
    def run(self) -> int:
        """Start, supervise until a stop signal or a fatal error, shut down. Returns the exit code."""
        self._install_signals()
        try:
            code = self._startup()
            if code is None:
                code = self._supervise()
        except ConfigError as exc:
            log.error("configuration invalid, not starting:\n%s", exc)
            self.notify.status(f"configuration invalid: {exc.problems[0] if exc.problems else exc}")
            code = 2
        except (StageError, OSError) as exc:  # devices, socket path, permissions: no traceback needed
            log.error("start-up failed: %s", exc)
            self.notify.status(f"start-up failed: {exc}")
            code = 1
        except Exception as exc:  # noqa: BLE001 - report, then shut down safely
            log.exception("daemon error: %s", exc)
            code = 1
        finally:
            clean = self._shutdown()
        if code == 0 and not clean:
            code = 1
        return code

    def request_stop(self, signum: int = signal.SIGTERM) -> None:
        """Ask the supervisor to stop (what SIGTERM does). Thread-safe."""
        if self._term_signal is None:
            self._term_signal = signum
        self._wake.set()

    def request_reload(self) -> None:
        """Ask the supervisor to reload the tuning (what SIGHUP does). Thread-safe."""
        self._hup_pending += 1
        self._wake.set()

    def _install_signals(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        signal.signal(signal.SIGTERM, lambda s, f: self.request_stop(s))
        signal.signal(signal.SIGINT, lambda s, f: self.request_stop(s))
        signal.signal(signal.SIGHUP, lambda s, f: self.request_reload())

    # ================================================================== start-up
    def _startup(self) -> int | None:
        log.info("stagectl daemon starting (pid %d, config %s, runtime dir %s)", os.getpid(), self.config_path,
                 self.runtime_dir)
        self._unclean = self.marker.read()
        if self._unclean is not None:
            log.warning("previous run did not stop cleanly (marker %s: %s): starting LATCHED in fault %s, "
                        "drive not enabled until `stagectl reset`", self.marker.path, json.dumps(self._unclean),
                        UNCLEAN_FAULT)
        self.notify.status("loading configuration")
        self.app_cfg, self.cfg = self._load_config(self.config_path)
        if self._term_signal is not None:
            return 0
        self.notify.status("opening and configuring devices")
        self.asm = self._build(self.app_cfg)
        loop = self.asm.loop
        self.state = Lifecycle.CONFIGURED
        log.info("configured: %s", ", ".join(f"{k}={v}" for k, v in self.asm.describe.items()) or "ok")
        self._start_telemetry(loop)
        self._start_control()
        if self._term_signal is not None:
            return 0
        # ---------------------------------------------------------------- unclean-end latch, marker
        if self._unclean is not None:
            loop.latch_fault(UNCLEAN_FAULT, _unclean_cause(self._unclean))
            self._unclean_latched = True  # the old marker stays until reset (see _track_unclean)
        else:
            self.marker.write(self.config_path)  # before the loop thread can enable the drive
        # ---------------------------------------------------------------- loop thread
        self._loop_thread = threading.Thread(target=self._loop_main, name="stagectl-loop", daemon=True)
        self._loop_thread.start()
        # the loop thread inherited the process's policy (SCHED_FIFO under the unit); the supervisor (YAML
        # reloads, JSON) steps down so it can never hold a CPU the loop needs
        demote_to_normal_priority()
        self.notify.status("enabling drive, starting loop")
        deadline = time.monotonic() + self.cfg.ready_timeout_s
        limit = self._overrun_limit()
        while True:
            if self._term_signal is not None:
                return 0
            st = loop.status()
            if not self._loop_thread.is_alive():
                raise StageError(f"control loop ended during start-up: {self._loop_end_reason()}")
            # latched at start (unclean end of the previous run): ready = cycling in fault, drive not enabled
            latched = (self._unclean_latched and st.get("state") == "fault"
                       and (st.get("fault") or {}).get("name") == UNCLEAN_FAULT)
            if st.get("state") == "fault" and not latched:
                raise StageError(f"fault during start-up: {_fault_text(st.get('fault'))}")
            if (st.get("state") == "active" or latched) and st.get("running"):
                self.health.add(time.monotonic(), st.get("cycle", 0), st.get("overruns", 0))
                # READY: drive enabled, loop cycling, and few overruns since we started watching it
                if ((latched or self._drive_enabled()) and self.health.advancing()
                        and len(self.health.samples) >= 5 and self.health.overrun_fraction() <= limit):
                    break
            if time.monotonic() > deadline:
                raise StageError(
                    f"loop not healthy within {self.cfg.ready_timeout_s:g} s (state {st.get('state')}, "
                    f"cycle {st.get('cycle')}, overrun fraction {self.health.overrun_fraction():.2%} "
                    f"(limit {limit:.2%}), drive enabled {self._drive_enabled()})")
            self._wake.wait(0.02)
        self._ready = True
        if latched:
            self.state = Lifecycle.FAULT
            self.notify.ready(self._status_line())
            log.warning("ready, LATCHED in fault %s (drive not enabled; `stagectl reset` enables it); "
                        "control socket %s", UNCLEAN_FAULT, self.socket_path)
            return None
        self.state = Lifecycle.ACTIVE
        self.notify.ready(self._status_line())
        log.info("ready: drive enabled, loop healthy; control socket %s", self.socket_path)
        return None

    def _loop_main(self) -> None:
        try:
            self._loop_result = self.asm.loop.run(stop=self._loop_stop)  # type: ignore[union-attr]
        except BaseException as exc:  # noqa: BLE001 - reported by the supervisor
            self._loop_error = exc
            log.exception("control loop ended with an error")
        finally:
            self._wake.set()

    def _loop_end_reason(self) -> str:
        if self._loop_error is not None:
            return f"{type(self._loop_error).__name__}: {self._loop_error}"
        r = self._loop_result
        return f"ended by {getattr(r, 'ended_by', '?')}" if r is not None else "unknown"

    def _start_telemetry(self, loop: Any) -> None:
        tc = self.cfg.telemetry
        if not tc.enabled:
            return
        if tc.directory:
            directory = Path(tc.directory)
        elif self.state_dir is not None:
            directory = self.state_dir / "telemetry"
        elif os.environ.get("STATE_DIRECTORY"):
            directory = Path(os.environ["STATE_DIRECTORY"].split(":")[0]) / "telemetry"
        else:
            directory = self.runtime_dir / "telemetry"
        period = float(getattr(loop, "period_s", 1e-3))
        self.ring = TelemetryRing(loop.columns, max(1024, int(math.ceil(tc.buffer_s / period))))
        self.writer = TelemetryWriter(self.ring, WriterSettings(
            directory=directory, continuous=tc.continuous, rotate_bytes=int(tc.rotate_mb * 1e6),
            rotate_s=tc.rotate_s, keep_files=tc.keep_files, flush_interval_s=tc.flush_interval_s,
            retry_s=tc.retry_s))
        self.writer.start()
        loop.add_sink(self.ring)
        log.info("telemetry: %s (%d-row ring, %.0f s at %g Hz)", directory, self.ring.capacity,
                 self.ring.capacity * period, 1.0 / period)

    def _start_control(self) -> None:
        c = self.cfg
        self.socket_path = self.runtime_dir / c.socket_name
        self.server = ControlServer(
            self.socket_path, self.handle, group=c.socket_group, max_clients=c.max_clients,
            max_line_bytes=c.max_line_bytes, max_out_bytes=c.max_out_bytes,
            idle_timeout_s=c.client_idle_timeout_s, reply_timeout_s=c.reply_timeout_s)
        self.server.start()

    def _overrun_limit(self) -> float:
        cfg = getattr(self.asm.loop, "cfg", None) if self.asm else None
        return float(getattr(cfg, "healthy_overrun_fraction", 0.01))

    def _loop_status_cached(self, max_age_s: float = 0.05) -> dict[str, Any]:
        """``loop.status()`` at most every ``max_age_s`` for clients: computing percentiles holds the GIL, so
        a client flooding ``status`` requests must not translate into loop lateness."""
        now = time.monotonic()
        with self._status_lock:
            if self._status_cache is None or now - self._status_cache[0] > max_age_s:
                self._status_cache = (now, self.asm.loop.status())  # type: ignore[union-attr]
            return self._status_cache[1]

    def _drive_state(self) -> str:
        act = getattr(self.asm.loop, "actuator", None) if self.asm else None
        st = getattr(act, "state", None)
        return str(getattr(st, "value", st))

    def _drive_enabled(self) -> bool:
        return self._drive_state() == "enabled"

    # ================================================================== supervision
    def _supervise(self) -> int:
        loop = self.asm.loop  # type: ignore[union-attr]
        wd = self.notify.watchdog_s
        tick = min(self.cfg.status_interval_s, wd / 4 if wd else 1.0, 0.5)
        next_status = 0.0
        last_loop_state = "fault" if self.state is Lifecycle.FAULT else "active"
        while True:
            self._wake.wait(tick)
            self._wake.clear()
            if self._term_signal is not None:
                log.info("%s received: stopping", signal.Signals(self._term_signal).name)
                return 0
            if self._loop_thread is not None and not self._loop_thread.is_alive():
                log.error("control loop stopped unexpectedly (%s)", self._loop_end_reason())
                self.notify.status(f"loop stopped: {self._loop_end_reason()}")
                return 1
            # the percentiles (lateness, exec time) only when a STATUS= line is due: they cost ~2 ms of GIL
            want_timing = time.monotonic() >= next_status
            st = loop.status(timing=want_timing)
            # -------------------------------------------------- watchdog (health check, not a timer; first,
            # so that the fault handling below cannot delay a due ping)
            self.health.add(time.monotonic(), st.get("cycle", 0), st.get("overruns", 0))
            frac = self.health.overrun_fraction()
            limit = self._overrun_limit()
            if self.health.advancing() and frac <= limit:
                if self.notify.watchdog():
                    self._watchdog_pings += 1
                if self._watchdog_reason:
                    log.warning("watchdog pings resumed (loop healthy again)")
                self._watchdog_reason = ""
            else:
                self._watchdog_withheld += 1
                reason = ("cycle counter not advancing" if not self.health.advancing()
                          else f"overruns in the last {self.health.window_s:g} s above "
                               f"loop.healthy_overrun_fraction {limit:.3%}")
                if reason != self._watchdog_reason:  # log each change of cause once, not every tick
                    log.error("watchdog withheld: %s (now %.3f%%)", reason, 100 * frac)
                self._watchdog_reason = reason
            self._track_unclean(st)
            # -------------------------------------------------- fault transitions
            lstate = st.get("state")
            if lstate != last_loop_state:
                # a client's cached loop snapshot (up to 50 ms old) must not contradict the new state
                with self._status_lock:
                    self._status_cache = None
            if lstate == "fault" and last_loop_state != "fault":
                self.state = Lifecycle.FAULT
                log.error("loop fault: %s; flushing telemetry", _fault_text(st.get("fault")))
                if self.writer is not None:
                    # bounded so the next watchdog ping stays in time (pinged just above; tick <= interval/4)
                    wait_s = min(2.0, wd / 2) if wd else 2.0
                    self.fault_flushes += 1
                    if not self.writer.flush(timeout=wait_s):
                        log.warning("telemetry flush after fault did not finish within %.1f s", wait_s)
                self.notify.status(self._status_line(st if want_timing else loop.status()))
            elif lstate == "active" and last_loop_state != "active":
                self.state = Lifecycle.ACTIVE
                log.info("loop active again")
            last_loop_state = lstate
            # -------------------------------------------------- control socket (the loop does not need it)
            if self.server is not None and not self.server.alive and not self._control_down:
                self._control_down = True
                log.error("control socket thread ended; the loop keeps running (restart the service to "
                          "get the socket back)")
            # -------------------------------------------------- reload
            if self._hup_pending and not (self._reload_thread and self._reload_thread.is_alive()):
                # in its own thread: loading the YAML and designing the new tuning (observer gain, feed-forward
                # model) may take longer than the watchdog interval; the supervisor keeps pinging meanwhile.
                # SIGHUPs arriving during a reload are served by one more reload after it.
                self._hup_pending = 0
                self._reload_thread = threading.Thread(target=self._reload, name="stagectl-reload", daemon=True)
                self._reload_thread.start()
            if want_timing:
                self.notify.status(self._status_line(st))
                next_status = time.monotonic() + self.cfg.status_interval_s

    def _unclean_pending(self, st: dict[str, Any] | None = None) -> bool:
        """The previous run's unclean end is not acknowledged yet: no ``reset`` has cleared the latch (or the
        latch was never applied, e.g. start-up failed before it)."""
        if self._unclean is None:
            return False
        if not self._unclean_latched or self.asm is None:
            return True
        if st is None:
            st = self.asm.loop.status()
        return (st.get("fault") or {}).get("name") == UNCLEAN_FAULT

    def _track_unclean(self, st: dict[str, Any]) -> None:
        """After the ``reset`` that cleared ``unclean_shutdown``: the marker now stands for this run."""
        if self._unclean is not None and self._unclean_latched and not self._unclean_pending(st):
            try:
                self.marker.write(self.config_path)
            except OSError as exc:  # the old marker is still there: a crash still latches the next start
                log.error("cannot rewrite the run marker %s: %s", self.marker.path, exc.strerror or exc)
                return
            log.warning("fault %s cleared by reset; marker %s now records this run", UNCLEAN_FAULT,
                        self.marker.path)
            self._unclean = None

    def _state_directory(self) -> Path:
        if self.state_dir is not None:
            return self.state_dir
        if os.environ.get("STATE_DIRECTORY"):
            return Path(os.environ["STATE_DIRECTORY"].split(":")[0])
        return self.runtime_dir

    def _status_line(self, st: dict[str, Any] | None = None) -> str:
        if st is None:
            st = self.asm.loop.status() if self.asm else {}
        late = st.get("lateness_us") or {}
        # lock-free reads (ints/str under the GIL): the writer holds its lock during file I/O, and a stalled
        # disk must not stall the supervisor (and with it the watchdog)
        tel = {"dropped": self.writer.ring.dropped, "error": self.writer.error} if self.writer else {}
        parts = [
            f"{self.state.value}",
            f"cycle {st.get('cycle', 0)}",
            f"x {_num(st.get('x_m'), 1e3, '.6f')} mm",
            f"late p99 {_num(late.get('p99'), 1, '.0f')} us",
            f"overruns {st.get('overruns', 0)}",
        ]
        if tel:
            parts.append(f"telemetry dropped {tel.get('dropped', 0)}" +
                         (f" ERROR {tel['error']}" if tel.get("error") else ""))
        if st.get("fault"):
            parts.append(f"fault {_fault_text(st.get('fault'))}")
        if self._watchdog_reason:
            parts.append(f"WATCHDOG WITHHELD: {self._watchdog_reason}")
        if self._control_down:
            parts.append("CONTROL SOCKET DOWN")
        return ", ".join(parts)

    # ================================================================== reload (SIGHUP)
    def _reload(self) -> None:
        """Runs in the reload thread (normal priority, like the supervisor that starts it)."""
        self.notify.reloading()
        t = time.time()
        try:
            new_app, _new_daemon = self._load_config(self.config_path)
            new_ctl = _controller_section(new_app)
            if _differs_outside_controller(self.app_cfg, new_app):
                log.warning("reload: only the controller section is applied at reload; "
                            "other changes need a restart")
            fut = self.asm.loop.request("retune", controller_config=new_ctl)  # type: ignore[union-attr]
            fut.result(timeout=max(2.0, self.cfg.reply_timeout_s))
        except concurrent.futures.TimeoutError:
            self._reload_rejected(t, "the loop did not apply the new tuning in time; old tuning kept")
        except Exception as exc:  # noqa: BLE001 - ConfigError, ValueError from retune...
            self._reload_rejected(t, str(exc))
        else:
            self.app_cfg = new_app
            if self.asm is not None:
                self.asm.controller_config = new_ctl
            self.reload_status = {"ok": True, "time": t, "error": None}
            log.info("reload: new controller tuning applied at a cycle boundary")
        self.notify.ready(self._status_line())

    def _reload_rejected(self, t: float, reason: str) -> None:
        self.reload_status = {"ok": False, "time": t, "error": reason}
        log.error("reload rejected, old tuning kept:\n%s", reason)

    # ================================================================== shutdown
    def _shutdown(self) -> bool:
        """Stop motion, stop the loop (drive disabled), flush telemetry, close. Returns True if clean."""
        if self.state is Lifecycle.STOPPED:
            return True
        prev = self.state
        self.state = Lifecycle.STOPPING
        self.notify.stopping("stopping: halting motion, disabling drive, flushing telemetry")
        clean = True
        budget_end = time.monotonic() + self.cfg.stop_timeout_s
        loop = self.asm.loop if self.asm else None
        th = self._loop_thread
        if loop is not None and th is not None and th.is_alive():
            if prev in (Lifecycle.ACTIVE, Lifecycle.CONFIGURED):
                self._halt_motion(loop, budget_end - 0.5 * self.cfg.stop_timeout_s)
            self._loop_stop.set()
            th.join(max(0.1, budget_end - time.monotonic()))
            if th.is_alive():
                log.error("control loop did not stop within %.1f s", self.cfg.stop_timeout_s)
                clean = False
        drive = "unknown"
        if self.asm is not None:
            drive = self._drive_state()
            if drive == "enabled":
                try:  # the loop could not do it: do it here (Device.disable is safe in any state)
                    self.asm.loop.actuator.disable()
                except Exception:  # noqa: BLE001
                    log.exception("disabling the drive failed")
                drive = self._drive_state()
            if drive in ("configured", "open", "closed"):
                drive = "disabled"
            elif drive == "fault":
                drive = "in fault (quick-stopped, not enabled)"
            else:
                drive = f"state {drive}"
                clean = False
        if self.server is not None:
            self.server.stop()
        if self.writer is not None:
            if self.ring is not None and loop is not None:
                loop.remove_sink(self.ring)
            if not self.writer.stop(timeout=max(1.0, budget_end - time.monotonic())):
                log.error("telemetry writer did not finish")
                clean = False
            tst = self.writer.status()
            log.info("telemetry flushed: %d rows written, %d dropped, %d lost%s", tst["rows_written"],
                     tst["dropped"], tst["lost"], f", error: {tst['error']}" if tst["error"] else "")
        self._settle_marker(th, drive)
        if self.asm is not None:
            try:
                self.asm.close()
            except Exception:  # noqa: BLE001
                log.exception("closing devices failed")
                clean = False
        self.state = Lifecycle.STOPPED
        res = self._loop_result
        msg = f"stopped: drive {drive}, {getattr(res, 'cycles', 0)} cycles"
        if self.writer is not None:
            msg += f", telemetry dropped {self.writer.status()['dropped']}"
        log.info(msg)
        self.notify.status(msg)
        self.notify.close()
        return clean

    def _settle_marker(self, th: threading.Thread | None, drive: str) -> None:
        """Remove the run marker if this stop is clean for the drive: a stop request (SIGTERM/SIGINT) or a failed
        start-up, the loop has ended and the drive is not enabled; kept while an inherited ``unclean_shutdown``
        was not cleared by ``reset``, and after a failure once running (the loop died: a crash)."""
        if self._ready and self._term_signal is None:
            log.error("run marker %s kept: the service failed while running; the next start is latched",
                      self.marker.path)
            return
        if th is not None and th.is_alive():
            log.error("run marker %s kept: the control loop did not stop", self.marker.path)
            return
        if self.asm is not None and self._drive_enabled():
            log.error("run marker %s kept: the drive is still enabled (%s)", self.marker.path, drive)
            return
        if self._unclean_pending():
            log.warning("run marker %s kept: fault %s was not cleared by reset; the next start is latched too",
                        self.marker.path, UNCLEAN_FAULT)
            return
        try:
            self.marker.remove()
        except OSError as exc:
            log.error("cannot remove the run marker %s: %s (the next start will be latched)", self.marker.path,
                      exc.strerror or exc)

    def _halt_motion(self, loop: Any, until: float) -> None:
        """Decelerate to a stop before disabling (bounded by ``until``); skipped in fault (already stopped)."""
        try:
            fut = loop.request("stop")
            res = fut.result(timeout=max(0.05, until - time.monotonic()))
        except Exception as exc:  # noqa: BLE001 - fault/not running: the loop stops the drive anyway
            log.info("stop before shutdown skipped: %s", exc)
            return
        x_stop = res.get("x_m") if isinstance(res, dict) else None
        if x_stop is None:
            return
        while time.monotonic() < until:
            st = loop.status()
            if st.get("state") != "active" or abs(float(st.get("x_ref_m", x_stop)) - x_stop) <= 1e-12 + 1e-9 * abs(x_stop):
                return
            time.sleep(0.005)
        log.warning("stage still decelerating at shutdown; disabling anyway")

    # ================================================================== status + requests
    def status(self) -> dict[str, Any]:
        """Everything an operator needs, as plain JSON-able values."""
        loop_st = self._loop_status_cached() if self.asm else {}
        return {
            "state": self.state.value,
            "pid": os.getpid(),
            "uptime_s": time.monotonic() - self._started_mono,
            "config": str(self.config_path),
            "loop": loop_st,
            "drive_enabled": self._drive_enabled(),
            "telemetry": self.writer.status() if self.writer else None,
            "reload": self.reload_status,
            "watchdog": {"interval_s": self.notify.watchdog_s, "pings": self._watchdog_pings,
                         "overrun_fraction_10s": self.health.overrun_fraction(),
                         "withheld": self._watchdog_withheld, "reason": self._watchdog_reason or None},
            "control": {"alive": self.server.alive if self.server else False,
                        "clients": self.server.clients if self.server else 0,
                        **(self.server.stats if self.server else {})},
            "fault_flushes": self.fault_flushes,
            "simulated": bool(self.asm.simulated) if self.asm else None,
        }

    def handle(self, req: dict[str, Any]) -> Any:
        """Control-socket request → reply dict or Future (runs in the control thread; never blocks)."""
        kind = req.get("request")
        if not isinstance(kind, str):
            raise RequestError("request", "missing; one of status, move, stop, reset, record, gains")
        fn = getattr(self, f"_req_{kind}", None)
        if fn is None:
            raise RequestError("request", f"unknown request {kind!r}; one of status, move, stop, reset, record, "
                                          "gains")
        return fn(req)

    def _need_loop(self) -> Any:
        if self.asm is None or self.state in (Lifecycle.UNCONFIGURED, Lifecycle.STOPPING, Lifecycle.STOPPED):
            raise RequestError("request", f"daemon is {self.state.value}")
        return self.asm.loop

    def _req_status(self, req: dict[str, Any]) -> dict[str, Any]:
        _only(req, _PLAIN_KEYS)
        return {"status": self.status()}

    def _req_move(self, req: dict[str, Any]) -> Any:
        _only(req, _MOVE_KEYS)
        kw = {}
        for key, unit in (("target_m", "m"), ("relative_m", "m"), ("max_velocity_m_s", "m/s")):
            if req.get(key) is not None:
                kw[key] = _number(req, key, unit)
        if ("target_m" in kw) == ("relative_m" in kw):
            raise RequestError("target_m", "give exactly one of target_m (absolute, m) or relative_m (m)")
        return _as_reply(self._need_loop().request("move", **kw))

    def _req_stop(self, req: dict[str, Any]) -> Any:
        _only(req, _PLAIN_KEYS)
        return _as_reply(self._need_loop().request("stop"))

    def _req_reset(self, req: dict[str, Any]) -> Any:
        _only(req, _PLAIN_KEYS)
        return _as_reply(self._need_loop().request("reset"))

    def _req_gains(self, req: dict[str, Any]) -> dict[str, Any]:
        _only(req, _PLAIN_KEYS)
        ctl = self.asm.controller_config if self.asm else None
        return {"controller": to_json(ctl), "reload": self.reload_status}

    def _req_record(self, req: dict[str, Any]) -> Any:
        _only(req, {"request", "id", "action", "name"})
        if self.writer is None:
            raise RequestError("request", "telemetry is disabled (daemon.telemetry.enabled: false)")
        action = req.get("action")
        if action == "start":
            try:
                path = self.writer.record_start(req.get("name"))  # type: ignore[arg-type]
            except OSError as exc:
                raise RequestError("name", f"cannot create the recording: {exc.strerror or exc}") from None
            return {"recording": str(path)}
        if action == "stop":
            # waits for the writer to drain and fsync: off the control thread, so other clients are served
            writer = self.writer
            fut: concurrent.futures.Future[dict[str, Any]] = concurrent.futures.Future()

            def stop_recording() -> None:
                try:
                    fut.set_result({"recording": writer.record_stop()})
                except Exception as exc:  # noqa: BLE001 - "action: no recording is running" -> error reply
                    fut.set_exception(exc)

            threading.Thread(target=stop_recording, name="stagectl-record-stop", daemon=True).start()
            return fut
        raise RequestError("action", f"must be start or stop (got {action!r})")

    def _req_fault(self, req: dict[str, Any]) -> Any:
        """Debug: inject a fault into the *simulated* plant (``daemon.allow_fault_injection`` and sim only)."""
        asm = self.asm
        if asm is None or not (self.cfg.allow_fault_injection and asm.simulated and asm.inject_fault):
            raise RequestError("request", "fault injection is only available on a simulated plant with "
                                          "daemon.allow_fault_injection: true")
        kw = {k: v for k, v in req.items() if k not in ("request", "id")}
        kind = kw.pop("kind", None)
        if not isinstance(kind, str):
            raise RequestError("kind", "name the fault to inject")
        res = asm.inject_fault(kind, **kw)
        return {"injected": kind, **(res if isinstance(res, dict) else {})}


# ====================================================================== helpers
def _only(req: dict[str, Any], allowed: set[str]) -> None:
    for key in req:
        if key not in allowed:
            raise RequestError(key, f"unknown field for {req.get('request')!r} (allowed: "
                                    f"{', '.join(sorted(allowed - {'request', 'id'})) or 'none'})")


def _number(req: dict[str, Any], key: str, unit: str) -> float:
    v = req[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise RequestError(key, f"expected a number in {unit}, got {v!r}")
    try:
        v = float(v)
    except OverflowError:  # an integer literal with hundreds of digits
        raise RequestError(key, f"must be finite ({unit}); got an integer too large for a float") from None
    if not math.isfinite(v):
        raise RequestError(key, f"must be finite ({unit})")
    return v


def _as_reply(fut: concurrent.futures.Future[Any]) -> concurrent.futures.Future[dict[str, Any]]:
    """Map the loop's future result onto a reply dict (errors stay errors)."""
    out: concurrent.futures.Future[dict[str, Any]] = concurrent.futures.Future()

    def done(f: concurrent.futures.Future[Any]) -> None:
        if f.cancelled():
            out.cancel()
            return
        exc = f.exception()
        if exc is not None:
            out.set_exception(exc)
        else:
            r = f.result()
            out.set_result(to_json(r) if isinstance(r, dict) else {"result": to_json(r)})

    fut.add_done_callback(done)
    return out


def _controller_section(app_cfg: Any) -> Any:
    ctl = getattr(app_cfg, "controller", None)
    if ctl is None:
        raise ConfigError("controller: section missing")
    return ctl


def _differs_outside_controller(old: Any, new: Any) -> bool:
    if not (dataclasses.is_dataclass(old) and dataclasses.is_dataclass(new)):
        return False
    for f in dataclasses.fields(old):
        if f.name in ("controller", "source", "path"):
            continue
        if getattr(old, f.name, None) != getattr(new, f.name, None):
            return True
    return False


def _fault_text(fault: Any) -> str:
    if not fault:
        return "-"
    if isinstance(fault, dict):
        name = fault.get("name") or fault.get("kind") or "fault"
        cause = fault.get("cause") or fault.get("detail") or ""
        return f"{name}: {cause}" if cause else str(name)
    return str(fault)


def _num(v: Any, scale: float, fmt: str) -> str:
    try:
        f = float(v) * scale
    except (TypeError, ValueError):
        return "-"
    return format(f, fmt) if math.isfinite(f) else "-"

