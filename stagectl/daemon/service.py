"""The stagectl service: a thin orchestrator of the daemon's parts.

* :mod:`~stagectl.daemon.lifecycle` -- states, start-up until READY, the safe shutdown, the STATUS= line;
* :mod:`~stagectl.daemon.watchdog` -- health-checked ``WATCHDOG=1`` pings;
* :mod:`~stagectl.daemon.marker` -- the run marker and the ``unclean_shutdown`` latch;
* :mod:`~stagectl.daemon.handlers` -- one function per control-socket request, on the typed loop requests;
* :mod:`~stagectl.daemon.reload` -- SIGHUP: reload the controller tuning;
* :func:`~stagectl.daemon.telemetry.start_telemetry` -- the ring and its writer thread;
* :class:`~stagectl.runtime.host.LoopHost` -- the loop thread (shared with ``stagectl run``).

Threads: the **loop thread** runs :meth:`ControlLoop.run` (real-time settings applied inside it); the
**main thread** is the supervisor (signals, watchdog, STATUS=, fault → telemetry flush) and starts a short-lived
**reload thread** per SIGHUP; the control socket, telemetry writer and log listener each have one
normal-priority thread. None of them takes a lock the loop takes; they talk to the loop only through
``loop.submit`` (a queue served at the cycle boundary), ``loop.status()`` (a snapshot) and the telemetry ring
(lock-free).

Signals: SIGTERM/SIGINT → stop motion (decelerate, bounded wait), stop the loop (it writes zero force and
disables the drive), flush and close telemetry, exit 0. SIGHUP → :mod:`~stagectl.daemon.reload`.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from stagectl.daemon._sched import demote_to_normal_priority
from stagectl.daemon.config import DaemonConfig
from stagectl.daemon.control import ControlServer
from stagectl.daemon.handlers import ReplyOrFuture, dispatch
from stagectl.daemon.lifecycle import (Assembly, AssemblyLike, Lifecycle, drive_state, fault_text, shut_down,
                                       status_line, wait_until_ready)
from stagectl.daemon.marker import RunMarker, UncleanLatch
from stagectl.daemon.paths import ServicePaths
from stagectl.daemon.reload import AppConfigLike, ConfigLoader, Reloader
from stagectl.daemon.sdnotify import SdNotifier
from stagectl.daemon.telemetry import TelemetryWriter, start_telemetry
from stagectl.daemon.watchdog import HealthWindow, Watchdog
from stagectl.drivers.base import DeviceState
from stagectl.errors import ConfigError, StageError
from stagectl.loop import ControlLoop
from stagectl.runtime.host import LoopHost
from stagectl.runtime.requests import RequestError
from stagectl.runtime.status import LoopResult, LoopState, LoopStatus

__all__ = ["Assembly", "Builder", "ConfigLoader", "HealthWindow", "Lifecycle", "StageService"]

log = logging.getLogger("stagectl.daemon")

#: app config -> Assembly (opens and configures the devices)
Builder = Callable[[Any], AssemblyLike]


class StageService:
    """The daemon. ``run()`` blocks in the calling (main) thread and returns the process exit code."""

    def __init__(self, config_path: str | os.PathLike[str], runtime_dir: str | os.PathLike[str] | None = None, *,
                 load_config: ConfigLoader, build: Builder, notifier: SdNotifier | None = None,
                 state_dir: str | os.PathLike[str] | None = None) -> None:
        self.paths = ServicePaths.from_env(config_path, runtime_dir, state_dir)
        self._load_config, self._build = load_config, build
        self.notify = notifier if notifier is not None else SdNotifier()
        self.state = Lifecycle.UNCONFIGURED
        self.app_cfg: AppConfigLike | None = None
        self.cfg = DaemonConfig()
        self.asm: AssemblyLike | None = None
        self.host: LoopHost | None = None
        self.writer: TelemetryWriter | None = None
        self.server: ControlServer | None = None
        self.watchdog = Watchdog(self.notify, 0.01)
        self.latch = UncleanLatch(RunMarker(self.paths.marker_dir), self.paths.config)
        self.reloader = Reloader(load_config, self.paths.config, self.notify, self.cfg.reply_timeout_s,
                                 self._reload_applied, lambda: self._status_line())
        self.fault_flushes = 0
        self._wake = threading.Event()
        self._term_signal: int | None = None
        self._started_mono = time.monotonic()
        self._control_down = False
        self._status_lock = threading.Lock()
        self._status_cache: tuple[float, LoopStatus] | None = None
        self._ready = False  # READY=1 sent (start-up finished)

    @property
    def loop_result(self) -> LoopResult | None:
        return self.host.result if self.host else None

    @property
    def reload_status(self) -> dict[str, Any] | None:
        return self.reloader.status

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

    def _stopping(self) -> bool:
        return self._term_signal is not None

    # ================================================================== start-up
    def _startup(self) -> int | None:
        p = self.paths
        log.info("stagectl daemon starting (pid %d, config %s, runtime dir %s)", os.getpid(), p.config, p.runtime_dir)
        self.latch.read()
        self.notify.status("loading configuration")
        self.app_cfg, self.cfg = self._load_config(p.config)
        self.reloader.reply_timeout_s = self.cfg.reply_timeout_s
        if self._stopping():
            return 0
        self.notify.status("opening and configuring devices")
        self.asm = asm = self._build(self.app_cfg)
        loop = asm.loop
        self.watchdog.limit = loop.cfg.healthy_overrun_fraction
        self.state = Lifecycle.CONFIGURED
        log.info("configured: %s", ", ".join(f"{k}={v}" for k, v in asm.describe.items()) or "ok")
        tc = self.cfg.telemetry
        self.writer = start_telemetry(tc, p.telemetry_dir(tc.directory), loop.columns, loop.period_s)
        c = self.cfg
        self.server = ControlServer(
            p.runtime_dir / c.socket_name, self.handle, group=c.socket_group, max_clients=c.max_clients,
            max_line_bytes=c.max_line_bytes, max_out_bytes=c.max_out_bytes,
            idle_timeout_s=c.client_idle_timeout_s, reply_timeout_s=c.reply_timeout_s)
        self.server.start()
        if self._stopping():
            return 0
        self.latch.arm(loop)  # the marker is written before the loop thread can enable the drive
        self.host = LoopHost(loop, sinks=[self.writer.ring] if self.writer else [], on_exit=self._wake.set)
        self.host.start()
        # the loop thread inherited the process's policy (SCHED_FIFO under the unit); the supervisor (YAML
        # reloads, JSON) steps down so it can never hold a CPU the loop needs
        demote_to_normal_priority()
        self.notify.status("enabling drive, starting loop")
        latched = wait_until_ready(asm, self.host, self.watchdog, self.latch, c.ready_timeout_s, self._stopping,
                                   self._wake)
        if latched is None:
            return 0
        self._ready = True
        self.state = Lifecycle.FAULT if latched else Lifecycle.ACTIVE
        self.notify.ready(self._status_line())
        if latched:
            log.warning("ready, LATCHED in fault %s (drive not enabled; `stagectl reset` enables it); control "
                        "socket %s", "unclean_shutdown", self.server.path)
        else:
            log.info("ready: drive enabled, loop healthy; control socket %s", self.server.path)
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
            if st.state is not last:
                with self._status_lock:  # a client's cached snapshot (<= 50 ms old) must not contradict it
                    self._status_cache = None
                self._loop_state_changed(st, last, wd)
            last = st.state
            if self.server is not None and not self.server.alive and not self._control_down:
                self._control_down = True
                log.error("control socket thread ended; the loop keeps running (restart the service to get the "
                          "socket back)")
            if self.app_cfg is not None:
                self.reloader.maybe_start(loop, self.app_cfg)
            if want_timing:
                self.notify.status(self._status_line(st))
                next_status = time.monotonic() + self.cfg.status_interval_s

    def _loop_state_changed(self, st: LoopStatus, last: LoopState, wd: float | None) -> None:
        if st.state is LoopState.FAULT:
            self.state = Lifecycle.FAULT
            log.error("loop fault: %s; flushing telemetry", fault_text(st.fault))
            if self.writer is not None:
                # bounded so the next watchdog ping stays in time (pinged just before; tick <= interval/4)
                wait_s = min(2.0, wd / 2) if wd else 2.0
                self.fault_flushes += 1
                if not self.writer.flush(timeout=wait_s):
                    log.warning("telemetry flush after fault did not finish within %.1f s", wait_s)
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
        halt = self.state in (Lifecycle.ACTIVE, Lifecycle.CONFIGURED)
        self.state = Lifecycle.STOPPING
        clean = shut_down(asm=self.asm, host=self.host, halt=halt, server=self.server, writer=self.writer,
                          latch=self.latch, failed_while_running=self._ready and self._term_signal is None,
                          notify=self.notify, stop_timeout_s=self.cfg.stop_timeout_s)
        self.state = Lifecycle.STOPPED
        return clean

    # ================================================================== status + requests
    def _status_line(self, st: LoopStatus | None = None) -> str:
        if st is None and self.asm is not None:
            st = self.asm.loop.status()
        return status_line(self.state, st, self.writer, self.watchdog.reason, self._control_down)

    def _loop_status_cached(self, loop: ControlLoop, max_age_s: float = 0.05) -> LoopStatus:
        """``loop.status()`` at most every ``max_age_s`` for clients: computing percentiles holds the GIL, so
        a client flooding ``status`` requests must not translate into loop lateness."""
        now = time.monotonic()
        with self._status_lock:
            if self._status_cache is None or now - self._status_cache[0] > max_age_s:
                self._status_cache = (now, loop.status())
            return self._status_cache[1]

    def status(self) -> dict[str, Any]:
        """Everything an operator needs, as plain JSON-able values."""
        asm, srv = self.asm, self.server
        return {
            "state": self.state.value, "pid": os.getpid(), "uptime_s": time.monotonic() - self._started_mono,
            "config": str(self.paths.config),
            "loop": self._loop_status_cached(asm.loop).as_json() if asm else {},
            "drive_enabled": asm is not None and drive_state(asm) is DeviceState.ENABLED,
            "telemetry": self.writer.status() if self.writer else None,
            "reload": self.reloader.status,
            "watchdog": self.watchdog.as_json(),
            "control": {"alive": srv.alive if srv else False, "clients": srv.clients if srv else 0,
                        **(srv.stats if srv else {})},
            "fault_flushes": self.fault_flushes,
            "simulated": bool(asm.simulated) if asm else None,
        }

    def need_loop(self) -> ControlLoop:
        """The loop, for a request that needs it; RequestError while the daemon cannot serve one."""
        if self.asm is None or self.state in (Lifecycle.UNCONFIGURED, Lifecycle.STOPPING, Lifecycle.STOPPED):
            raise RequestError("request", f"daemon is {self.state.value}")
        return self.asm.loop

    def handle(self, req: Mapping[str, object]) -> ReplyOrFuture:
        """Control-socket request → reply dict or Future (runs in the control thread; never blocks)."""
        return dispatch(self, req)
