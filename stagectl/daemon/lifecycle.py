"""The service's lifecycle: its states, what it hosts, start-up until READY, and the safe shutdown.

Lifecycle (``status()["state"]``)::

    unconfigured --config valid, devices opened+configured--> configured
    configured --loop running, drive enabled, loop healthy--> active      (READY=1 sent here, not before)
    active <--loop latches a fault / `reset` clears it--> fault
    any --SIGTERM/SIGINT--> stopping --> stopped                          (STOPPING=1)
    unclean end of the previous run --> fault (latched ``unclean_shutdown``, drive NOT enabled; READY=1)
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from stagectl.daemon.control import ControlServer
from stagectl.daemon.marker import UNCLEAN_FAULT, UncleanLatch
from stagectl.daemon.remote import LoopLike
from stagectl.daemon.sdnotify import SdNotifier
from stagectl.daemon.telemetry import TelemetryWriter
from stagectl.daemon.watchdog import Watchdog
from stagectl.drivers.base import DeviceState
from stagectl.errors import ConfigError, StageError
from stagectl.runtime.host import LoopHost
from stagectl.runtime.status import FaultInfo, LoopState, LoopStatus

__all__ = ["Assembly", "Lifecycle", "StatusCache", "announce_ready", "drive_state", "drive_text", "failure_code", "flush_after_fault", "fault_text", "shut_down", "status_line", "wait_until_ready"]

log = logging.getLogger("stagectl.daemon")


class Lifecycle(enum.Enum):
    UNCONFIGURED = "unconfigured"
    CONFIGURED = "configured"
    ACTIVE = "active"
    FAULT = "fault"
    STOPPING = "stopping"
    STOPPED = "stopped"


@dataclass
class Assembly:
    """What the service needs from the assembled application (built by :func:`stagectl.daemon.assemble.build_assembly`
    from a :class:`stagectl.app.Stage`; tests build it around their own loop).

    ``loop`` is the :class:`~stagectl.loop.ControlLoop`; ``close()`` releases devices and buses (idempotent);
    ``controller_config`` is the tuning in force; ``inject_fault(kind, **kw)`` exists only for simulated
    plants (the ``fault`` debug request); ``simulated`` says the plant is simulated.
    """

    loop: LoopLike
    close: Callable[[], None]
    controller_config: object = None
    simulated: bool = False
    inject_fault: Callable[..., dict[str, Any]] | None = None
    describe: dict[str, Any] = field(default_factory=dict)


def drive_state(asm: Assembly) -> DeviceState:
    """The drive's (the loop's actuator's) lifecycle state."""
    return asm.loop.actuator.state


def drive_text(asm: Assembly, st: LoopStatus | None) -> str:
    """The drive as an operator sees it: ``enabled`` only while the loop controls it (ACTIVE);
    ``quick_stopped`` while the device is still enabled but the loop has latched a fault and quick-stopped
    it (braking, not following commands); otherwise the device state (``configured``, ``fault``, ...)."""
    ds = drive_state(asm)
    if ds is DeviceState.ENABLED:
        loop_state = st.state if st is not None else asm.loop.state
        if loop_state is LoopState.FAULT:
            return "quick_stopped"
        return "enabled" if loop_state is LoopState.ACTIVE else str(ds.value)
    return str(ds.value)


class StatusCache:
    """``loop.status()`` for clients: state, fault, counters and position always live (cheap), the timing
    percentiles (~2 ms of interpreter time) at most every ``max_age_s``, so a client flooding ``status`` cannot
    turn into loop lateness and a reply never shows a state the loop has already left."""

    def __init__(self, max_age_s: float = 0.05) -> None:
        self.max_age_s = max_age_s
        self._lock = threading.Lock()
        self._cache: tuple[float, LoopStatus] | None = None

    def get(self, loop: LoopLike) -> LoopStatus:
        now = time.monotonic()
        with self._lock:
            if self._cache is None or now - self._cache[0] > self.max_age_s:
                self._cache = (now, loop.status())
                return self._cache[1]
            timed = self._cache[1]
        return dataclasses.replace(loop.status(timing=False), lateness_us=timed.lateness_us, exec_us=timed.exec_us)

    def clear(self) -> None:
        with self._lock:
            self._cache = None


def flush_after_fault(writer: TelemetryWriter | None, watchdog_s: float | None) -> bool:
    """Flush telemetry after a loop fault, bounded so the next watchdog ping stays in time (the supervisor has
    just pinged; its tick is at most a quarter of the interval). Returns True if a flush was attempted."""
    if writer is None:
        return False
    wait_s = min(2.0, watchdog_s / 2) if watchdog_s else 2.0
    if not writer.flush(timeout=wait_s):
        log.warning("telemetry flush after fault did not finish within %.1f s", wait_s)
    return True


def announce_ready(latched: bool, socket_path: Path) -> None:
    if latched:
        log.warning("ready, LATCHED in fault %s (drive not enabled; `stagectl reset` enables it); control socket %s",
                    UNCLEAN_FAULT, socket_path)
    else:
        log.info("ready: drive enabled, loop healthy; control socket %s", socket_path)


def failure_code(exc: Exception, notify: SdNotifier) -> int:
    """Report a failure of start-up or supervision (log + ``STATUS=``); returns the exit code: 2 for an invalid
    configuration, 1 otherwise (devices, socket path, permissions need no traceback; anything else gets one)."""
    if isinstance(exc, ConfigError):
        log.error("configuration invalid, not starting:\n%s", exc)
        notify.status(f"configuration invalid: {exc.problems[0] if exc.problems else exc}")
        return 2
    if isinstance(exc, (StageError, OSError)):
        log.error("start-up failed: %s", exc)
        notify.status(f"start-up failed: {exc}")
    else:
        log.exception("daemon error: %s", exc)
    return 1


def fault_text(fault: FaultInfo | None) -> str:
    if fault is None:
        return "-"
    return f"{fault.name}: {fault.cause}" if fault.cause else fault.name


def _num(v: float | None, scale: float, fmt: str) -> str:
    if v is None or not math.isfinite(v * scale):
        return "-"
    return format(v * scale, fmt)


def status_line(state: Lifecycle, st: LoopStatus | None, writer: TelemetryWriter | None, watchdog_reason: str,
                control_down: bool, health_policy: str = "realtime") -> str:
    """The ``STATUS=`` text: state, cycle, position, lateness, overruns, telemetry, fault, warnings."""
    late = st.lateness_us if st is not None else None
    parts = [state.value, f"cycle {st.cycle if st else 0}", f"x {_num(st.x_m if st else None, 1e3, '.6f')} mm",
             f"late p99 {_num(late.p99 if late else None, 1, '.0f')} us", f"overruns {st.overruns if st else 0}"]
    if writer is not None:
        # lock-free reads (ints/str under the GIL): the writer holds its lock during file I/O, and a stalled
        # disk must not stall the supervisor (and with it the watchdog)
        err = writer.error
        lost = writer.lost
        if err:
            parts.append(f"TELEMETRY NOT RECORDING ({err}; {lost} rows lost, {writer.ring.dropped} dropped)")
        else:
            parts.append(f"telemetry dropped {writer.ring.dropped}" + (f" lost {lost}" if lost else ""))
    if st is not None and st.fault is not None:
        parts.append(f"fault {fault_text(st.fault)}")
    if health_policy == "liveness":
        parts.append("health liveness (simulated stage)")
    if watchdog_reason:
        parts.append(f"WATCHDOG WITHHELD: {watchdog_reason}")
    if control_down:
        parts.append("CONTROL SOCKET DOWN")
    return ", ".join(parts)


def wait_until_ready(asm: Assembly, host: LoopHost, watchdog: Watchdog, latch: UncleanLatch, timeout_s: float,
                     stopping: Callable[[], bool], wake: threading.Event) -> bool | None:
    """Wait until the loop is healthy: cycling, few overruns, drive enabled (or latched in
    ``unclean_shutdown``). Returns True if latched, False if active, None if a stop was requested.
    Raises StageError when the loop ends, faults or stays unhealthy for ``timeout_s``."""
    loop = asm.loop
    deadline = time.monotonic() + timeout_s
    while not stopping():
        st = loop.status(timing=False)
        if not host.alive:
            raise StageError(f"control loop ended during start-up: {host.end_reason()}")
        # latched at start (unclean end of the previous run): ready = cycling in fault, drive not enabled
        latched = latch.latched and st.state is LoopState.FAULT and latch.is_latched(st)
        if st.state is LoopState.FAULT and not latched:
            raise StageError(f"fault during start-up: {fault_text(st.fault)}")
        enabled = drive_state(asm) is DeviceState.ENABLED
        if (st.state is LoopState.ACTIVE or latched) and st.running:
            watchdog.sample(st)
            # READY: drive enabled, loop cycling, and few overruns since we started watching it
            if (latched or enabled) and watchdog.healthy() and len(watchdog.health.samples) >= 5:
                return latched
        if time.monotonic() > deadline:
            raise StageError(
                f"loop not healthy within {timeout_s:g} s (state {st.state.value}, cycle {st.cycle}, overrun "
                f"fraction {watchdog.health.overrun_fraction():.2%} (limit {watchdog.limit:.2%}), drive "
                f"enabled {enabled})")
        wake.wait(0.02)
    return None


def shut_down(*, asm: Assembly | None, host: LoopHost | None, halt: bool, server: ControlServer | None,
              writer: TelemetryWriter | None, latch: UncleanLatch, failed_while_running: bool,
              notify: SdNotifier, stop_timeout_s: float) -> bool:
    """Stop motion (if ``halt``), stop the loop (drive disabled), flush telemetry, settle the run marker,
    close the devices. Returns True if clean."""
    notify.stopping("stopping: halting motion, disabling drive, flushing telemetry")
    clean = True
    budget_end = time.monotonic() + stop_timeout_s
    if host is not None and host.alive:
        if halt:
            host.halt_motion(budget_end - 0.5 * stop_timeout_s)
        host.stop()
        if not host.wait(max(0.1, budget_end - time.monotonic())):
            log.error("control loop did not stop within %.1f s", stop_timeout_s)
            clean = False
    drive = "unknown"
    if asm is not None:
        if drive_state(asm) is DeviceState.ENABLED:
            try:  # the loop could not do it: do it here (Device.disable is safe in any state)
                asm.loop.actuator.disable()
            except Exception:  # noqa: BLE001
                log.exception("disabling the drive failed")
        ds = drive_state(asm)
        if ds in (DeviceState.CONFIGURED, DeviceState.OPEN, DeviceState.CLOSED):
            drive = "disabled"
        elif ds is DeviceState.FAULT:
            drive = "in fault (quick-stopped, not enabled)"
        else:
            drive = f"state {ds.value}"
            clean = False
    if server is not None:
        server.stop()
    if writer is not None:
        if host is not None:
            host.remove_sinks()
        if not writer.stop(timeout=max(1.0, budget_end - time.monotonic())):
            log.error("telemetry writer did not finish")
            clean = False
        tst = writer.status()
        log.info("telemetry flushed: %d rows written, %d dropped, %d lost%s", tst["rows_written"], tst["dropped"],
                 tst["lost"], f", error: {tst['error']}" if tst["error"] else "")
    latch.settle(failed_while_running=failed_while_running, loop_alive=host is not None and host.alive,
                 drive_enabled=asm is not None and drive_state(asm) is DeviceState.ENABLED, drive=drive,
                 st=asm.loop.status(timing=False) if asm is not None else None)
    if asm is not None:
        try:
            asm.close()
        except Exception:  # noqa: BLE001
            log.exception("closing devices failed")
            clean = False
    res = host.result if host is not None else None
    msg = f"stopped: drive {drive}, {res.cycles if res else 0} cycles"
    if writer is not None:
        msg += f", telemetry dropped {writer.status()['dropped']}"
    log.info(msg)
    notify.status(msg)
    notify.close()
    return clean
