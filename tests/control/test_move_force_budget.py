"""Moves planned within the usable force (stagectl.control.trajectory.ForceBudget).

Oracle: the planned reference sampled every 0.1 ms; its force m·|a| + F_s + F_v·|v| never exceeds the budget,
checked point by point (not through the planner's own formula)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from stagectl.control.trajectory import ForceBudget, Move, Scenario, TrajectoryGenerator

B = ForceBudget(mass_kg=2.0, force_n=1.2, static_n=0.9, viscous_n_s_m=10.0)


def _run(gen: TrajectoryGenerator, t_s: float, dt: float = 1e-4) -> np.ndarray:
    out = []
    for _ in range(int(round(t_s / dt))):
        r = gen.step(dt)
        out.append((r.x_m, r.v_m_s, r.a_m_s2))
    return np.array(out)


def _force(a: np.ndarray, b: ForceBudget) -> np.ndarray:
    return b.mass_kg * np.abs(a[:, 2]) + b.static_n + b.viscous_n_s_m * np.abs(a[:, 1])


def test_a_move_within_the_budget_is_left_alone() -> None:
    m = Move(by_m=1e-3, max_velocity_m_s=0.005, max_acceleration_m_s2=0.1, max_jerk_m_s3=100.0)
    assert B.move_force_n(m) == pytest.approx(2 * 0.1 + 0.9 + 0.05)  # 1.15 N <= 1.2 N
    assert B.fit(m) is m


@pytest.mark.parametrize("v_max", [0.01, 0.05])  # (0.05 m/s: the viscous force alone would take 0.5 N)
def test_a_move_asking_more_is_planned_within_it_and_still_ends_on_target(v_max: float) -> None:
    asked = Move(by_m=1e-3, max_velocity_m_s=v_max, max_acceleration_m_s2=1.0, max_jerk_m_s3=1e4)
    gen = TrajectoryGenerator(0.0)
    seen: list[tuple[Move, Move]] = []
    gen.force_budget, gen.on_move_slowed = B, lambda a, p: seen.append((a, p))
    gen.load(Scenario("fast", (asked,)))
    ref = _run(gen, 1.0)
    assert len(seen) == 1 and seen[0][0] is asked and gen.moves_slowed == 1
    planned = seen[0][1]
    assert planned.max_acceleration_m_s2 < asked.max_acceleration_m_s2
    # the jerk time a/j is kept
    assert planned.max_acceleration_m_s2 / planned.max_jerk_m_s3 == pytest.approx(1.0 / 1e4)
    assert np.max(_force(ref, B)) <= B.force_n * (1 + 1e-9)
    assert np.max(_force(ref, B)) > 0.9 * B.force_n  # and it uses the budget (a and v peak apart: not all of it)
    assert ref[-1, 0] == pytest.approx(1e-3, abs=1e-15) and ref[-1, 1] == 0.0
    # without a budget the same move asks 3 N
    free = TrajectoryGenerator(0.0)
    free.load(Scenario("fast", (asked,)))
    assert np.max(_force(_run(free, 1.0), B)) > 2.0 * B.force_n


def _signed_force(a: np.ndarray, b: ForceBudget) -> np.ndarray:
    """The force the model asks of the actuator, m·a + sgn(v)·(F_s + F_v·|v|): braking, the friction helps."""
    return b.mass_kg * a[:, 2] + np.sign(a[:, 1]) * (b.static_n + b.viscous_n_s_m * np.abs(a[:, 1]))


def test_the_stop_decelerates_within_the_budget() -> None:
    gen = TrajectoryGenerator(0.0)
    gen.force_budget = B
    gen.move(0.1, max_velocity_m_s=0.01, max_acceleration_m_s2=0.1, max_jerk_m_s3=100.0)
    _run(gen, 0.3)  # cruising at 10 mm/s
    assert gen.sample().v_m_s == pytest.approx(0.01)
    end = gen.stop(max_acceleration_m_s2=5.0, max_jerk_m_s3=1e4)  # asked: 10 N of deceleration
    ref = _run(gen, 0.5)
    assert np.max(np.abs(_signed_force(ref, B))) <= B.force_n * (1 + 1e-9)
    assert np.max(B.mass_kg * np.abs(ref[:, 2])) == pytest.approx(B.force_n)  # decelerating at F/m, not 10 N
    assert ref[-1, 0] == pytest.approx(end) and ref[-1, 1] == 0.0


@pytest.mark.parametrize("v0", [0.025, 0.0299])
def test_a_stop_from_a_fast_motion_is_not_stretched_by_the_friction(v0: float) -> None:
    """A motion not planned within the budget (a scan; here a move run without one) at a speed whose friction
    nearly takes the budget (F_s + F_v·v0 → 1.2 N) stops as asked (0.1 m/s² ≤ F/m): the friction brakes with the
    actuator. Charged against the deceleration it left (1.2 − 0.9 − 10·v0)/2 m/s²: 12.5 and 894 mm of travel
    instead of 3.1 and 4.5 mm."""
    gen = TrajectoryGenerator(0.0)
    gen.move(1.0, max_velocity_m_s=v0, max_acceleration_m_s2=0.1, max_jerk_m_s3=100.0)
    _run(gen, 0.6)
    assert gen.sample().v_m_s == pytest.approx(v0)
    gen.force_budget = B
    x0 = gen.sample().x_m
    end = gen.stop(max_acceleration_m_s2=0.1, max_jerk_m_s3=100.0)
    assert end - x0 < 1.1 * v0 * v0 / (2 * 0.1) + v0 * 0.1 / 100.0  # v0²/2a and the jerk ramp's share
    ref = _run(gen, 1.0)
    assert ref[-1, 0] == pytest.approx(end) and ref[-1, 1] == 0.0
    assert np.max(np.abs(_signed_force(ref, B))) <= B.force_n * (1 + 1e-9)


@pytest.mark.parametrize("v_max", [0.0279, 0.0281, 0.029, 0.05])
def test_a_move_over_the_budget_by_its_speed_keeps_what_the_acceleration_leaves(v_max: float) -> None:
    """A slow acceleration (2 kg x 0.01 m/s^2 = 0.02 N) leaves 0.28 N of the 0.3 N room above F_s for the viscous
    force: 28 mm/s. A move asking 28.1 mm/s is planned at 28 mm/s (not at half the room's 15 mm/s), continuous in
    what it asks, and within the budget."""
    asked = Move(by_m=1e-2, max_velocity_m_s=v_max, max_acceleration_m_s2=0.01, max_jerk_m_s3=1.0)
    planned = B.fit(asked)
    assert B.move_force_n(planned) <= B.force_n * (1 + 1e-12)
    assert planned.max_velocity_m_s == pytest.approx(min(v_max, 0.028))
    assert planned.max_acceleration_m_s2 == pytest.approx(0.01)


def test_friction_alone_over_the_budget_leaves_the_move_as_asked() -> None:
    stuck = ForceBudget(mass_kg=2.0, force_n=0.8, static_n=0.9)
    m = Move(by_m=1e-3, max_acceleration_m_s2=1.0)
    assert stuck.fit(m) is m
    assert math.isclose(stuck.move_force_n(m), 2.9)
