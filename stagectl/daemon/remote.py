"""The daemon's view of a loop running in its own process (:mod:`stagectl.daemon.loopproc`).

:class:`RemoteLoop` has the surface the service uses of a :class:`~stagectl.loop.ControlLoop` (``status``,
``submit``, ``columns``, ``period_s``, ``cfg``, ``limits``, ``actuator.state``, ``latch_fault``, ``run``,
``add_sink``), implemented on the shared-memory block (:class:`~stagectl.runtime.shm.LoopShm`):

* ``status()`` reads the loop's seqlocked snapshot and computes the timing percentiles from the shared cycle
  statistics here, in the daemon's process (the loop never spends time on a reader);
* ``submit()`` writes a fixed-size request record into the command ring (the loop takes it at its next cycle
  boundary) and returns a Future that the reply ring resolves;
* ``run()`` is what :class:`~stagectl.runtime.host.LoopHost`'s thread runs: it sends the start message,
  forwards the host's stop event, collects replies (woken by the loop's wake-up pipe) and returns the loop
  process's :class:`~stagectl.runtime.status.LoopResult` when it ends.
"""

from __future__ import annotations

import concurrent.futures
import json
import logging
import math
import os
import pickle
import select
import signal
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

from stagectl.daemon.telemetry import SharedTelemetryRing
from stagectl.drivers.base import DeviceState
from stagectl.errors import StageError
from stagectl.loop import ControlLoop
from stagectl.runtime.config import LoopConfig
from stagectl.runtime.inbox import Reply
from stagectl.runtime.protocols import TelemetrySink
from stagectl.runtime.requests import (
    IlcRequest,
    LoopRequest,
    MotionLimits,
    MoveRequest,
    RequestError,
    ResetRequest,
    RetuneRequest,
    ShutdownRequest,
    StopRequest,
)
from stagectl.runtime.shm import (
    BLOB_BYTES,
    CMD_HEAD,
    CMD_SLOTS,
    CMD_TAIL,
    REP_HEAD,
    REP_SLOTS,
    REP_TAIL,
    S_CYCLE,
    S_DRIVE,
    S_EXEC_MAX,
    S_FAULT_CYCLE,
    S_FAULT_T,
    S_FAULTS,
    S_HAS_FAULT,
    S_LATE_MAX,
    S_OVERRUNS,
    S_RUNNING,
    S_STATE,
    S_T,
    S_U,
    S_X,
    S_XREF,
    STATUS_SEQ,
    STOP_REQ,
    LoopShm,
)
from stagectl.runtime.stats import CycleStats
from stagectl.runtime.status import FaultInfo, LoopResult, LoopState, LoopStateError, LoopStatus
from stagectl.safety import SafetyFault

__all__ = ["DEVICE_STATES", "KIND_CODES", "LOOP_STATES", "LoopLike", "RemoteLoop", "reply_error"]

log = logging.getLogger("stagectl.daemon")

#: request kind -> code in a command record
KIND_CODES = {"move": 1, "stop": 2, "reset": 3, "shutdown": 4, "retune": 5, "fault": 6, "ilc": 7}
LOOP_STATES = tuple(LoopState)
DEVICE_STATES = tuple(DeviceState)
#: command slots kept free for stop, reset and shutdown: a flood of moves never locks them out
RESERVED_SLOTS = 8


def reply_error(payload: dict[str, Any]) -> BaseException:
    """The exception an error reply from the loop process stands for (its text as the loop raised it)."""
    msg = str(payload.get("error", "error in the loop process"))
    kind = payload.get("kind")
    field = payload.get("field")
    if isinstance(field, str) and msg.startswith(field + ": "):
        return RequestError(field, msg[len(field) + 2:])
    if kind == "state":
        return LoopStateError(msg)
    if kind == "value":
        return ValueError(msg)
    return StageError(msg)


class _DriveView:
    """``loop.actuator`` for the service: the drive's state as the loop process last published it."""

    def __init__(self, remote: RemoteLoop) -> None:
        self._remote = remote

    @property
    def state(self) -> DeviceState:
        code = self._remote.shm.status[S_DRIVE]
        return DEVICE_STATES[int(code)] if math.isfinite(code) else DeviceState.CONFIGURED

    def disable(self) -> None:
        """Ask the loop process to end: its loop disables the drive on the way out."""
        self._remote.request_end()


class RemoteLoop:
    """See the module docstring. Built by :func:`stagectl.daemon.loopproc.spawn_loop_process`."""

    def __init__(self, *, pid: int, conn: Connection, wake_fd: int, shm: LoopShm, info: dict[str, Any]) -> None:
        self.pid = pid
        self.conn = conn
        self.wake_fd = wake_fd
        self.shm = shm
        self.columns: tuple[str, ...] = tuple(info["columns"])
        self.period_s = float(info["period_s"])
        self.cfg: LoopConfig = info["cfg"]
        self.limits: MotionLimits = info["limits"]
        self.ring: SharedTelemetryRing | None = None  # the shared telemetry ring, when telemetry is on
        self.actuator = _DriveView(self)
        self.controller = None  # in the loop process
        self._stats = CycleStats(shm.layout.window, (shm.late, shm.exec, shm.skip))
        self._cmd_lock = threading.Lock()
        self._pending: dict[int, Reply] = {}
        self._next_id = 1
        self._blob_cmd = -1  # command index of the last request that carried a blob
        self._latch: tuple[str, str] | None = None
        self._sinks: tuple[TelemetrySink, ...] = ()
        self._ended = False
        self._exit_status: int | None = None
        self.result: LoopResult | None = None
        self.error: str | None = None
        self.replies_lost = 0
        # the learner's telemetry columns (ilc:), read from the last telemetry row the writer drained
        cols = self.columns
        self._ilc_cols = (tuple(cols.index(c) for c in ("u_ilc", "ilc_iteration", "ilc_rms_m"))
                          if "ilc_iteration" in cols else None)
        self._ilc_last: tuple[float, float, float] | None = None
        #: called (in the thread running :meth:`run`) when the published loop state or fault count changed
        self.on_state_change: Callable[[], None] | None = None
        self._seen_state: tuple[float, float] | None = None

    # ------------------------------------------------------------------ sinks (telemetry is shared memory)
    def add_sink(self, sink: TelemetrySink) -> None:
        """The shared ring is the loop process's own sink already. Any other sink (a live stream's tap) is fed
        here in the daemon, from the telemetry writer's taps (:meth:`feed_sinks`), row by row and in order;
        never in the loop process."""
        if sink is self.ring:
            return
        with self._cmd_lock:
            self._sinks = (*self._sinks, sink)

    def remove_sink(self, sink: TelemetrySink) -> None:
        with self._cmd_lock:
            self._sinks = tuple(s for s in self._sinks if s is not sink)

    def feed_sinks(self, first: int, rows: Any) -> None:
        """Writer tap: every drained block of telemetry rows to the daemon-side sinks (writer thread)."""
        ic = self._ilc_cols
        if ic is not None and len(rows):
            last = rows[-1]
            self._ilc_last = (float(last[ic[0]]), float(last[ic[1]]), float(last[ic[2]]))
        for sink in self._sinks:
            for row in rows:
                sink.append(row)

    def latch_fault(self, name: str, cause: str) -> FaultInfo:
        """Latched by the loop process before its loop starts (sent with the start message)."""
        self._latch = (name, cause)
        return SafetyFault(name, cause, 0.0, 0)

    # ------------------------------------------------------------------ status
    @property
    def state(self) -> LoopState:
        """The loop's state as last published (cheap: no statistics)."""
        code = self.shm.status[S_STATE]
        return LOOP_STATES[int(code)] if math.isfinite(code) else LoopState.CONFIGURED

    def _snapshot(self) -> tuple[list[float], str]:
        ctl, st = self.shm.ctl, self.shm.status
        vals: list[float] = []
        text = ""
        for _ in range(10000):
            s1 = int(ctl[STATUS_SEQ])
            if s1 & 1:
                continue
            vals = st.tolist()
            text = LoopShm.get_text(self.shm.fault_text) if vals[S_HAS_FAULT] == 1.0 else ""
            if int(ctl[STATUS_SEQ]) == s1:
                break
        else:  # the writer died mid-update (sequence left odd): its last values are all there is
            vals = st.tolist()
            text = LoopShm.get_text(self.shm.fault_text) if vals[S_HAS_FAULT] == 1.0 else ""
        return vals, text

    def status(self, timing: bool = True) -> LoopStatus:
        """The loop process's snapshot (see :meth:`stagectl.loop.ControlLoop.status`); never waits for it."""
        v, text = self._snapshot()
        code = v[S_STATE]
        state = LOOP_STATES[int(code)] if math.isfinite(code) else LoopState.CONFIGURED
        fault = None
        if v[S_HAS_FAULT] == 1.0:
            name, _, cause = text.partition("\n")
            fault = SafetyFault(name, cause, v[S_FAULT_T], int(v[S_FAULT_CYCLE]))
        cycle = int(v[S_CYCLE]) if math.isfinite(v[S_CYCLE]) else 0
        stats = self._stats
        stats.late_max = v[S_LATE_MAX] if math.isfinite(v[S_LATE_MAX]) else 0.0
        stats.exec_max = v[S_EXEC_MAX] if math.isfinite(v[S_EXEC_MAX]) else 0.0
        n = cycle + 1
        frac = stats.overrun_fraction(n)
        running = v[S_RUNNING] == 1.0
        x, x_ref = v[S_X], v[S_XREF]
        return LoopStatus(
            state=state, fault=fault, t_s=v[S_T], x_m=x, x_ref_m=x_ref, e_m=x_ref - x, u_n=v[S_U], cycle=cycle,
            overruns=int(v[S_OVERRUNS]), recent_overrun_fraction=frac, period_s=self.period_s, running=running,
            healthy=bool(running and state is LoopState.ACTIVE and frac <= self.cfg.healthy_overrun_fraction),
            lateness_us=stats.lateness(n) if timing else None, exec_us=stats.execution(n) if timing else None,
            faults=int(v[S_FAULTS]),
            ilc=self._ilc_status(),
        )

    def _ilc_status(self) -> dict[str, Any] | None:
        """The learner's iteration, RMS of its last repetition [m] and force [N] from the telemetry (the full state:
        the ``ilc`` request); None without a learner."""
        if self._ilc_cols is None:
            return None
        last = self._ilc_last
        if last is None:
            return {"iteration": None, "last_rms_m": None, "u_ilc_n": None}
        return {"iteration": int(last[1]), "last_rms_m": last[2], "u_ilc_n": last[0]}
    def check_state_change(self) -> bool:
        """Call ``on_state_change`` if the loop's state or fault count changed since the last look (the loop
        process wakes :meth:`run` when it publishes a change). Returns True if it changed."""
        st = self.shm.status
        now = (float(st[S_STATE]), float(st[S_FAULTS]))
        if now == self._seen_state:
            return False
        self._seen_state = now
        if self.on_state_change is not None:
            self.on_state_change()
        return True

    # ------------------------------------------------------------------ requests
    def submit(self, req: LoopRequest) -> Reply:
        """Queue ``req`` for the loop process (thread-safe). A move outside the limits is refused here."""
        blob = b""
        a = b = c = math.nan
        if isinstance(req, MoveRequest):
            req.check_limits(self.limits)
            a = req.target_m if req.target_m is not None else math.nan
            b = req.relative_m if req.relative_m is not None else math.nan
            c = req.max_velocity_m_s if req.max_velocity_m_s is not None else math.nan
        elif isinstance(req, RetuneRequest):
            blob = pickle.dumps(req.controller_config)
        elif isinstance(req, IlcRequest):
            blob = pickle.dumps((req.action, req.motion))
        return self._post(KIND_CODES[req.KIND], a, b, c, blob,
                          reserved=isinstance(req, (StopRequest, ResetRequest, ShutdownRequest)))

    def inject_fault(self, kind: str, **kw: Any) -> Reply:
        """Debug (simulated stage): inject a fault in the loop process at its next cycle boundary."""
        return self._post(KIND_CODES["fault"], math.nan, math.nan, math.nan, pickle.dumps((kind, kw)),
                          reserved=False)

    def _post(self, kind: int, a: float, b: float, c: float, blob: bytes, reserved: bool) -> Reply:
        if len(blob) > BLOB_BYTES:
            raise RequestError("request", f"{len(blob)} bytes of arguments, more than {BLOB_BYTES}")
        if self._ended:
            raise LoopStateError("the control loop is not running")
        fut: Reply = concurrent.futures.Future()
        ctl, cmd = self.shm.ctl, self.shm.cmd
        with self._cmd_lock:
            head = int(ctl[CMD_HEAD])
            queued = head - int(ctl[CMD_TAIL])
            if queued >= CMD_SLOTS - (0 if reserved else RESERVED_SLOTS):
                raise RequestError("request", f"loop busy: {queued} requests queued; try again")
            if blob:
                if int(ctl[CMD_TAIL]) <= self._blob_cmd:
                    raise RequestError("request", "loop busy: the previous retune/fault request is not taken yet")
                self.shm.blob[: len(blob)] = memoryview(blob)
                self._blob_cmd = head
            rid = self._next_id
            self._next_id += 1
            self._pending[rid] = fut
            cmd[head % CMD_SLOTS] = (rid, kind, a, b, c, len(blob))
            ctl[CMD_HEAD] = head + 1  # publish after the record
        return fut

    def collect_replies(self) -> None:
        """Resolve the futures of the replies the loop process has posted (monitor thread)."""
        ctl, rep = self.shm.ctl, self.shm.rep
        tail = int(ctl[REP_TAIL])
        head = int(ctl[REP_HEAD])
        while tail < head:
            slot = tail % REP_SLOTS
            rid = int(rep[slot, 0])
            ok = rep[slot, 1] == 1.0
            text = LoopShm.get_text(self.shm.rep_text[slot])
            tail += 1
            ctl[REP_TAIL] = tail
            with self._cmd_lock:
                fut = self._pending.pop(rid, None)
            if fut is None or fut.done():
                continue
            try:
                payload = json.loads(text)
            except ValueError:
                payload = {"error": f"unreadable reply from the loop process: {text[:200]!r}"}
            try:
                if ok and isinstance(payload, dict):
                    fut.set_result(payload)
                else:
                    fut.set_exception(reply_error(payload if isinstance(payload, dict) else {}))
            except concurrent.futures.InvalidStateError:  # cancelled meanwhile (reply timeout)
                pass

    def _fail_pending(self, why: str) -> None:
        with self._cmd_lock:
            pending, self._pending = self._pending, {}
        for fut in pending.values():
            if not fut.done():
                try:
                    fut.set_exception(LoopStateError(why))
                except concurrent.futures.InvalidStateError:
                    pass

    # ------------------------------------------------------------------ run / end
    def request_end(self) -> None:
        """Ask the loop process to end its loop (drive disabled on the way out). Safe from any thread."""
        self.shm.ctl[STOP_REQ] = 1

    @property
    def ended(self) -> bool:
        return self._ended

    def run(self, *, cycles: int | None = None, duration_s: float | None = None,
            stop: threading.Event | None = None) -> LoopResult:
        """Start the loop process's loop and supervise it until it ends (LoopHost's thread). ``cycles`` and
        ``duration_s`` are not supported across the process boundary (the daemon runs until stopped)."""
        if cycles is not None or duration_s is not None:
            raise StageError("run: a loop process runs until stopped (cycles/duration_s not supported)")
        self.conn.send({"go": True, "latch": self._latch})
        stop_sent = False
        try:
            while True:
                if stop is not None and stop.is_set() and not stop_sent:
                    self.request_end()
                    stop_sent = True
                try:
                    ready, _, _ = select.select([self.wake_fd, self.conn.fileno()], [], [], 0.05)
                except InterruptedError:
                    ready = []
                if self.wake_fd in ready:
                    try:
                        os.read(self.wake_fd, 4096)
                    except BlockingIOError:
                        pass
                self.collect_replies()
                self.check_state_change()
                if self.conn.fileno() in ready or self._child_exited():
                    self._finish()
                    break
        finally:
            self._ended = True
            self.collect_replies()
            self._fail_pending("the control loop is not running")
        if self.result is None:
            raise StageError(f"loop process: {self.error or 'ended without a result'}")
        return self.result

    def _child_exited(self) -> bool:
        if self._exit_status is not None:
            return True
        try:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
        except ChildProcessError:
            self._exit_status = -1
            return True
        if pid == 0:
            return False
        self._exit_status = status
        return True

    def _finish(self) -> None:
        """Read the loop process's final message (result or error), then reap it."""
        try:
            if self.conn.poll(2.0):
                msg = self.conn.recv()
                if isinstance(msg, dict):
                    self.result = msg.get("result")
                    self.error = msg.get("error")
        except (EOFError, OSError, pickle.UnpicklingError) as exc:
            self.error = self.error or f"lost contact ({type(exc).__name__})"
        if self.result is None and self.error is None:
            self.error = "the loop process ended unexpectedly"
            if self._exit_status is not None and os.WIFSIGNALED(self._exit_status):
                self.error += f" (signal {signal.Signals(os.WTERMSIG(self._exit_status)).name})"
        self.reap(5.0)

    def reap(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for the loop process to exit; True once it has."""
        end = time.monotonic() + timeout_s
        while not self._child_exited():
            if time.monotonic() >= end:
                return False
            time.sleep(0.01)
        return True

    def close(self, timeout_s: float = 5.0) -> None:
        """End the loop process (ask, then SIGKILL after ``timeout_s``), reap it, release the block."""
        if not self._child_exited():
            self.request_end()
            try:
                self.conn.send({"go": False, "latch": None})  # still waiting for its start message
            except (OSError, ValueError):
                pass
            if not self.reap(timeout_s):
                log.error("loop process %d did not end within %.1f s; killing it", self.pid, timeout_s)
                try:
                    os.kill(self.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                self.reap(5.0)
        self._ended = True
        self._fail_pending("the control loop is not running")
        for closer in (self.conn.close, lambda: os.close(self.wake_fd)):
            try:
                closer()
            except OSError:
                pass
        self.shm.unlink()
        self.shm.close()


#: what the service drives: a loop in this process or in its own
LoopLike = ControlLoop | RemoteLoop
