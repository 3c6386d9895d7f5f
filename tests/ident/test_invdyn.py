"""Inverse dynamics respects the zero-order-hold convention (RECORDINGS.md, DISCOVERY_NOTES §3)."""

from __future__ import annotations

import numpy as np
import pytest

from stagectl.ident import discover as dsc
from stagectl.ident.recording import Recording
from stagectl.ident.signals import prepare, shift_zoh


def _rigid_body(n: int = 6000, dt: float = 1e-3, m: float = 2.5, fv: float = 8.0, delay_samples: float = 0.0,
                seed: int = 3) -> Recording:
    """Exact ZOH simulation of m·a = u(t − τ) − fv·v (no friction jump, no noise): u[k] held over [t_k, t_k+1)."""
    rng = np.random.default_rng(seed)
    # smooth random force: band-limited noise plus a slow sine keeps the stage moving
    u = np.convolve(rng.standard_normal(n), np.ones(15) / 15, mode="same") * 4.0 + 3.0 * np.sin(
        2 * np.pi * 0.7 * np.arange(n) * dt)
    ua = shift_zoh(u, delay_samples)
    x = np.zeros(n)
    v = 0.0
    xk = 0.0
    for k in range(n - 1):
        # exact solution of m·dv/dt = ua − fv·v over one interval with ua held
        a_ = fv / m
        e = np.exp(-a_ * dt)
        v_inf = ua[k] / fv
        x_next = xk + v_inf * dt + (v - v_inf) * (1 - e) / a_
        v = v_inf + (v - v_inf) * e
        xk = x_next
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
    assert fit.hyp.nl["delay_s"] < 0.05e-3


def test_fractional_delay_is_recovered() -> None:
    rec = _rigid_body(delay_samples=1.4)
    ds = dsc.make_dataset(rec)
    cur = dsc.fit_start(ds)
    fit = dsc.fit_candidate(ds, cur, "delay")
    assert fit.hyp.nl["delay_s"] == pytest.approx(1.4e-3, abs=0.05e-3)


def test_prepare_marks_rest_as_stuck() -> None:
    n = 3000
    t = np.arange(n) * 1e-3
    x = np.where(t < 1.0, 0.0, 1e-3 * np.sin(2 * np.pi * (t - 1.0)))
    x = np.round(x / 1e-9) * 1e-9
    sig = prepare(Recording(t=t, x=x, u=np.zeros(n)))
    assert not sig.moving[100:900].any()
    assert sig.moving[1020:1200].all()  # the sine peaks (v = 0) at t = 1.25 s
    assert not sig.evaluate[:1000].any()
