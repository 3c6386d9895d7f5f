"""Each safety check latches a named fault, zeroes the drive within 3 cycles, logs its cause, and only an
explicit reset clears it (simulated time, PlantIO)."""

from __future__ import annotations

import logging
import math

import pytest

from stagectl.runtime.requests import MotionLimits, MoveRequest, ResetRequest

from stagectl.drivers.base import DeviceState, FaultKind
from stagectl.errors import ConfigError
from stagectl.loop import LoopState, LoopStateError
from stagectl.safety import Safety, SafetyConfig
from stagectl.schema import load


class ForceProbe:
    """Sink recording the force actually applied to the plant each cycle."""

    def __init__(self, io):
        self.io = io
        self.applied: list[float] = []

    def append(self, row):
        self.applied.append(self.io.applied_force_n)


def _drive_to_fault(make, trigger, *, settle=20, after=12, safety=None):
    """Move, then fire ``trigger`` at the end of cycle ``settle`` (inside the same run)."""
    loop, io, plant, ctl, clock = make(safety=safety)
    probe = ForceProbe(io)
    loop.add_sink(probe)

    def hook():
        if loop.cycle == settle:
            trigger(loop, io, plant, ctl)

    loop.on_cycle = hook
    loop.submit(MoveRequest(target_m=20e-6, max_velocity_m_s=0.5e-3))
    loop.run(cycles=settle + 1 + after)
    assert any(abs(f) > 1e-3 for f in probe.applied[:settle])  # the drive was pushing before the fault
    return loop, io, plant, ctl, probe


CASES = {
    "emcy": (lambda lp, io, pl, c: io.inject_fault(FaultKind.EMCY, "overcurrent", 0x2310), None),
    "heartbeat_lost": (lambda lp, io, pl, c: io.inject_fault(FaultKind.HEARTBEAT_LOST, "no heartbeat"), None),
    "drive_fault": (lambda lp, io, pl, c: io.inject_fault(FaultKind.DRIVE_FAULT, "statusword fault bit"), None),
    "not_finite": (lambda lp, io, pl, c: io.glitch(math.nan), None),
    "stale_position": (lambda lp, io, pl, c: io.drop_samples(10), None),
    "position_limit": (lambda lp, io, pl, c: io.glitch(0.0102), {"max_velocity_m_s": 100.0}),
    "velocity_limit": (lambda lp, io, pl, c: io.glitch(pl.x_m + 300e-6), {"following_error_m": 1e-3}),
    "following_error": (lambda lp, io, pl, c: setattr(pl, "push_n", 40.0), {"following_error_m": 5e-6}),
    "force_limit": (
        lambda lp, io, pl, c: setattr(pl, "push_n", -30.0),
        {"max_force_n": 10.0, "following_error_m": 1e-2, "force_saturation_time_s": 0.003,
         "max_velocity_m_s": 10.0},
    ),
    "loop_error": (lambda lp, io, pl, c: setattr(c, "fail_next", True), None),
}


@pytest.mark.parametrize("name", list(CASES))
def test_fault_latches_stops_drive_and_needs_reset(make, name, caplog):
    trigger, safety = CASES[name]
    caplog.set_level(logging.ERROR, logger="stagectl.loop")
    loop, io, plant, ctl, probe = _drive_to_fault(make, trigger, safety=safety)
    loop.on_cycle = None
    st = loop.status()
    assert st.state is LoopState.FAULT
    assert st.fault.name == name, st.fault
    assert st.fault.cause
    # logged with its cause
    assert any(name in r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR)
    # the drive output is zero within 3 cycles of the fault and stays zero
    k_fault = st.fault.cycle
    assert 20 <= k_fault <= 27
    after = probe.applied[k_fault + 3:]
    assert after and all(f == 0.0 for f in after), probe.applied[k_fault - 2:]
    # motion requests are refused while faulted
    fut = loop.submit(MoveRequest(relative_m=1e-6))
    plant.push_n = 0.0
    plant.v_m_s = 0.0  # the stage has come to rest before the operator resets
    loop.run(cycles=3)
    with pytest.raises(LoopStateError, match="fault"):
        fut.result(timeout=0)
    assert loop.status().state is LoopState.FAULT  # still latched: nothing but reset clears it
    # explicit reset: bumpless restart at the measured position
    rst = loop.submit(ResetRequest())
    loop.run(cycles=30)
    out = rst.result(timeout=0)
    assert out["cleared"]["name"] == name and out["state"] == "active"
    st = loop.status()
    assert st.fault is None and st.state is LoopState.CONFIGURED
    assert ctl.resets[-1] == pytest.approx(st.x_ref_m, abs=1e-12)  # restarted where it stood
    assert io.state is DeviceState.CONFIGURED  # disabled again at the end of the run


def test_quick_stop_issued_in_the_same_cycle(make):
    stops = []

    def trigger(loop, io, plant, ctl):
        orig = io.quick_stop
        io.quick_stop = lambda: (stops.append(loop.cycle), orig())
        io.inject_fault(FaultKind.EMCY, "x")

    loop, io, plant, ctl, probe = _drive_to_fault(make, trigger, after=5)
    assert stops == [loop.status().fault.cycle] == [21]  # read and stopped in the next cycle


def test_reset_then_new_fault_latches_again(make):
    loop, io, plant, ctl, probe = _drive_to_fault(make, lambda lp, io, pl, c: io.inject_fault(FaultKind.EMCY))
    assert loop.status().fault.name == "emcy"
    rst = loop.submit(ResetRequest())

    def hook():
        if loop.cycle == 40:
            io.glitch(math.nan)

    loop.on_cycle = hook
    loop.run(cycles=30)
    assert rst.result(timeout=0)["state"] == "active"
    assert loop.status().fault.name == "not_finite"


def test_safety_config_bounds_and_cross_check():
    with pytest.raises(ConfigError) as ei:
        load(SafetyConfig, {"min_position_m": 0.01, "max_position_m": -0.01, "max_force_n": -1,
                            "stale_cycle": 2}, "safety")
    msg = str(ei.value)
    assert "safety.max_force_n: must be > 0 N" in msg
    assert "safety.stale_cycle: unknown key (did you mean stale_cycles" in msg


def test_safety_unit_checks():
    s = Safety(SafetyConfig(min_position_m=-1e-3, max_position_m=1e-3, following_error_m=1e-6,
                            following_error_time_s=0.002, max_force_n=5.0, force_saturation_time_s=0.002),
               1e-3)
    s.restart(0.0)
    assert not s.check_tracking(0.000, 0, 0.0, 2e-6)  # outside the window, but not for long enough
    assert not s.check_tracking(0.001, 1, 0.0, 2e-6)
    assert s.check_tracking(0.002, 2, 0.0, 2e-6)
    assert s.fault.name == "following_error"
    s.clear()
    assert s.limit_force(0.0, 0, 7.0) == 5.0 and s.fault is None  # clamped
    assert s.limit_force(0.001, 1, -7.0) == -5.0
    assert s.limit_force(0.003, 2, 9.0) == 0.0 and s.fault.name == "force_limit"
    first = s.fault
    s.latch("emcy", "later", 1.0, 9)
    assert s.fault is first  # the first fault stays latched
    c = s.cfg
    limits = MotionLimits(c.min_position_m, c.max_position_m, c.max_velocity_m_s)  # as the loop builds them
    with pytest.raises(ValueError, match="target_m"):
        limits.check_position(2e-3, "target_m")


def test_the_controllers_own_clamp_counts_as_saturated():
    """A controller clamping at (or below) max_force_n never hands the safety a force outside ±max_force_n:
    its ``limited`` flag keeps the saturation clock running, so a blocked stage or a full-force limit cycle
    still latches force_limit."""
    s = Safety(SafetyConfig(min_position_m=-1e-3, max_position_m=1e-3, max_force_n=10.0,
                            force_saturation_time_s=0.002), 1e-3)
    s.restart(0.0)
    assert s.limit_force(0.000, 0, 10.0, clamped=True) == 10.0
    assert s.limit_force(0.001, 1, -8.0, clamped=True) == -8.0  # the controller's own, lower limit
    assert s.limit_force(0.002, 2, 10.0, clamped=True) == 0.0 and s.fault.name == "force_limit"
    assert "controller's limit (10 N)" in s.fault.cause
    s.clear()
    assert s.limit_force(0.010, 3, 10.0, clamped=True) == 10.0
    assert s.limit_force(0.011, 4, 3.0) == 3.0  # not clamped: the clock restarts
    assert s.limit_force(0.012, 5, 10.0, clamped=True) == 10.0 and s.fault is None


def test_not_finite_anywhere_latches():
    """NaN/inf in the measurement, the reference or the controller output each latch ``not_finite``."""
    cfg = SafetyConfig(min_position_m=-1e-3, max_position_m=1e-3)
    for bad in (math.nan, math.inf, -math.inf):
        s = Safety(cfg, 1e-3)
        s.restart(0.0)
        assert s.check_measurement(0.0, 0, bad, True, None) and s.fault.name == "not_finite"
        s = Safety(cfg, 1e-3)
        s.restart(0.0)
        assert s.check_tracking(0.0, 0, 0.0, bad) and s.fault.name == "not_finite"
        assert "reference" in s.fault.cause
        s = Safety(cfg, 1e-3)
        assert s.limit_force(0.0, 0, bad) == 0.0 and s.fault.name == "not_finite"
        assert "controller output" in s.fault.cause
        s.clear()
        assert s.fault is None
