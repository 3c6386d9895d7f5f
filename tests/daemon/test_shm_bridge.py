"""The shared-memory protocol between the loop process and the daemon, exercised in one process on simulated
time: the loop side (Bridge as the loop's per-cycle hook) and the daemon side (RemoteLoop) on one real block.

The oracle is the loop itself: what RemoteLoop reports must equal what the ControlLoop reports, and a request
sent through the rings must have the effect and the reply it has when submitted directly.
"""

from __future__ import annotations

import math
import os
import threading
from multiprocessing import Pipe

import numpy as np
import pytest
from stagectl.drivers.base import FaultKind
from stagectl.sim.direct import PlantIO
from support import RampReference

from stagectl.clock import SimClock
from stagectl.control.api import Command
from stagectl.daemon.lifecycle import Assembly
from stagectl.daemon.loopproc import Bridge
from stagectl.daemon.remote import RESERVED_SLOTS, RemoteLoop
from stagectl.daemon.telemetry import SharedTelemetryRing
from stagectl.loop import ControlLoop, LoopConfig
from stagectl.runtime.requests import MoveRequest, RequestError, ResetRequest, StopRequest
from stagectl.runtime.shm import CMD_SLOTS, LoopShm, ShmLayout
from stagectl.runtime.stats import CycleStats
from stagectl.runtime.status import LoopState, LoopStateError
from stagectl.safety import Safety, SafetyConfig


class MassPlant:
    """m·a = u − c·v (semi-implicit Euler), 1 nm resolution."""

    resolution_m = 1e-9

    def __init__(self) -> None:
        self.x_m = self.v_m_s = 0.0

    def step(self, u_n: float, dt_s: float) -> None:
        for _ in range(10):
            self.v_m_s += (u_n - 5.0 * self.v_m_s) * dt_s / 10
            self.x_m += self.v_m_s * dt_s / 10

    def measure(self) -> float:
        return round(self.x_m / 1e-9) * 1e-9

    def measure_counts(self) -> int:
        return round(self.x_m / 1e-9)


class PD:
    term_names = ("u_pid",)

    def __init__(self) -> None:
        self.x_prev = 0.0

    def reset(self, x_m: float) -> None:
        self.x_prev = x_m

    def retune(self, cfg) -> None:
        pass

    def step(self, dt, x, ref) -> Command:
        v, self.x_prev = (x - self.x_prev) / dt, x
        u = 4e4 * (ref.x_m - x) + 400.0 * (ref.v_m_s - v)
        return Command(u, {"u_pid": u})


@pytest.fixture
def pair():
    period = 1e-3
    io = PlantIO(MassPlant(), period, delay_cycles=1)
    io.open()
    io.configure()
    safety = Safety(SafetyConfig(min_position_m=-0.01, max_position_m=0.01, following_error_m=1e-3,
                                 max_force_n=50.0, max_velocity_m_s=0.05, stale_cycles=3), period)
    loop = ControlLoop(clock=SimClock(), sensor=io, actuator=io, controller=PD(),
                       reference=RampReference(v_default=2e-3), safety=safety,
                       cfg=LoopConfig(period_s=period, stats_window=256))

    def inject(kind, **kw):
        io.inject_fault(FaultKind(kind), detail="through the rings")
        return {}

    asm = Assembly(loop=loop, close=io.close, simulated=True, inject_fault=inject)
    shm = LoopShm.create(ShmLayout(len(loop.columns), 1024, 256))
    loop.stats = CycleStats(256, (shm.late, shm.exec, shm.skip))
    ring = SharedTelemetryRing(loop.columns, shm.tel, shm.ctl)
    loop.add_sink(ring)
    wake_r, wake_w = os.pipe2(os.O_NONBLOCK)
    bridge = Bridge(loop, asm, shm, wake_w, threading.Event())
    loop.on_cycle = bridge.on_cycle
    conn, _ = Pipe()
    remote = RemoteLoop(pid=os.getpid(), conn=conn, wake_fd=wake_r,
                        shm=LoopShm.attach(shm.name, shm.layout),
                        info={"columns": loop.columns, "period_s": period, "cfg": loop.cfg, "limits": loop.limits})
    remote.ring = SharedTelemetryRing(loop.columns, remote.shm.tel, remote.shm.ctl)
    shm.unlink()
    yield loop, remote, bridge, io
    os.close(wake_w)
    os.close(wake_r)
    conn.close()


def test_status_through_the_block_equals_the_loops_own(pair):
    loop, remote, bridge, _ = pair
    loop.run(cycles=300)
    bridge.publish(running=False)
    mine, theirs = loop.status(), remote.status()
    for f in ("state", "fault", "t_s", "x_m", "x_ref_m", "u_n", "cycle", "overruns", "faults", "running",
              "recent_overrun_fraction"):
        assert getattr(theirs, f) == getattr(mine, f), f
    assert theirs.lateness_us == mine.lateness_us and theirs.exec_us == mine.exec_us  # percentiles, daemon-side
    first, rows = remote.ring.drain()
    assert first == 0 and len(rows) == 300
    np.testing.assert_allclose(rows[:, 0], np.arange(300) * 1e-3, rtol=0, atol=1e-12)


def test_requests_and_replies_go_through_the_rings(pair):
    loop, remote, _, _ = pair
    move = remote.submit(MoveRequest(target_m=2e-4))
    with pytest.raises(RequestError) as err:  # limits are checked daemon-side, before the ring
        remote.submit(MoveRequest(target_m=1.0))
    assert err.value.field == "target_m"
    loop.run(cycles=5)
    remote.collect_replies()
    assert move.result(0) == {"target_m": 2e-4, "duration_s": pytest.approx(0.1)}
    fault = remote.inject_fault("emcy")
    loop.run(cycles=3)
    remote.collect_replies()
    assert fault.result(0)["injected"] == "emcy"
    refused = remote.submit(MoveRequest(relative_m=1e-5))
    loop.run(cycles=2)
    remote.collect_replies()
    with pytest.raises(LoopStateError, match="fault"):
        refused.result(0)
    st = remote.status()
    assert st.state is LoopState.FAULT and st.fault.name == "emcy" and st.faults == 1
    reset = remote.submit(ResetRequest())
    loop.run(cycles=2)
    remote.collect_replies()
    assert reset.result(0)["cleared"]["name"] == "emcy"
    assert remote.status().state is LoopState.ACTIVE  # published before the reply was posted


def test_a_flood_of_moves_leaves_room_for_stop(pair):
    loop, remote, _, _ = pair
    moves = []
    with pytest.raises(RequestError, match="busy"):
        for _ in range(CMD_SLOTS):
            moves.append(remote.submit(MoveRequest(relative_m=1e-7)))
    assert len(moves) == CMD_SLOTS - RESERVED_SLOTS
    stops = [remote.submit(StopRequest()) for _ in range(RESERVED_SLOTS)]  # still accepted
    loop.run(cycles=3)
    remote.collect_replies()
    assert all("x_m" in s.result(0) for s in stops)
    assert all("target_m" in m.result(0) for m in moves)
    assert math.isfinite(remote.status().x_ref_m)


def test_shared_telemetry_ring_counts_what_it_cannot_hold():
    shm = LoopShm.create(ShmLayout(2, 4, 16))
    shm.unlink()
    ring = SharedTelemetryRing(("t", "x"), shm.tel, shm.ctl)
    for k in range(6):
        ring.append((k, 10.0 * k))
    assert ring.dropped == 2 and ring.backlog == 4
    first, rows = ring.drain(3)
    assert first == 0 and rows[:, 0].tolist() == [0, 1, 2]
    for k in range(6, 9):  # wraps around the end of the buffer
        ring.append((k, 10.0 * k))
    assert ring.dropped == 2  # room again after the drain: nothing more dropped
    first, rows = ring.drain()
    assert first == 3 and rows[:, 0].tolist() == [3, 6, 7, 8]
    ring.append((1.0, 2.0, 3.0))  # wrong width: counted, not stored
    assert ring.bad_rows == 1 and ring.backlog == 0


def test_a_state_change_wakes_the_daemon_side_once_published(pair):
    """A fault and a reset each write a wake-up after the cycle's status is published, and the daemon side sees
    the new state when it looks (the service's supervisor is woken instead of waiting for its tick)."""
    loop, remote, _, io = pair
    calls: list[LoopState] = []
    remote.on_state_change = lambda: calls.append(remote.state)
    loop.run(cycles=5)
    remote.check_state_change()  # the first look records the state
    calls.clear()

    def drain() -> bytes:
        try:
            return os.read(remote.wake_fd, 4096)
        except BlockingIOError:
            return b""

    drain()
    loop.run(cycles=5)
    assert drain() == b"" and not remote.check_state_change()  # nothing changed: no wake-up, no call
    io.inject_fault(FaultKind.EMCY, "wake test")
    loop.run(cycles=2)
    assert b"s" in drain()
    assert remote.check_state_change() and calls == [LoopState.FAULT]
    reset = remote.submit(ResetRequest())
    loop.run(cycles=2)
    assert b"s" in drain()
    remote.collect_replies()
    assert reset.result(0)["state"] == "active"
    assert remote.check_state_change() and calls == [LoopState.FAULT, LoopState.ACTIVE]


def test_sigterm_inside_the_loop_threads_own_stop_set_does_not_deadlock(pair, monkeypatch):
    """The daemon's stop request makes the loop thread set ``stop`` (Bridge.on_cycle); a SIGTERM arriving right
    then runs its handler in that same thread (Python runs handlers in the main thread: the loop process's loop
    thread) while ``threading.Event.set`` holds the event's lock. The handler must not take it again: it would
    wait for its own thread for ever (before: ``lambda s, f: stop.set()``)."""
    import signal

    from stagectl.daemon import loopproc

    loop, remote, bridge, _ = pair
    monkeypatch.setattr(loopproc._Ending, "armed", True)  # no backstop (faulthandler exit) in the test process
    handled = []

    class SignalInsideSet(threading.Event):
        def set(self):
            with self._cond:  # where threading.Event.set holds its lock
                handler(signal.SIGTERM, None)  # a SIGTERM delivered now runs its handler here
                handled.append(True)
            super().set()

    stop = SignalInsideSet()
    handler = loopproc._on_sigterm(stop)
    bridge.stop = stop
    remote.request_end()
    result = {}
    th = threading.Thread(target=lambda: result.setdefault("r", loop.run(stop=stop)), daemon=True)
    th.start()
    th.join(30)  # failure guard: a handler waiting for the lock never returns
    assert not th.is_alive() and handled == [True] and result["r"].ended_by == "stop"
    # outside any set(), the handler sets the event itself
    other = threading.Event()
    loopproc._on_sigterm(other)(signal.SIGTERM, None)
    assert other.is_set()
