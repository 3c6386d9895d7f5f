"""The controller features of this round together: the rest loop's gains (``rest_kd_fraction``,
``rest_dob_bandwidth_fraction``), the settle move from ahead (``settle.ahead_stiffness_fraction``: a force u_k kept
out of the observer's input) and the command schedule (``predict_next_force``; the observer told the predicted
force). Real controller, the plain elasto-plastic oracle plant of test_settle_ahead, simulated time."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from tests.control.test_settle_ahead import PERIOD, ElastoPlasticStage, _high, _with, seed  # noqa: F401


def _ahead_run(seed: Any, cfg: Any, until: Any = None) -> tuple[Any, ElastoPlasticStage, Any, float, list[Any]]:
    """The controller with the seed model 20 % high after a 10 µm move that ends ahead; stepped until ``until(ctl)``
    (None: to the end of the hold). Returns (controller, plant, generator, last x, rows)."""
    from stagectl.control.controller import StageController
    from stagectl.control.trajectory import Dwell, Move, Scenario, TrajectoryGenerator

    ctl = StageController(cfg, PERIOD, model=_high(seed))
    ctl.reset(0.0)
    gen = TrajectoryGenerator(0.0)
    mv = Move(by_m=10e-6, max_velocity_m_s=1e-3, max_acceleration_m_s2=0.05, max_jerk_m_s3=20.0)
    sc = Scenario(name="one", segments=(mv, Dwell(0.15)), start_m=0.0)
    gen.load(sc)
    plant = ElastoPlasticStage()
    x = 0.0
    rows: list[Any] = []
    for _ in range(round(sc.duration_s(0.0) / PERIOD)):
        ref = gen.step(PERIOD)
        cmd = ctl.step(PERIOD, x, ref)
        rows.append((cmd.force_n, ctl._u_k, ctl.state.u_obs_prev_n, ctl._ahead_pass))
        x = plant.step(cmd.force_n)
        if until is not None and until(ctl):
            break
    return ctl, plant, gen, x, rows


def test_reset_restarts_the_rest_gains_dwell(seed: Any) -> None:
    # the rest gains switch in only after REST_GAINS_DWELL_S held still: after reset() too (the dwell counted
    # before the reset is not this standstill's)
    from stagectl.control.api import Reference
    from stagectl.control.controller import REST_GAINS_DWELL_S, StageController

    c = seed.controller
    assert c.rest_kd_fraction < 1.0
    ctl = StageController(c, PERIOD)
    ctl.reset(0.0)
    ref = Reference(0.0, 0.0, 0.0)
    for _ in range(int(REST_GAINS_DWELL_S / PERIOD) + 5):
        ctl.step(PERIOD, 0.0, ref)
    assert ctl.pid.cfg.kd_n_s_m == pytest.approx(c.rest_kd_fraction * c.pid.kd_n_s_m)
    ctl.reset(0.0)
    assert ctl.pid.cfg.kd_n_s_m == c.pid.kd_n_s_m
    ctl.step(PERIOD, 0.0, ref)
    assert ctl.pid.cfg.kd_n_s_m == c.pid.kd_n_s_m, "the rest gains came back at the first step after reset()"


def test_retune_to_no_observer_during_the_continuation_from_ahead(seed: Any) -> None:
    # a live retune that switches the observer off while the continuation from ahead carries its force u_k outside
    # the observer: u_k goes with the observer's estimate (into the integrator) without a step in u, and the
    # continuation goes on without it (no handover to an observer that is not there)
    cfg = _with(seed, 1.0)
    ctl, plant, gen, x, rows = _ahead_run(seed, cfg, until=lambda c: c._ahead_pass == 1 and c._sm.tau_s > 0.002)
    assert ctl._u_k != 0.0 and ctl._sm.active
    u_before = rows[-1][0]
    ctl.retune(dataclasses.replace(cfg, dob=dataclasses.replace(cfg.dob, kind="none")))
    assert ctl.dob is None
    us = []
    for _ in range(60):
        cmd = ctl.step(PERIOD, x, gen.step(PERIOD))
        us.append(cmd.force_n)
        x = plant.step(cmd.force_n)
    assert ctl._u_k == 0.0 and not ctl._sm.active
    assert all(np.isfinite(us))
    # no step at the retune beyond the steps the continuation itself makes
    steps = np.abs(np.diff([r[0] for r in rows[-6:]]))
    assert abs(us[0] - u_before) <= 2.0 * steps.max() + 1e-3


def test_held_cycle_leaves_the_continuation_force_out_of_the_observer_input(seed: Any) -> None:
    # a stale cycle that holds the feedback (beyond stale_predict_cycles) keeps u_k in the command; the observer's
    # input stays u − u_ff − u_k, as at a step
    cfg = dataclasses.replace(_with(seed, 1.0), stale_predict_cycles=0)
    ctl, plant, gen, x, rows = _ahead_run(seed, cfg, until=lambda c: c._ahead_pass == 1 and c._sm.tau_s > 0.002)
    assert ctl._u_k != 0.0
    cmd = ctl.hold(PERIOD, gen.step(PERIOD))
    st = ctl.state
    assert st.u_obs_prev_n == pytest.approx(cmd.force_n - st.u_ff_n - ctl._u_k, abs=1e-12)
