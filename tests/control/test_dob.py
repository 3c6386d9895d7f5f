"""Disturbance observers: convergence, bandwidth, Kalman gain vs filterpy, dlqe predictor-form conversion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stagectl.control.dob import DobConfig, KalmanDob, QFilterDob, make_dob

M = 2.0
DT = 1e-4


def _simulate(dut, d_n: float, n: int, u_fn=lambda k: 0.0, m: float = M, dt: float = DT) -> np.ndarray:
    """Exact ZOH mass m·ẍ = u − d; the observer gets the position, the backward-difference velocity and u."""
    x = v = 0.0
    x_prev = 0.0
    u_prev = 0.0
    est = np.empty(n)
    for k in range(n):
        v_hat = (x - x_prev) / dt if k else 0.0
        est[k] = dut.step(dt, x, v_hat, u_prev)
        u = u_fn(k)
        a = (u - d_n) / m
        x_prev = x
        x, v = x + v * dt + a * dt * dt / 2, v + a * dt
        u_prev = u
    return est


@pytest.mark.parametrize("kind", ["qfilter", "kalman"])
def test_constant_disturbance_is_estimated(kind):
    dut = make_dob(DobConfig(kind=kind, bandwidth_hz=50.0, command_delay_samples=0), M, DT)
    dut.reset(0.0)
    est = _simulate(dut, 0.7, 2000, u_fn=lambda k: 0.3 * math.sin(2 * math.pi * 5 * k * DT))
    assert est[-1] == pytest.approx(0.7, rel=1e-3)
    assert dut.state.d_hat_n == est[-1]


def test_qfilter_step_response_has_the_configured_bandwidth():
    g = 2 * math.pi * 50.0
    dut = QFilterDob(DobConfig(kind="qfilter", bandwidth_hz=50.0, command_delay_samples=0), M)
    dut.reset(0.0)
    est = _simulate(dut, 1.0, 400)
    k = int(round(1.0 / g / DT))  # one time constant 1/g
    assert est[k] == pytest.approx(1 - math.exp(-1), abs=0.05)
    k5 = int(round(5.0 / g / DT))
    assert est[k5] == pytest.approx(1.0, abs=0.02)


def test_qfilter_retune_keeps_estimate():
    """Change the bandwidth mid-run while the mass accelerates: d̂ continues without a jump."""
    dut = QFilterDob(DobConfig(kind="qfilter", bandwidth_hz=50.0, command_delay_samples=0), M)
    dut.reset(0.0)
    x = v = x_prev = 0.0
    u, d = 1.0, 0.4
    est = []
    for k in range(1000):
        if k == 600:
            dut.retune(DobConfig(kind="qfilter", bandwidth_hz=120.0, command_delay_samples=0), M)
        v_hat = (x - x_prev) / DT if k else 0.0
        est.append(dut.step(DT, x, v_hat, u if k else 0.0))
        a = (u - d) / M
        x_prev = x
        x, v = x + v * DT + a * DT * DT / 2, v + a * DT
    assert est[599] == pytest.approx(d, rel=1e-6)  # exact discrete form: no bias under acceleration
    assert abs(est[600] - est[599]) < 1e-6
    assert est[-1] == pytest.approx(d, rel=1e-6)


def test_kalman_gain_matches_filterpy_converged_gain():
    from filterpy.kalman import KalmanFilter

    from stagectl.control.design import _kalman_matrices, kalman_gain_for_noise

    r, q = 1e-8, 0.05  # well-conditioned numbers (with r = 1 nm the plain iteration loses ~3 digits)
    K, P = kalman_gain_for_noise(M, 1e-3, r, q)
    A, B, C = _kalman_matrices(M, 1e-3)
    kf = KalmanFilter(dim_x=3, dim_z=1, dim_u=1)
    kf.F, kf.B, kf.H = A, B, C
    kf.Q = np.diag([0.0, 0.0, q * q * 1e-3])
    kf.R = np.array([[r * r]])
    kf.P = np.eye(3) * 1e-6
    for _ in range(2000):
        kf.predict(u=np.array([[0.0]]))
        kf.update(np.array([[0.0]]))
    assert np.allclose(K, kf.K[:, 0], rtol=1e-5, atol=0)


def test_dlqe_predictor_gain_is_converted_to_filter_form():
    import control

    from stagectl.control.design import _kalman_matrices, kalman_gain_for_noise

    K, _ = kalman_gain_for_noise(M, 1e-3, 1e-9, 50.0)
    K_ctl, _ = kalman_gain_for_noise(M, 1e-3, 1e-9, 50.0, use_control=True)
    assert np.allclose(K, K_ctl, rtol=1e-6)  # scipy DARE (loop process) == converted dlqe (tune)
    A, _, C = _kalman_matrices(M, 1e-3)
    L, _, _ = control.dlqe(A, np.eye(3), C, np.diag([0, 0, 2500 * 1e-3]), np.array([[1e-18]]))
    L = np.asarray(L)[:, 0]
    assert np.allclose(A @ K, L, rtol=1e-6)
    assert not np.allclose(K, L, rtol=1e-2)  # using L directly would be wrong
    # the filter error dynamics (I - K C) A are stable
    assert np.all(np.abs(np.linalg.eigvals((np.eye(3) - np.outer(K, C[0])) @ A)) < 1)


def test_kalman_bandwidth_from_config():
    from stagectl.control.design import observer_bandwidth_hz

    dut = KalmanDob(DobConfig(kind="kalman", bandwidth_hz=30.0), M, 1e-3)
    assert observer_bandwidth_hz(np.array(dut.K), M, 1e-3) == pytest.approx(30.0, rel=1e-3)
    fast = KalmanDob(DobConfig(kind="kalman", bandwidth_hz=90.0), M, 1e-3)
    assert abs(fast.K[2]) > abs(dut.K[2])


def test_command_delay_matches_a_delayed_actuator():
    """With an actuator that applies u one sample late, the delay-matched observer is exact."""
    cfg = DobConfig(kind="qfilter", bandwidth_hz=50.0, command_delay_samples=1)
    dut = QFilterDob(cfg, M)
    dut.reset(0.0)
    x = v = x_prev = 0.0
    u_hist = [0.0, 0.0]
    errs = []
    for k in range(3000):
        v_hat = (x - x_prev) / DT if k else 0.0
        d = dut.step(DT, x, v_hat, u_hist[-1])
        errs.append(d - 0.2)
        u = 0.5 * math.sin(2 * math.pi * 3 * k * DT)
        u_hist.append(u)
        a = (u_hist[-2] - 0.2) / M  # applied one sample late
        x_prev = x
        x, v = x + v * DT + a * DT * DT / 2, v + a * DT
    assert abs(errs[-1]) < 1e-3


@pytest.mark.parametrize("dt", [0.0, -1e-4, math.nan])
@pytest.mark.parametrize("kind", ["qfilter", "kalman"])
def test_bad_dt_raises(kind, dt):
    dut = make_dob(DobConfig(kind=kind), M, 1e-3)
    with pytest.raises(ValueError, match="dt"):
        dut.step(dt, 0.0, 0.0, 0.0)


def test_none_kind_builds_nothing():
    assert make_dob(DobConfig(kind="none"), M, 1e-3) is None


def _noise_impulse(period_s: float | None, n: int = 5000) -> float:
    """Net force impulse [N·s] of a Q-filter observer fed only encoder noise (±1 count of 1 nm, no motion, no
    force) at intervals jittered by ±0.2 T, each estimate held for a period."""
    import random

    rng = random.Random(3)
    dob = QFilterDob(DobConfig(kind="qfilter", bandwidth_hz=100.0, command_delay_samples=0), M, period_s)
    dob.reset(0.0)
    x_prev = total = 0.0
    for _ in range(n):
        dt = 1e-3 * (1.0 + rng.uniform(-0.2, 0.2))
        x = 1e-9 * rng.choice((-1, 0, 1))
        total += dob.step(dt, x, (x - x_prev) / dt, 0.0) * 1e-3
        x_prev = x
    return total


def test_qfilter_noise_leaves_no_net_impulse_under_jittered_sampling():
    """Stepped with the period's coefficients whatever the interval (``period_s``), the observer's response to the
    encoder noise, a second difference of the position, telescopes: its net impulse stays at the size of one
    sample's response; with α and K_v following the jittered interval each sample leaves a net impulse and the
    sum grows (a low-frequency force noise: the pre-sliding cosine's error under jitter, bench timing)."""
    per_sample = abs(_noise_impulse(1e-3))
    following = abs(_noise_impulse(None))
    # one sample's response: K_v·|Δv̂| over the filter's time constant, |Δv̂| ≤ 2 counts / 0.8 T
    one = 2.0 * (1.0 - math.exp(-2 * math.pi * 100.0 * 1e-3)) / 1e-3 * 2.5e-6 / (2 * math.pi * 100.0)
    assert per_sample < one
    assert following > 3.0 * per_sample, (following, per_sample)


@pytest.mark.parametrize("a_ref", [True, False])
def test_qfilter_skipped_interval_under_acceleration(a_ref):
    """A rigid mass accelerating under a constant net force, sampled every T with one interval of 2T (a skipped
    slot): stepped with T's coefficients the observer expects the velocity change of a period; told the
    reference's acceleration it takes off the change of the extra time and the estimate stays exact, else it
    is off by a fraction of the net force for two steps."""
    T = 1e-3
    dob = QFilterDob(DobConfig(kind="qfilter", bandwidth_hz=100.0, command_delay_samples=0), M, T)
    dob.reset(0.0)
    tau, u = 0.3, 0.5
    acc = (u - tau) / M
    t = x_prev = 0.0
    err = []
    for k in range(300):
        dt = 2 * T if k == 200 else T
        t += dt
        x = 0.5 * acc * t * t
        d = dob.step(dt, x, (x - x_prev) / dt, u, acc if a_ref else 0.0)
        x_prev = x
        if k >= 150:
            err.append(abs(d - tau))
    if a_ref:
        assert max(err) < 1e-9
    else:
        assert max(err) > 0.1 * (u - tau)


@pytest.mark.parametrize("kind", ["none", "kalman"])
def test_a_qfilter_switched_on_in_a_slowed_down_loop_gets_its_period(repo_root, kind):
    """A retune that builds a new Q-filter observer while the loop is slowed down (``set_timing_scale`` s = 2) gives
    it the period s·T and the scaled bandwidth, as the running observer has (before, it got T: it stepped with the
    period's coefficients for a loop that samples at 2T until the next change of the scale)."""
    import dataclasses

    from stagectl.config import load_app_config
    from stagectl.control.controller import StageController

    cfg = load_app_config(repo_root / "config" / "sim.yaml")
    T = cfg.loop.period_s
    c = cfg.controller
    assert c.dob.kind == "qfilter"
    ref = StageController(c, T)
    ref.set_timing_scale(2.0)
    ctl = StageController(dataclasses.replace(c, dob=dataclasses.replace(c.dob, kind=kind)), T)
    ctl.set_timing_scale(2.0)
    ctl.retune(c)
    assert isinstance(ctl.dob, QFilterDob) and isinstance(ref.dob, QFilterDob)
    assert ctl.dob.period_s == ref.dob.period_s == 2 * T
    assert ctl.dob.cfg.bandwidth_hz == ref.dob.cfg.bandwidth_hz == c.dob.bandwidth_hz / 2


def _slowed_pair(perturb_after_retune: bool) -> tuple[QFilterDob, float, float]:
    """An observer at T, then slowed down ×3 (period 3T, bandwidth /3: as ``set_timing_scale``), sampled on time at
    T on a rigid mass under a constant force u against a disturbance τ; optionally one interval of 1.001 T right
    after the retune. Returns the observer, τ and the mass's acceleration."""
    T = 1e-3
    cfg = DobConfig(kind="qfilter", bandwidth_hz=100.0, command_delay_samples=0)
    dob = QFilterDob(cfg, M, T)
    dob.reset(0.0)
    tau, u = 0.3, 0.5
    acc = (u - tau) / M
    t = x_prev = 0.0
    for k in range(400):
        if k == 100:
            dob.period_s = 3 * T
            dob.retune(DobConfig(kind="qfilter", bandwidth_hz=100.0 / 3, command_delay_samples=0), M)
        dt = 1.001 * T if (perturb_after_retune and k == 101) else T
        t += dt
        x = 0.5 * acc * t * t
        dob.step(dt, x, (x - x_prev) / dt, u if k >= 150 else 0.0, acc)
        x_prev = x
    return dob, tau, acc


def test_qfilter_retune_follows_the_period_whatever_the_intervals():
    """A retune after the period changed (``set_timing_scale``) designs the filter for the new period P at once,
    whatever the last interval was: an interval of 1.001 T after it changes the estimate by < 1e-6 of the force,
    not the filter (before: the retune kept the old period's α, K_v until the first interval that differed from the
    last one, so the observer of a loop slowed down with on-time samples ran with T's coefficients, and with P's
    after any late sample: at the end the perturbed one estimated the 0.3 N disturbance, the other −0.1 N, its
    reference-acceleration term made for P's steps)."""
    a, _, _ = _slowed_pair(False)
    b, _, _ = _slowed_pair(True)
    assert a._c_dt == b._c_dt == 3e-3
    assert abs(a.state.d_hat_n - b.state.d_hat_n) < 1e-6


def test_qfilter_slowed_down_on_time_runs_at_its_designed_rate():
    """Period 3T, sampled at T (a loop whose slow-down level lags its samples): each sample takes the part f = h̄/P
    = 1/3 of a step of P's filter, 1 − a = (1 − α_P)/3, with P's K_v: the estimate of a rigid mass's disturbance
    stays exact under any force (no mass error: a full step of P's filter per sample would have run the observer 3×
    faster with K_v a third of the one the samples need), and a step in the disturbance is followed with that
    decay per sample."""
    T = 1e-3
    P = 3 * T
    cfg = DobConfig(kind="qfilter", bandwidth_hz=100.0 / 3, command_delay_samples=0)
    dob = QFilterDob(DobConfig(kind="qfilter", bandwidth_hz=100.0, command_delay_samples=0), M, T)
    dob.reset(0.0)
    dob.period_s = P
    dob.retune(cfg, M)
    a_exp = 1.0 - (1.0 - math.exp(-2 * math.pi * 100.0 / 3 * P)) / 3
    x = v = x_prev = 0.0
    errs = []
    for k in range(400):
        tau = 0.2 if k >= 200 else 0.0  # (applied from step 200's interval on)
        u = 0.5 * math.sin(0.05 * k)
        d = dob.step(T, x, (x - x_prev) / T if k else 0.0, u_prev if k else 0.0)
        if 150 <= k < 200:
            assert abs(d) < 1e-9  # exact under a varying force: no inertia in the estimate
        if k >= 202:
            errs.append(abs(d - 0.2))
        assert dob.step_fraction == pytest.approx(1 / 3 if k else 1.0, rel=1e-12)
        acc = (u - tau) / M
        x_prev = x
        x, v = x + v * T + 0.5 * acc * T * T, v + acc * T
        u_prev = u
    ratios = np.array(errs[1:20]) / np.array(errs[:19])
    assert ratios == pytest.approx(a_exp, rel=1e-6)


def test_kalman_observer_decay_is_not_slowed_down_with_the_loop(repo_root):
    """``set_timing_scale`` leaves a Kalman observer's bandwidth as it is; the filters the controller matches to
    the observer (rest spring, the learners' gate: ``StageController._dob_decay``) then decay at its bandwidth, as
    the stuck-stage limit does (``_d_g``), not at f_DOB/s (before: exp(−2π·f_DOB/3·T) at s = 3)."""
    import dataclasses

    from stagectl.config import load_app_config
    from stagectl.control.api import Reference
    from stagectl.control.controller import StageController

    cfg = load_app_config(repo_root / "config" / "sim.yaml")
    T = cfg.loop.period_s
    c = cfg.controller
    ctl = StageController(dataclasses.replace(c, dob=dataclasses.replace(c.dob, kind="kalman")), T)
    ctl.set_timing_scale(3.0)
    ctl.step(T, 0.0, Reference(1e-6, 1e-3, 0.0))
    assert isinstance(ctl.dob, KalmanDob) and ctl.dob.cfg.bandwidth_hz == c.dob.bandwidth_hz
    a = math.exp(-2.0 * math.pi * c.dob.bandwidth_hz * T)
    assert ctl._dob_decay(T) == pytest.approx(a, rel=1e-12)
    assert ctl._dob_decay(3 * T) == pytest.approx(a**3, rel=1e-12)


def test_qfilter_period_set_after_construction_takes_partial_steps():
    """``period_s`` is a public attribute: an observer built without one and given P later keeps the mean span
    from there (h̄ starts at P), as one built with P: partial steps on samples at P/3 (before, h̄ stayed NaN and
    every sample took a whole step)."""
    cfg = DobConfig(kind="qfilter", bandwidth_hz=50.0, command_delay_samples=0)
    p = 3e-3
    late = QFilterDob(cfg, M)
    late.period_s = p
    late.retune(cfg, M)
    built = QFilterDob(cfg, M, p)
    for _ in range(50):
        assert late.step(p / 3.0, 0.0, 0.0, 1.0) == built.step(p / 3.0, 0.0, 0.0, 1.0)
    assert late.step_fraction == built.step_fraction < 0.5
