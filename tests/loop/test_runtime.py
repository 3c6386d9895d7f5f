"""The runtime layer's mechanisms: typed requests (validated once), the typed status, the loop host, the
recording CSV writer. Simulated time only."""

from __future__ import annotations

import math
import re
import threading

import numpy as np
import pytest

from stagectl.errors import StageError
from stagectl.loop import LoopState
from stagectl.outputs import plain
from stagectl.ident.recording import RecordingCsv
from stagectl.recorder import Recorder
from stagectl.runtime.host import LoopHost
from stagectl.runtime.requests import (
    MotionLimits,
    MoveRequest,
    RequestError,
    ResetRequest,
    RetuneRequest,
    StopRequest,
    parse_request,
)


# ------------------------------------------------------------------------------------------------ requests
@pytest.mark.parametrize(("kw", "field", "text"), [
    ({"target_m": math.nan}, "target_m", "finite (m)"),
    ({"relative_m": math.inf}, "relative_m", "finite (m)"),
    ({"target_m": "1e-3"}, "target_m", "number in m"),
    ({"target_m": True}, "target_m", "number in m"),
    ({"target_m": 10**400}, "target_m", "too large"),
    ({"target_m": 0.0, "relative_m": 0.0}, "target_m", "exactly one"),
    ({}, "target_m", "exactly one"),
    ({"target_m": 0.0, "max_velocity_m_s": 0.0}, "max_velocity_m_s", "> 0 m/s"),
    ({"target_m": 0.0, "max_velocity_m_s": [1]}, "max_velocity_m_s", "number in m/s"),
])
def test_move_request_is_validated_on_construction_naming_field_and_unit(kw, field, text):
    with pytest.raises(RequestError, match=re.escape(text)) as ei:
        MoveRequest.from_fields(kw)
    assert ei.value.field == field and str(ei.value).startswith(f"{field}: ")
    assert isinstance(ei.value, ValueError) and isinstance(ei.value, StageError)  # caught either way


def test_direct_construction_validates_too_and_requests_are_frozen():
    with pytest.raises(RequestError, match="relative_m"):
        MoveRequest(relative_m=math.nan)
    dut = MoveRequest(target_m=1, max_velocity_m_s=2)
    assert dut.target_m == 1.0 and isinstance(dut.target_m, float)
    with pytest.raises(AttributeError):
        dut.target_m = 2.0  # type: ignore[misc]
    with pytest.raises(RequestError, match="controller_config: required"):
        RetuneRequest(None)


def test_limits_are_checked_by_the_request_against_the_stage():
    lim = MotionLimits(-0.01, 0.01, 0.05)
    MoveRequest(target_m=0.01, max_velocity_m_s=0.05).check_limits(lim)
    with pytest.raises(RequestError, match=r"target_m: 0.02 m outside soft limits \[-0.01, 0.01\] m"):
        MoveRequest(target_m=0.02).check_limits(lim)
    with pytest.raises(RequestError, match=r"max_velocity_m_s: must be > 0 and <= 0.05 m/s"):
        MoveRequest(relative_m=0.0, max_velocity_m_s=0.06).check_limits(lim)
    MoveRequest(relative_m=0.5).check_limits(lim)  # relative: only the loop knows where it ends
    assert lim.check_relative(0.004, 0.006) == pytest.approx(0.01)
    with pytest.raises(RequestError, match=r"relative_m: 0.007 m from the current target 0.004 m ends at 0.011 m, "
                                           r"outside soft limits \[-0.01, 0.01\] m"):
        lim.check_relative(0.004, 0.007)  # the distance the user gave, not only where it ends


def test_move_errors_name_the_users_option():
    from stagectl.commands.clients import move_error_for_user

    assert move_error_for_user("relative_m: 1 m from ...") == "move --by: 1 m from ..."
    assert move_error_for_user("target_m: 5 m outside") == "move --to: 5 m outside"
    assert move_error_for_user("max_velocity_m_s: must be > 0") == "move --max-velocity: must be > 0"
    assert move_error_for_user("move: loop is fault; reset first") == "move: loop is fault; reset first"


def test_socket_parsing_and_the_typed_form_build_the_same_requests():
    line = {"request": "move", "id": 7, "relative_m": -1e-4, "max_velocity_m_s": 2e-3}
    dut = parse_request("move", line)
    assert dut == MoveRequest(relative_m=-1e-4, max_velocity_m_s=2e-3)
    assert dut == MoveRequest.from_fields({"relative_m": -1e-4, "max_velocity_m_s": 2e-3})
    assert dut.to_json() == {"request": "move", "relative_m": -1e-4, "max_velocity_m_s": 2e-3}
    assert parse_request("stop", {"request": "stop"}) == StopRequest()
    assert parse_request("reset", {"request": "reset", "id": "x"}) == ResetRequest()
    with pytest.raises(RequestError) as ei:
        parse_request("move", {"request": "move", "target_m": 0.0, "speed": 1})
    assert ei.value.field == "speed" and "allowed: max_velocity_m_s, relative_m, target_m" in str(ei.value)
    with pytest.raises(RequestError) as ei:
        parse_request("stop", {"request": "stop", "now": True})
    assert ei.value.field == "now" and "allowed: none" in str(ei.value)
    with pytest.raises(RequestError) as ei:
        parse_request("shutdown", {"request": "shutdown"})  # not a socket request
    assert ei.value.field == "request"
    with pytest.raises(RequestError) as ei:
        parse_request("jump", {"request": "jump"})
    assert ei.value.field == "request" and "one of move, stop, reset" in str(ei.value)


def test_submit_takes_the_typed_request(rig):
    loop, io, plant, ctl, clock, sink = rig
    fut = loop.submit(MoveRequest(target_m=20e-6, max_velocity_m_s=1e-3))
    with pytest.raises(RequestError, match="target_m.*soft limits"):
        loop.submit(MoveRequest(target_m=0.5))
    loop.run(cycles=50)
    assert fut.result(timeout=0) == {"target_m": 20e-6, "duration_s": pytest.approx(0.02)}


def test_a_cancelled_request_is_never_executed(rig):
    """The daemon cancels a request whose reply timed out; the loop must then not apply it."""
    loop, io, plant, ctl, clock, sink = rig
    loop.run(cycles=5)
    before = loop.status().x_ref_m
    cancelled = loop.submit(MoveRequest(relative_m=20e-6, max_velocity_m_s=1e-3))
    assert cancelled.cancel()
    kept = loop.submit(StopRequest())
    loop.run(cycles=50)
    assert cancelled.cancelled()
    assert kept.result(timeout=0)["x_m"] == pytest.approx(before)
    assert loop.status().x_ref_m == pytest.approx(before)


# ------------------------------------------------------------------------------------------------ status
def test_status_is_typed_and_its_json_form_keeps_the_socket_shape(rig):
    loop, *_ = rig
    before = loop.status()
    assert before.state is LoopState.CONFIGURED and before.fault is None and not before.running
    assert math.isnan(before.x_m)
    js = before.as_json()
    assert js["state"] == "configured" and js["x_m"] is None and js["fault"] is None  # NaN is not JSON
    assert set(js["lateness_us"]) == {"p50", "p99", "max"}
    assert set(js) == {"state", "fault", "t_s", "x_m", "x_ref_m", "e_m", "u_n", "cycle", "overruns",
                       "recent_overrun_fraction", "period_s", "running", "healthy", "lateness_us", "exec_us", "faults",
                       "in_position"}
    loop.latch_fault("unclean_shutdown", "test")
    loop.run(cycles=3)
    st = loop.status(timing=False)
    assert st.state is LoopState.FAULT and st.fault is not None and st.fault.name == "unclean_shutdown"
    assert st.lateness_us is None
    assert plain(st, json=True)["fault"] == {"name": "unclean_shutdown", "cause": "test", "t_s": 0.0, "cycle": 0}


# ------------------------------------------------------------------------------------------------ host
def test_host_runs_the_loop_in_its_thread_with_its_sinks(rig, rows):
    loop, io, plant, ctl, clock, sink = rig
    exited = threading.Event()
    dut = LoopHost(loop, sinks=[rows], on_exit=exited.set)
    dut.start(cycles=120)
    assert dut.started
    assert dut.wait(60) and exited.is_set()
    res = dut.finish(timeout_s=1.0)
    assert res is not None and res.cycles == 120 and res.ended_by == "cycles"
    assert len(rows.rows) == 120 and dut.end_reason() == "ended by cycles"
    loop.run(cycles=5)
    assert len(rows.rows) == 120  # the host's sink was removed when it finished
    with pytest.raises(RuntimeError, match="already started"):
        dut.start()


def test_host_stop_halts_motion_and_reraises_a_loop_error(make):
    loop, io, plant, ctl, clock = make()
    dut = LoopHost(loop)
    fut = loop.submit(MoveRequest(target_m=5e-6, max_velocity_m_s=1e-3))
    dut.start()
    fut.result(timeout=60)
    dut.halt_motion(until_mono=float("inf"))  # returns once the reference stands where the stop put it
    st = loop.status(timing=False)
    assert st.state is LoopState.ACTIVE
    res = dut.finish(timeout_s=60)
    assert res is not None and res.ended_by == "stop" and res.fault is None
    assert not dut.alive

    loop2, io2, *_ = make(startup_cycles=2)
    io2.drop_samples(10)  # no position at start: run raises in the loop thread
    dut2 = LoopHost(loop2)
    dut2.start(cycles=5)
    with pytest.raises(StageError, match="startup_cycles"):
        dut2.finish(timeout_s=60)
    assert "StageError" in dut2.end_reason()


def test_an_interrupt_inside_wait_does_not_make_the_running_loop_look_ended(make):
    """Ctrl-C (or the CLI's SIGTERM) raises KeyboardInterrupt in the main thread while it waits on the host. On
    CPython 3.11 an interrupted Thread.join marks the live thread stopped; the host judged by is_alive, so `run`
    went on to close the devices under a loop still running and printed "loop": null (audit16's SIGTERM test)."""
    import signal

    loop, *_ = make()
    dut = LoopHost(loop)
    dut.start()  # until stopped

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    before = signal.signal(signal.SIGALRM, interrupt)
    try:
        signal.setitimer(signal.ITIMER_REAL, 0.05)
        with pytest.raises(KeyboardInterrupt):
            dut.wait(60)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, before)
    assert dut.alive and not dut.wait(0)
    res = dut.finish(timeout_s=60)
    assert res is not None and res.ended_by == "stop" and not dut.alive


def test_a_second_interrupt_inside_finish_waits_for_the_loop_to_end(make):
    """`run` after Ctrl-C: host.finish() stops the loop and waits; a second interrupt there (Ctrl-C again, or a
    supervisor's SIGTERM) raised out of finish while the loop thread still ran its last cycle, and the
    command's `with build_stage(...)` then disabled and closed the devices under it. finish() keeps waiting
    (bounded by its time-out) and raises the interrupt once the loop has ended."""
    import signal

    loop, *_ = make()
    dut = LoopHost(loop)
    got = threading.Event()
    in_cycle = threading.Event()
    main = threading.main_thread().ident
    assert main == threading.get_ident()

    class InterruptOnStop:
        sent = False

        def append(self, row):  # loop thread, first cycle: it lasts until finish() asked the loop to stop
            if not self.sent:
                self.sent = True
                in_cycle.set()
                dut._stop.wait(60)
                signal.pthread_kill(main, signal.SIGINT)
                got.wait(60)  # the main thread took the interrupt inside finish(); this cycle is not over

    def interrupt(signum, frame):
        got.set()
        raise KeyboardInterrupt

    loop.add_sink(InterruptOnStop())
    before = signal.signal(signal.SIGINT, interrupt)
    try:
        dut.start()  # until stopped
        # finish() only once the loop is inside its first cycle: asked to stop before it, the loop ends without
        # a cycle and nothing is interrupted (the race a loaded machine showed)
        assert in_cycle.wait(60)
        with pytest.raises(KeyboardInterrupt):
            try:
                dut.finish(timeout_s=60)
            finally:
                alive_when_raised = dut.alive
    finally:
        signal.signal(signal.SIGINT, before)
    assert got.is_set()
    assert not alive_when_raised  # the devices may be closed now: the loop no longer uses them


def test_an_interrupt_inside_the_stage_teardown_still_closes_everything(make):
    """A command's `with build_stage(...)` ends by disabling the drive and closing every device and bus; a
    SIGTERM (now a KeyboardInterrupt in the main thread) landing inside one of those steps skipped all the
    others (only Exception was caught): the remaining devices and the bus left open. Each step is done, and
    the interrupt raised once they all are."""
    from stagectl.app import Teardown
    from stagectl.drivers.base import DeviceState

    _, drive, *_ = make()
    _, encoder, *_ = make()
    drive.enable()
    closed = []

    def interrupted_disable():  # the signal arrives inside the drive's disable
        raise KeyboardInterrupt

    drive.disable = interrupted_disable
    td = Teardown(devices=[encoder, drive], closers=[lambda: closed.append("bus")], actuator=drive)
    with pytest.raises(KeyboardInterrupt):
        td.close()
    assert drive.state is DeviceState.CLOSED and encoder.state is DeviceState.CLOSED
    assert closed == ["bus"]


# ------------------------------------------------------------------------------------------------ CSV writer
def test_one_recording_csv_writer_for_the_recorder_and_the_daemon(tmp_path):
    from stagectl.daemon.telemetry import TelemetryRing, TelemetryWriter, WriterSettings

    cols = ("t", "x", "u")
    data = np.array([[0.0, 1e-9 / 3, -0.5], [1e-3, math.pi * 1e-6, 2.0]])
    dut = RecordingCsv(cols)
    assert dut.header == "t,x,u\n"
    assert dut.rows(data) == "0,3.33333333333e-10,-0.5\n0.001,3.14159265359e-06,2\n"
    rec = Recorder(cols)
    for r in data:
        rec.append(tuple(r))
    a = rec.write_csv(tmp_path / "a.csv").read_text()  # run outputs: 10 significant digits
    assert a == "t,x,u\n0,3.333333333e-10,-0.5\n0.001,3.141592654e-06,2\n"
    ring = TelemetryRing(cols, 16)
    writer = TelemetryWriter(ring, WriterSettings(directory=tmp_path / "tel"))
    for r in data:
        ring.append(tuple(r))
    writer.stop()  # never started: drains in this thread
    (b,) = (tmp_path / "tel").glob("telemetry-*.csv")
    assert b.read_text() == dut.header + dut.rows(data)  # telemetry: 12


def test_late_cycle_warnings_say_once_that_they_are_expected_without_realtime(caplog) -> None:
    """Issue 15: the overrun warnings on an ordinary PC come with one hint line (why, and where the fix is),
    then only the rate-limited counts."""
    import logging

    from stagectl.runtime.stats import LatenessWarner

    w = LatenessWarner(late_s=500e-6, interval_s=10.0)
    with caplog.at_level(logging.WARNING):
        w.note(0.1, 2e-3, 0, 1e-3, 1)
        w.note(0.2, 2e-3, 0, 1e-3, 2)  # within the interval: counted, not logged
        w.note(10.5, 1e-4, 1, 1e-3, 3)  # a skipped slot after the interval: logged, no second hint
        w.note(10.6, 1e-4, 0, 1e-3, 3)  # on time: nothing
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 3 and lines[0].startswith("loop timing: 1 late/overrun cycles")
    assert "expected without real-time scheduling" in lines[1] and "Installing on a stage PC" in lines[1]
    assert lines[2].startswith("loop timing: 2 late/overrun cycles")
