"""Issue 12 item 2: the rest loop (standstill: integrator held, observer, rest spring) of every shipped config that has
one meets the PM 40° / GM 8 dB floor on the stuck stage over the θ range (``stagectl tune``'s analysis), and the
analysis' verdict on a *free* stage is what a plain simulation of the controller on a free mass shows."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest

CONFIG = Path(__file__).resolve().parents[2] / "config"


def _rest(name: str) -> dict:
    from stagectl.commands.tune import _rest_loops
    from stagectl.config import load_app_config

    app = load_app_config(str(CONFIG / name))
    ctl = app.controller
    nd = ctl.design_delay_samples if ctl.design_delay_samples is not None else app.io.delay_cycles
    m = ctl.mass_kg or 2.0
    rest = _rest_loops(app, ctl, m, ctl.dob.nominal_mass_kg or m, app.loop.period_s, nd, simulate=False)
    assert rest is not None
    return rest


@pytest.mark.parametrize("name", ["sim.yaml", "hil-canopen.yaml", "stage-canopen.yaml", "hil-serial.yaml"])
def test_shipped_rest_loop_meets_the_floor_on_the_stuck_stage(name):
    rest = _rest(name)
    stuck = rest["loops"]["rest/stuck"]
    assert stuck["closed_loop_stable"] and stuck["healthy"], stuck
    assert stuck["phase_margin_deg"] >= 40.0 and stuck["gain_margin_db"] >= 8.0
    for row in rest["theta_sweep"]:  # every θ the adaptation allows, not only the worst one reported
        assert row["closed_loop_stable"] and row["phase_margin_deg"] >= 40.0 and row["gain_margin_db"] >= 8.0


def _free_mass_growth(phi: float, gate: bool = False) -> float:
    """The sim.yaml controller held at rest on a plain free 2 kg mass (exact ZOH, one period of I/O delay), kicked
    by 1 nm; the guard (its release distance, hunting band and stiffness test) and the spring's clamp widened or off
    so that the loop stays linear. Returns max|x| over the last 0.1 s of 0.4 s divided by the kick."""
    from stagectl.config import load_app_config
    from stagectl.control.api import Reference
    from stagectl.control.controller import StageController

    app = load_app_config(str(CONFIG / "sim.yaml"))
    c = dataclasses.replace(app.controller, rest_stiffness_fraction=phi, rest_spring_range_m=1e-3,
                            rest_spring_release_m=1e-2, rest_spring_rearm_m=5e-3,
                            rest_spring_held_fraction=app.controller.rest_spring_held_fraction if gate else 0.0)
    ctl = StageController(c, app.timing)
    T, m = app.loop.period_s, 2.0
    x, v, u_applied, x0 = 1e-9, 0.0, 0.0, 1e-9
    ctl.reset(0.0)
    ref = Reference(0.0, 0.0, 0.0)
    late = 0.0
    n = int(0.4 / T)
    for k in range(n):
        u_next = ctl.step(T, x, ref).force_n
        x, v = x + v * T + u_applied * T * T / (2 * m), v + u_applied * T / m
        u_applied = u_next  # one period of I/O delay
        if k > n - int(0.1 / T):
            late = max(late, abs(x))
        if abs(x) > 1e-3:
            return math.inf
    return late / x0


def test_free_stage_rest_loop_matches_the_analysis():
    """The analysis says the rest loop with the full spring is unstable on a free mass and stable without it; a plain
    simulation of the controller itself agrees (the guard and the stiffness test off, the clamp widened: linear).
    With the stiffness test on, a free mass gets only the spring of a stage not seen held (its force is ~0:
    ``rest_spring_unconfirmed_kp_fraction`` 0 in config/sim.yaml), and the analysis of that loop (tune's rest/free
    line) is healthy, and the simulation of the gated controller decays as the spring-less one does."""
    from stagectl.commands.tune import _free_spring, _rest_loops  # noqa: F401  (same analysis as above)
    from stagectl.config import load_app_config

    free = _rest("sim.yaml")["loops"]["rest/free"]
    assert free["closed_loop_stable"] and free["healthy"]
    ctl = load_app_config(str(CONFIG / "sim.yaml")).controller
    assert _free_spring(ctl, 3e5) == 0.0
    assert _free_spring(dataclasses.replace(ctl, rest_spring_held_fraction=0.0), 3e5) == 3e5
    assert _free_mass_growth(0.5) > 1e3
    assert _free_mass_growth(0.0) < 1.0
    assert _free_mass_growth(0.5, gate=True) == _free_mass_growth(0.0, gate=True) < 1.0


def test_rest_gains_act_only_while_the_stage_is_held_and_switch_bumplessly():
    """config/sim.yaml's rest gains: at rest with the stage still, K_d × rest_kd_fraction and the observer at
    rest_dob_bandwidth_fraction × its bandwidth after REST_GAINS_DWELL_S, with the command at the switch the same as a
    controller without rest gains gives (bumpless: PID term and d̂ keep their values); a stage that slips
    (|v̂| > REST_GAINS_EXIT_M_S) gets the moving gains back at once."""
    from stagectl.config import load_app_config
    from stagectl.control.api import Reference
    from stagectl.control.controller import REST_GAINS_DWELL_S, StageController

    app = load_app_config(str(CONFIG / "sim.yaml"))
    c = app.controller
    assert c.rest_kd_fraction < 1.0 and c.rest_dob_bandwidth_fraction < 1.0
    ctl = StageController(c, app.timing)
    plain = StageController(dataclasses.replace(c, rest_kd_fraction=1.0, rest_dob_bandwidth_fraction=1.0), app.timing)
    T = app.loop.period_s
    ref = Reference(0.0, 0.0, 0.0)
    x = 20e-9
    switched = None
    for ct in (ctl, plain):
        ct.reset(0.0)
    for k in range(int(REST_GAINS_DWELL_S / T) + 5):
        u, u0 = ctl.step(T, x, ref).force_n, plain.step(T, x, ref).force_n
        if switched is None and ctl.pid.cfg.kd_n_s_m != c.pid.kd_n_s_m:
            switched = k
            assert u == pytest.approx(u0, abs=1e-12)  # no step in the command at the switch
        elif switched is None:
            assert u == u0
    assert switched is not None and switched * T >= REST_GAINS_DWELL_S - 1.5 * T
    assert ctl.pid.cfg.kd_n_s_m == pytest.approx(c.rest_kd_fraction * c.pid.kd_n_s_m)
    assert ctl.dob.cfg.bandwidth_hz == pytest.approx(c.rest_dob_bandwidth_fraction * c.dob.bandwidth_hz)
    ctl.step(T, x + 60e-9, ref)  # 60 µm/s: the stage slips
    assert ctl.pid.cfg.kd_n_s_m == c.pid.kd_n_s_m and ctl.dob.cfg.bandwidth_hz == c.dob.bandwidth_hz
