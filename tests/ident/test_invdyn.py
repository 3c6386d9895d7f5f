"""Inverse dynamics respects the zero-order-hold convention (docs/recordings.md, docs/discovery.md §3)."""

from __future__ import annotations

import numpy as np
import pytest

from stagectl.ident import discover as dsc
from stagectl.ident.effects import DELAY
from stagectl.ident.recording import Recording
from stagectl.ident.signals import hat_average, prepare


def _rigid_body(n: int = 6000, dt: float = 1e-3, m: float = 2.5, fv: float = 8.0, delay_samples: float = 0.0,
                seed: int = 3, sub: int = 10) -> Recording:
    """Exact simulation of m·a = u(t − τ) − fv·v (no friction jump, no noise): u[k] held over [t_k, t_k+1),
    applied τ later (so it switches inside an interval for fractional τ); ``sub`` exact sub-steps per sample."""
    rng = np.random.default_rng(seed)
    # smooth random force: band-limited noise plus a slow sine keeps the stage moving
    u = np.convolve(rng.standard_normal(n), np.ones(15) / 15, mode="same") * 4.0 + 3.0 * np.sin(
        2 * np.pi * 0.7 * np.arange(n) * dt)
    h = dt / sub
    a_ = fv / m
    e = np.exp(-a_ * h)
    x = np.zeros(n)
    v = 0.0
    xk = 0.0
    tau = delay_samples * dt
    for k in range(n - 1):
        for j in range(sub):
            idx = int(np.floor(k + (j + 0.5) / sub - tau / dt))  # the command applied in this sub-step
            ua = u[max(idx, 0)]
            v_inf = ua / fv
            xk += v_inf * h + (v - v_inf) * (1 - e) / a_
            v = v_inf + (v - v_inf) * e
        x[k + 1] = xk
    return Recording(t=np.arange(n) * dt, x=x, u=u, source="rigid-body")


def test_zoh_pairing_recovers_mass_and_viscous_exactly() -> None:
    rec = _rigid_body()
    ds = dsc.make_dataset(rec)
    fit = dsc.fit_start(ds)
    assert fit.hyp.theta["m"] == pytest.approx(2.5, rel=2e-3)
    assert fit.hyp.theta["fv"] == pytest.approx(8.0, rel=2e-3)
    assert fit.hyp.theta["fc"] == pytest.approx(0.0, abs=2e-3)


def test_no_spurious_delay_from_zoh() -> None:
    """Pairing u[k] with a[k] would invent half a sample of delay; the ZOH-consistent pairing finds none."""
    rec = _rigid_body()
    ds = dsc.make_dataset(rec)
    cur = dsc.fit_start(ds)
    fit = dsc.fit_candidate(ds, cur, "delay")
    assert DELAY.shape(fit.hyp).delay_s < 0.05e-3


def test_fractional_delay_is_recovered() -> None:
    rec = _rigid_body(delay_samples=1.4)
    ds = dsc.make_dataset(rec)
    cur = dsc.fit_start(ds)
    fit = dsc.fit_candidate(ds, cur, "delay")
    assert DELAY.shape(fit.hyp).delay_s == pytest.approx(1.4e-3, abs=0.05e-3)


def test_hat_average_pairs_delayed_zoh_force_exactly() -> None:
    """Second difference of an exactly integrated double integrator = hat-kernel average of the delayed force."""
    rng = np.random.default_rng(0)
    n, dt, m, sub = 200, 1e-3, 2.0, 40
    u = rng.standard_normal(n)
    for s in (0.0, 0.4, 1.4, 2.7):
        x, v, xs = 0.0, 0.0, [0.0]
        h = dt / sub
        for k in range(n - 1):
            for j in range(sub):
                ua = u[max(int(np.floor(k + (j + 0.5) / sub - s)), 0)]
                x += v * h + 0.5 * ua / m * h * h
                v += ua / m * h
            xs.append(x)
        xa = np.array(xs)
        acc = (xa[2:] - 2 * xa[1:-1] + xa[:-2]) / dt**2
        np.testing.assert_allclose(m * acc[10:-2], hat_average(u, s)[1:-1][10:-2], atol=1e-8)


def test_prepare_marks_rest_as_stuck() -> None:
    n = 3000
    t = np.arange(n) * 1e-3
    x = np.where(t < 1.0, 0.0, 1e-3 * np.sin(2 * np.pi * (t - 1.0)))
    x = np.round(x / 1e-9) * 1e-9
    sig = prepare(Recording(t=t, x=x, u=np.zeros(n)))
    assert not sig.moving[100:900].any()
    assert sig.moving[1020:1200].all()  # the sine peaks (v = 0) at t = 1.25 s
    assert not sig.evaluate[:1000].any()


def test_default_cutoff_is_a_stage_property_not_a_sample_rate_fraction() -> None:
    """Audit: fs/10 at 5 kHz (500 Hz) raised the metric's noise floor ~56-fold and buried effects that
    are plain at 1 kHz (blind set: a 5 kHz offset case was missed). Default: min(fs/10, 100 Hz)."""
    import numpy as np

    from stagectl.ident.recording import Recording
    from stagectl.ident.signals import prepare

    floors = {}
    for fs in (500.0, 1000.0, 5000.0):
        t = np.arange(int(8 * fs)) / fs
        rng = np.random.default_rng(0)
        x = 1e-3 * np.sin(2 * np.pi * 0.5 * t) + 5e-9 * rng.standard_normal(t.size)
        sig = prepare(Recording(t=t, x=x, u=np.zeros_like(t)))
        assert sig.cutoff_hz == pytest.approx(min(fs / 10, 100.0))
        floors[fs] = sig.noise_floor_n(1.0)
    # same noise, same cut-off: the floor no longer grows with the sample rate (it did by (fs ratio)^2.5)
    assert floors[5000.0] < 3.0 * floors[1000.0]
