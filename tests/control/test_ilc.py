"""Iterative learning control, pure part (stagectl.control.ilc): design check, update law on a lifted linear
plant (an independent time-domain simulation of the closed loop), robustness when the plant changes between
repetitions, the learner's ramp (bumpless on/off), freeze, and save/load."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stagectl.control.dob import DobConfig
from stagectl.control.ilc import (
    IlcConfig,
    IlcLearner,
    IlcPlant,
    Repetition,
    design_ilc,
    ilc_update,
    learning_window,
    process_sensitivity,
)
from stagectl.control.pid import PidConfig

T = 1e-3
PID = PidConfig(kp_n_m=3.92e4, ki_n_m_s=9.86e5, kd_n_s_m=468.0, derivative_cutoff_hz=200.0)
PLANT = IlcPlant(mass_kg=2.0, period_s=T, delay_samples=1, pid=PID, dob=DobConfig(kind="qfilter", bandwidth_hz=100.0))


def closed_loop_error(u_ilc: np.ndarray, r: np.ndarray, mass_kg: float, extra_delay: int = 0) -> np.ndarray:
    """Time-domain simulation of the discrete loop (independent of the frequency-domain design): ZOH rigid mass
    ``mass_kg`` with 1 + ``extra_delay`` samples of I/O delay, the PID of :mod:`stagectl.control.pid` (no
    observer), the learned force added to the command. Returns e = r − x per sample, two periods run, the
    second returned (periodic steady state)."""
    kp, ki, kd = PID.kp_n_m, PID.ki_n_m_s, PID.kd_n_s_m
    b = math.exp(-2 * math.pi * PID.derivative_cutoff_hz * T)
    n = r.size
    x = v = 0.0
    i_term = d_f = 0.0
    e_prev = 0.0
    pipe = [0.0] * (1 + extra_delay)
    out = np.zeros(n)
    for k in range(2 * n):
        j = k % n
        e = r[j] - x
        i_term += ki * e * T
        d_f = b * d_f + (1 - b) * (e - e_prev) / T
        e_prev = e
        u = kp * e + i_term + kd * d_f + u_ilc[j]
        pipe.append(u)
        ua = pipe.pop(0)
        # exact ZOH step of the mass
        x += v * T + 0.5 * ua / mass_kg * T * T
        v += ua / mass_kg * T
        if k >= n:
            out[j] = e
    return out


def test_process_sensitivity_matches_a_time_domain_simulation():
    """G at one frequency from the plain simulation (no observer: DOB kind none) equals the closed form."""
    plant = IlcPlant(2.0, T, 1, PID)
    n = 500
    f0 = 10.0 / (n * T)  # 20 Hz, on the DFT grid
    t = np.arange(n) * T
    u = 0.01 * np.sin(2 * math.pi * f0 * t)
    e = closed_loop_error(u, np.zeros(n), 2.0)
    g_sim = -np.fft.rfft(e)[10] / np.fft.rfft(u)[10]
    g = process_sensitivity(np.array([f0]), plant)[0]
    assert abs(g_sim - g) / abs(g) < 1e-3


def test_default_design_passes_the_convergence_check_and_the_scalar_lead_form_fails_it():
    d = design_ilc(IlcConfig(), PLANT, 1000)
    assert d.monotonic and d.rho < 1 and d.rho_robust < 1
    assert d.summary()["monotonic"] is True
    lead = design_ilc(IlcConfig(learning="lead"), PLANT, 1000)
    assert not lead.monotonic  # the compliance of a PI loop turns the phase by +90° at low frequency


def test_update_converges_on_a_linear_plant_with_a_wrong_mass():
    """The plant is 20 % heavier than the design model (and PID only): the error falls every repetition, down
    to what Q lets through."""
    plant = IlcPlant(2.0, T, 1, PID)
    n = 400
    t = np.arange(n) * T
    r = 2e-6 * (1 - np.cos(2 * math.pi * t / (n * T)))  # one period of a 2.5 Hz raised cosine
    d = design_ilc(IlcConfig(alpha=0.8, q_cutoff_hz=100.0), plant, n)
    u = np.zeros(n)
    norms = []
    for _ in range(8):
        e = closed_loop_error(u, r, 2.4)
        norms.append(float(np.linalg.norm(e)))
        u = ilc_update(u, e, d)
    assert all(b < a for a, b in zip(norms, norms[1:])), norms
    assert norms[-1] < 0.05 * norms[0], norms


def test_no_divergence_when_the_plant_changes_between_repetitions():
    """Mass alternately −20 % / +20 % and one extra sample of delay every third repetition: the learned force
    stays bounded, the error does not grow and stays well below the first pass (a signal right for both masses
    does not exist: with the default full inverse (α = 1) the error settles at 1/3 of the first pass)."""
    plant = IlcPlant(2.0, T, 1, PID)
    n = 400
    t = np.arange(n) * T
    r = 2e-6 * (1 - np.cos(2 * math.pi * t / (n * T)))
    d = design_ilc(IlcConfig(), plant, n)
    u = np.zeros(n)
    norms, u_norms = [], []
    for k in range(20):
        mass = 1.6 if k % 2 else 2.4
        e = closed_loop_error(u, r, mass, extra_delay=1 if k % 3 == 2 else 0)
        norms.append(float(np.linalg.norm(e)))
        u = ilc_update(u, e, d)
        u_norms.append(float(np.linalg.norm(u)))
    assert max(norms[5:]) < 0.4 * norms[0], norms
    assert max(norms[5:]) <= 1.05 * min(norms[5:]), norms  # no growth
    assert max(u_norms[10:]) < 1.5 * max(u_norms[:10]), u_norms


class _Rep:
    """A repetition source driven by hand: motion name, restart counter, time into it, length."""

    def __init__(self, length_s: float = 0.1):
        self.index = 1
        self.tau = 0.0
        self.length_s = length_s
        self.on = True

    def __call__(self) -> Repetition | None:
        return Repetition("scan", self.index, self.tau, self.length_s) if self.on else None


def _learner(tmp_path, **kw) -> tuple[IlcLearner, _Rep]:
    rep = _Rep()
    cfg = IlcConfig(enabled=True, store_dir=tmp_path, **kw)
    return IlcLearner(cfg, PLANT, rep, base_dir=tmp_path), rep


def _run_rep(lr: IlcLearner, rep: _Rep, e_fn=lambda i: 1e-8) -> list[float]:
    """One repetition's cycles (tau = 0 .. length); returns the outputs."""
    n = int(round(rep.length_s / T)) + 1
    out = []
    for i in range(n):
        rep.tau = i * T
        out.append(lr.step(i * T, e_fn(i)))
    rep.index += 1
    return out


def test_learner_ramps_in_and_out_and_freezes(tmp_path):
    lr, rep = _learner(tmp_path, ramp_s=0.05)
    lr.start()
    _run_rep(lr, rep)  # a first pass, learned from at the next boundary
    _run_rep(lr, rep)
    assert lr.iteration == 1 and np.abs(lr.u).max() > 0
    lr.u[:] = 1.0  # a known signal: the output is the ramp itself
    lr.stop()
    outs = _run_rep(lr, rep)
    steps = np.abs(np.diff([1.0, *outs]))
    assert steps.max() <= T / 0.05 + 1e-12 and outs[-1] == 0.0  # ramped out, never a step
    lr.start()
    outs = _run_rep(lr, rep)
    assert np.abs(np.diff([0.0, *outs])).max() <= T / 0.05 + 1e-12 and outs[-1] == pytest.approx(1.0)
    rep.tau = 0.02
    lr.step(0.0, 1e-8)  # the repetition before is complete: learned from here
    it, u_kept = lr.iteration, lr.u.copy()
    lr.freeze("emcy")
    assert lr.step(0.0, 1e-8) == 0.0 and lr.frozen == "emcy" and not lr.learning
    _run_rep(lr, rep)
    _run_rep(lr, rep)
    assert lr.iteration == it  # nothing learned from the repetition of the fault, nor after it
    np.testing.assert_array_equal(lr.u, u_kept)  # the learned signal is kept, unchanged
    lr.start()
    assert lr.frozen is None and lr.learning


def test_save_load_round_trip(tmp_path):
    lr, rep = _learner(tmp_path)
    lr.start()
    for _ in range(3):
        _run_rep(lr, rep, lambda i: 1e-8 * math.sin(i / 5))
    saved = lr.save()
    assert saved["saved"].endswith("scan.npz") and lr.iteration == 2
    other, _ = _learner(tmp_path)
    got = other.load("scan")
    assert got["samples"] == lr.u.size and other.iteration == 2
    np.testing.assert_array_equal(other.u, lr.u)
    assert other.rms_history == lr.rms_history
    with pytest.raises(ValueError, match="motion"):
        other.load("../etc/passwd")
    with pytest.raises(ValueError, match="no saved signal"):
        other.load("nothing")
    slow = IlcLearner(IlcConfig(store_dir=tmp_path), IlcPlant(2.0, 2e-3, 1, PID), _Rep(), base_dir=tmp_path)
    with pytest.raises(ValueError, match="period"):
        slow.load("scan")


def test_start_is_refused_when_the_convergence_check_fails(tmp_path):
    lr, _ = _learner(tmp_path, learning="lead")
    with pytest.raises(ValueError, match="convergence check"):
        lr.start()


def test_the_learned_force_decays_when_the_repeated_motion_is_taken_over(tmp_path):
    """A move request ends the repeated motion mid-way: the force ramps to 0 over ramp_s, no step."""
    lr, rep = _learner(tmp_path, ramp_s=0.02)
    lr.start()
    _run_rep(lr, rep)
    rep.tau = 0.0
    lr.step(0.0, 0.0)  # the new repetition begins (the last one is learned from here)
    lr.u[:] = 0.5
    lr.gain = 1.0
    rep.tau = 0.03
    u0 = lr.step(0.0, 0.0)
    assert u0 == 0.5
    rep.on = False
    outs = [lr.step(0.0, 0.0) for _ in range(30)]
    steps = np.abs(np.diff([u0, *outs]))
    assert steps.max() <= 0.5 * T / 0.02 + 1e-12 and outs[-1] == 0.0


def test_learning_window_opens_where_the_reference_moves_with_a_tail_and_smooth_edges():
    n = 1000
    moving = np.zeros(n, dtype=bool)
    moving[200:400] = True
    w = learning_window(moving, T, tail_s=0.05, taper_s=0.02)
    assert np.all((w >= 0) & (w <= 1))
    assert np.allclose(w[215:440], 1.0) and np.abs(w[:185]).max() < 1e-12 and np.abs(w[465:]).max() < 1e-12
    assert np.abs(np.diff(w)).max() < 0.1  # raised-cosine edges, no step
    assert not learning_window(np.zeros(n, dtype=bool), T, 0.05, 0.02).any()


def _circulant(h: np.ndarray, n: int) -> np.ndarray:
    """Dense matrix of the real circulant operator with rfft-grid response ``h``."""
    return np.stack([np.fft.irfft(h * np.fft.rfft(np.eye(n)[:, j]), n) for j in range(n)], axis=1)


def test_the_window_on_the_force_keeps_the_check_and_on_the_error_would_not():
    """Lifted (dense) oracle, plant 20 % heavier than the model: W·Q·(I − L·G), the update with the window on the
    learned force, has 2-norm ≤ max_f |Q·(1 − L·G)| (the check (3), 1 in the unlearned DC bin); windowing the
    error as well, W·Q·(I − L·W·G), exceeds 1: the window does not commute with L·G."""
    n = 96
    d = design_ilc(IlcConfig(), PLANT, n)
    g = process_sensitivity(d.freq_hz, PLANT, mass_kg=2.4)
    moving = np.zeros(n, dtype=bool)
    moving[20:50] = True
    W = np.diag(learning_window(moving, T, 0.01, 0.01))
    Q, L, G = _circulant(d.q, n), _circulant(d.learn, n), _circulant(g, n)
    bound = max(1.0, float(np.abs(d.q * (1 - d.learn * g)).max()))
    eye = np.eye(n)
    assert np.linalg.norm(W @ Q @ (eye - L @ G), 2) <= bound + 1e-9
    assert np.linalg.norm(W @ Q @ (eye - L @ W @ G), 2) > 1.0


def test_the_guard_rolls_an_update_back_and_halves_the_gain_when_the_error_grows(tmp_path):
    lr, rep = _learner(tmp_path)
    lr.start()
    sine = lambda a: (lambda i: a * math.sin(2 * math.pi * i / 50))  # noqa: E731
    for _ in range(3):
        _run_rep(lr, rep, sine(2e-8))  # each learned from at the next boundary
    assert lr.iteration == 2 and lr.gain_scale == 1.0 and lr.guard_rollbacks == 0
    u2 = lr.u.copy()
    _run_rep(lr, rep, sine(6e-8))  # repetition 3 learned from (u3); repetition 4: 3x the error, growth
    assert lr.iteration == 3 and not np.array_equal(lr.u, u2)
    rep.tau = 0.0
    lr.step(0.0, 0.0)  # the boundary: the grown repetition is judged
    assert lr.guard_rollbacks == 1 and lr.gain_scale == 0.5 and lr.iteration == 3
    np.testing.assert_array_equal(lr.u, u2)  # the last update rolled back
    assert lr.status()["guard_rollbacks"] == 1
