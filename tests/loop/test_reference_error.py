"""An exception raised by the reference generator inside the loop's cycle is a latched ``loop_error``: the force
on the stage goes to 0 in the same cycle (the drive's quick stop), the loop keeps supervising, motion is refused
until a reset, and after the reset the stage follows a move again. The error is the real
:class:`~stagectl.control.trajectory.TrajectoryGenerator`'s (a triangle too short for its speed, bound when the
move before it ends), not a mock. A scenario carrying such a segment is refused before the loop runs."""

from __future__ import annotations

import logging

import pytest

from stagectl.control.reference import TrajectoryReference
from stagectl.control.trajectory import Move, Scenario, Triangle
from stagectl.errors import ConfigError
from stagectl.loop import LoopState, LoopStateError
from stagectl.runtime.requests import MoveRequest, ResetRequest

SHORT = Triangle(span_m=1e-6, velocity_m_s=1e-3)  # needs >= 11 µm at 0.1 m/s²


def test_a_generator_error_in_the_cycle_latches_loop_error_and_stops(make, caplog) -> None:
    caplog.set_level(logging.ERROR, logger="stagectl.loop")
    loop, io, plant, _ctl, _clock = make()
    ref = TrajectoryReference()
    loop.reference = ref
    applied: list[float] = []

    class Probe:
        def append(self, row: tuple[float, ...]) -> None:
            applied.append(io.applied_force_n)

    loop.add_sink(Probe())
    futs = []

    def on_cycle() -> None:  # (one run: a new run() starts from a hold, which resets the generator)
        if loop.cycle == 5:
            futs.append(loop.submit(MoveRequest(target_m=20e-6, max_velocity_m_s=1e-3)))
        elif loop.cycle == 8:  # bound (and refused by the generator) when the move ends, inside the cycle
            ref.gen.queue(SHORT)

    loop.on_cycle = on_cycle
    n = 200
    res = loop.run(cycles=n)
    loop.on_cycle = None
    duration = futs[0].result(timeout=0)["duration_s"]
    assert duration < 0.1
    assert res.ended_by == "cycles" and res.cycles == n  # the loop went on supervising
    st = loop.status()
    assert st.state is LoopState.FAULT and st.fault is not None and st.fault.name == "loop_error"
    assert "triangle: span" in st.fault.cause and st.fault.cause.startswith("ValueError")
    k_f = st.fault.cycle
    assert 6 + int(duration / loop.period_s) - 2 <= k_f <= 6 + int(duration / loop.period_s) + 2  # at its end
    assert any(abs(f) > 1e-3 for f in applied[: k_f - 10])
    assert all(f == 0.0 for f in applied[k_f:])  # quick stop from the latching cycle on
    lines = [r.getMessage() for r in caplog.records if "FAULT loop_error" in r.getMessage()]
    assert len(lines) == 1
    refused = loop.submit(MoveRequest(relative_m=1e-6))
    loop.run(cycles=3)
    with pytest.raises(LoopStateError, match="reset first"):
        refused.result(timeout=0)
    # reset: the generator holds the measured position (its bad queue dropped) and the stage follows a move
    fut = loop.submit(ResetRequest())
    loop.run(cycles=3)
    assert fut.result(timeout=0)["state"] == "active"
    mv = loop.submit(MoveRequest(relative_m=5e-6, max_velocity_m_s=1e-3))
    loop.run(cycles=150)
    assert loop.status().fault is None and loop.status().state is not LoopState.FAULT
    assert mv.result(timeout=0)["target_m"] == pytest.approx(loop.status().x_ref_m)
    assert abs(plant.x_m - loop.status().x_ref_m) < 1e-6


def test_a_scenario_with_a_segment_that_cannot_run_is_refused_before_the_loop() -> None:
    ref = TrajectoryReference()
    sc = Scenario(name="bad", segments=(Move(by_m=1e-6), SHORT))
    with pytest.raises(ConfigError) as ei:
        ref.set_scenario(sc)
    assert str(ei.value).startswith("scenario bad: segments[1] (triangle): triangle: span 1e-06 m too short")
    assert "\n" not in str(ei.value) and ref.scenario is None


def test_a_repeated_motion_is_named_never_read_from_a_file_in_the_cycle() -> None:
    ref = TrajectoryReference()
    ref.hold(0.0, 0.0)
    with pytest.raises(ConfigError, match="^motion: give a scenario name"):
        ref.run_scenario(0.0, "scan.yaml")
