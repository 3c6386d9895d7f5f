"""The commissioning analyses against plain reference implementations (no loop, milliseconds each)."""

from __future__ import annotations

import itertools
from collections.abc import Callable
import math

import numpy as np
import pytest
from scipy import signal

from stagectl.commission import analysis as an
from stagectl.commission.controllers import SanityProbe, log_bins, multisine, probe_levels
from stagectl.control import design
from stagectl.errors import DataError, StageError
from stagectl.recorder import Recorder


def _closed_loop_record(m: float, k: float, c: float, delay: int, T: float, n_per: int, periods: int,
                        seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plain reference: exact ZOH discretisation of m x'' + c x' + k x = u(t − delay·T), a PD controller
    holding x = 0, a known multisine d added to its output, 0.5 nm sensor noise."""
    sysd = signal.cont2discrete((np.array([[0, 1], [-k / m, -c / m]]), np.array([[0], [1 / m]]),
                                 np.array([[1, 0]]), np.array([[0]])), T, method="zoh")
    A, B = sysd[0], sysd[1]
    bins = log_bins(n_per, 2, int(0.45 * n_per), 40)
    d = np.tile(multisine(n_per, bins, 0.05), periods)
    rng = np.random.default_rng(seed)
    s = np.zeros((2, 1))
    q = [0.0] * delay
    x_out, u_out = np.zeros(d.size), np.zeros(d.size)
    xp = 0.0
    for i in range(d.size):
        x = float(s[0, 0]) + 0.5e-9 * rng.standard_normal()
        u = -2e4 * x - 150.0 * (x - xp) / T + d[i]
        xp = x
        x_out[i], u_out[i] = x, u
        q.append(u)
        s = A @ s + B * q.pop(0)
    return x_out, u_out, bins


def test_frf_fit_recovers_mass_delay_and_stiffness() -> None:
    T, n_per = 1e-3, 500
    x, u, bins = _closed_loop_record(m=3.0, k=2e5, c=30.0, delay=1, T=T, n_per=n_per, periods=5)
    frf = an.estimate_frf(x, u, n_per, bins, T)
    fit = an.fit_plant(frf, T, mass_guess_kg=1.5)
    assert fit.mass_kg == pytest.approx(3.0, rel=0.02)
    assert fit.delay_s == pytest.approx(1e-3, abs=0.05e-3)
    # the resonance from the first pass over every line, which locates it (fit_plant's docstring). The reported
    # stiffness is the mass band's (150-450 Hz here, well above f0 = 41 Hz), where k is loose: 2.75e5 N/m on one
    # machine, 2e5 on another (a known limit, docs/commissioning.md), so it is not asserted to 10 %.
    ok = frf.p_std / np.maximum(np.abs(frf.p), 1e-300) < 0.3
    th, _sd, _rms, _n = an._fit_band(frf, ok, T, 1.5)
    f0 = math.sqrt(th[2] / math.exp(th[0])) / (2 * math.pi)
    assert f0 == pytest.approx(math.sqrt(2e5 / 3.0) / (2 * math.pi), rel=0.02)
    assert fit.presliding_resonance_hz == pytest.approx(f0, rel=0.5)
    assert fit.mass_std_kg < 0.05 * fit.mass_kg
    assert fit.resonances_hz == []


def test_measured_margins_agree_with_python_control_on_an_exact_frf() -> None:
    T, m = 1e-3, 2.0
    pid = design.design_pid(m, 25.0, T, 1)
    f = np.logspace(0, math.log10(450), 400)
    p = an.plant_response(f, m, 0.0, 0.0, T, T)   # ZOH mass + one sample of delay, as design.plant_tf
    K = an.controller_response(f, T, pid, "none", 100.0, m, 1)
    ours = an.margins_from_response(f, p * K)
    ref = design.analyse_design(m, T, pid, 1)[0]
    assert ours.phase_margin_deg == pytest.approx(ref.phase_margin_deg, abs=1.0)
    assert ours.gain_margin_db == pytest.approx(ref.gain_margin_db, abs=0.3)


def _drive_probe(sign: int, m: float = 2.0, f_c: float = 0.5, f_lim: float = 4.0,
                 f_acc: float | None = None, v_stop: float = 0.02) -> SanityProbe:
    """The probe against a plain mass with Coulomb friction whose force input has the given sign."""
    T = 1e-3
    probe = SanityProbe(f_lim_n=f_lim, d_detect_m=2e-5, d_acc_m=1e-4, v_stop_m_s=v_stop, f_acc_n=f_acc)
    x = v = 0.0
    probe.reset(x)
    for _ in range(20000):
        u = sign * probe.step(T, x)
        if probe.done:
            break
        f = u - f_c * np.sign(v) if v != 0 else (0.0 if abs(u) <= f_c else u - f_c * np.sign(u))
        v_new = v + f / m * T
        if v != 0 and np.sign(v_new) != np.sign(v) and abs(u) <= f_c:
            v_new = 0.0
        x += 0.5 * (v + v_new) * T
        v = v_new
    return probe


def test_sanity_probe_measures_the_mass_and_catches_a_wrong_sign() -> None:
    ok = _drive_probe(+1)
    res = an.evaluate_probe(ok.dirs, ok.f_lim, ok.d_detect, expected_mass_kg=2.0)
    assert res.mass_kg == pytest.approx(2.0, rel=0.1)
    # the force when the motion is detected: above the true breakaway by the ramp during the detection travel
    assert 0.5 <= min(res.breakaway_n) <= 0.7
    bad = _drive_probe(-1)
    with pytest.raises(an.SanityError, match="wrong sign"):
        an.evaluate_probe(bad.dirs, bad.f_lim, bad.d_detect, expected_mass_kg=2.0)
    with pytest.raises(an.SanityError, match="scale"):
        an.evaluate_probe(ok.dirs, ok.f_lim, ok.d_detect, expected_mass_kg=20.0)


def test_a_probe_stopped_by_the_velocity_cap_names_max_velocity() -> None:
    """`commission --max-velocity 1e-4` (0.1 mm/s) on the seed stage: each acceleration level ends at the speed
    cap within a few samples, so no mass is measured; the message must name the cap that did it (it advised
    only --max-stroke or --max-force)."""
    slow = _drive_probe(+1, v_stop=0.9 * 0.8 * 1e-4)
    with pytest.raises(an.SanityError) as err:
        an.evaluate_probe(slow.dirs, slow.f_lim, slow.d_detect, None, v_stop_m_s=slow.v_stop)
    msg = str(err.value)
    assert "--max-velocity" in msg and "7.2e-05 m/s" in msg and "\n" not in msg, msg


def test_probe_levels_scale_with_the_breakaway_and_the_force_cap() -> None:
    # room under the cap: 1.5 and 2.5 x the breakaway (the levels of every stage that fitted before)
    assert probe_levels(1.0, 7.0) == pytest.approx((1.5, 2.5))
    # a high-friction stage: the headroom above F_b, split 1 : 3, both levels above F_b and apart
    f1, f2 = probe_levels(2.2, 3.5)
    assert 2.2 < f1 < f2 == 3.5 and f2 >= 1.2 * f1
    # a 1.67 kg stage with 1.9 N Coulomb friction: under F_max/2 = 3.5 N only, the old fixed multiples gave no
    # mass; the levels scaled up to F_max = 7 N measure it
    ok = _drive_probe(+1, m=1.67, f_c=1.9, f_lim=3.5, f_acc=7.0)
    assert an.evaluate_probe(ok.dirs, ok.f_lim, ok.d_detect, None).mass_kg == pytest.approx(1.67, rel=0.1)
    tight = _drive_probe(+1, m=1.67, f_c=1.9, f_lim=2.2, f_acc=2.2)
    with pytest.raises(an.SanityError, match="too little force under the cap"):
        an.evaluate_probe(tight.dirs, tight.f_lim, tight.d_detect, None)


def test_frf_amplitude_keeps_a_sliding_stage_in_the_following_error_band() -> None:
    """The predicted peak error against a plain time-domain simulation of the linear loop (python-control),
    and the amplitude rule: nominal on a heavy stage, scaled down on a light one."""
    import control

    T, n_per, fe = 1e-3, 1000, 50e-6
    bins = log_bins(n_per, 2, int(0.45 * n_per), 60)
    wave = multisine(n_per, bins, 1.0)
    f = bins / (n_per * T)
    nominal = 0.08 * 7.0 * math.sqrt(2.0 / bins.shape[0])

    def amp(m: float, fb: float, fe_m: float = fe) -> tuple[an.FrfAmplitude, object, object]:
        pid = design.design_pid(m, 15.0, T, 1)
        K = an.controller_response(f, T, pid, "qfilter", 50.0, m, 1)
        a = an.frf_amplitude(wave, bins, nominal, T, m, K, 1.5 * T, fb, fe_m, 1e-9)
        Hu, Hy = design.qfilter_tfs(m, 50.0, T, 1)
        return a, design.plant_tf(m, T, 1), (design.pid_tf(pid, T) + Hy) / (1 - Hu)

    heavy, _, _ = amp(5.2, 0.5)
    assert heavy.amplitude_n == nominal and heavy.limit == "nominal"
    # a 2 kg stage with 0.97 N breakaway slides clearly under the nominal 2 N peak and keeps it
    assert amp(2.0, 0.97)[0].limit == "nominal"
    # frictionless 0.8 kg: scaled to 0.6 following-error limits ...
    light, P, K = amp(0.8, 0.0)
    assert light.amplitude_n < 0.6 * nominal and light.limit == "sliding error"
    assert light.predicted_peak_error_m == pytest.approx(an.FRF_SLIDE_ERROR_X_FE * fe)
    # ... checked against the frictionless mass under the loop, three periods, peak of the last
    t = np.arange(3 * n_per) * T
    resp = control.forced_response(control.feedback(P, K), t, np.tile(wave * light.amplitude_n, 3))
    peak = float(np.abs(np.asarray(resp.outputs)[-n_per:]).max())
    assert peak == pytest.approx(light.predicted_peak_error_m, rel=0.15)
    assert peak < fe
    # light stages with much friction (0.80 kg / 0.78 N, 1.26 kg / 1.66 N): no sliding amplitude keeps the band
    # without stick-slip, so the peak force stays at half the breakaway
    for m, fb in ((0.8, 0.78), (1.26, 1.66)):
        sticky, _, _ = amp(m, fb)
        assert sticky.limit == "breakaway" and sticky.peak_force_n == pytest.approx(an.FRF_STICK_X_BREAKAWAY * fb)
    with pytest.raises(StageError, match="frf: the largest safe multisine"):
        amp(0.8, 0.0, fe_m=1e-9)


# ---------------------------------------------------------------------------------------- pre-sliding fit
#: a GMS stage for the pre-sliding tests: the shipped model's elements at Fs = 1.3 N, no micro-damping
_GMS = {"model": "gms", "k_n_m": [454610.0, 111088.0, 45601.0, 16402.0, 6899.0, 4295.0],
        "alpha": [0.378, 0.138, 0.148, 0.177, 0.112, 0.047], "fs_n": 1.3, "fc_n": 1.15, "vs_m_s": 1e-3,
        "delta": 2.0, "c_n_s": 1e8, "viscous_n_s_m": 0.0, "sigma1_n_s_m": 0.0}


def _loops_path(T: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A long move, then loops of log-spaced travel back and forth (the commissioning's pre-sliding
    experiment): the true path, and as measured with 0.5 nm noise and 1 nm quantisation."""
    pts = [0.0, 300e-6]
    for A in (25e-6 / 2 ** i for i in range(6)):
        pts += [300e-6 - A, 300e-6]
    x = [np.zeros(1)]
    for a, b in itertools.pairwise(pts):
        n = max(int(0.75 / T) if abs(b - a) < 100e-6 else int(1.0 / T), 2)
        s = np.linspace(0.0, 1.0, n)
        x.append(a + (b - a) * (1 - np.cos(np.pi * s[1:])) / 2)
        x.append(np.full(50, b))
    xs = np.concatenate(x)
    rng = np.random.default_rng(seed)
    return xs, np.round((xs + 0.5e-9 * rng.standard_normal(xs.shape)) / 1e-9) * 1e-9


def test_play_operator_is_the_gms_along_a_noisy_path() -> None:
    """Oracle: Σ k_i·z_i of the play (fit._play) with the true break-aways is the GMS force (C → ∞, no
    damping) along a measured, noisy, quantised path, where the sensor noise reverses the increment at
    every standstill (a direction from a central difference was 10 mN off here)."""
    from stagectl.commission.fit import _play
    from stagectl.friction import build

    T = 1e-3
    x = _loops_path(T, 0)[1]
    t = np.arange(x.shape[0]) * T
    gms = build(_GMS).force_along(x, t)
    k = np.array(_GMS["k_n_m"])
    deltas = np.array(_GMS["alpha"]) * 1.3 / k
    vb = np.concatenate([[0.0], np.diff(x) / T])
    g = 1.15 + 0.15 * np.exp(-(vb / 1e-3) ** 2)
    assert np.abs(_play(x, deltas, g / 1.3) @ k - gms).max() < 1e-6


def test_play_on_the_interpolated_path_keeps_the_turning_points_between_samples() -> None:
    """After a fast move the stage rings (85 Hz here, 12 samples a period) with turning points between the
    1 kHz samples. Reference: the GMS (``force_along``) on the path at 10 µs, read at the samples. The play on
    the samples misses the extrema and keeps a state offset through the rest that follows; on the path
    spline-interpolated to PRESLIDING_UPSAMPLE points a period it stays within half of that."""
    from stagectl.commission.fit import PRESLIDING_UPSAMPLE, _play, upsample_path
    from stagectl.friction import build

    T, up = 1e-3, 100
    t = np.arange(int(0.6 / T) * up + 1) * (T / up)
    w = 2 * np.pi * 85.0
    # a 40 µm move (ends at t = 0.1 s), decaying ringing of 3 µm (it slips the stiff elements), then a rest and a slow 1 µm creep back
    move = 40e-6 * np.clip(t / 0.1, 0.0, 1.0) ** 2 * (3 - 2 * np.clip(t / 0.1, 0.0, 1.0))
    ring = np.where(t > 0.1, 3e-6 * np.exp(-(t - 0.1) / 0.04) * np.sin(w * (t - 0.1)), 0.0)
    creep = -1e-6 * np.clip((t - 0.4) / 0.2, 0.0, 1.0)
    xf = move + ring + creep
    ref = build(_GMS).force_along(xf, t)[::up]
    x = xf[::up]
    k = np.array(_GMS["k_n_m"])
    deltas = np.array(_GMS["alpha"]) * 1.3 / k

    def err(path: np.ndarray, n: int) -> float:
        vb = np.concatenate([[0.0], np.diff(path) / (T / n)])
        g = 1.15 + 0.15 * np.exp(-(vb / 1e-3) ** 2)
        f = _play(path, deltas, g / 1.3)[::n] @ k
        return float(np.abs(f - ref)[int(0.3 / T):].max())  # the rest and the creep after the ringing

    sampled = err(x, 1)
    fine = err(upsample_path(x, PRESLIDING_UPSAMPLE), PRESLIDING_UPSAMPLE)
    assert sampled > 3e-3  # measured 4.9 mN
    assert fine < sampled / 2  # measured 1.8 mN: the spline's own error at 12 samples a period


def test_presliding_fit_recovers_the_elements_and_the_delay() -> None:
    """fit_presliding on a synthetic loop recording (u = m·a + GMS, applied 1 ms late, noisy quantised
    sensor): the reversal curve ΔF(s) = Σ k_i·min(s, 2Δ_i) within 0.3 % up to 20 µm of travel (the
    fixed grid alone: 0.7 %), and the delay (with the damping it trades against) within 0.1 ms."""
    from stagectl.commission.fit import fit_presliding
    from stagectl.friction import build

    T, m = 1e-3, 2.6
    xt, x = _loops_path(T, 1)  # the force acts on the true path; the fit sees the measured one
    n = x.shape[0]
    f = build(_GMS).force_along(xt, np.arange(n) * T)
    a = np.zeros(n)
    a[1:-1] = (xt[2:] - 2 * xt[1:-1] + xt[:-2]) / T ** 2
    i = np.arange(n, dtype=float)
    u = np.interp(i + 1.5, i, m * a + f)  # u_k acts over [t_{k+1}, t_{k+2}): 1 ms + half a sample
    sliding = {"fc_n": 1.15, "fs_n": 1.3, "vs_m_s": 1e-3, "delta": 2.0, "viscous_n_s_m": 0.0}
    p = fit_presliding(Recorder.of(("x", "u"), np.column_stack([x, u])), m, T, 0.9e-3, sliding, None)  # the FRF's delay, 0.1 ms short
    k_fit, d_fit = np.array(p["k_n_m"]), np.array(p["break_away_m"])
    k = np.array(_GMS["k_n_m"])
    d = np.array(_GMS["alpha"]) * 1.3 / k
    for s in np.geomspace(0.2e-6, 20e-6, 15):
        true = float((k * np.minimum(s, 2 * d)).sum())
        assert abs(float((k_fit * np.minimum(s, 2 * d_fit)).sum()) / true - 1) < 3e-3, s
    # the delay and the micro-damping trade (u(t − τ + c) ≈ u(t − τ) + c·u̇: a damping c·k·ż looks like
    # a shorter delay); their sum is the true 1 ms (no damping here)
    assert abs(p["delay_s"] + p["damping_s"] - 1e-3) < 0.1e-3, (p["delay_s"], p["damping_s"])


def _slow_passes(force: Callable[[np.ndarray, np.ndarray], np.ndarray], seed: int = 0) -> Recorder:
    """A slow-passes recording built by hand: ±1 mm at 0.3 mm/s both ways (1 ms samples) with 0.5 nm sensor
    noise, ``u = force(x, direction) + 5 mN`` noise, the reference columns the loop records."""
    T, v, L = 1e-3, 3e-4, 2e-3
    n1 = int(L / v / T)
    x = np.concatenate([np.full(300, -1e-3), -1e-3 + v * T * np.arange(n1), np.full(300, 1e-3),
                        1e-3 - v * T * np.arange(n1)])
    vr = np.concatenate([np.zeros(300), np.full(n1, v), np.zeros(300), np.full(n1, -v)])
    rng = np.random.default_rng(seed)
    u = force(x, np.sign(vr)) + 0.005 * rng.standard_normal(x.size)
    xm = x + 0.5e-9 * rng.standard_normal(x.size)
    return Recorder.of(("t", "x", "u", "v_ref", "a_ref"), np.column_stack([T * np.arange(x.size), xm, u, vr,
                                                                          np.zeros(x.size)]))


def test_cogging_evidence_names_a_periodic_force_the_same_both_ways() -> None:
    """A cogging force of 20 mN at 0.37 mm (4 % of a 0.5 N Coulomb level, 4x the force noise) is named,
    with its amplitude, period and phase; the same force changing sign with the direction (a friction
    ripple) and plain friction are not."""
    from stagectl.commission.fit import cogging_evidence

    lam, A, phi = 0.37e-3, 0.02, 0.7
    cog = _slow_passes(lambda x, d: 0.5 * d + 0.3 + A * np.sin(2 * np.pi * x / lam + phi))
    ev = cogging_evidence(cog, 1.0, 1e-3)
    assert ev["present"] and ev["confidence"] == "high", ev
    assert abs(ev["wavelength_m"] / lam - 1) < 0.01 and abs(ev["amplitude_n"] / A - 1) < 0.1
    assert abs(math.remainder(ev["phase_rad"] - phi, 2 * math.pi)) < 0.15
    ripple = _slow_passes(lambda x, d: d * (0.5 + A * np.sin(2 * np.pi * x / lam + phi)))
    assert not cogging_evidence(ripple, 1.0, 1e-3)["present"]
    plain_ = cogging_evidence(_slow_passes(lambda x, d: 0.5 * d + 800.0 * x), 1.0, 1e-3)  # friction and a spring
    assert not plain_["present"] and plain_["ratio"] < 5.0, plain_


def test_cogging_evidence_does_not_name_a_smooth_trend_along_the_pass() -> None:
    """A force that curves smoothly with position (a nonlinear spring: 2e4·x² N, 20 mN at the ends of the
    ±1 mm pass) is no cogging, although the longest sinusoid scanned fits it well (ratio ≈ 66: it was named
    with "high" confidence); a true cogging of two periods over the travel still is, at its period."""
    from stagectl.commission.fit import cogging_evidence

    trend = cogging_evidence(_slow_passes(lambda x, d: 0.5 * d + 800.0 * x + 2e4 * x * x), 1.0, 1e-3)
    assert trend["ratio"] >= 5.0 and not trend["present"], trend  # strong scan peak, rejected as a trend
    assert "trend" in trend["reason"]
    lam = 1.0e-3  # two periods over the 2 mm travel
    cog = cogging_evidence(_slow_passes(lambda x, d: 0.5 * d + 0.02 * np.sin(2 * np.pi * x / lam)), 1.0, 1e-3)
    assert cog["present"] and abs(cog["wavelength_m"] / lam - 1) < 0.03, cog


def test_cogging_period_is_the_least_squares_one_when_few_periods_fit_the_travel() -> None:
    """1.76 periods over the ±1 mm pass (generated plant 3: 82 mN at 1.135 mm with a 23 mN offset): the
    period is the one with the lowest residual, not the largest amplitude (the per-direction slope takes a
    part of a long sinusoid, and the largest amplitude came out 1.073 mm, 5 % short). Oracle: a plain dense
    least squares over λ (1 µm steps) with the same constant and slope per direction."""
    from stagectl.commission.fit import cogging_evidence

    lam, A = 1.135e-3, 0.0824
    rec = _slow_passes(lambda x, d: 0.46 * d + 0.023 + A * np.sin(2 * np.pi * x / lam))
    ev = cogging_evidence(rec, 1.0, 1e-3)
    assert ev["present"], ev
    x, u, d = rec.col("x"), rec.col("u"), np.sign(rec.col("v_ref"))
    sel = d != 0
    x, u, d = x[sel], u[sel], d[sel]
    xc = x - 0.5 * (x.max() + x.min())
    pos, neg = (d > 0).astype(float), (d < 0).astype(float)
    best = (np.inf, 0.0)
    for lam_i in np.arange(1.0e-3, 1.3e-3, 1e-6):
        cols = np.column_stack([pos, neg, pos * xc, neg * xc, np.sin(2 * np.pi * x / lam_i),
                                np.cos(2 * np.pi * x / lam_i)])
        r = u - cols @ np.linalg.lstsq(cols, u, rcond=None)[0]
        best = min(best, (float(r @ r), float(lam_i)))
    assert abs(best[1] / lam - 1) < 0.003, best
    assert abs(ev["wavelength_m"] / best[1] - 1) < 0.005 and abs(ev["amplitude_n"] / A - 1) < 0.03, (ev, best)


def test_speed_ladder_feedforward_learns_the_friction_line_from_paired_cruises() -> None:
    """The constant-velocity ladder's feed-forward (controllers.SpeedLadderFeedforward) against the plain line
    F(v) = sgn(v)·Fc + b·v: each cruise's commanded force also carries a position-dependent force (cogging,
    offset: the same in both directions over a pass) that the pairing must cancel; the slowest speed's level
    is distorted (short pass, elements still loading) and must not enter the slope; a one-way cruise (the
    repositioning move) updates nothing; the Coulomb term is off while the reference stands."""
    from stagectl.commission.controllers import SpeedLadderFeedforward
    from stagectl.control.api import Reference
    from stagectl.control.friction_ff import CoulombFeedforward

    fc, b, fc0, T = 0.46, 35.0, 0.40, 1e-3
    ff = CoulombFeedforward(fc0)
    lad = SpeedLadderFeedforward(ff, settle_s=0.05)

    def cruise(v: float, extra_n: float, n: int = 300) -> None:
        for _ in range(n):
            lad.before(Reference(0.0, v, 0.0))
            assert ff.coulomb_n == lad.coulomb_n
            lad.observe(T, Reference(0.0, v, 0.0), math.copysign(fc, v) + b * v + extra_n)
        for _ in range(20):  # dwell
            lad.before(Reference(0.0, 0.0, 0.0))
            assert ff.coulomb_n == 0.0
            lad.observe(T, Reference(0.0, 0.0, 0.0), 0.0)

    speeds = [0.16e-3, 0.4e-3, 1.0e-3, 2.5e-3]
    for i, v in enumerate(speeds):
        slow_bias = -0.1 if i == 0 else 0.0  # the slowest pass reads low in both directions
        cruise(v, 0.07 * (i + 1) + math.copysign(slow_bias, v))
        cruise(-v, 0.07 * (i + 1) - math.copysign(slow_bias, v))
        if i == 1:
            # slope from the two fastest speeds only, the slowest left out: nothing yet
            assert ff.viscous_n_s_m == 0.0
    assert len(lad.updates) == len(speeds)
    assert ff.viscous_n_s_m == pytest.approx(b, rel=1e-9)
    assert lad.coulomb_n == pytest.approx(min(fc, fc0))  # never above the probe's starting level
    cruise(-8e-3, 0.3)  # a one-way cruise (repositioning): no pair, no update
    assert len(lad.updates) == len(speeds)


def _trapezoid(x0: float, x1: float, v: float, a: float, T: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plain trapezoidal move x0 → x1 at ``v`` [m/s], ``a`` [m/s²]: reference x, v, a per period ``T``."""
    d, s = abs(x1 - x0), math.copysign(1.0, x1 - x0)
    ta = v / a
    if a * ta * ta > d:  # triangular
        ta = math.sqrt(d / a)
        v = a * ta
    tc = (d - a * ta * ta) / v
    te = 2 * ta + tc
    t = np.arange(int(math.ceil(te / T)) + 1) * T
    vel = np.clip(np.minimum(a * t, a * (te - t)), 0.0, v)
    acc = np.where(t < ta, a, np.where(t <= ta + tc, 0.0, np.where(t < te, -a, 0.0)))
    pos = x0 + s * np.where(t < ta, 0.5 * a * t * t, np.where(
        t <= ta + tc, 0.5 * a * ta * ta + v * (t - ta), d - 0.5 * a * np.clip(te - t, 0.0, None) ** 2))
    return pos, s * vel, s * acc


def _cv_plant_record(m: float, fc: float, fs: float, vs: float, fv: float, cog_n: float, cog_l: float,
                     off: float, speeds: np.ndarray, v_rep: float, T: float = 1e-3, stroke: float = 2e-3,
                     cog_phase: float = 0.0, loop_hz: float = 15.0,
                     delay_cycles: int = 0) -> tuple[np.ndarray, ...]:
    """Plain reference: a mass with Stribeck + viscous friction (Karnopp stick), a cogging force and an
    offset, under a PD + integral + inertia feed-forward loop (``loop_hz``, 15 Hz as the experiments), driven through the commissioning's
    layout of constant-velocity passes (each speed both ways, one-way repositioning cruises at ``v_rep``
    between them); Euler at T/8; the force acts ``delay_cycles`` periods after it is computed. Returns t, x, u,
    v_ref, a_ref."""
    refs = []
    pos = stroke / 2  # where the experiment before left it
    for v in speeds.tolist():
        L = min(stroke, max(v * 2.0, 0.05 * stroke))
        a = min(v * v / (0.1 * L), 2.0 / m)
        for x1, vv in ((-L / 2, v_rep), (L / 2, v), (-L / 2, v)):
            if abs(x1 - pos) > 1e-12:
                refs.append(_trapezoid(pos, x1, vv, 3.0 / m if vv == v_rep else a, T))
                pos = x1
            refs.append((np.full(100, pos), np.zeros(100), np.zeros(100)))  # dwell
    refs.append(_trapezoid(pos, 0.0, v_rep, 3.0 / m, T))
    xr, vr, ar = (np.concatenate([r[i] for r in refs]) for i in range(3))
    w = 2 * math.pi * loop_hz
    kp, kd, ki = m * w * w, 2 * 0.7 * m * w, m * w ** 3 / 10
    sub, h = 8, T / 8
    x = v = integ = 0.0
    xs, us = np.zeros(xr.size), np.zeros(xr.size)
    for i in range(xr.size):
        e = xr[i] - x
        integ += e * T
        u = kp * e + kd * (vr[i] - v) + ki * integ + m * ar[i]
        xs[i], us[i] = x, u
        ua = us[i - delay_cycles] if i >= delay_cycles else 0.0
        for _ in range(sub):
            drive = ua - cog_n * math.sin(2 * math.pi * x / cog_l + cog_phase) - off
            if v == 0.0 and abs(drive) <= fs:
                continue  # stuck
            sgn = math.copysign(1.0, v if v != 0.0 else drive)
            fr = sgn * (fc + (fs - fc) * math.exp(-((v / vs) ** 2))) + fv * v
            vn = v + h * (drive - fr) / m
            if v != 0.0 and vn * v < 0.0:
                vn = 0.0  # sticks on a velocity reversal within the step
            x += h * 0.5 * (v + vn)
            v = vn
    return np.arange(xr.size) * T, xs, us, vr, ar


def test_constant_velocity_fit_reads_the_settled_passes_only() -> None:
    """Coulomb and viscous from the constant-velocity passes of a plain simulated stage (a heavy one with
    cogging and an offset, like generated plant 21), called as the commissioning calls it (the designed
    passes, both ways, each long enough to have settled): every segment it reads lies on the simulation's own
    friction curve within 2 mN, and Coulomb and viscous come out within 2 %. The previous call (every
    steady reference segment, as on stages without the speed ladder) also read the one-way repositioning cruises, one of them 56 mN off the curve,
    and its viscous term was more than 5 % off."""
    m, fc, fs, vs, fv, off = 8.9, 0.89, 1.08, 1.4e-3, 39.0, -0.07
    speeds = np.geomspace(16e-3 / 100, 16e-3, 6)
    t, x, u, v_ref, a_ref = _cv_plant_record(m, fc, fs, vs, fv, 0.2, 1.14e-3, off, speeds, 8e-3)

    def curve(v: float) -> float:
        return math.copysign(fc + (fs - fc) * math.exp(-((v / vs) ** 2)), v) + fv * v + off

    segs = an.cv_segments(t, x, u, v_ref, a_ref, m, speeds=speeds)
    assert len(segs) >= 10 and {s.v_m_s > 0 for s in segs} == {True, False}
    assert max(abs(s.f_n - curve(s.v_m_s)) for s in segs) < 2e-3
    new = an.cv_friction(segs)
    assert new.coulomb_n == pytest.approx(fc, rel=0.02)
    assert new.viscous_n_s_m == pytest.approx(fv, rel=0.02)
    old_segs = an.cv_segments(t, x, u, v_ref, a_ref, m)
    assert max(abs(s.f_n - curve(s.v_m_s)) for s in old_segs) > 0.03
    assert abs(an.cv_friction(old_segs).viscous_n_s_m / fv - 1) > 0.05


@pytest.mark.parametrize("cog_n, cog_l, phase", [(0.19, 0.681e-3, 1.89), (0.3, 0.5e-3, 1.0)])
def test_constant_velocity_fit_reads_each_speeds_odd_part(cog_n: float, cog_l: float, phase: float) -> None:
    """A cogging whose period is longer than the slow passes (0.32 mm at 0.16 mm/s) does not average out
    over them: it puts up to its amplitude into the mean of both directions alike (the even part). The
    fit pairs each speed's + and − passes and reads their odd part only. Plain simulation of fresh stage
    k102 of tests/commission/plant_kinds.py (3.68 kg, Fc 0.89 N, Fs 1.068 N, vs 2.03 mm/s, 5.6 N s/m,
    cogging 0.19 N of 0.681 mm at phase 1.89) and of a 0.3 N, 0.5 mm cogging, the oracle being its own
    friction curve: Coulomb and Fs within 2 %, vs within 10 %, viscous within 15 %. Fitting the 12 segment
    means as they were gave Coulomb 15 % high and a negative viscous on both (the curve bent through the
    slowest pair's 0.16 N of even part, which the measured speeds, 0.1656 vs 0.1606 mm/s, let an odd curve
    reach); on the commissioned k102 it was Fs = 6·10²⁷⁸ N and a fault under the new feed-forward."""
    m, fc, fs, vs, fv = 3.68, 0.89, 1.068, 2.03e-3, 5.6
    speeds = np.geomspace(16e-3 / 100, 16e-3, 6)
    t, x, u, v_ref, a_ref = _cv_plant_record(m, fc, fs, vs, fv, cog_n, cog_l, 0.0, speeds, 8e-3, cog_phase=phase)
    segs = an.cv_segments(t, x, u, v_ref, a_ref, m, speeds=speeds)
    assert len(segs) == 12
    slow = sorted(segs, key=lambda s: abs(s.v_m_s))[:2]
    assert abs(slow[0].f_n + slow[1].f_n) > 0.1  # the cogging's even part on the slowest pair
    c = an.cv_friction(segs)
    assert c.coulomb_n == pytest.approx(fc, rel=0.02)
    assert c.viscous_n_s_m == pytest.approx(fv, rel=0.15)
    assert c.stribeck is not None
    assert c.stribeck["fs_n"] == pytest.approx(fs, rel=0.02) and c.stribeck["vs_m_s"] == pytest.approx(vs, rel=0.1)
    vk, fo, fe = an.odd_points(segs)
    pos = sorted((s for s in segs if s.v_m_s > 0), key=lambda s: s.v_m_s)
    assert vk.size == 6 and np.allclose(fo + fe, [s.f_n for s in pos])  # F+ = odd + even
    assert c.points is not None and np.allclose(c.points[0], np.concatenate([vk, -vk]))


def test_a_pass_that_rings_on_the_stribeck_slope_is_read_at_its_mean_curve() -> None:
    """Where the Stribeck slope is about as negative as the loop's damping is positive (a k106-like stage:
    1.36 kg, Fs 2.04 N, Fc 1.70 N, vs 1.06 mm/s, 0.42 N cogging, a 24 Hz loop with one period of delay), the
    loop rings along the 1 mm/s passes (plain simulation as the oracle): those passes' means are the curve
    averaged over the rung speeds, well above the curve at their mean speed, and a curve fitted through them
    had vs +7.6 % and δ 1.86 for 2. With each pass's short-window speeds the means are corrected by the
    fitted curve's average over them and the curve refitted: vs and Fs within 3 % (vs +0.9 %, δ 1.96), the
    viscous within 8 %, Coulomb within 1 %."""
    m, fc, fs, vs, fv = 1.36, 1.70, 2.04, 1.06e-3, 2.42
    speeds = np.geomspace(16e-3 / 100, 16e-3, 6)
    t, x, u, v_ref, a_ref = _cv_plant_record(m, fc, fs, vs, fv, 0.42, 1.35e-3, 0.0, speeds, 8e-3, loop_hz=24.0,
                                             delay_cycles=1)

    def curve(v: float) -> float:
        return math.copysign(fc + (fs - fc) * math.exp(-((v / vs) ** 2)), v) + fv * v

    segs = an.cv_segments(t, x, u, v_ref, a_ref, m, speeds=speeds, delay_s=1.5e-3)
    assert len(segs) == 12
    ring = [s for s in segs if abs(abs(s.v_m_s) / 1.01e-3 - 1) < 0.1]
    assert len(ring) == 2
    assert all(abs(s.f_n - curve(s.v_m_s)) > 0.01 for s in ring)  # the ringing passes read high
    got = an.cv_friction(segs).stribeck
    assert got is not None
    assert got["vs_m_s"] == pytest.approx(vs, rel=0.03)
    assert got["fs_n"] == pytest.approx(fs, rel=0.03)
    assert got["fc_n"] == pytest.approx(fc, rel=0.01)
    assert got["viscous_n_s_m"] == pytest.approx(fv, rel=0.08)
    assert all(s.v_window is not None for s in ring)  # the correction had the passes' speeds


def test_stick_slip_passes_are_not_read_as_sliding_friction() -> None:
    """A light stage with a steep Stribeck dip (like generated plant 36: 0.97 kg, Fs 0.78 N, Fc 0.61 N, vs
    0.49 mm/s, cogging 0.09 N) stick-slips on its slowest passes under the experiments' 15 Hz loop. Plain
    simulation (Karnopp stick, the commissioning's pass layout) as the oracle: every pass the fit reads lies
    on the simulation's own sliding curve within 10 mN, the stick-slip passes (one of them > 40 mN below the
    curve) are set aside with the share of samples the stage stood, and the sliding curve is then refitted
    with Fs held at the pre-sliding level, which gives Coulomb within 2 %. The previous code read the
    stick-slip passes as points of the curve (its free fit: δ at the bound 4, and on the commissioned plant 36
    a cosine 700× the exact model's)."""
    from stagectl.commission import fit as cfit

    m, fc, fs, vs, fv = 0.97, 0.61, 0.78, 0.49e-3, 4.6
    speeds = np.geomspace(16e-3 / 100, 16e-3, 6)
    t, x, u, v_ref, a_ref = _cv_plant_record(m, fc, fs, vs, fv, 0.09, 0.62e-3, 0.0, speeds, 8e-3)

    def curve(v: float) -> float:
        return math.copysign(fc + (fs - fc) * math.exp(-((v / vs) ** 2)), v) + fv * v

    dropped: list[an.CvSegment] = []
    segs = an.cv_segments(t, x, u, v_ref, a_ref, m, speeds=speeds, dropped=dropped)
    assert len(segs) >= 6 and {s.v_m_s > 0 for s in segs} == {True, False}
    assert max(abs(s.f_n - curve(s.v_m_s)) for s in segs) < 0.01
    assert min(abs(s.v_m_s) for s in dropped) < 0.2e-3 and all(s.stuck_fraction > 0.3 for s in dropped)
    assert max(abs(s.f_n - curve(s.v_m_s)) for s in segs + dropped) > 0.04
    free = an.cv_friction(segs).stribeck
    assert free is not None
    fr = dict(free, stick_slip_m_s=max(abs(s.v_m_s) for s in dropped))
    pts = (np.array([s.v_m_s for s in segs]), np.array([s.f_n for s in segs]))
    refit = cfit._refit_stribeck({"evidence_ratio": 10 * cfit.PRESLIDING_EVIDENCE_RATIO, "level_n": fs}, fr, pts)
    assert refit is not None and refit["fs_n"] == pytest.approx(fs)
    assert refit["fc_n"] == pytest.approx(fc, rel=0.02)
    # the dip below the slowest sliding pass (1 mm/s): the passes' means there see only its tail (a few mN), which
    # any δ fits with a matching vs; δ is held at 2 and vs bounded below by the fastest stick-slipping pass's
    # speed over √2. The curve is then within half the drop Fs − Fc of the true one from 0 to 2 mm/s (65 mN
    # of 170 mN, vs 0.28 mm/s; main: vs 92 µm/s, δ 1.5, 137 mN)
    assert refit["delta"] == pytest.approx(2.0)
    assert 0.5 < refit["vs_m_s"] / vs < 2.0
    vv = np.linspace(0.0, 2e-3, 201)[1:]
    got = (refit["fc_n"] + (refit["fs_n"] - refit["fc_n"]) * np.exp(-((vv / refit["vs_m_s"]) ** refit["delta"]))
           + refit["viscous_n_s_m"] * vv)
    assert float(np.max(np.abs(got - np.array([curve(float(w)) for w in vv])))) < (fs - fc) / 2


def test_a_friction_ripple_is_kept_only_when_the_slow_passes_show_it() -> None:
    """The slow passes (plain force functions: the oracle) decide a friction ripple discover named. A
    claimed 1.6 µm ripple of 16 % (generated plant 38's, not in that plant) on passes without it is refused;
    a true 10 % ripple of 20 µm is confirmed; one the passes cannot sample (< 4 rows per period) is refused
    as unchecked. Before, discover's word was final (plant 38's cosine: 270× the exact model's)."""
    from stagectl.commission.fit import ripple_evidence

    plain = _slow_passes(lambda x, d: 0.5 * d + 0.05)
    claim = {"amplitude": 0.16, "wavelength_m": 1.6e-6, "phase_rad": 0.0}
    ev = ripple_evidence(plain, 1.0, 1e-3, claim, 0.5)
    assert not ev["present"] and ev["measured_n"] < 0.1 * ev["predicted_n"], ev
    lam, phi = 20e-6, 0.4
    real = _slow_passes(lambda x, d: 0.5 * d * (1 + 0.1 * np.sin(2 * np.pi * x / lam + phi)) + 0.05)
    ev = ripple_evidence(real, 1.0, 1e-3, {"amplitude": 0.1, "wavelength_m": lam, "phase_rad": phi}, 0.5)
    assert ev["present"] and ev["measured_n"] == pytest.approx(0.05, rel=0.1), ev
    ev = ripple_evidence(real, 1.0, 1e-3, {"amplitude": 0.1, "wavelength_m": 0.8e-6, "phase_rad": 0.0}, 0.5)
    assert not ev["present"] and ev["rows_per_period"] < 4


def test_a_ripple_finer_than_the_sensor_quantum_is_not_checked() -> None:
    """The slow passes at 0.3 µm per row through a 1 µm sensor quantum: most rows repeat the position (median
    step 0), so λ = 1.6 µm is sampled at most 1.6 times per period; a true 16 % ripple there cannot be checked,
    and the evidence must say so (before: 1.6e9 rows per period and "the slow passes show 36.7 mN" of 80 mN)."""
    from stagectl.commission.fit import ripple_evidence

    lam, q = 1.6e-6, 1e-6
    fine = _slow_passes(lambda x, d: 0.5 * d * (1 + 0.16 * np.sin(2 * np.pi * x / lam)) + 0.05)
    xq = np.round(np.asarray(fine.col("x")) / q) * q
    rec = Recorder.of(("t", "x", "u", "v_ref", "a_ref"),
                      np.column_stack([fine.col("t"), xq, fine.col("u"), fine.col("v_ref"), fine.col("a_ref")]))
    claim = {"amplitude": 0.16, "wavelength_m": lam, "phase_rad": 0.0}
    ev = ripple_evidence(rec, 1.0, 1e-3, claim, 0.5)
    assert not ev["present"] and ev["rows_per_period"] == pytest.approx(1.6, rel=0.01), ev
    assert "cannot be checked" in ev["reason"]
    ev = ripple_evidence(fine, 1.0, 1e-3, claim, 0.5)  # the same passes with a 1 nm-class sensor: confirmed
    assert ev["present"] and ev["rows_per_period"] == pytest.approx(lam / 0.3e-6, rel=0.01), ev


def test_one_disturbed_pass_does_not_bend_the_stribeck_curve() -> None:
    """Generated plant 34 (0.51 kg, Fc 1.43 N, Fs 1.54 N, vs 2.76 mm/s, δ 2, 30.7 N s/m): its slowest − pass
    read 24 mN below its + pass, with a standard error of 12 mN against 0.03-0.3 mN for the others, and the
    plain least-squares curve through the pairs took δ = 2.94, 5-11 mN too high at the triangle's 1.57 mm/s
    (tracking 2.4× the exact model's). Plain simulation of a stage with that friction (3.68 kg: the plain
    15 Hz loop stick-slips the 0.51 kg one on its slow passes; the oracle is its own curve), with a
    disturbance of 60 mN over half of the slowest − pass added to the force the loop needed: the pair's
    standard error shows it, the plain curve leaves a pair beyond the outlier limit, the weighted curve
    (each pair's standard error with the unexplained scatter added) leaves that pair beyond it, and with the
    pair set aside the curve is within 0.5 mN of the true one from 0.1 to 16 mm/s, δ within 0.05 of 2 (the
    plain curve: 9 mN off, δ 3.3). Without the disturbance the plain fit stays (no weights)."""
    m, fc, fs, vs, fv = 3.68, 1.4316, 1.5358, 2.762e-3, 30.671
    speeds = np.geomspace(16e-3 / 100, 16e-3, 6)
    t, x, u, v_ref, a_ref = _cv_plant_record(m, fc, fs, vs, fv, 0.0, 0.5e-3, 0.0, speeds, 8e-3)

    def curve(v: np.ndarray) -> np.ndarray:
        return np.asarray(np.sign(v) * (fc + (fs - fc) * np.exp(-((np.abs(v) / vs) ** 2))) + fv * v)

    clean = an.cv_friction(an.cv_segments(t, x, u, v_ref, a_ref, m, speeds=speeds))
    assert clean.points_sigma is None and clean.stribeck is not None and clean.stribeck.get("weighted") is False
    # the slowest − pass: the window the fit reads (its steady part), half of it pushed by +60 mN
    steady = np.flatnonzero((np.abs(a_ref) < 1e-12) & (np.isclose(v_ref, -speeds[0])))
    i0, i1 = steady[0] + (steady[-1] - steady[0]) // 5, steady[-1] - (steady[-1] - steady[0]) // 5
    ud = u.copy()
    ud[i0:(i0 + i1) // 2] += 0.06
    segs = an.cv_segments(t, x, ud, v_ref, a_ref, m, speeds=speeds)
    slow = min((s for s in segs if s.v_m_s < 0), key=lambda s: abs(s.v_m_s))
    assert slow.f_std_n > 20 * np.median([s.f_std_n for s in segs])
    from stagectl.ident.identify import fit_stribeck_curve

    se: list[float] = []
    vk, fo, _ = an.odd_points(segs, errors=se)
    vv, ff = np.concatenate([vk, -vk]), np.concatenate([fo, -fo])
    plain = fit_stribeck_curve(vv, ff)
    sig = an.stribeck_point_errors(plain, vv, ff, np.concatenate([se, se]))
    assert an.stribeck_outlier_z(plain, vv, ff, sig) > an.stribeck_outlier_limit(vk.size)
    c = an.cv_friction(segs)
    assert c.stribeck is not None and c.points_sigma is not None and c.stribeck["weighted"] is True
    grid = np.geomspace(0.1e-3, 16e-3, 40)
    err = np.abs(an.stribeck_curve_at({**c.stribeck, "offset_n": 0.0}, grid) - curve(grid))
    assert float(err.max()) < 0.5e-3
    assert abs(c.stribeck["delta"] - 2.0) < 0.05 and c.stribeck["set_aside_pairs"] == 1
    assert c.points_sigma[np.argmin(np.abs(c.points[0]))] > 1e3 * float(np.median(c.points_sigma))  # (the − pass)
    # the plain fit of the same points is visibly bent (the regression this guards)
    err_plain = np.abs(an.stribeck_curve_at({**plain, "offset_n": 0.0}, grid) - curve(grid))
    assert float(err_plain.max()) > 2.0 * float(err.max())


def test_weighted_stribeck_fit_with_equal_errors_is_the_plain_fit() -> None:
    """``fit_stribeck_curve`` with every point's standard error equal minimises the same cost as without
    (scaled): the same curve to the solver's tolerance; a point given a 100× error is all but ignored."""
    from stagectl.ident.identify import fit_stribeck_curve

    fc, fs, vs, dl, fv = 0.8, 1.0, 1e-3, 2.0, 5.0
    v = np.geomspace(0.1e-3, 16e-3, 7)
    v = np.concatenate([v, -v])
    f = np.sign(v) * (fc + (fs - fc) * np.exp(-((np.abs(v) / vs) ** dl))) + fv * v
    f = f + 1e-4 * np.cos(np.arange(v.size))  # a deterministic 0.1 mN scatter
    plain = fit_stribeck_curve(v, f)
    same = fit_stribeck_curve(v, f, sigma_n=np.full(v.size, 3e-4))
    for k in ("fc_n", "fs_n", "viscous_n_s_m"):
        assert same[k] == pytest.approx(plain[k], rel=1e-3, abs=1e-6)
    bad = f.copy()
    bad[0] += 0.05  # 50 mN off at the slowest + point
    sg = np.full(v.size, 3e-4)
    sg[0] = 0.03
    w = fit_stribeck_curve(v, bad, sigma_n=sg)
    assert w["fs_n"] == pytest.approx(fs, abs=3e-3) and w["vs_m_s"] == pytest.approx(vs, rel=0.1)
    with pytest.raises(DataError):
        fit_stribeck_curve(v, f, sigma_n=np.zeros(v.size))


def test_the_pre_sliding_level_replaces_an_extrapolated_fs_the_passes_allow() -> None:
    """Generated plant 38 (Fc 0.4693 N, Fs 0.5707 N, vs 0.355 mm/s, δ 2, 18.1 N s/m, a 52 mN offset): its
    passes' odd parts lay within 0.14 mN of the true curve (1.1 mN at 16 mm/s), standard errors 0.1-3.6 mN,
    and the curve through them took Fs 0.585 N with δ 1.56 — 72 % of the excess is left at the slowest pass
    (0.16 mm/s), so the old test called Fs measured, and the pre-sliding elements fitted on that curve made
    the cosine 2.2× the exact model's. The same points (synthetic, the oracle being the true curve): the
    plain curve is > 10 mN off somewhere below 16 mm/s; with the pre-sliding level (0.5718 N measured, or the
    true 0.5707 N) the refit holds Fs there within a χ² rise of 3.84 and is within 1.5 mN of the true curve
    from 10 µm/s to 16 mm/s; a level the passes contradict (0.60 N) or one within the points' errors of the
    curve's Fs leaves the curve alone."""
    from stagectl.commission import fit as cfit

    fc, fs, vs, fv = 0.4693, 0.5707, 0.355e-3, 18.114
    speeds = np.array([0.159, 0.402, 1.010, 2.541, 6.36, 15.8]) * 1e-3
    odd_err = np.array([0.06, -0.135, 0.095, 0.06, 0.135, 1.115]) * 1e-3  # plant 38's, against its true curve
    se = np.array([0.115, 0.76, 0.14, 0.243, 0.415, 3.568]) * 1e-3

    def curve(v: np.ndarray) -> np.ndarray:
        return np.asarray(np.sign(v) * (fc + (fs - fc) * np.exp(-((np.abs(v) / vs) ** 2))) + fv * v)

    segs: list[an.CvSegment] = []
    for v, e, s in zip(speeds, odd_err, se):
        segs += [an.CvSegment(float(v), float(curve(np.array(v)) + e + 0.052), float(s * math.sqrt(2)), 500),
                 an.CvSegment(float(-v), float(curve(np.array(-v)) - e + 0.052), float(s * math.sqrt(2)), 500)]
    cv = an.cv_friction(segs)
    assert cv.stribeck is not None and cv.points is not None and cv.points_error is not None
    grid = np.geomspace(10e-6, 16e-3, 40)
    plain = cv.stribeck
    assert float(np.max(np.abs(an.stribeck_curve_at({**plain, "offset_n": 0.0}, grid) - curve(grid)))) > 10e-3
    assert math.exp(-((speeds[0] / plain["vs_m_s"]) ** plain["delta"])) > cfit.STRIBECK_OBSERVED_FRACTION
    fr = {k: plain[k] for k in ("fc_n", "fs_n", "vs_m_s", "delta", "viscous_n_s_m", "v_min_m_s")}
    pts = (*cv.points, np.zeros(0), cv.points_error)
    for level in (0.5718, fs):
        out = cfit._refit_stribeck({"level_n": level, "evidence_ratio": 1e9}, fr, pts)
        assert out is not None and out["fs_n"] == pytest.approx(level) and out["level_chi2_rise"] <= 3.84
        assert float(np.max(np.abs(an.stribeck_curve_at({**out, "offset_n": 0.0}, grid) - curve(grid)))) < 1.5e-3
    assert cfit._refit_stribeck({"level_n": 0.60, "evidence_ratio": 1e9}, fr, pts) is None
    assert cfit._refit_stribeck({"level_n": plain["fs_n"] + 5e-5, "evidence_ratio": 1e9}, fr, pts) is None
    # without the points' errors (a caller that has none) nothing changes either
    assert cfit._refit_stribeck({"level_n": 0.5718, "evidence_ratio": 1e9}, fr, cv.points) is None


def test_stribeck_pair_set_aside_leaves_the_offset_and_the_standard_errors() -> None:
    """A pair the weighted Stribeck fit sets aside (one slowest − pass pushed by 60 mN, its own error
    showing it) is left out of the offset and the standard errors as it is out of the line: the offset
    stays within 0.5 mN of the true 20 mN (with the pair: +5 mN, its even part is moved by half the push
    over six pairs) and its standard error within 3× the undisturbed passes' (with the pair: the 60 mN
    residual counts in every standard error)."""
    fc, fs, vs, fv, f0 = 1.4316, 1.5358, 2.762e-3, 30.671, 0.02

    def force(v: float) -> float:
        return float(np.sign(v) * (fc + (fs - fc) * np.exp(-((abs(v) / vs) ** 2))) + fv * v + f0)

    segs = []
    for k, s in enumerate(np.geomspace(16e-3 / 100, 16e-3, 6)):
        for sg in (1, -1):
            v = sg * s * (1 + 0.002 * np.cos(3 * k + sg))  # measured speeds differ a little
            segs.append(an.CvSegment(v, force(v) + 2e-4 * np.sin(5 * k + 2 * sg), 2e-4, 400))
    clean = an.cv_friction(segs)
    assert clean.points_sigma is None and abs(clean.offset_n - f0) < 0.1e-3
    i = next(j for j, s in enumerate(segs) if s.v_m_s < 0)  # the slowest − pass
    segs[i] = an.CvSegment(segs[i].v_m_s, segs[i].f_n + 0.06, 3e-3, 400)
    c = an.cv_friction(segs)
    assert c.stribeck is not None and c.stribeck["set_aside_pairs"] == 1
    assert c.points_sigma is not None and c.points_sigma[0] > 1e3 * float(np.median(c.points_sigma))
    assert abs(c.offset_n - f0) < 0.5e-3
    assert c.offset_std_n < 3 * clean.offset_std_n
    assert c.coulomb_std_n < 3 * clean.coulomb_std_n and abs(c.coulomb_n - fc) < 1e-3
    assert c.used == 10  # the segments of the pairs kept


def _fast_loops(vs_m_s: float) -> tuple[Recorder, float]:
    """Loops of 25 µm down to 0.8 µm travel in 40 ms each (the largest reaches 1 mm/s) after a 300 µm move,
    on a GMS with Fs 1.3 N, Fc 1.0 N and Stribeck velocity ``vs_m_s`` (u = m·a + GMS, applied 1 ms late;
    0.5 nm noise, 1 nm quantum). Returns the recording and the mass [kg]."""
    from stagectl.friction import build

    gms = dict(_GMS, fc_n=1.0, vs_m_s=vs_m_s)
    T, m = 1e-3, 2.6
    pts = [0.0, 300e-6]
    for A in (25e-6 / 2 ** i for i in range(6)):
        pts += [300e-6 - A, 300e-6]
    segs = [np.zeros(1)]
    for a, b in itertools.pairwise(pts):
        s = np.linspace(0.0, 1.0, int(0.04 / T) if abs(b - a) < 100e-6 else int(1.0 / T))
        segs += [a + (b - a) * (1 - np.cos(np.pi * s[1:])) / 2, np.full(200, b)]
    xt = np.concatenate(segs)
    x = np.round((xt + 0.5e-9 * np.random.default_rng(1).standard_normal(xt.shape)) / 1e-9) * 1e-9
    n = x.shape[0]
    a = np.zeros(n)
    a[1:-1] = (xt[2:] - 2 * xt[1:-1] + xt[:-2]) / T ** 2
    i = np.arange(n, dtype=float)
    u = np.interp(i + 1.5, i, m * a + build(gms).force_along(xt, i * T))
    return Recorder.of(("x", "u"), np.column_stack([x, u])), m


def test_the_pre_sliding_level_does_not_inherit_an_extrapolated_vs_error() -> None:
    """Passes from 1 mm/s (``v_min_m_s``) on a GMS with vs 0.3 mm/s: the curve's vs is below the slowest pass,
    at the stick-slip bound (``vs_bound_m_s``), and may be 10 % off either way. The loops are fitted with vs 0.27
    and 0.33 mm/s: the level Σ k_i·Δ_i stays within 0.1 % of the true Fs either way (measured 0.04 %; the
    rows up to the slowest pass's speed gave +0.29 / −0.22 %: fresh plant k111's level took a bounded vs's
    −9 % as +0.39 % of Fs, and its cosine tracked 34x the exact model's)."""
    from stagectl.commission.fit import fit_presliding

    rec, m = _fast_loops(3e-4)
    for vs in (2.7e-4, 3.3e-4):
        sliding = {"fc_n": 1.0, "fs_n": 1.3, "vs_m_s": vs, "delta": 2.0, "viscous_n_s_m": 0.0, "v_min_m_s": 1e-3,
                   "vs_bound_m_s": vs}
        level = fit_presliding(rec, m, 1e-3, 1e-3, sliding, None)["level_n"]
        assert abs(level / 1.3 - 1) < 1e-3, (vs, level)


def test_the_loops_find_a_stribeck_velocity_the_passes_only_bound() -> None:
    """The same loops: the passes (from 1 mm/s) stick-slipped up to 0.38 mm/s, so they bound vs from below at
    0.27 mm/s (fit.STICK_SLIP_VS_RATIO) and the curve sat at the bound. With the level held, the loops'
    rows around vs find 0.3 mm/s within 3 %, and a curve already right is left (nothing gained)."""
    from stagectl.commission.fit import STICK_SLIP_VS_RATIO, _vs_from_loops

    rec, m = _fast_loops(3e-4)
    fr = {"fc_n": 1.0, "fs_n": 1.3, "vs_m_s": 2.7e-4, "delta": 2.0, "viscous_n_s_m": 0.0, "v_min_m_s": 1e-3,
          "stick_slip_m_s": 2.7e-4 * STICK_SLIP_VS_RATIO}
    found = _vs_from_loops([rec], m, 1e-3, 1e-3, fr, None)
    assert found is not None and abs(found["vs_m_s"] / 3e-4 - 1) < 0.03, found
    assert found["level_n"] == fr["fs_n"]  # the level held is the curve's (fit_models passes the model's fs_n)
    assert _vs_from_loops([rec], m, 1e-3, 1e-3, dict(fr, vs_m_s=3e-4), None) is None


def test_the_flat_line_that_replaces_a_curve_beyond_the_fastest_pass_keeps_the_set_aside_pair_out() -> None:
    """Passes on a nearly flat friction curve (Fs 1.45 N, Fc 1.4316 N, vs 20 mm/s: its drop lies beyond the
    fastest pass at 16 mm/s) with one middle − pass pushed by 15-25 mN: the weighted fit sets that pair aside, and its
    curve, beyond the fastest pass, is replaced by the flat line Fc + Fv·v. The line leaves the pair out as the
    returned Coulomb and viscous do: its Fc and Fv are theirs (with the pair in: 2 mN apart), and it does not
    move with the push (a 15 or 25 mN push, the same line)."""
    fc, fs, vs, fv, f0 = 1.4316, 1.45, 20e-3, 30.671, 0.02

    def force(v: float) -> float:
        return float(np.sign(v) * (fc + (fs - fc) * np.exp(-((abs(v) / vs) ** 2))) + fv * v + f0)

    out = []
    for push in (0.015, 0.025):
        segs = []
        for k, s in enumerate(np.geomspace(16e-3 / 100, 16e-3, 6)):
            for sg in (1, -1):
                v = sg * s * (1 + 0.002 * np.cos(3 * k + sg))
                segs.append(an.CvSegment(v, force(v) + 2e-4 * np.sin(5 * k + 2 * sg), 2e-4, 400))
        segs[7] = an.CvSegment(segs[7].v_m_s, segs[7].f_n + push, 3e-3, 400)  # the 4th pair's − pass
        c = an.cv_friction(segs)
        st = c.stribeck
        assert st is not None and st.get("beyond_fastest_vs_m_s", 0.0) > 16e-3 and st["fs_n"] == st["fc_n"]
        assert st.get("set_aside_pairs") == 1 and c.used == 10
        assert st["fc_n"] == pytest.approx(c.coulomb_n, abs=1e-9)
        assert st["viscous_n_s_m"] == pytest.approx(c.viscous_n_s_m, abs=1e-6)
        out.append(st["fc_n"])
    assert out[0] == pytest.approx(out[1], abs=1e-9)


def test_rigid_margins_match_the_discrete_design_at_a_whole_period_of_delay() -> None:
    # the model that judges the friction experiments' stiffer tunings where the FRF's mass is not credible
    # (sequence.Commissioning._experiment_crossover): the discrete loop tune's design rule analyses, and
    # a quarter period more delay costs phase at the crossover
    T, m = 1e-3, 0.8632
    for hz in (26.0, 15.0):
        pid = design.design_pid(m, hz, T, 1)
        d = design.analyse_design(m, T, pid, 1, 50.0, 1, dob_mass_kg=m)[-1].summary()
        mm = an.rigid_margins(T, m, T, pid, 50.0)
        assert mm.phase_margin_deg == pytest.approx(d["phase_margin_deg"], abs=0.5)
        assert mm.gain_margin_db == pytest.approx(d["gain_margin_db"], abs=0.3)
        later = an.rigid_margins(T, m, 1.25 * T, pid, 50.0)
        assert later.phase_margin_deg == pytest.approx(mm.phase_margin_deg - 90.0 * mm.crossover_hz * T, abs=0.3)
