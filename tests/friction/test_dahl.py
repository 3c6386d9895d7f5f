"""Dahl: TV6 virgin curve, exact (step-independent) update, path agreement, energy, config errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stagectl.errors import ConfigError
from stagectl.friction import build

SPEC = {"model": "dahl", "sigma0_n_m": 1e5, "fc_n": 1.0}


@pytest.fixture(scope="module")
def dut():
    return build(SPEC)


def test_tv6_virgin_curve(dut):
    x_um = np.array([0.0, 1.0, 5.0, 10.0, 30.0, 50.0])
    f = dut.force_along(x_um * 1e-6, np.arange(x_um.size, dtype=float))
    np.testing.assert_allclose(f, [0.0, 0.095163, 0.393469, 0.632121, 0.950213, 0.993262], atol=1e-6)
    np.testing.assert_allclose(dut.virgin(x_um * 1e-6), f, atol=1e-12)
    # odd: moving the other way gives the negative curve
    f_neg = dut.force_along(-x_um * 1e-6, np.arange(x_um.size, dtype=float))
    np.testing.assert_allclose(f_neg, -f, atol=1e-12)


@pytest.mark.parametrize("exponent", [0.5, 1.0, 2.0])
def test_update_is_exact_for_any_step(dut, exponent):
    m = dut.replace(exponent=exponent)
    coarse = m.force_along(np.array([0.0, 20e-6, 5e-6]), np.array([0.0, 1.0, 2.0]))
    xf = np.concatenate([np.linspace(0.0, 20e-6, 1001), np.linspace(20e-6, 5e-6, 1001)[1:]])
    fine = m.force_along(xf, np.arange(xf.size, dtype=float))
    assert coarse[1] == pytest.approx(fine[1000], abs=1e-12)
    assert coarse[2] == pytest.approx(fine[-1], abs=1e-12)
    # the force never exceeds Fc coming from rest, and saturates at Fc
    assert np.all(np.abs(fine) <= 1.0 + 1e-15)
    far = m.force_along(np.array([0.0, 1e-2]), np.array([0.0, 1.0]))[1]
    # closed forms of dF/dx = σ0(1 − F/Fc)^i from rest: i = 2 approaches Fc algebraically, i <= 1 reaches it
    assert far == pytest.approx(1.0 - 1.0 / (1.0 + 1e5 * 1e-2) if exponent == 2.0 else 1.0, abs=1e-12)


def test_exponent_matches_ode_integration(dut):
    # dF/dx = sigma0·(1 − F/Fc)^i integrated by fine RK4 as an independent reference
    i = 2.0
    m = dut.replace(exponent=i)
    f, x, h = 0.0, 0.0, 1e-8
    while x < 10e-6 - 1e-15:
        def rhs(ff: float) -> float:
            return 1e5 * (1.0 - ff) ** i
        k1 = rhs(f)
        k2 = rhs(f + 0.5 * h * k1)
        k3 = rhs(f + 0.5 * h * k2)
        k4 = rhs(f + h * k3)
        f += h * (k1 + 2 * k2 + 2 * k3 + k4) / 6
        x += h
    got = m.force_along(np.array([0.0, 10e-6]), np.array([0.0, 1.0]))[1]
    assert got == pytest.approx(f, abs=1e-9)


def test_paths_agree_and_viscous_sign(dut, paths):
    m = dut.replace(viscous_n_s_m=2.0)
    rng = np.random.default_rng(5)
    t = np.linspace(0.0, 1.0, 3001)
    x = np.cumsum(rng.normal(0.0, 1e-6, t.size))
    fa = m.force_along(x, t)
    sc, kf = paths(m, x, t)
    batch = type(m).force_along_batch([m.params, dut.params], x, t)
    np.testing.assert_allclose(sc, fa, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(kf, fa, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(batch[0], fa, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(batch[1], dut.force_along(x, t), rtol=1e-13, atol=1e-15)
    # steady sliding with v < 0 gives F = −Fc + σ2·v < 0
    tt = np.linspace(0.0, 1.0, 101)
    assert m.force_along(-1e-3 * tt, tt)[-1] == pytest.approx(-1.0 - 2e-3, abs=1e-9)


def test_derivative_matches_i1_law(dut):
    s = np.array([0.3])
    assert dut.derivative(s, 2e-3)[0] == pytest.approx(1e5 * (2e-3 - 2e-3 * 0.3), rel=1e-12)
    assert dut.derivative(s, -2e-3)[0] == pytest.approx(1e5 * (-2e-3 - 2e-3 * 0.3), rel=1e-12)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-40e-6, 40e-6), min_size=1, max_size=6), st.sampled_from([0.5, 1.0, 3.0]))
def test_energy_dissipated_over_closed_paths(turns, exponent):
    m = build({**SPEC, "exponent": exponent})
    pts = np.array([0.0, *turns, 0.0])
    xs = np.concatenate([np.linspace(a, b, 400, endpoint=False) for a, b in zip(pts[:-1], pts[1:])] + [[0.0]])
    f = m.force_along(xs, np.arange(xs.size, dtype=float))
    work = float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(xs)))
    # from the relaxed state: work in = dissipation + stored elastic energy >= 0
    assert work >= -1e-12
    assert math.isfinite(work)


def test_build_rejects_bad_input():
    with pytest.raises(ConfigError, match=r"friction\.fc: unknown key"):
        build({**SPEC, "fc": 1.0})
    with pytest.raises(ConfigError, match=r"friction\.fc_n: must be > 0 N"):
        build({**SPEC, "fc_n": 0.0})
    with pytest.raises(ConfigError, match=r"friction\.exponent: must be >= 0"):
        build({**SPEC, "exponent": -1.0})
