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

**Ending is bounded** (:func:`_arm_backstop`). From the moment the loop process is told to end (SIGTERM, which
is also what the daemon's death delivers) or begins closing its devices for any reason, it is gone within
:data:`END_GRACE_S` (5 s, the time the daemon itself gives it before SIGKILL): ``faulthandler`` then writes
every thread's stack to stderr (the journal) and calls ``_exit(1)`` from its own C thread, which needs neither
the GIL nor any lock of the process; should that write block (stderr full), the kernel ends the process
:data:`HARD_KILL_AFTER_S` later on SIGALRM, whose default action nothing in this process overrides. Killed
that way the drive is not disabled over the bus: it stops itself, since the SYNC and the controller heartbeat
stop with the process (the drive's heartbeat consumer 0x1016 / SYNC supervision, docs/safety.md §7). That is
the fault reaction the drive has anyway for a crashed controller; what the backstop prevents is an orphan that
keeps the devices and the instance lock (a daemon restart waits 10 s for a dead daemon's loop process) with no
end. Two ways a close could hang for ever are removed as well: the log writer's stop joined its thread without
a time-out (a writer blocked on a full stderr, e.g. a stalled journal or a pipe nobody reads, kept the process
forever; now :meth:`DaemonLogging.close` waits at most 1 s here), and the SIGTERM handler set the ``stop``
event, which takes the event's lock: arriving while the loop thread (the main thread, where Python runs
handlers) was inside its own ``stop.set()`` for the daemon's stop request, it waited for its own thread.

Besides the loop thread it has only the queued log writer and, during a reload, one thread that designs
the new tuning (observer gains) before the loop swaps it in. No client, socket, reload parsing, journal or
telemetry file of the daemon can take this process's interpreter lock. The exclusive instance lock's file
descriptor is inherited, so a second daemon cannot start while an orphaned loop process still runs.
"""

from __future__ import annotations

import ctypes
import faulthandler
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

#: [s] once told to end (SIGTERM / the daemon's death) or closing, the loop process is gone within this long
#: (faulthandler dumps the stacks and exits); the daemon's own RemoteLoop.close gives it as long before SIGKILL
END_GRACE_S = 5.0
#: [s] after END_GRACE_S the kernel ends the process on SIGALRM (default action) should the dump's write block
HARD_KILL_AFTER_S = 2.0


class _Ending:
    """The loop process's end, shared with its SIGTERM handler (plain attributes: a handler takes no lock)."""

    armed = False  # the backstop runs
    setting_stop = False  # the loop thread is inside its own stop.set(): the handler must not call it too
    grace_s = END_GRACE_S


def _arm_backstop() -> None:
    """From now on this process ends within ``grace_s`` (+ HARD_KILL_AFTER_S) whatever it is blocked in.

    Idempotent (a second SIGTERM does not push the end back). Safe in a signal handler: a system call and
    faulthandler's watchdog, no lock of this process."""
    if _Ending.armed:
        return
    _Ending.armed = True
    grace = _Ending.grace_s
    try:  # (never raise: this may run in a signal handler, at any point of the loop thread)
        signal.setitimer(signal.ITIMER_REAL, grace + HARD_KILL_AFTER_S)  # SIGALRM: SIG_DFL, set at the start
    except (OSError, ValueError):
        pass
    try:
        faulthandler.dump_traceback_later(grace, exit=True, file=2)  # stacks to stderr (the journal), _exit(1)
    except (OSError, ValueError, RuntimeError):
        pass


def _on_sigterm(stop: threading.Event) -> Callable[[int, Any], None]:
    def handler(signum: int, frame: Any) -> None:
        _arm_backstop()
        if _Ending.setting_stop:  # the loop thread (or this handler, nested), interrupted in set(), completes it
            return
        _Ending.setting_stop = True
        try:
            stop.set()
        finally:
            _Ending.setting_stop = False
    return handler


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
        self.on_wait()

    def on_wait(self) -> None:
        """The loop's ``on_wait`` hook (a paced wait for the drive: no cycle runs): the same as a cycle's, without
        the chained per-cycle hook, so a client's stop, reset or status is answered during the wait, not after it."""
        self.publish()
        ctl = self.shm.ctl
        if ctl[STOP_REQ] and not self.stop.is_set():
            _Ending.setting_stop = True  # a SIGTERM handler running inside set() must not take its lock again
            try:
                self.stop.set()
            finally:
                _Ending.setting_stop = False
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
           parent_pid: int, log_level: int, rt: tuple[int, int] | None, end_grace_s: float) -> int:
    """The loop process's body (see the module docstring); returns its exit code."""
    stop = threading.Event()
    _Ending.grace_s = end_grace_s
    signal.signal(signal.SIGALRM, signal.SIG_DFL)  # the backstop's last resort: the kernel ends the process
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _on_sigterm(stop))
    # the forking thread's signal mask is inherited: SIGTERM (the daemon's death) and SIGALRM must get through
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM, signal.SIGALRM})
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
            loop.on_wait = bridge.on_wait
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
            _arm_backstop()  # closing: bounded from here, whatever asm.close or the log writer block in
            try:
                asm.close()
            except Exception:
                log.exception("closing devices failed")
            if bridge is not None:
                bridge.publish(running=False)
                bridge.shm.ctl[PHASE] = 2
    finally:
        _arm_backstop()
        logs.close(timeout_s=1.0)  # a writer blocked on a full stderr must not keep the process


def _is_config_error(exc: BaseException) -> bool:
    from stagectl.errors import ConfigError

    return isinstance(exc, ConfigError)


def spawn_loop_process(build: Builder, app_cfg: Any, *, telemetry_buffer_s: float, timeout_s: float,
                       stopping: Callable[[], bool], end_grace_s: float = END_GRACE_S) -> Assembly:
    """Fork the loop process, let it build the stage, attach its shared block; returns an Assembly whose
    ``loop`` is a :class:`~stagectl.daemon.remote.RemoteLoop` (``close`` ends the process).
    ``telemetry_buffer_s`` (0 = no telemetry) sizes the shared ring in loop time. Raises StageError (or ConfigError) when the
    build fails or takes longer than ``timeout_s``. ``end_grace_s``: the loop process's backstop (see the
    module docstring)."""
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
            code = _child(build, app_cfg, child_conn, wake_w, telemetry_buffer_s, parent_pid, level, rt,
                          end_grace_s)
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
