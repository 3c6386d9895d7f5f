"""A move that starts on a blind cycle (``StageController.hold`` past ``stale_predict_cycles``) takes the same start
edge as a fresh one (``_start_edge``): the stop synchronisation completes before the model's first step, also
without an observer (the rest integral's force leaves the PID integrator), and a settle move from ahead hands its
reversal force u_k to the observer on that cycle, not on the next fresh sample.

Simulated time, the real controller on config/sim.yaml's settings; the settle case closes the loop over the plain
elasto-plastic oracle plant of test_settle_ahead.py.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.control.test_settle_ahead import PERIOD, ElastoPlasticStage, _high, _with

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def seed() -> Any:
    from stagectl.config import load_app_config

    return load_app_config(REPO / "config" / "sim.yaml")


@pytest.mark.parametrize("x_stuck", [50e-9, -50e-9])
def test_a_blind_start_without_an_observer_loads_the_rest_integral(seed: Any, x_stuck: float) -> None:
    from stagectl.control.controller import StageController
    from stagectl.control.trajectory import Reference

    c = seed.controller
    c = dataclasses.replace(c, dob=dataclasses.replace(c.dob, kind="none"), rest_integral_hz=10.0,
                            stale_predict_cycles=0)
    rest, move = Reference(0.0, 0.0, 0.0), Reference(0.0, 0.0, 0.05)
    after = {}
    for blind in (False, True):
        ctl = StageController(c, PERIOD)
        ctl.reset(0.0)
        for _ in range(400):  # a stage stuck 50 nm off its target: the rest integral builds up, its sync is armed
            ctl.step(PERIOD, x_stuck, rest)
        r0, i0 = ctl._ri_i, ctl.pid.state.i_n
        assert ctl._sync_armed and abs(r0) > 0.02  # (more than one period of the rest sync can load)
        cmd = ctl.hold(PERIOD, move) if blind else ctl.step(PERIOD, x_stuck, move)
        assert ("stale" in cmd.limited) == blind
        assert not ctl._sync_armed
        # the start edge moved R (all but the last period's worth of the rest sync's load) out of the rest integral
        # and the PID integrator into the model (a fresh step then restarts the rest integral: R's remainder is
        # dropped there)
        loaded, dropped = r0 - ctl._ri_i, i0 - ctl.pid.state.i_n
        after[blind] = dropped
        if blind:
            assert loaded * r0 > 0.0 and abs(loaded) > 0.5 * abs(r0)
            assert dropped == pytest.approx(loaded, rel=1e-9)
    assert after[True] == pytest.approx(after[False], rel=0.02)  # the same load as on a fresh start edge


def test_a_blind_start_during_a_settle_move_from_ahead_hands_over_its_force(seed: Any) -> None:
    from stagectl.control.controller import StageController
    from stagectl.control.trajectory import Dwell, Move, Scenario, TrajectoryGenerator

    kw = {"max_velocity_m_s": 1e-3, "max_acceleration_m_s2": 0.05, "max_jerk_m_s3": 20.0}
    sc = Scenario(name="x", segments=(Move(by_m=10e-6, **kw), Dwell(0.01), Move(by_m=-10e-6, **kw), Dwell(0.05)),
                  start_m=0.0)
    gen = TrajectoryGenerator(0.0)
    gen.load(sc)
    refs = [gen.step(PERIOD) for _ in range(round(sc.duration_s(0.0) / PERIOD))]
    moving = np.flatnonzero([not (r.v_m_s == 0.0 and r.a_m_s2 == 0.0) for r in refs])
    s = int(moving[np.flatnonzero(np.diff(moving) > 1)[0] + 1])  # the second move's first sample
    n = seed.controller.stale_predict_cycles + 1  # stale cycles ending on the start edge: the last one is blind
    errors = {}
    for blind in (False, True):
        ctl = StageController(_with(seed, 1.0), PERIOD, model=_high(seed))
        ctl.reset(0.0)
        plant = ElastoPlasticStage()
        x, e = 0.0, []
        for i, ref in enumerate(refs):
            if i == s:
                assert ctl._sm.active and ctl._sm.stiff and ctl._u_k != 0.0  # the continuation from ahead runs
                u_k, d_hat = ctl._u_k, ctl.state.d_hat_n
            stale = blind and s - n < i <= s
            cmd = ctl.hold(PERIOD, ref) if stale else ctl.step(PERIOD, x, ref)
            if i == s:
                assert ("predicted" in cmd.limited) is False and ("stale" in cmd.limited) == blind
                # on the start edge itself: u_k left the continuation for the observer, the ahead pass ended
                assert ctl._u_k == 0.0 and not ctl._sm.stiff and ctl._ahead_pass == 0
                if blind:  # the observer took u_k, and the sync loaded (most of) it into the model
                    assert abs(ctl.state.d_hat_n) < 0.5 * abs(d_hat + u_k)
            e.append(ref.x_m - x)
            x = plant.step(cmd.force_n)
        errors[blind] = float(np.max(np.abs(e[s:])))
    assert errors[True] <= 1.2 * errors[False], errors
