"""The rest integral (controller docstring, "Rest integral"; ``controller.rest_integral_hz``): a stage stuck off its
target at standstill, held there by a position-dependent force the model does not know (cogging, an offset), is
brought into the ±10 nm band within the hold; simulated time (lock-step)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

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
    end inside ±10 nm (the last half of each hold within 25 nm), without a limit cycle or a fault."""
    from stagectl.bench.control import steps_check

    cfg, base = cogged
    off = steps_check(cfg, base, hold_s=0.5)
    on = steps_check(cfg, dataclasses.replace(base, rest_integral_hz=3.0), hold_s=0.5)
    assert off["fault"] is None and off["settled"] <= 2
    assert on["fault"] is None and on["limit_cycle"] is False
    # (late excursion: 98 nm when the integral waited REST_INTEGRAL_DWELL_S after each of its own increments of the
    # stage's approach; 10 nm now that, once it has acted on the stiff side, it goes on while the stage approaches)
    assert on["settled"] == 4 and on["max_late_excursion_m"] <= 25e-9
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


def test_without_an_observer_the_rest_integral_goes_into_the_pid_integrator(cogged):
    """No observer: its force goes into the PID's integrator (nothing else moves a stuck stage there: the integrator
    alone takes an error away at K_i/Σk); while the reference moves it adds nothing. With an observer it goes into
    the estimate and the integrator is left alone."""
    from stagectl.control.api import Reference
    from stagectl.control.controller import StageController
    from stagectl.control.dob import DobConfig

    cfg, base = cogged
    # (without the stop synchronisation, which hands what the integrator holds of it to the model's state)
    c = dataclasses.replace(base, rest_integral_hz=3.0,
                            feedforward=dataclasses.replace(base.feedforward, rest_sync_hz=0.0))
    runs = {}
    for kind in ("none", "qfilter"):
        cc = c if kind == "qfilter" else dataclasses.replace(c, dob=DobConfig(kind="none"))
        ctl = StageController(cc, cfg.timing)
        ctl.reset(0.0)
        for _ in range(100):
            ctl.step(1e-3, -100e-9, Reference(0.0, 0.0, 0.0))
        assert ctl._ri_n > 0.0  # the stage short of the target (x < x_r, the model relaxed: stiff both ways): pushed on
        runs[kind] = (ctl._ri_n, ctl.pid.state.i_n)
        for i in range(20):
            ctl.step(1e-3, 1e-9 * i, Reference(1e-9 * i, 1e-6, 0.0))
        assert ctl._ri_n == 0.0
    ri, integ = runs["none"]
    assert integ == pytest.approx(ri, rel=0.05)  # the PID's own K_i·Σe·T over 0.1 s at 100 nm is ~1e-3 of it
    assert abs(runs["qfilter"][1]) < 0.05 * runs["qfilter"][0]


def test_without_an_observer_a_stage_stopped_off_target_settles(repo_root):
    """config/sim.yaml's seed stage run with no observer (as commissioning writes where every observer design missed
    the margin floor on the measured FRF; rest spring and settle move off): its 10 µm steps stop 30-620 nm off and
    the PID integrator alone (K_i/Σk ≈ 0.2 s⁻¹) leaves all four outside ±10 nm through the 0.25 s hold; the rest
    integral at commissioning's no-observer rate brings every step into the band within ~0.13 s (3 Hz: ~0.2-0.23 s),
    without a fault or a limit cycle."""
    from stagectl.bench.control import steps_check
    from stagectl.commission.sequence import REST_INTEGRAL_NO_OBSERVER_HZ
    from stagectl.config import load_app_config
    from stagectl.control.dob import DobConfig

    cfg = load_app_config(repo_root / "config" / "sim.yaml")
    c = cfg.controller
    plain = dataclasses.replace(c, dob=DobConfig(kind="none"), rest_stiffness_fraction=0.0, rest_kd_fraction=1.0,
                                rest_dob_bandwidth_fraction=1.0, rest_spring_section_count=1,
                                settle=dataclasses.replace(c.settle, move_s=0.0, ahead_stiffness_fraction=0.0))
    off = steps_check(cfg, plain, hold_s=0.25)
    on = steps_check(cfg, dataclasses.replace(plain, rest_integral_hz=REST_INTEGRAL_NO_OBSERVER_HZ), hold_s=0.25)
    assert off["fault"] is None and off["settled"] == 0
    assert on["fault"] is None and on["limit_cycle"] is False and on["settled"] == 4
    assert max(on["settle_s"]) < 0.2


def _standstill_after_a_move(base, hz: float, creeping_before: bool) -> tuple[list[float], list[float]]:
    """The controller stepped on positions written here (no plant): optionally a standstill at 0 in which the stage
    still creeps in from 300 nm ahead at 5 µm/s when the reference moves on (the integral waits), then a 1 µm move
    followed exactly, then a standstill at 1 µm: 100 nm behind for 5 ms, then 100 nm ahead for 150 ms (one
    crossing of the ±50 nm band). Returns the forces with the rest integral at ``hz`` and with it off."""
    from stagectl.control.api import Reference
    from stagectl.control.controller import StageController

    T = 1e-3
    seq = [(Reference(0.0), 300e-9 - 5e-6 * T * k) for k in range(31)] if creeping_before else []
    seq += [(Reference(1e-7 * k, 1e-4), 1e-7 * k) for k in range(1, 11)]
    seq += [(Reference(1e-6), 1e-6 - 100e-9)] * 5 + [(Reference(1e-6), 1e-6 + 100e-9)] * 150
    out = []
    for f in (hz, 0.0):
        ctl = StageController(dataclasses.replace(base, rest_integral_hz=f), T)
        ctl.reset(seq[0][1])
        out.append([ctl.step(T, x, ref).force_n for ref, x in seq])
    return out[0], out[1]


def test_each_standstill_starts_the_integral_afresh(cogged):
    """The side of the band the stage was last seen on belongs to its standstill: a standstill that ended with the
    stage beyond -50 nm, still creeping in, left it behind, and in the next standstill a single crossing counted as
    the second swing of a hunt: the integral was off for the whole standstill (no force added, the stage left
    100 nm ahead). Now the standstill acts as one without that history does."""
    _, base = cogged
    base = dataclasses.replace(base, feedforward=dataclasses.replace(base.feedforward, rest_sync_hz=0.0))
    on, off = _standstill_after_a_move(base, 3.0, True)
    on_fresh, off_fresh = _standstill_after_a_move(base, 3.0, False)
    added, added_fresh = on[-1] - off[-1], on_fresh[-1] - off_fresh[-1]
    assert added_fresh < -0.05  # the stage ahead: pushed back (by up to the model's Coulomb level)
    assert added == pytest.approx(added_fresh, rel=0.02)  # (at its bound θ·F_c; θ depends a little on the history)


def _stuck_behind(base, soft: float, monkeypatch) -> tuple[float, float]:
    """The controller stepped on positions written here (no plant): a 10 µm move followed exactly (the model copy's
    elements slip forward, as the plant's do), then 0.3 s at rest with the stage stuck 60 nm short of the target.
    Returns (what the rest integral added, the model's tangent stiffness towards the target) at the end."""
    import stagectl.control.controller as cc
    from stagectl.control.api import Reference
    from stagectl.control.controller import StageController

    T = 1e-3
    monkeypatch.setattr(cc, "REST_INTEGRAL_SOFT_FRACTION", soft, raising=False)  # 0: the stiffness-scaled gain only
    ctl = StageController(dataclasses.replace(base, rest_integral_hz=3.0), T)
    ctl.reset(0.0)
    ref = _move_10um(ctl, T)
    for _ in range(300):
        ctl.step(T, ref.x_m - 60e-9, Reference(ref.x_m))
    return ctl._ri_n, ctl.ff.tangent_n_m(1)


def test_a_stage_stuck_behind_is_pushed_through_its_break_away(cogged, monkeypatch):
    """Behind the target the model's elements slip (tangent stiffness ~0 towards it): a gain of k_t there added
    nothing (the observer takes the P force as a disturbance, so the stage stayed 50-250 nm short through the hold:
    generated plants 29 and 36 commissioned). The soft side ramps at the break-away gain k_b = min(Σk, ΔF_b/r) instead,
    bounded by θ·F_c."""
    _, base = cogged
    base = dataclasses.replace(base, feedforward=dataclasses.replace(base.feedforward, rest_sync_hz=0.0))
    fr = base.feedforward.model.friction
    added_old, k_t = _stuck_behind(base, 0.0, monkeypatch)
    added, _ = _stuck_behind(base, 0.25, monkeypatch)
    assert k_t < 0.05 * fr.stiffness_n_m  # the soft side (the stiff side: Σk)
    gap = fr.params.fs_n - fr.params.fc_n
    assert abs(added_old) < 0.1 * gap  # the stiffness-scaled gain: next to nothing
    assert 0.5 * gap < added <= fr.params.fc_n * 1.01  # past the break-away gap within 0.3 s, within the bound


def _closed_loop_from_behind(base, plant_cfg, soft: float, monkeypatch, hold_s: float = 0.4) -> list[float]:
    """Lock-step, the controller on a plant (one cycle of I/O delay): the plant is first slid forward open loop
    (a force just past its static level for 1 µm, then below its Coulomb level until it stops), the controller
    stepped on the same positions as the reference; then the target is set 60 nm ahead of the stuck stage and the
    loop closed. Returns the error x_r − x [m] per period over ``hold_s``."""
    from stagectl.sim.plant import StagePlant

    import stagectl.control.controller as cc
    from stagectl.control.api import Reference
    from stagectl.control.controller import StageController

    T = 1e-3
    fp = plant_cfg.friction.params
    monkeypatch.setattr(cc, "REST_INTEGRAL_SOFT_FRACTION", soft, raising=False)  # 0: the stiffness-scaled gain only
    plant = StagePlant(plant_cfg)
    plant.reset(0.0)
    ctl = StageController(dataclasses.replace(base, rest_integral_hz=3.0), T)
    ctl.reset(0.0)
    x_prev, phase, u = 0.0, 0, 0.0
    for _ in range(400):
        if phase == 0 and plant.x_m > 1e-6:
            phase = 1
        if phase == 1 and plant.v_m_s <= 2e-6:
            phase, u = 2, plant.friction_n  # stuck, its elements at their forward slip limit
        if phase < 2:
            u = 1.02 * fp.fs_n if phase == 0 else 0.9 * fp.fc_n
        plant.step(u, T)
        x = plant.measure()
        ctl.step(T, x, Reference(x, (x - x_prev) / T if phase < 2 else 0.0, 0.0))
        x_prev = x
    assert phase == 2
    target = plant.x_m + 60e-9
    errors = []
    for _ in range(int(hold_s / T)):
        u_next = ctl.step(T, plant.measure(), Reference(target)).force_n
        plant.step(u, T)
        u = u_next
        errors.append(target - plant.x_m)
    return errors


def test_a_stage_stuck_short_of_its_target_settles_in_closed_loop(cogged, repo_root, monkeypatch):
    """The seed stage's plant slid forward and stuck 60 nm short of its target (its elements at their slip limit):
    with the stiffness-scaled gain the error crept in at ~0.15 µm/s (23 nm left after 0.25 s, in the band after
    0.37 s); the push at the break-away gain (while the stage creeps in at less than REST_INTEGRAL_SOFT_STILL_M_S)
    brings it into ±10 nm within 0.22 s and it stays there, without hunting."""
    from stagectl.config import load_app_config

    _, base = cogged
    plant_cfg = load_app_config(repo_root / "config" / "sim.yaml").sim.plant
    old = _closed_loop_from_behind(base, plant_cfg, 0.0, monkeypatch)
    new = _closed_loop_from_behind(base, plant_cfg, 0.25, monkeypatch)
    assert old[0] > 50e-9 and new[0] > 50e-9  # it starts stuck behind
    assert old[249] > 15e-9  # without the push: still short after 0.25 s
    late = new[250:]
    assert max(abs(e) for e in late) <= 10e-9  # settled within 0.25 s and stays in the band
    assert min(new) > -15e-9  # the push was taken back at the break-away: no slide past the target


def test_without_an_observer_the_rest_loop_is_the_pid_with_k_r_in_its_integrator(repo_root):
    """design.analyse_rest without an observer (dob_bandwidth_hz 0): the rest integral has the PID integrator's form,
    so the stuck loop is the full PID with K_i + K_r (one integrator, not two poles at z = 1, which read as an
    unstable loop); it crosses over near f_r on the stuck stage (|P| ≈ 1/Σk there) with PM near 90°."""
    import control

    from stagectl.config import load_app_config
    from stagectl.control.design import analyse, analyse_rest, pid_tf

    cfg = load_app_config(repo_root / "config" / "sim.yaml")
    c = cfg.controller
    fr = c.feedforward.model.friction
    k, damp = fr.stiffness_n_m, fr.damping_n_s_m
    args = (2.0, cfg.loop.period_s, c.pid, cfg.io.delay_cycles, 0.0, 0, k, damp, 0.0)
    f_r = 6.0
    with_ri = analyse_rest(*args, integrator_held=False, rest_integral_n_m_s=2 * math.pi * f_r * k)[0]
    # the same loop built here: the stuck stage (ZOH, the I/O delay) times the PID with K_i + K_r
    z = control.tf([1.0, 0.0], [1.0], cfg.loop.period_s)
    stuck = control.c2d(control.tf([1.0], [2.0, damp, k]), cfg.loop.period_s, "zoh") / z ** cfg.io.delay_cycles
    pid = dataclasses.replace(c.pid, ki_n_m_s=c.pid.ki_n_m_s + 2 * math.pi * f_r * k)
    same = analyse("direct", stuck * pid_tf(pid, cfg.loop.period_s), cfg.loop.period_s, 2000)
    assert with_ri.summary()["closed_loop_stable"]
    assert with_ri.crossover_hz == pytest.approx(f_r, rel=0.15)
    assert with_ri.phase_margin_deg > 70.0
    for key in ("phase_margin_deg", "gain_margin_db", "crossover_hz"):
        assert with_ri.summary()[key] == pytest.approx(same.summary()[key], rel=1e-6)


def _move_after_a_short_dwell_ahead(base, sync_on_start: bool) -> tuple[float, float, float, float]:
    """The controller without an observer stepped on positions written here (no plant): a 10 µm move followed
    exactly, 150 ms at rest with the stage stuck 150 nm ahead (the rest integral pulls it back through the PID
    integrator, its synchronisation hands part of that to the model), then a move on starts. Returns (the PID
    integrator at the end of the dwell, and after the move's first step; the force at that step; the model's
    force there) [N]."""
    from stagectl.control.api import Reference
    from stagectl.control.controller import StageController

    T = 1e-3
    cc = dataclasses.replace(base, feedforward=dataclasses.replace(base.feedforward, rest_sync_on_start=sync_on_start))
    ctl = StageController(cc, T)
    ctl.reset(0.0)
    ref = _move_10um(ctl, T)
    x_r = ref.x_m
    for _ in range(150):
        ctl.step(T, x_r + 150e-9, Reference(x_r))
    i_dwell = ctl.pid.state.i_n
    out = ctl.step(T, x_r + 150e-9, Reference(x_r, 1e-5, 0.0))
    return i_dwell, ctl.pid.state.i_n, out.force_n, ctl.state.u_ff_n


def test_without_an_observer_a_move_takes_the_rest_integrals_force_into_the_model(repo_root):
    """Without an observer the rest integral's force R sits in the PID integrator until the stop synchronisation has
    handed it to the model; a move that starts before that finished carried the rest of R in the integrator into the
    move, where only K_i·e unwinds it (fresh plant k105's matched twin: R = -0.53 N against a move forward at
    F_c = 0.85 N, the stage stuck 9 µm behind, then a following-error fault). On the move's start edge
    (``feedforward.rest_sync_on_start``) the rest is loaded into the model: the integrator keeps only the PID's own
    part, and the force moves from the integrator into the feed-forward."""
    from stagectl.config import load_app_config
    from stagectl.control.dob import DobConfig

    c = load_app_config(repo_root / "config" / "sim.yaml").controller
    base = dataclasses.replace(c, dob=DobConfig(kind="none"), rest_stiffness_fraction=0.0, rest_kd_fraction=1.0,
                               rest_dob_bandwidth_fraction=1.0, rest_spring_section_count=1, rest_integral_hz=6.0,
                               settle=dataclasses.replace(c.settle, move_s=0.0, ahead_stiffness_fraction=0.0))
    assert base.feedforward.rest_sync_hz > 0.0
    i_dwell, i_on, u_on, ff_on = _move_after_a_short_dwell_ahead(base, True)
    _, i_off, u_off, ff_off = _move_after_a_short_dwell_ahead(base, False)
    assert i_dwell < -0.05  # the stage ahead: pulled back, and the synchronisation has not loaded all of it yet
    assert i_off == pytest.approx(i_dwell, abs=1e-3)  # (false: carried into the move)
    assert abs(i_on) < 0.1 * abs(i_dwell)  # loaded into the model: the PID's own K_i·Σe·T is left
    assert ff_on - ff_off == pytest.approx(i_dwell, rel=0.1)  # the model holds it now
    assert u_on == pytest.approx(u_off, abs=0.1 * abs(i_dwell))  # the force on the stage barely moves


def _move_10um(ctl: Any, T: float) -> Any:
    """Runs ``ctl`` along a 10 µm jerk-limited move, the stage following the reference exactly, to the
    reference's rest (at least 5 samples); returns the reference at rest."""
    from stagectl.control.trajectory import Move, TrajectoryGenerator

    gen = TrajectoryGenerator(0.0)
    gen.queue(Move(by_m=10e-6, max_velocity_m_s=1e-3, max_acceleration_m_s2=0.05, max_jerk_m_s3=20.0))
    ref = gen.step(T)
    k = 0
    while ref.v_m_s != 0.0 or ref.a_m_s2 != 0.0 or k < 5:
        ctl.step(T, ref.x_m, ref)
        k += 1
        ref = gen.step(T)
    return ref
