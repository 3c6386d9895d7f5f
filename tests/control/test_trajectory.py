"""Trajectory generator: limits, exact arrival, continuity, runtime replacement (scripted dt, no clock)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stagectl.control.api import Reference
from stagectl.control.trajectory import (
    Cosine,
    Dwell,
    Move,
    Scenario,
    Sine,
    TrajectoryGenerator,
    Triangle,
    benchmark_scenarios,
    demo_scenario,
    parse_segments,
)
from stagectl.errors import ConfigError
from stagectl.schema import load


def _run(gen: TrajectoryGenerator, dt: float, n: int | None = None) -> np.ndarray:
    if n is None:
        n = int(math.ceil(gen.remaining_s() / dt)) + 5
    out = np.empty((n + 1, 3))
    out[0] = gen.sample()
    for k in range(1, n + 1):
        out[k] = gen.step(dt)
    return out


@pytest.mark.parametrize("dist", [10e-6, -10e-6, 1e-3, 37e-9, 0.02])
def test_move_respects_limits_and_arrives_exactly(dist):
    vmax, amax, jmax = 2e-3, 0.05, 20.0
    dut = TrajectoryGenerator(1e-3)
    dut.move(1e-3 + dist, vmax, amax, jmax)
    dt = 1e-3 if abs(dist) > 1e-3 else 1e-4
    r = _run(dut, dt)
    x, v, a = r[:, 0], r[:, 1], r[:, 2]
    tol = 1e-9
    assert np.all(np.abs(v) <= vmax * (1 + tol))
    assert np.all(np.abs(a) <= amax * (1 + tol))
    jerk = np.diff(a) / dt
    assert np.all(np.abs(jerk) <= jmax * (1 + 1e-6))
    # no overshoot: monotonic towards the target, velocity never changes sign
    assert np.all(np.sign(v) * np.sign(dist) >= 0)
    assert np.all((x - 1e-3) * np.sign(dist) <= abs(dist) * (1 + 1e-12) + 1e-18)
    assert x[-1] == 1e-3 + dist  # exact arrival (snapped), then holds at rest
    assert v[-1] == 0.0 and a[-1] == 0.0
    assert dut.done
    # position is the integral of velocity (consistency of x, v, a)
    assert np.allclose(np.diff(x), (v[1:] + v[:-1]) / 2 * dt, atol=abs(dist) * 1e-3 + 1e-15)


def test_move_reaches_velocity_limit_on_long_moves():
    dut = TrajectoryGenerator(0.0)
    dut.move(0.02, 2e-3, 0.05, 20.0)
    r = _run(dut, 1e-3)
    assert r[:, 1].max() == pytest.approx(2e-3, rel=1e-9)


def test_cosine_and_sine_shapes():
    dut = TrajectoryGenerator(5e-6)
    dut.replace(Cosine(amplitude_m=10e-6, frequency_hz=1.0, cycles=1))
    r = _run(dut, 1e-3, 1000)
    t = np.arange(1001) * 1e-3
    assert np.allclose(r[:, 0], 5e-6 + 10e-6 * (1 - np.cos(2 * np.pi * t)) / 2, atol=1e-15)
    assert np.allclose(r[:, 1], 10e-6 * np.pi * np.sin(2 * np.pi * t), atol=1e-15)
    assert r[500, 0] == pytest.approx(15e-6)
    dut = TrajectoryGenerator(0.0)
    dut.replace(Sine(amplitude_m=1e-6, frequency_hz=2.0, cycles=2))
    r = _run(dut, 1e-3, 250)
    assert r[125, 0] == pytest.approx(1e-6 * math.sin(2 * math.pi * 2 * 0.125))


def test_triangle_scan_hits_ends_exactly_with_rounded_reversals():
    spec = Triangle(span_m=1e-3, velocity_m_s=1.57e-3, max_acceleration_m_s2=0.02, max_jerk_m_s3=1.0, cycles=2)
    dut = TrajectoryGenerator(0.0)
    dut.replace(spec)
    dt = 1e-4
    r = _run(dut, dt)
    x, v, a = r.T
    assert x.max() == pytest.approx(1e-3, abs=1e-10)  # sampled turning point (a·dt²/8 = 2.5e-11 m)
    assert x.min() >= -1e-15
    assert x[-1] == 0.0 and v[-1] == 0.0
    assert np.all(np.abs(v) <= 1.57e-3 * (1 + 1e-9))
    assert np.all(np.abs(a) <= 0.02 * (1 + 1e-9))
    assert np.all(np.abs(np.diff(a)) / dt <= 1.0 * (1 + 1e-6))
    # two out-and-back cycles: the velocity changes sign 3 times (+ - + -)
    s = np.sign(v[np.abs(v) > 1e-4])
    assert int(np.count_nonzero(np.diff(s))) == 3


def test_triangle_too_short_is_a_clear_error():
    dut = TrajectoryGenerator(0.0)
    with pytest.raises(ValueError, match="too short"):
        dut.replace(Triangle(span_m=1e-7, velocity_m_s=1e-2, max_acceleration_m_s2=0.01, max_jerk_m_s3=1.0))


def test_replace_running_move_is_continuous():
    dut = TrajectoryGenerator(0.0)
    dut.move(1e-3, 2e-3, 0.05, 20.0)
    dt = 1e-4
    prev = dut.sample()
    for _ in range(150):  # mid-acceleration
        prev = dut.step(dt)
    assert prev.v_m_s > 0 and prev.a_m_s2 != 0
    dut.move(-0.2e-3, 2e-3, 0.05, 20.0)  # reverse target while moving
    after = dut.step(dt)
    # no jump: x, v, a move by at most what the limits allow in one dt
    assert abs(after.x_m - prev.x_m) <= 2e-3 * dt * 1.01
    assert abs(after.v_m_s - prev.v_m_s) <= 0.05 * dt * 1.01
    assert abs(after.a_m_s2 - prev.a_m_s2) <= 20.0 * dt * 1.01
    r = _run(dut, dt)
    assert r[-1, 0] == -0.2e-3
    assert np.all(np.abs(np.diff(r[:, 2])) / dt <= 20.0 * (1 + 1e-6))


def test_queue_appends_after_current_motion():
    dut = TrajectoryGenerator(0.0)
    dut.move(10e-6, replace=False)
    dut.move(0.0, replace=False)
    dut.queue(Dwell(0.1))
    total = dut.remaining_s()
    r = _run(dut, 1e-4)
    assert r[:, 0].max() == pytest.approx(10e-6)
    assert r[-1, 0] == 0.0
    assert total > 0.1


def test_scenarios_durations_and_parsing():
    sc = benchmark_scenarios()
    assert set(sc) == {"cosine", "triangle", "steps"}
    assert sc["cosine"].duration_s() == pytest.approx(3.2)
    assert 0.5 < sc["steps"].duration_s() < 5
    assert demo_scenario().duration_s() > 1
    data = {"name": "mine", "segments": [{"kind": "move", "to_m": 1e-6}, {"kind": "dwell", "duration_s": 0.1},
                                         {"kind": "cosine", "amplitude_m": 1e-6, "frequency_hz": 2}]}
    s = load(Scenario, data, "scenario")
    assert isinstance(s.segments[0], Move) and isinstance(s.segments[2], Cosine)
    with pytest.raises(ConfigError) as ei:
        load(Scenario, {"name": "x", "segments": [{"kind": "jump"}, {"kind": "move"},
                                                    {"kind": "dwell", "duration_s": -1}]}, "scenario")
    msg = str(ei.value)
    assert "scenario.segments[0].kind" in msg
    assert "to_m or by_m" in msg
    assert "scenario.segments[2].duration_s" in msg
    problems: list[str] = []
    assert parse_segments("nope", "s", problems) is None and problems


@pytest.mark.parametrize("dt", [0.0, -1e-3, math.nan, math.inf])
def test_step_rejects_bad_dt(dt):
    with pytest.raises(ValueError, match="dt"):
        TrajectoryGenerator(0.0).step(dt)


def test_hold_when_empty():
    dut = TrajectoryGenerator(3e-6)
    assert dut.step(1e-3) == Reference(3e-6, 0.0, 0.0)


def test_final_reference_reports_where_the_queue_ends():
    dut = TrajectoryGenerator(0.0)
    dut.move(10e-6)
    dut.queue([Dwell(0.1), Move(by_m=5e-6)])
    end = dut.final_reference()
    assert end == Reference(10e-6 + 5e-6, 0.0, 0.0)  # by_m is added to the segment's start position
    _run(dut, 1e-3)
    assert dut.sample() == end and dut.done


@pytest.mark.parametrize("n_steps", [5, 40, 120])  # accelerating (a ≠ 0), cruising, decelerating
def test_stop_is_jerk_limited_and_holds_where_it_comes_to_rest(n_steps):
    dut = TrajectoryGenerator(0.0)
    dut.move(200e-6, max_velocity_m_s=2e-3, max_acceleration_m_s2=0.05, max_jerk_m_s3=20.0)
    dut.queue(Dwell(0.5))
    dt = 1e-4
    for _ in range(n_steps * 10):
        dut.step(dt)
    x0, v0, a0 = dut.sample()
    assert v0 > 0
    end = dut.stop(max_acceleration_m_s2=0.05, max_jerk_m_s3=20.0)
    assert end >= x0 and dut.remaining_s() > 0 and dut.final_reference() == Reference(end, 0.0, 0.0)
    tr = _run(dut, dt)
    assert np.all(tr[:, 1] >= -1e-15)  # never reverses
    assert np.max(np.abs(tr[:, 2])) <= 0.05 * (1 + 1e-9)
    assert np.max(np.abs(np.diff(tr[:, 2]))) <= 20.0 * dt * (1 + 1e-6)  # jerk bound: no step in a
    assert abs(tr[1, 0] - x0) < 2e-3 * dt * 1.01  # continuous in x from the stop request
    assert dut.done and tuple(dut.sample()) == (end, 0.0, 0.0)


def test_stop_at_rest_holds_in_place():
    dut = TrajectoryGenerator(7e-6)
    dut.queue(Dwell(1.0))
    dut.step(1e-3)
    assert dut.stop() == 7e-6 and dut.done
    with pytest.raises(ValueError, match="max_jerk_m_s3"):
        dut.stop(max_jerk_m_s3=0.0)
