"""The rest integral (controller docstring, "Rest integral"; ``controller.rest_integral_hz``): a stage stuck off its
target at standstill, held there by a position-dependent force the model does not know (cogging, an offset), is
brought into the ±10 nm band within the hold; simulated time (lock-step)."""

from __future__ import annotations

import dataclasses
import math

import pytest


@pytest.fixture(scope="module")
def cogged(repo_root):
    """config/sim.yaml's seed stage with cogging (0.1 N, 1 mm) and an offset (0.05 N) that the controller's model
    does not have, and its controller without the rest spring and the settle move (what commissioning writes when
    the rest spring fails its checks): the moves stop 100-200 nm off and the observer alone (g·K_p/Σk ≈ 1 s⁻¹)
    leaves them there through a 0.5 s hold."""
    from stagectl.config import load_app_config
    from stagectl.friction.effects import Cogging, Effects, Offset

    cfg = load_app_config(repo_root / "config" / "sim.yaml")
    eff = Effects(cogging=Cogging(amplitude_n=0.1, wavelength_m=1e-3, phase_rad=0.3), offset=Offset(force_n=0.05))
    cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, plant=dataclasses.replace(cfg.sim.plant,
                                                                                              effects=eff)))
    c = cfg.controller
    assert c.feedforward.rest_sync_hz > 0.0  # the integral's force is handed to the model before the next move
    base = dataclasses.replace(c, rest_stiffness_fraction=0.0, rest_kd_fraction=1.0, rest_dob_bandwidth_fraction=1.0,
                               rest_spring_section_count=1,
                               settle=dataclasses.replace(c.settle, move_s=0.0, ahead_stiffness_fraction=0.0))
    return cfg, base


def test_steps_stuck_off_target_settle_with_the_rest_integral(cogged):
    """Without it 2 of the 4 10 µm steps are still 100-200 nm off at the end of the 0.5 s hold; with 3 Hz all four
    end inside ±10 nm, without a limit cycle or a fault."""
    from stagectl.bench.control import steps_check

    cfg, base = cogged
    off = steps_check(cfg, base, hold_s=0.5)
    on = steps_check(cfg, dataclasses.replace(base, rest_integral_hz=3.0), hold_s=0.5)
    assert off["fault"] is None and off["settled"] <= 2
    assert on["fault"] is None and on["limit_cycle"] is False
    assert on["settled"] == 4 and on["max_late_excursion_m"] <= 0.12e-6
    # the moves themselves are the same (the integral waits until the stage no longer approaches the target)
    done = [a for a in off["settle_s"] if a is not None]
    assert done and [b for a, b in zip(off["settle_s"], on["settle_s"]) if a is not None] == pytest.approx(done,
                                                                                                         abs=3e-3)


def test_the_rest_integral_costs_the_stuck_rest_loop_a_few_degrees(repo_root):
    """design.analyse_rest with the integral's gain K_r = 2π·f_r·Σk (the stiff side) on config/sim.yaml's stuck
    plant: it acts at a few Hz, the stuck stage's resonance is at ~90 Hz, so PM and GM move by little; the stuck
    loop's integral action is the observer's plus K_r (quasi-static rest mode (g·K_p + K_r)/(Σk + K_p))."""
    from stagectl.config import load_app_config
    from stagectl.control.design import analyse_rest

    cfg = load_app_config(repo_root / "config" / "sim.yaml")
    c = cfg.controller
    fr = c.feedforward.model.friction
    k, damp = fr.stiffness_n_m, fr.damping_n_s_m
    args = (2.0, cfg.loop.period_s, c.pid, cfg.io.delay_cycles, c.dob.bandwidth_hz, c.dob.command_delay_samples,
            k, damp, 0.0)
    without = analyse_rest(*args)[0]
    with_ri = analyse_rest(*args, rest_integral_n_m_s=2 * math.pi * 3.0 * k)[0]
    assert with_ri.phase_margin_deg == pytest.approx(without.phase_margin_deg, abs=5.0)
    assert with_ri.gain_margin_db == pytest.approx(without.gain_margin_db, abs=0.5)
    big = analyse_rest(*args, rest_integral_n_m_s=2 * math.pi * 300.0 * k)[0]
    assert big.phase_margin_deg < without.phase_margin_deg - 10.0  # the term is really in the loop


def test_the_rest_integral_needs_an_observer_and_stays_off_in_motion(cogged):
    """No observer: nothing to hand its force to, so it does not act (the integrator would carry a positioning force
    into the next move); while the reference moves it adds nothing."""
    from stagectl.control.api import Reference
    from stagectl.control.controller import StageController
    from stagectl.control.dob import DobConfig

    cfg, base = cogged
    c = dataclasses.replace(base, rest_integral_hz=3.0)
    ctl = StageController(dataclasses.replace(c, dob=DobConfig(kind="none")), cfg.timing)
    ctl.reset(0.0)
    for _ in range(100):
        ctl.step(1e-3, -100e-9, Reference(0.0, 0.0, 0.0))
    assert ctl._ri_n == 0.0
    ctl = StageController(c, cfg.timing)
    ctl.reset(0.0)
    for _ in range(100):
        ctl.step(1e-3, -100e-9, Reference(0.0, 0.0, 0.0))
    assert ctl._ri_n > 0.0  # the stage short of the target (x < x_r, the model relaxed: stiff both ways): pushed on
    for i in range(20):
        ctl.step(1e-3, 1e-9 * i, Reference(1e-9 * i, 1e-6, 0.0))
    assert ctl._ri_n == 0.0
