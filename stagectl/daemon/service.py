"""The stagectl service: a thin orchestrator of the daemon's parts.

:mod:`~stagectl.daemon.lifecycle` (states, start-up until READY, safe shutdown, STATUS= line),
:mod:`~stagectl.daemon.watchdog` (health-checked ``WATCHDOG=1``), :mod:`~stagectl.daemon.marker` (run marker,
``unclean_shutdown`` latch), :mod:`~stagectl.daemon.handlers` (one function per socket request, on the typed
loop requests), :mod:`~stagectl.daemon.reload` (SIGHUP), :func:`~stagectl.daemon.telemetry.start_telemetry`,
and :class:`~stagectl.runtime.host.LoopHost` (the loop thread, shared with ``stagectl run``).

Threads: the **loop thread** (real-time settings applied inside it); the **main thread**, the supervisor
(signals, watchdog, STATUS=, fault → telemetry flush), starting a **reload thread** per SIGHUP; one
normal-priority thread each for the control socket, telemetry writer and log listener. None takes a lock the
loop takes: they reach it only through ``loop.submit`` (served at the cycle boundary), ``loop.status()`` and
the lock-free telemetry ring. SIGTERM/SIGINT → stop motion, stop the loop (zero force, drive disabled), flush
telemetry, exit 0; exit 1 on a runtime failure, 2 on an invalid configuration.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from stagectl.config.daemon import DaemonConfig
from stagectl.daemon import lifecycle
from stagectl.daemon._sched import demote_to_normal_priority
from stagectl.daemon.control import ControlServer
from stagectl.daemon.handlers import ReplyOrFuture, dispatch, dispatch_observer
from stagectl.daemon.instance import InstanceLock
from stagectl.daemon.lifecycle import Assembly, Lifecycle
from stagectl.daemon.marker import RunMarker, UncleanLatch
from stagectl.daemon.paths import ServicePaths
from stagectl.daemon.reload import AppConfigLike, ConfigLoader, Reloader
from stagectl.daemon.sdnotify import SdNotifier
from stagectl.daemon.telemetry import TelemetryWriter, check_writable, start_telemetry
from stagectl.daemon.watchdog import HealthWindow, Watchdog
from stagectl.errors import StageError
from stagectl.daemon.remote import LoopLike, RemoteLoop
from stagectl.runtime.host import LoopHost
from stagectl.runtime.requests import RequestError
from stagectl.runtime.status import LoopResult, LoopState, LoopStatus

__all__ = ["Assembly", "Builder", "ConfigLoader", "HealthWindow", "Lifecycle", "StageService"]

log = logging.getLogger("stagectl.daemon")

Builder = Callable[[Any], Assembly]  #: app config -> assembly (opens and configures the devices)
PathArg = str | os.PathLike[str]


class StageService:
    """The daemon. ``run()`` blocks in the calling (main) thread and returns the process exit code."""

    def __init__(self, config_path: PathArg, runtime_dir: PathArg | None = None, *, load_config: ConfigLoader,
                 build: Builder, notifier: SdNotifier | None = None, state_dir: PathArg | None = None) -> None:
        self.paths = ServicePaths.from_env(config_path, runtime_dir, state_dir)
        self._load_config, self._build = load_config, build
        self.notify = notifier if notifier is not None else SdNotifier()
        self.state = Lifecycle.UNCONFIGURED
        self.app_cfg: AppConfigLike | None = None
        self.cfg = DaemonConfig()
        self.asm: Assembly | None = None
        self.host: LoopHost | None = None
        self.writer: TelemetryWriter | None = None
        self.server: ControlServer | None = None
        self.observer: ControlServer | None = None
        self.instance = InstanceLock(self.paths.runtime_dir, self.paths.state_dir)
        self.health_policy = "realtime"
        self.telemetry_problem: str | None = None  # the telemetry directory was not writable at start
        self._faults_seen = 0
        self.watchdog = Watchdog(self.notify, 0.01)
        self.latch = UncleanLatch(RunMarker(self.paths.marker_dir), self.paths.config)
        self.reloader = Reloader(load_config, self.paths.config, self.notify, self.cfg.reply_timeout_s,
                                 self._reload_applied, lambda: self._status_line())
        self._wake, self._started_mono = threading.Event(), time.monotonic()
        self._status_cache = lifecycle.StatusCache()
        self._term_signal: int | None = None
        self.fault_flushes, self._control_down, self._ready = 0, False, False  # _ready: READY=1 sent

    @property
    def loop_result(self) -> LoopResult | None:
        return self.host.result if self.host else None

    # ================================================================== main
    def run(self) -> int:
        """Start, supervise until a stop signal or a fatal error, shut down. Returns the exit code."""
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, lambda s, f: self.request_stop(s))
            signal.signal(signal.SIGINT, lambda s, f: self.request_stop(s))
            signal.signal(signal.SIGHUP, lambda s, f: self.request_reload())
        try:
            code = self._startup()
            if code is None:
                code = self._supervise()
        except Exception as exc:  # noqa: BLE001 - report, then shut down safely
            code = lifecycle.failure_code(exc, self.notify)
        finally:
            clean = self._shutdown()
        return 1 if code == 0 and not clean else code

    def request_stop(self, signum: int = signal.SIGTERM) -> None:
        """Ask the supervisor to stop (what SIGTERM does). Thread-safe."""
        if self._term_signal is None:
            self._term_signal = signum
        self._wake.set()

    def request_reload(self) -> None:
        """Ask the supervisor to reload the tuning (what SIGHUP does). Thread-safe."""
        self.reloader.request()
        self._wake.set()

    def _stopping(self) -> bool:  # a stop was requested
        return self._term_signal is not None

    # ================================================================== start-up
    def _startup(self) -> int | None:
        p = self.paths
        log.info("stagectl daemon starting (pid %d, config %s, runtime dir %s)", os.getpid(), p.config,
                 p.runtime_dir)
        self.instance.acquire()  # first: a second daemon touches nothing of the first one's
        self.latch.read()
        self.notify.status("loading configuration")
        self.app_cfg, self.cfg = self._load_config(p.config)
        self.reloader.reply_timeout_s = self.cfg.reply_timeout_s
        if self._stopping():
            return 0
        tc = self.cfg.telemetry
        tel_dir = p.telemetry_dir(tc.directory)
        if tc.enabled:  # before any device is opened: `refuse` must not have touched the stage
            self.telemetry_problem = check_writable(tel_dir)
            if self.telemetry_problem is not None:
                if tc.on_error == "refuse":
                    raise StageError(f"telemetry directory not writable: {self.telemetry_problem} "
                                     f"(daemon.telemetry.on_error: refuse); not starting")
                log.error("telemetry directory not writable: %s; running WITHOUT telemetry, every row counted "
                          "as lost (daemon.telemetry.on_error: report)", self.telemetry_problem)
        self.notify.status("opening and configuring devices")
        if self.cfg.isolation == "process":
            from stagectl.daemon.loopproc import spawn_loop_process

            self.notify.status("starting the loop process (it opens and configures the devices)")
            self.asm = asm = spawn_loop_process(
                self._build, self.app_cfg, telemetry_buffer_s=tc.buffer_s if tc.enabled else 0.0,
                timeout_s=max(60.0, self.cfg.ready_timeout_s), stopping=self._stopping)
        else:
            self.asm = asm = self._build(self.app_cfg)
        loop = asm.loop
        self.health_policy = self.cfg.health if self.cfg.health != "auto" else (
            "liveness" if asm.simulated else "realtime")
        # liveness: a simulated stage loses nothing when a cycle is late (the plant steps with the loop), so
        # READY and the watchdog ask only that the loop cycles; real devices also need few skipped slots
        self.watchdog.limit = 1.0 if self.health_policy == "liveness" else loop.cfg.healthy_overrun_fraction
        log.info("health policy %s (%s)", self.health_policy,
                 "loop cycling" if self.health_policy == "liveness"
                 else f"cycling, at most {loop.cfg.healthy_overrun_fraction:.2%} skipped slots")
        self.state = Lifecycle.CONFIGURED
        log.info("configured: %s", ", ".join(f"{k}={v}" for k, v in asm.describe.items()) or "ok")
        shared_ring = loop.ring if isinstance(loop, RemoteLoop) else None
        self.writer = start_telemetry(tc, tel_dir, loop.columns, loop.period_s, ring=shared_ring)
        if self.writer is not None and isinstance(loop, RemoteLoop):
            self.writer.add_tap(loop.feed_sinks)  # daemon-side sinks (the scope's stream) fed from the writer
        if self.writer is not None and self.telemetry_problem is not None:
            self.writer.report_error(self.telemetry_problem)  # READY's STATUS= says so from the first line
        self.server = ControlServer.from_config(p.runtime_dir / self.cfg.socket_name, self.handle, self.cfg)
        self.server.start()
        if self.cfg.observer_socket_name:
            self.observer = ControlServer.from_config(p.runtime_dir / self.cfg.observer_socket_name,
                                                      self.handle_observer, self.cfg)
            self.observer.group = self.cfg.observer_group
            self.observer.start()
        if self._stopping():
            return 0
        self.latch.arm(loop)  # the marker is written before the loop thread can enable the drive
        loop.on_state_change = self._wake.set  # a fault or a reset wakes the supervisor at once (no tick of lag)
        self.host = LoopHost(loop, sinks=[self.writer.ring] if self.writer else [], on_exit=self._wake.set)
        self.host.start()
        demote_to_normal_priority()  # the loop thread keeps the unit's SCHED_FIFO; the supervisor steps down
        self.notify.status("enabling drive, starting loop")
        latched = lifecycle.wait_until_ready(asm, self.host, self.watchdog, self.latch,
                                             self.cfg.ready_timeout_s, self._stopping, self._wake)
        if latched is None:
            return 0
        self._ready = True
        self.state = Lifecycle.FAULT if latched else Lifecycle.ACTIVE
        self.notify.ready(self._status_line())
        lifecycle.announce_ready(latched, self.server.path)
        if self.app_cfg is not None and self.cfg.isolation == "process":
            # the first SIGHUP then needs no import of python-control; never beside a loop thread (isolation:
            # thread), whose process must not import it (docs/architecture.md §3)
            self.reloader.warm(self.app_cfg)
        return None

    # ================================================================== supervision
    def _supervise(self) -> int:
        asm, host = self.asm, self.host
        if asm is None or host is None:
            raise StageError("supervise: the service did not start")
        loop = asm.loop
        wd = self.notify.watchdog_s
        tick = min(self.cfg.status_interval_s, wd / 4 if wd else 1.0, 0.5)
        next_status = 0.0
        last = LoopState.FAULT if self.state is Lifecycle.FAULT else LoopState.ACTIVE
        while True:
            self._wake.wait(tick)
            self._wake.clear()
            if self._term_signal is not None:
                log.info("%s received: stopping", signal.Signals(self._term_signal).name)
                return 0
            if not host.alive:
                log.error("control loop stopped unexpectedly (%s)", host.end_reason())
                self.notify.status(f"loop stopped: {host.end_reason()}")
                return 1
            # the percentiles (lateness, exec time) only when a STATUS= line is due: they cost ~2 ms of GIL
            want_timing = time.monotonic() >= next_status
            st = loop.status(timing=want_timing)
            self.watchdog.check(st)  # first, so that the fault handling below cannot delay a due ping
            self.latch.track(st)
            if st.faults > self._faults_seen and st.state is not LoopState.FAULT:
                # a fault and its reset both fell between two ticks: handle the fault all the same
                self._status_cache.clear()
                self._loop_state_changed(st, LoopState.ACTIVE, wd, fault_missed=True)
            self._faults_seen = st.faults
            if st.state is not last:
                self._status_cache.clear()
                self._loop_state_changed(st, last, wd)
            last = st.state
            if self.server is not None and not self.server.alive and not self._control_down:
                self._control_down = True
                log.error("control socket thread ended; the loop keeps running (restart the service to get "
                          "the socket back)")
            if self.app_cfg is not None:
                self.reloader.maybe_start(loop, self.app_cfg)
            if want_timing:
                self.notify.status(self._status_line(st))
                next_status = time.monotonic() + self.cfg.status_interval_s

    def _loop_state_changed(self, st: LoopStatus, last: LoopState, wd: float | None,
                            fault_missed: bool = False) -> None:
        if fault_missed:
            log.error("loop fault (already cleared by a reset before the supervisor looked); flushing telemetry")
            self.fault_flushes += lifecycle.flush_after_fault(self.writer, wd)
            return
        if st.state is LoopState.FAULT:
            self.state = Lifecycle.FAULT
            log.error("loop fault: %s; flushing telemetry", lifecycle.fault_text(st.fault))
            self.fault_flushes += lifecycle.flush_after_fault(self.writer, wd)
            self.notify.status(self._status_line(st if st.lateness_us is not None else None))
        elif st.state is LoopState.ACTIVE and last is not LoopState.ACTIVE:
            self.state = Lifecycle.ACTIVE
            log.info("loop active again")

    def _reload_applied(self, new_app: AppConfigLike) -> None:
        self.app_cfg = new_app
        if self.asm is not None:
            self.asm.controller_config = new_app.controller

    # ================================================================== shutdown
    def _shutdown(self) -> bool:
        if self.state is Lifecycle.STOPPED:
            return True
        if not self.instance.held:  # another daemon holds the directories: nothing of ours to stop or clean
            self.state = Lifecycle.STOPPED
            self.notify.close()
            return True
        if self.observer is not None:
            self.observer.stop()
        halt = self.state in (Lifecycle.ACTIVE, Lifecycle.CONFIGURED)
        self.state = Lifecycle.STOPPING
        clean = lifecycle.shut_down(
            asm=self.asm, host=self.host, halt=halt, server=self.server, writer=self.writer, latch=self.latch,
            failed_while_running=self._ready and self._term_signal is None, notify=self.notify,
            stop_timeout_s=self.cfg.stop_timeout_s)
        self.state = Lifecycle.STOPPED
        self.instance.release()
        return clean

    # ================================================================== status + requests
    def _status_line(self, st: LoopStatus | None = None) -> str:
        if st is None and self.asm is not None:
            st = self.asm.loop.status()
        return lifecycle.status_line(self.state, st, self.writer, self.watchdog.reason, self._control_down,
                                     self.health_policy)

    def status(self) -> dict[str, Any]:
        """Everything an operator needs, as plain JSON-able values."""
        asm, srv = self.asm, self.server
        loop_st = self._status_cache.get(asm.loop) if asm else None
        state = self.state
        if loop_st is not None and state in (Lifecycle.ACTIVE, Lifecycle.FAULT):  # the loop's own, not a tick old
            state = Lifecycle.FAULT if loop_st.state is LoopState.FAULT else Lifecycle.ACTIVE
        drive = lifecycle.drive_text(asm, loop_st) if asm is not None else "none"
        return {
            "state": state.value, "pid": os.getpid(), "uptime_s": time.monotonic() - self._started_mono,
            "config": str(self.paths.config),
            "loop": loop_st.as_json() if loop_st is not None else {},
            "health_policy": self.health_policy,
            "isolation": self.cfg.isolation,
            "loop_pid": asm.loop.pid if asm is not None and isinstance(asm.loop, RemoteLoop) else os.getpid(),
            # enabled = powered AND under control: a drive the loop has quick-stopped (fault reaction) is not
            "drive_enabled": drive == "enabled", "drive": drive,
            "telemetry": self.writer.status() if self.writer else None,
            "reload": self.reloader.status,
            "watchdog": self.watchdog.as_json(),
            "control": {"alive": srv.alive if srv else False, "clients": srv.clients if srv else 0,
                        **(srv.stats if srv else {})},
            "fault_flushes": self.fault_flushes,
            "simulated": bool(asm.simulated) if asm else None,
        }

    def need_loop(self) -> LoopLike:
        """The loop, for a request that needs it; RequestError while the daemon cannot serve one."""
        if self.asm is None or self.state in (Lifecycle.UNCONFIGURED, Lifecycle.STOPPING, Lifecycle.STOPPED):
            raise RequestError("request", f"daemon is {self.state.value}")
        return self.asm.loop

    def handle(self, req: Mapping[str, object]) -> ReplyOrFuture:
        """Control-socket request → reply dict or Future (runs in the control thread; never blocks)."""
        return dispatch(self, req)

    def handle_observer(self, req: Mapping[str, object]) -> ReplyOrFuture:
        """Observer-socket request: the read-only kinds only (status, gains, the telemetry stream)."""
        return dispatch_observer(self, req)
