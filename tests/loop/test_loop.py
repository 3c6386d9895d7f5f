"""ControlLoop scheduling, telemetry, requests and teardown in simulated time (no wall-clock sleeps)."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from stagectl.clock import SimClock
from stagectl.drivers.base import DeviceState, FaultKind
from stagectl.errors import StageError
from stagectl.loop import BASE_COLUMNS, FLAG_COLUMNS, LoopState, LoopStateError
from stagectl.runtime.requests import MoveRequest, ResetRequest, RetuneRequest, ShutdownRequest, StopRequest, parse_request


def test_absolute_deadlines_and_columns(rig):
    loop, io, plant, ctl, clock, sink = rig
    res = loop.run(cycles=250)
    assert res.cycles == 250 and res.overruns == 0 and res.ended_by == "cycles"
    t = np.array([r[0] for r in sink.rows])
    assert len(t) == 250
    np.testing.assert_allclose(t, np.arange(250) * 1e-3, rtol=0, atol=1e-12)  # t_k = k·T exactly
    assert loop.columns == BASE_COLUMNS + ("u_pid", "u_inertia") + FLAG_COLUMNS
    assert all(len(r) == len(loop.columns) for r in sink.rows)
    assert io.n_sync == 252  # a warm-up SYNC before enabling, one priming SYNC at start, one per cycle
    assert io.state is DeviceState.CONFIGURED  # disabled on the way out
    assert loop.status().state is LoopState.CONFIGURED


def test_duration_runs_exact_cycle_count(rig):
    loop, *_ = rig
    res = loop.run(duration_s=0.5)
    assert res.cycles == 500 and res.ended_by == "duration"


class StallingClock(SimClock):
    """Simulated time where chosen cycles take longer than a period (an overrun)."""

    def __init__(self, stalls: dict[int, float]):
        super().__init__()
        self.stalls = stalls
        self.k = 0

    def on_cycle(self) -> None:
        self.t_s += self.stalls.get(self.k, 0.0)
        self.k += 1


def test_overruns_are_counted_and_skipped_not_caught_up(make, rows):
    loop, io, plant, ctl, _ = make()
    clock = StallingClock({10: 3.5e-3, 50: 1.6e-3})
    loop.clock = clock
    loop.on_cycle = clock.on_cycle
    loop.add_sink(rows)
    res = loop.run(cycles=100)
    t = np.array([r[0] for r in rows.rows]) * 1e3  # ms
    # cycle 10 starts at 10 ms and ends at 13.5 ms: slots 11 and 12 are skipped (counted), slot 13 runs
    # 0.5 ms late, then the loop is back on the grid at 14 ms: one late cycle, no catch-up burst
    assert res.overruns == 2
    assert t[11] == pytest.approx(13.5, abs=1e-9) and t[12] == pytest.approx(14.0, abs=1e-9)
    assert np.sum(np.diff(t) < 1.0 - 1e-9) == 2  # only the two late cycles are closer than T to the next
    grid = t[12:] - np.round(t[12:])
    assert np.count_nonzero(np.abs(grid) > 1e-9) == 1  # every other cycle sits on its deadline
    # cycle 50 (slot 52) ends at 53.6 ms: 0.6 ms late, within one period -> not an overrun
    assert t[51] == pytest.approx(53.6, abs=1e-9)
    st = loop.status()
    assert st.lateness_us.max == pytest.approx(600.0, rel=1e-6)
    assert st.overruns == 2
    light = loop.status(timing=False)  # the supervisor's cheap form: same counters, no percentiles
    assert light.lateness_us is None and light.exec_us is None
    keys = ("cycle", "overruns", "recent_overrun_fraction", "healthy", "state")
    assert {k: getattr(light, k) for k in keys} == {k: getattr(st, k) for k in keys}


def test_move_request_tracks_and_reports(rig):
    loop, io, plant, ctl, clock, sink = rig
    fut = loop.submit(MoveRequest(target_m=50e-6, max_velocity_m_s=1e-3))
    res = loop.run(cycles=200)
    assert fut.result(timeout=0)["target_m"] == 50e-6
    assert fut.result()["duration_s"] == pytest.approx(0.05, rel=1e-6)
    assert res.fault is None
    st = loop.status()
    assert abs(st.x_m - 50e-6) < 1e-6
    e = np.array([r[loop.columns.index("e")] for r in sink.rows])
    assert np.max(np.abs(e)) < 5e-6


def test_request_validation_names_the_field(rig):
    loop = rig[0]
    with pytest.raises(ValueError, match="target_m.*soft limits"):
        loop.submit(MoveRequest(target_m=0.5))
    with pytest.raises(ValueError, match="max_velocity_m_s"):
        loop.submit(MoveRequest(target_m=1e-6, max_velocity_m_s=10.0))
    with pytest.raises(ValueError, match="relative_m"):
        loop.submit(MoveRequest(relative_m=math.nan))
    with pytest.raises(ValueError, match="unknown request 'jump'"):
        parse_request("jump", {"request": "jump"})
    with pytest.raises(ValueError, match="speed"):
        MoveRequest.from_fields({"target_m": 0.0, "speed": 1})
    with pytest.raises(ValueError, match="exactly one"):
        loop.submit(MoveRequest(target_m=0.0, relative_m=0.0))
    # relative target only known in the loop: rejected on the future
    fut = loop.submit(MoveRequest(relative_m=0.02))
    loop.run(cycles=3)
    with pytest.raises(ValueError, match="relative_m.*soft limits"):
        fut.result(timeout=0)


def test_shutdown_stop_and_pending_futures(rig):
    loop, io, plant, ctl, clock, sink = rig
    f_move = loop.submit(MoveRequest(relative_m=1e-3))
    f_stop = loop.submit(StopRequest())
    f_shut = loop.submit(ShutdownRequest())
    res = loop.run(cycles=1000)
    assert res.ended_by == "shutdown" and res.cycles == 1
    assert "x_m" in f_stop.result(timeout=0)
    assert f_move.done() and f_shut.result(timeout=0) == {"cycles": 0}
    late = loop.submit(StopRequest())  # queued after run: fails when the next run ends without serving it?
    loop.run(cycles=1)
    assert late.result(timeout=0)["x_m"] == pytest.approx(loop.status().x_ref_m)


def test_retune_applied_at_cycle_boundary_and_bad_tuning_rejected(rig):
    loop, io, plant, ctl, clock, sink = rig
    good = loop.submit(RetuneRequest(controller_config={"kp": 1e4}))
    bad = loop.submit(RetuneRequest(controller_config={"kp": -1.0}))
    loop.run(cycles=2)
    assert good.result(timeout=0) == {"retuned": True} and ctl.kp == 1e4
    with pytest.raises(ValueError, match="kp"):
        bad.result(timeout=0)
    assert loop.status().state is LoopState.CONFIGURED and loop.status().fault is None


def test_failing_sink_is_removed_and_loop_continues(rig):
    loop, io, plant, ctl, clock, sink = rig

    class Broken:
        def append(self, row):
            raise OSError("disk full")

    loop.add_sink(Broken())
    res = loop.run(cycles=20)
    assert res.cycles == 20 and res.fault is None and len(sink.rows) == 20


def test_status_from_another_thread_while_running(rig):
    loop, io, plant, ctl, clock, sink = rig
    stop = threading.Event()
    result = {}
    submitted: list = []
    after = [0]  # cycles ended since the move was served
    one_more = threading.Event()

    def on_cycle():  # the loop's per-cycle hook, called once the cycle's status snapshot is taken
        if submitted and submitted[0].done():
            after[0] += 1
            if after[0] == 2:  # the cycle that served the move, and the next one, have ended
                one_more.set()

    loop.on_cycle = on_cycle
    th = threading.Thread(target=lambda: result.setdefault("r", loop.run(stop=stop)))
    th.start()
    try:
        fut = loop.submit(MoveRequest(target_m=1e-6))
        submitted.append(fut)
        fut.result(timeout=30)  # served at a cycle boundary in the loop thread
        # the future completes inside the serving cycle: a status read now may still show the cycle before it;
        # wait (on the loop's own hook, not the clock) until a later cycle has ended
        assert one_more.wait(timeout=30)
        st = loop.status()
        assert st.running and st.healthy and st.state is LoopState.ACTIVE
        assert st.cycle >= 1
    finally:
        stop.set()
        th.join(timeout=30)
    assert result["r"].ended_by == "stop"
    assert not loop.status().running and not loop.status().healthy


def test_run_disables_drive_even_when_start_fails(make):
    loop, io, plant, ctl, clock = make(startup_cycles=3)
    io.drop_samples(10)  # no position within the start-up grace
    with pytest.raises(StageError, match="no position from plant_io within loop.startup_cycles 3"):
        loop.run(cycles=5)
    assert io.state is DeviceState.CONFIGURED


def test_requests_pending_when_run_ends_fail(make):
    loop, io, plant, ctl, clock = make()
    fut = loop.submit(MoveRequest(target_m=1e-6))
    stop = threading.Event()
    stop.set()  # the run ends before its first cycle boundary: the request is never served
    res = loop.run(stop=stop)
    assert res.cycles == 0 and res.ended_by == "stop"
    with pytest.raises(LoopStateError, match="not running"):
        fut.result(timeout=0)


def test_monotonic_clock_uses_absolute_sleep_and_never_sleeps_for_past_deadlines():
    from stagectl.clock import MonotonicClock, apply_realtime

    clk = MonotonicClock()
    assert clk.absolute  # clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME) found through ctypes
    t = clk.now()
    clk.sleep_until(t - 1.0)  # a deadline in the past returns at once (an overrun is the loop's business)
    assert clk.now() >= t
    rep = apply_realtime(fifo_priority=None, cpus=None, mlock=False, timer_slack_ns=None, gc_freeze=False)
    assert rep.notes == [] and rep.fifo_priority is None  # nothing requested, nothing changed, never raises


def test_device_time_mode_skips_slots_without_desynchronising(make, rows):
    """Virtual devices stepping one period per SYNC: loop time = executed cycles × T, dt = T."""
    loop, io, plant, ctl, _ = make()
    clock = StallingClock({10: 3.5e-3})
    loop.clock, loop.on_cycle, loop.device_time = clock, clock.on_cycle, True
    loop.add_sink(rows)
    res = loop.run(cycles=50)
    t = np.array([r[0] for r in rows.rows])
    assert res.overruns == 2  # still counted (wall-clock lateness)
    np.testing.assert_allclose(t, np.arange(50) * 1e-3, atol=1e-12)  # but the simulation just slowed down


def test_start_waits_for_a_late_first_sample_then_stale_checks_apply(make, rows):
    """Start-up grace: stale samples before the first fresh one are waited for (loop.startup_cycles);
    afterwards the steady-state stale-position check (stale_cycles = 3) is unchanged."""
    loop, io, plant, ctl, clock = make(startup_cycles=50)
    loop.add_sink(rows)
    io.drop_samples(20)  # the first 20 SYNCs bring no fresh position (e.g. a late first TPDO under load)
    calls = []

    def on_cycle():
        calls.append(1)
        if len(calls) == 10:
            io.drop_samples(3)  # in steady state, 3 stale cycles still latch the fault

    loop.on_cycle = on_cycle
    res = loop.run(cycles=20)
    assert ctl.resets == [0.0] and rows.rows[0][0] == 0.0  # loop time starts at the first fresh sample
    assert res.fault is not None and res.fault.name == "stale_position" and res.fault.cycle == 12


def test_start_gives_up_after_startup_cycles(make):
    loop, io, plant, ctl, clock = make(startup_cycles=5)
    io.drop_samples(10)
    with pytest.raises(StageError, match="startup_cycles 5"):
        loop.run(cycles=3)
    assert io.state is DeviceState.CONFIGURED and clock.now() == pytest.approx(4e-3)


def test_realtime_settings_are_applied_in_the_loop_thread(make):
    """FIFO, affinity, mlockall, timer slack and gc.freeze are applied in the thread that runs the loop,
    each either applied or explained in a note (never an exception)."""
    import dataclasses
    import gc
    import os

    from stagectl.loop import RealtimeConfig

    loop, io, plant, ctl, clock = make()
    cpu = min(os.sched_getaffinity(0))
    rt = RealtimeConfig(fifo_priority=10, cpus=(cpu,), mlock=True, timer_slack_ns=1, gc_freeze=True)
    loop.cfg = dataclasses.replace(loop.cfg, realtime=rt)
    loop.realtime = True
    box = {}

    def target():
        box["res"] = loop.run(cycles=5)
        box["affinity"] = os.sched_getaffinity(0)
        box["policy"] = os.sched_getscheduler(0)

    try:
        th = threading.Thread(target=target)
        th.start()
        th.join(timeout=60)
    finally:
        gc.unfreeze()
        import ctypes
        import ctypes.util

        ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").munlockall()  # undo MCL_FUTURE for this worker
    rep = box["res"].realtime
    assert rep["gc_frozen"] is True and rep["timer_slack_ns"] == 1
    assert rep["cpus"] == [cpu] and box["affinity"] == {cpu}
    assert os.sched_getaffinity(0) != {cpu} or os.cpu_count() == 1  # only the loop thread was pinned
    if rep["fifo_priority"] == 10:
        assert box["policy"] == os.SCHED_FIFO
    else:
        assert any("SCHED_FIFO" in n for n in rep["notes"])
    assert rep["mlocked"] or any("mlockall" in n for n in rep["notes"])


def test_stale_rows_say_so_and_record_the_held_terms(make, rows):
    """A stale sample below the stale limit holds the force; its row has ``stale`` = 1 and the held
    controller terms (not zeros, which drew false chatter), so ``u`` = Σ terms on every row."""
    loop, io, plant, ctl, clock = make()
    loop.add_sink(rows)
    loop.submit(MoveRequest(target_m=1e-4))
    calls = []

    def on_cycle():
        calls.append(1)
        if len(calls) == 30:
            io.drop_samples(2)  # below stale_cycles: held, no fault

    loop.on_cycle = on_cycle
    res = loop.run(cycles=60)
    assert res.fault is None
    cols = loop.columns
    data = np.array(rows.rows)
    stale = data[:, cols.index("stale")]
    assert stale.sum() == 2 and set(np.flatnonzero(stale)) == {30, 31}
    for name in ("u_pid", "u_inertia"):
        col = data[:, cols.index(name)]
        assert col[30] == col[29] == col[31]  # held
    assert data[29, cols.index("u_pid")] != 0.0  # (so "held" is not "zeroed")
    np.testing.assert_allclose(data[:, cols.index("u")], data[:, cols.index("u_pid")] + data[:, cols.index("u_inertia")],
                               rtol=0, atol=1e-9)
    assert np.all(data[:, cols.index("skipped")] == 0)  # simulated time: nothing skipped


def test_fault_counter_sees_a_fault_already_cleared_by_reset(make):
    """``status().faults`` counts faults entered, so a supervisor that looks only after the reset still sees one."""
    loop, io, plant, ctl, clock = make()
    seen = []

    def on_cycle():
        seen.append(1)
        if len(seen) == 5:
            io.inject_fault(FaultKind.EMCY, detail="test")
        if len(seen) == 8:
            loop.submit(ResetRequest())

    loop.on_cycle = on_cycle
    loop.run(cycles=20)
    st = loop.status()
    assert st.faults == 1 and st.fault is None


def test_on_state_change_runs_in_the_fault_cycle_and_the_reset_cycle(make):
    from stagectl.drivers.base import FaultKind
    from stagectl.runtime.requests import ResetRequest

    loop, io, plant, ctl, clock = make()
    seen: list[tuple[int, str]] = []
    loop.on_state_change = lambda: seen.append((loop.cycle, loop.state.value))
    loop.on_cycle = lambda: loop.cycle == 10 and io.inject_fault(FaultKind.EMCY, "x")
    loop.run(cycles=20)
    assert seen == [(11, "fault")]  # the cycle that latched it (cycle counter not yet advanced)
    loop.on_cycle = None
    fut = loop.submit(ResetRequest())
    loop.run(cycles=3)
    assert fut.result(timeout=0)["state"] == "active"
    assert seen == [(11, "fault"), (20, "active")]
