"""The constant-velocity passes' ramps come from an error budget, and keep a sticky stage inside it.

Oracle: a plain stage written here (mass; one elastoplastic Maxwell-slip element for the friction: stiffness K,
slipping at the Stribeck level F_c + (F_s − F_c)·exp(−(v/v_s)²), plus viscous; one cycle of I/O delay, 10
sub-steps a period), not the simulator, driven by the real ``StageController`` with the friction experiments'
tuning as the sequence builds it (the FRF's mass, 13 % low; a Coulomb feed-forward of 80 % of the probe's
breakaway). The stage is generated plant 35 (1.74 kg, F_c 0.68 N; K the sum of its GMS stiffnesses), whose
16 mm/s pass over the 2 mm stroke faulted on main (ramps 10 % of the pass, 1.28 m/s²): it stopped past its
end, stuck there with the observer wound up, and the pass back lurched out of the 50 µm band.
:func:`sequence.pass_budget` / :func:`sequence.pass_acceleration` take the ramp from
``e ≈ δm·m·a·g_step + (c + ΔF/v)·a·g_ramp ≤ e_max/2`` with the loop's gains computed from the tuning.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from stagectl.commission import sequence as seq
from stagectl.control import design
from stagectl.control.api import Reference
from stagectl.control.controller import ControllerConfig, FeedforwardConfig, StageController
from stagectl.control.dob import DobConfig

sys.path.insert(0, str(Path(__file__).parent))
from plain_stage import MaxwellSlipStage
from test_sticky_moves import _trapezoid

T = 1e-3
E_MAX = 50e-6
F_MAX = 7.0
# generated plant 35 and what the sequence knew of it when the passes ran (report.json of the main run)
STAGE = {"mass": 1.7393, "fs": 0.8735, "fc": 0.6822, "visc": 3.257, "vs": 0.00195, "k": 2.28e6,
         "m_est": 1.515, "m_probe": 1.666, "m_std": 0.031, "fb": (0.9643, 0.9013)}


def _tuning(m_est: float, ff_n: float) -> ControllerConfig:
    pid = design.design_pid(m_est, seq.COMMISSION_CROSSOVER_X_PERIOD / T, T, 1)
    return ControllerConfig(mass_kg=m_est, max_force_n=F_MAX, pid=pid, hold_integrator_at_rest=False,
                            stuck_dob_fraction=math.inf,
                            dob=DobConfig(kind="qfilter", bandwidth_hz=seq.COMMISSION_DOB_X_PERIOD / T,
                                          command_delay_samples=1),
                            feedforward=FeedforwardConfig(kind="coulomb", coulomb_n=ff_n, inertia=True,
                                                          inertia_lookahead=False))


def _peak_error_of_passes(a: float, v: float = 0.016, half_m: float = 1e-3) -> float:
    """Peak |x_ref - x| over a pass out and back at ``v`` (±``half_m``), ramps at ``a``; 0.1 s dwells."""
    st = STAGE
    ctl = StageController(_tuning(st["m_est"], seq.COULOMB_GUESS_FRACTION * min(st["fb"])), T)
    x = -half_m
    ctl.reset(x)
    refs = ([Reference(-half_m)] * 100 + _trapezoid(-half_m, half_m, v, a) + [Reference(half_m)] * 100
            + _trapezoid(half_m, -half_m, v, a))
    stage = MaxwellSlipStage(st, x0_m=x)
    peak = 0.0
    for ref in refs:
        u = ctl.step(T, stage.x, ref).force_n
        peak = max(peak, abs(ref.x_m - stage.x))
        stage.period(u, T)
    return peak


def test_loop_error_gains_match_a_plain_pid_observer_loop() -> None:
    """g_step, g_ramp against the closed loop's own numbers: a unit force step on the tuning's mass is held
    by P + I + observer; its peak lies between 1/(m·ω_c²)·0.3 and 1/K_p (P alone) and the ramp's peak is
    finite and below the step's over a 1 s horizon (the integrator and the observer both follow a ramp)."""
    cfg = _tuning(STAGE["m_est"], 0.0)
    g_step, g_ramp = seq.loop_error_gains(cfg, T, 1)
    wc = 2 * math.pi * seq.COMMISSION_CROSSOVER_X_PERIOD / T
    assert 0.3 / (STAGE["m_est"] * wc * wc) < g_step < 1.0 / cfg.pid.kp_n_m
    assert 0.0 < g_ramp < g_step


def test_pass_ramps_from_the_budget_keep_a_sticky_stage_inside_half_the_band() -> None:
    st = STAGE
    v, L = 0.016, 2e-3
    a_old = min(v * v / (0.1 * L), 0.3 * F_MAX / st["m_est"])  # main's rule: ramps 10 % of the pass
    # as the sequence: a sticky stage (ρ = 4.3 > STICKY_FF_OFF_RATIO) is given no credit for the flip
    b = seq.pass_budget(_tuning(st["m_est"], 0.0), T, 1, st["m_probe"], st["m_std"], max(st["fb"]), 0.0, E_MAX)
    a = seq.pass_acceleration(a_old, v, b)
    assert a < 0.5 * a_old
    assert seq.pass_acceleration(a_old, v, b) == a
    new = _peak_error_of_passes(a)
    assert new <= 0.5 * E_MAX, new
    # the oracle can fail: main's ramps take the same stage past half the limit
    old_peak = _peak_error_of_passes(a_old)
    assert old_peak > 0.5 * E_MAX
    # the sequence does not run the budget's 0.20 m/s² on this pass: the readability floor (0.505 m/s², a
    # 2 mm pass at 16 mm/s) binds, and there the pass peaks past half the band (29.5 µm), inside the limit
    a_seq = seq.pass_acceleration(a_old, v, b, seq.readable_acceleration(v, L, T))
    assert a_seq == seq.readable_acceleration(v, L, T) > 2 * a
    seq_peak = _peak_error_of_passes(a_seq)
    assert 0.5 * E_MAX < seq_peak < min(old_peak, E_MAX), (seq_peak, old_peak)


def test_pass_budget_leaves_a_heavy_stage_and_a_slow_pass_alone() -> None:
    """Only where the budget needs it: a 7 kg stage (gen 37-like, breakaway 1.2 N, the flip credited) keeps
    main's ramps on its fastest pass, and a 2.5 mm/s pass keeps its 10 %-of-the-pass ramps on plant 35."""
    heavy = seq.pass_budget(_tuning(6.8, 0.0), T, 1, 7.0, 0.05, 1.18, 2 * seq.COULOMB_GUESS_FRACTION, E_MAX)
    a_heavy = min(0.016 ** 2 / (0.1 * 2e-3), 0.3 * F_MAX / 6.8)
    assert seq.pass_acceleration(a_heavy, 0.016, heavy) == a_heavy
    st = STAGE
    b = seq.pass_budget(_tuning(st["m_est"], 0.0), T, 1, st["m_probe"], st["m_std"], max(st["fb"]), 0.0, E_MAX)
    a_25 = max(0.0025 ** 2 / (0.1 * 2e-3), 0.02)
    assert seq.pass_acceleration(a_25, 0.0025, b) == a_25
