"""The loop in its own process: it owns the devices and runs nothing but the loop.

:func:`spawn_loop_process` forks the daemon (after the instance lock, the configuration and the telemetry
check; before any device is opened, before any socket or helper thread of the daemon exists). The **loop
process**:

1. ignores SIGINT/SIGHUP (the daemon orchestrates), turns SIGTERM into "end the loop", and asks the kernel
   for SIGTERM when the daemon dies (``PR_SET_PDEATHSIG``, which fires when the *forking thread* ends: the
   service forks from the thread that runs it to the end, its main thread): the loop then stops the drive
   itself;
2. builds the stage (opens and configures the devices) with the daemon's builder;
3. creates the shared-memory block (:class:`~stagectl.runtime.shm.LoopShm`), records its cycle statistics
   there and feeds its telemetry rows into the shared ring, sends the block's name and the loop's facts
   (columns, period, limits, tuning) over a pipe, and waits for the start message;
4. runs ``loop.run`` in its main thread, with a :class:`Bridge` as the loop's per-cycle hook: publish the
   status snapshot, take queued requests at the cycle boundary, post replies, end on request;
5. sends its :class:`~stagectl.runtime.status.LoopResult`, closes the devices and exits with ``os._exit``.

Besides the loop thread it has only the queued log writer and, during a reload, one thread that designs
the new tuning (observer gains) before the loop swaps it in. No client, socket, reload parsing, journal or
telemetry file of the daemon can take this process's interpreter lock. The exclusive instance lock's file
descriptor is inherited, so a second daemon cannot start while an orphaned loop process still runs.
"""

from __future__ import annotations

import ctypes
import logging
import math
import os
import pickle
import signal
import threading
import traceback
from collections.abc import Callable
from multiprocessing import Pipe
from multiprocessing.connection import Connection
from typing import Any

from stagectl.daemon._sched import SCHED_RESET_ON_FORK, demote_to_normal_priority
from stagectl.daemon.lifecycle import Assembly
from stagectl.daemon.remote import DEVICE_STATES, KIND_CODES, LOOP_STATES, RemoteLoop
from stagectl.daemon.telemetry import SharedTelemetryRing
from stagectl.errors import StageError, short
from stagectl.loop import ControlLoop
from stagectl.outputs import plain
from stagectl.runtime.requests import (
    IlcRequest,
    LoopRequest,
    MoveRequest,
    RequestError,
    ResetRequest,
    RetuneRequest,
    ShutdownRequest,
    StopRequest,
)
from stagectl.runtime.shm import (
    CMD_HEAD,
    CMD_SLOTS,
    CMD_TAIL,
    FAULT_TEXT,
    PHASE,
    REP_HEAD,
    REP_SLOTS,
    REP_TAIL,
    S_HAS_FAULT,
    STATUS_SEQ,
    STOP_REQ,
    LoopShm,
    ShmLayout,
)
from stagectl.runtime.stats import CycleStats
from stagectl.runtime.status import LoopStateError
from stagectl.safety import SafetyFault

__all__ = ["Bridge", "spawn_loop_process"]

log = logging.getLogger("stagectl.loop")

Builder = Callable[[Any], Assembly]
_KINDS = {v: k for k, v in KIND_CODES.items()}


def _error_payload(exc: BaseException) -> dict[str, Any]:
    msg = str(exc) or type(exc).__name__
    if len(msg) > 1000:
        msg = f"{msg[:1000]}... ({len(msg) - 1000} more characters)"
    kind = "state" if isinstance(exc, LoopStateError) else "value" if isinstance(exc, ValueError) else "other"
    return {"error": msg, "kind": kind, "field": getattr(exc, "field", None)}


class Bridge:
    """The loop process's side of the shared block, run as the loop's ``on_cycle`` hook (loop thread).

    Per cycle: publish the status snapshot (seqlock), end the loop if the daemon asked, and take the queued
    request records (a single compare when there are none). Requests go to ``loop.submit`` and are executed
    at the next cycle boundary exactly as in one process; their replies are posted by the futures' callbacks.
    """

    def __init__(self, loop: ControlLoop, asm: Assembly, shm: LoopShm, wake_fd: int,
                 stop: threading.Event) -> None:
        self.loop, self.asm, self.shm = loop, asm, shm
        self.wake_fd = wake_fd
        self.stop = stop
        self.chained = loop.on_cycle
        self._last_fault: SafetyFault | None = None
        self.replies_dropped = 0
        self._drive = loop.actuator
        self._loop_thread = threading.get_ident()  # built in the thread that runs the loop
        self._wake_due = False
        loop.on_state_change = self._state_changed

    # ------------------------------------------------------------------ per cycle
    def on_cycle(self) -> None:
        if self.chained is not None:
            self.chained()
        self.publish()
        ctl = self.shm.ctl
        if ctl[STOP_REQ]:
            self.stop.set()
        if ctl[CMD_HEAD] != ctl[CMD_TAIL]:
            self.take_requests()

    def _state_changed(self) -> None:
        """The loop entered FAULT or left it: wake the daemon once this cycle's state is published."""
        self._wake_due = True

    def _wake(self) -> None:
        try:
            os.write(self.wake_fd, b"s")
        except (BlockingIOError, OSError):
            pass  # a wake-up is pending already

    def publish(self, running: bool | None = None) -> None:
        """The status snapshot into shared memory (a few stores; the fault text only when it changed)."""
        loop = self.loop
        ctl, st = self.shm.ctl, self.shm.status
        t, x, x_ref, u, k = loop._snap  # the loop's own per-cycle snapshot (status() without the statistics)
        seq = int(ctl[STATUS_SEQ])
        ctl[STATUS_SEQ] = seq + 1
        run = loop._running if running is None else running
        st[:12] = (LOOP_STATES.index(loop.state), t, x, x_ref, u, k, loop.overruns, loop.faults,
                   1.0 if run else 0.0, DEVICE_STATES.index(self._drive.state), loop.stats.late_max,
                   loop.stats.exec_max)
        fault = loop.safety.fault
        if fault is not self._last_fault:
            self._last_fault = fault
            if fault is None:
                st[S_HAS_FAULT] = 0.0
            else:
                LoopShm.put_text(self.shm.fault_text, f"{fault.name}\n{fault.cause}"[: FAULT_TEXT - 1])
                st[12:15] = (fault.t_s, fault.cycle, 1.0)
        ctl[STATUS_SEQ] = seq + 2
        if self._wake_due:  # the daemon's supervisor reads the new state now, not at its next tick
            self._wake_due = False
            self._wake()

    def take_requests(self) -> None:
        ctl, cmd = self.shm.ctl, self.shm.cmd
        tail, head = int(ctl[CMD_TAIL]), int(ctl[CMD_HEAD])
        while tail < head:
            rid_f, kind_f, a, b, c, nblob = cmd[tail % CMD_SLOTS].tolist()
            rid, kind = int(rid_f), _KINDS.get(int(kind_f), "?")
            blob = self.shm.blob[: int(nblob)].tobytes() if nblob else b""
            tail += 1
            ctl[CMD_TAIL] = tail  # the record (and blob) are copied: the slot is free again
            try:
                self._take(rid, kind, a, b, c, blob)
            except Exception as exc:  # noqa: BLE001 - a refused request is a reply, never a loop error
                self.reply(rid, None, exc)

    def _take(self, rid: int, kind: str, a: float, b: float, c: float, blob: bytes) -> None:
        req: LoopRequest
        if kind == "move":
            def opt(v: float) -> float | None:
                return None if math.isnan(v) else v
            req = MoveRequest(target_m=opt(a), relative_m=opt(b), max_velocity_m_s=opt(c))
        elif kind == "stop":
            req = StopRequest()
        elif kind == "reset":
            req = ResetRequest()
        elif kind == "shutdown":
            req = ShutdownRequest()
        elif kind == "ilc":
            action, motion = pickle.loads(blob)
            req = IlcRequest(action=action, motion=motion)
        elif kind == "retune":
            # designing the tuning (observer gains) is the heavy part: a helper thread, never this cycle
            threading.Thread(target=self._retune, args=(rid, blob), name="stagectl-retune", daemon=True).start()
            return
        elif kind == "fault":
            fault_kind, kw = pickle.loads(blob)
            if self.asm.inject_fault is None:
                raise RequestError("request", "fault injection is only available on a simulated plant")
            res = self.asm.inject_fault(fault_kind, **kw)
            self.reply(rid, {"injected": fault_kind, **(res if isinstance(res, dict) else {})}, None)
            return
        else:
            raise RequestError("request", f"unknown request code {short(kind)}")
        fut = self.loop.submit(req)
        fut.add_done_callback(lambda f: self.reply(rid, f.result() if f.exception() is None else None,
                                                   f.exception()))

    def _retune(self, rid: int, blob: bytes) -> None:
        demote_to_normal_priority()  # started from the loop thread: never compete with it at its priority
        try:
            cfg = pickle.loads(blob)
            fut = self.loop.submit(RetuneRequest(cfg))
            fut.add_done_callback(lambda f: self.reply(rid, f.result() if f.exception() is None else None,
                                                       f.exception()))
        except Exception as exc:  # noqa: BLE001 - a bad tuning is a reply
            self.reply(rid, None, exc)

    def reply(self, rid: int, result: dict[str, Any] | None, exc: BaseException | None) -> None:
        """Post a reply record and wake the daemon (any thread of this process; never blocks)."""
        ctl = self.shm.ctl
        head = int(ctl[REP_HEAD])
        if head - int(ctl[REP_TAIL]) >= REP_SLOTS:
            self.replies_dropped += 1  # the daemon does not collect (it times the request out)
            return
        payload = _error_payload(exc) if exc is not None else plain(result or {}, json=True)
        if threading.get_ident() == self._loop_thread:
            self.publish()  # the state the request left (reset: active) is visible before its reply
        self.shm.put_reply(head % REP_SLOTS, rid, exc is None, payload)
        ctl[REP_HEAD] = head + 1
        self._wake()


def inherited_realtime() -> tuple[int, int] | None:
    """(policy, priority) if the calling thread runs SCHED_FIFO/RR (e.g. the unit's CPUSchedulingPolicy=fifo),
    else None. Read in the daemon before the fork: with ``CPUSchedulingResetOnFork=yes`` the child starts at
    SCHED_OTHER and must take the policy back itself."""
    try:
        policy = os.sched_getscheduler(0) & ~SCHED_RESET_ON_FORK
        if policy in (os.SCHED_FIFO, os.SCHED_RR):
            return policy, os.sched_getparam(0).sched_priority
    except (OSError, AttributeError):
        pass
    return None


def _restore_realtime(rt: tuple[int, int] | None) -> None:
    if rt is None:
        return
    try:
        os.sched_setscheduler(0, rt[0], os.sched_param(rt[1]))
        log.info("loop process: scheduling policy %d priority %d of the service restored after fork", *rt)
    except OSError as exc:
        log.warning("loop process: cannot take the service's real-time priority back (%s); set "
                    "loop.realtime.fifo_priority", exc.strerror or exc)


def _set_pdeathsig(sig: int) -> None:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, sig, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _child(build: Builder, app_cfg: Any, conn: Connection, wake_fd: int, telemetry_buffer_s: float,
           parent_pid: int, log_level: int, rt: tuple[int, int] | None) -> int:
    """The loop process's body (see the module docstring); returns its exit code."""
    stop = threading.Event()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda s, f: stop.set())
    _set_pdeathsig(signal.SIGTERM)
    if os.getppid() != parent_pid:  # the daemon died before the request took effect
        return 1
    from stagectl.daemon.logging import DaemonLogging

    logs = DaemonLogging(log_level)  # the daemon's queue listener thread does not exist in this process
    try:
        try:
            asm = build(app_cfg)
        except BaseException as exc:  # noqa: BLE001 - reported to the daemon, which reports it
            conn.send({"error": f"{type(exc).__name__}: {exc}"[:4000], "config_error": _is_config_error(exc)})
            return 1
        loop = asm.loop
        if not isinstance(loop, ControlLoop):
            conn.send({"error": "the builder must return a ControlLoop"})
            return 1
        bridge: Bridge | None = None
        try:
            telemetry_rows = 0
            if telemetry_buffer_s > 0:
                n = max(1024, math.ceil(telemetry_buffer_s / loop.period_s))
                telemetry_rows = 1 << (n - 1).bit_length()
            rows = telemetry_rows or 2
            shm = LoopShm.create(ShmLayout(len(loop.columns), rows, int(loop.cfg.stats_window)))
            loop.stats = CycleStats(int(loop.cfg.stats_window), (shm.late, shm.exec, shm.skip))
            if telemetry_rows:
                loop.add_sink(SharedTelemetryRing(loop.columns, shm.tel, shm.ctl))
            bridge = Bridge(loop, asm, shm, wake_fd, stop)
            loop.on_cycle = bridge.on_cycle
            bridge.publish(running=False)
            conn.send({"shm": shm.name, "layout": (len(loop.columns), rows, int(loop.cfg.stats_window)),
                       "columns": loop.columns, "period_s": loop.period_s, "cfg": loop.cfg, "limits": loop.limits,
                       "simulated": asm.simulated, "describe": asm.describe,
                       "controller_config": asm.controller_config, "pid": os.getpid()})
            try:
                go = conn.recv()
            except (EOFError, OSError):  # the daemon is gone before starting us: close the devices, exit
                return 1
            shm.unlink()  # both processes have it mapped: no name left behind whatever happens next
            if not (isinstance(go, dict) and go.get("go")) or stop.is_set() or shm.ctl[STOP_REQ]:
                return 0
            latch = go.get("latch")
            if latch:
                loop.latch_fault(str(latch[0]), str(latch[1]))
            shm.ctl[PHASE] = 1
            if loop.cfg.realtime.fifo_priority is None:  # the unit's CPUSchedulingPolicy, reset by the fork
                _restore_realtime(rt)
            try:
                result = loop.run(stop=stop)
            except BaseException as exc:
                log.exception("control loop ended with an error")
                bridge.publish(running=False)
                conn.send({"error": f"{type(exc).__name__}: {exc}"[:4000]})
                return 1
            bridge.publish(running=False)
            conn.send({"result": result})
            return 0
        finally:
            try:
                asm.close()
            except Exception:
                log.exception("closing devices failed")
            if bridge is not None:
                bridge.publish(running=False)
                bridge.shm.ctl[PHASE] = 2
    finally:
        logs.close()


def _is_config_error(exc: BaseException) -> bool:
    from stagectl.errors import ConfigError

    return isinstance(exc, ConfigError)


def spawn_loop_process(build: Builder, app_cfg: Any, *, telemetry_buffer_s: float, timeout_s: float,
                       stopping: Callable[[], bool]) -> Assembly:
    """Fork the loop process, let it build the stage, attach its shared block; returns an Assembly whose
    ``loop`` is a :class:`~stagectl.daemon.remote.RemoteLoop` (``close`` ends the process).
    ``telemetry_buffer_s`` (0 = no telemetry) sizes the shared ring in loop time. Raises StageError (or ConfigError) when the
    build fails or takes longer than ``timeout_s``."""
    parent_conn, child_conn = Pipe(duplex=True)
    wake_r, wake_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
    parent_pid = os.getpid()
    level = logging.getLogger().getEffectiveLevel()
    rt = inherited_realtime()
    pid = os.fork()
    if pid == 0:  # ---------------------------------------------------------------- the loop process
        code = 1
        try:
            parent_conn.close()
            os.close(wake_r)
            code = _child(build, app_cfg, child_conn, wake_w, telemetry_buffer_s, parent_pid, level, rt)
        except BaseException:  # noqa: BLE001 - never return into the daemon's code
            traceback.print_exc()
        finally:
            os._exit(code)
    child_conn.close()
    os.close(wake_w)

    def abandon() -> None:
        try:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
        except (ProcessLookupError, ChildProcessError):
            pass
        parent_conn.close()
        os.close(wake_r)

    deadline_left = timeout_s
    while not parent_conn.poll(min(0.1, deadline_left)):
        deadline_left -= 0.1
        done, _ = os.waitpid(pid, os.WNOHANG)
        if done:
            parent_conn.close()
            os.close(wake_r)
            raise StageError("loop process ended while building the stage (see the log)")
        if stopping() or deadline_left <= 0:
            abandon()
            if stopping():
                raise StageError("stop requested while the loop process was building the stage")
            raise StageError(f"the loop process did not build the stage within {timeout_s:g} s")
    try:
        info = parent_conn.recv()
    except (EOFError, OSError) as exc:
        abandon()
        raise StageError(f"loop process lost while building the stage ({type(exc).__name__})") from None
    if "error" in info:
        try:
            os.waitpid(pid, 0)
        except ChildProcessError:
            pass
        parent_conn.close()
        os.close(wake_r)
        if info.get("config_error"):
            from stagectl.errors import ConfigError

            raise ConfigError([str(info["error"])])
        raise StageError(f"building the stage failed in the loop process: {info['error']}")
    cols, rows, window = info["layout"]
    try:
        shm = LoopShm.attach(info["shm"], ShmLayout(int(cols), int(rows), int(window)))
    except BaseException:
        abandon()
        raise
    remote = RemoteLoop(pid=pid, conn=parent_conn, wake_fd=wake_r, shm=shm, info=info)
    if telemetry_buffer_s > 0:
        remote.ring = SharedTelemetryRing(remote.columns, shm.tel, shm.ctl)
    log.info("loop process %d owns the devices (shared block %d kB)", pid, shm.layout.size() // 1024)

    def inject(kind: str, **kw: Any) -> Any:
        return remote.inject_fault(kind, **kw)

    return Assembly(loop=remote, close=remote.close, controller_config=info["controller_config"],
                    simulated=bool(info["simulated"]), inject_fault=inject if info["simulated"] else None,
                    describe={**info["describe"], "loop_pid": pid, "isolation": "process"})
