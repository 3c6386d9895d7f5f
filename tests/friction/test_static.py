"""Static Coulomb + viscous + Stribeck model (tag ``stribeck``): TV1, Karnopp values, frictional lag."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stagectl.errors import ConfigError
from stagectl.friction import build

TV1 = {"model": "stribeck", "fc_n": 1.0, "fs_n": 1.5, "vs_m_s": 1e-3}


@pytest.mark.parametrize(
    "delta,v,g",
    [(2.0, 0.5e-3, 1.389400), (1.0, 0.5e-3, 1.303265), (2.0, 1e-3, 1.183940), (1.0, 1e-3, 1.183940),
     (2.0, 2e-3, 1.009158), (1.0, 2e-3, 1.067668), (2.0, 5e-3, 1.000000), (1.0, 5e-3, 1.003369)],
)
def test_tv1_stribeck_values_and_symmetry(delta, v, g):
    dut = build({**TV1, "delta": delta})
    assert dut.stribeck(v) == pytest.approx(g, abs=1e-6)
    assert dut.stribeck(-v) == pytest.approx(-g, abs=1e-6)
    assert dut.force(dut.initial_state(), v) == pytest.approx(g, abs=1e-6)


def test_g_at_vs_is_fc_plus_excess_over_e():
    for delta in (0.5, 1.0, 2.0, 3.0):
        dut = build({**TV1, "delta": delta})
        assert dut.stribeck(1e-3) == pytest.approx(1.0 + 0.5 / math.e, rel=1e-12)


def test_viscous_and_karnopp_kernel_values():
    dut = build({**TV1, "viscous_n_s_m": 0.4, "stick_velocity_m_s": 2e-6})
    assert dut.n_states == 0
    assert dut.stribeck(0.01) == pytest.approx(1.0 + 0.5 * math.exp(-100) + 0.004)
    k = dut.kernel()
    assert (k.breakaway_n, k.stick_velocity_m_s) == (1.5, 2e-6)
    assert dut.force(dut.initial_state(), 0.0) == 0.0  # sgn(0) = 0: the plant's stick band handles v = 0


def test_coulomb_viscous_special_case():
    dut = build({"model": "stribeck", "fc_n": 0.7, "fs_n": 0.7, "viscous_n_s_m": 3.0})
    v = np.array([-2e-3, -1e-6, 1e-6, 5e-3])
    np.testing.assert_allclose([dut.stribeck(x) for x in v], np.sign(v) * 0.7 + 3.0 * v, rtol=1e-12)


def test_no_lag_is_exactly_static_along_a_trajectory():
    dut = build({**TV1, "viscous_n_s_m": 0.4})
    t = np.linspace(0.0, 1.0, 2001)
    x = 2e-3 * np.sin(2 * np.pi * 3 * t)
    f = dut.force_along(x, t)
    v = np.diff(x) / np.diff(t)
    np.testing.assert_allclose(f[1:], [dut.stribeck(vk) for vk in v], rtol=1e-13)


def test_frictional_lag_first_order_response():
    lag = 5e-3
    dut = build({**TV1, "lag_s": lag})
    assert dut.n_states == 1
    np.testing.assert_allclose(dut.initial_state(), [0.5])
    v = 2e-3
    t = np.linspace(0.0, 0.03, 301)
    f = dut.force_along(v * t, t)
    e_ss = 0.5 * math.exp(-4.0)
    expected = 1.0 + e_ss + (0.5 - e_ss) * np.exp(-t[1:] / lag)
    np.testing.assert_allclose(f[1:], expected, rtol=1e-12)
    assert f[-1] == pytest.approx(dut.stribeck(v), rel=1e-2)  # approaches the static curve
    # the derivative form agrees with the exact update for a small step
    s = dut.initial_state()
    d = dut.derivative(s, v)
    s2 = s.copy()
    dut.step(s2, v * 1e-7, v, 1e-7)
    assert (s2[0] - s[0]) / 1e-7 == pytest.approx(d[0], rel=1e-4)


def test_lag_zero_limit_is_continuous():
    t = np.linspace(0.0, 0.01, 101)
    x = 1e-3 * np.sin(2 * np.pi * 100 * t)
    f0 = build(TV1).force_along(x, t)
    f1 = build({**TV1, "lag_s": 1e-9}).force_along(x, t)
    np.testing.assert_allclose(f1[1:], f0[1:], atol=1e-9)


@pytest.mark.parametrize(
    "bad,key",
    [({"fs_n": -0.5}, "fs_n"), ({"vs_m_s": 0.0}, "friction.vs_m_s"), ({"fc_n": -1.0}, "friction.fc_n"),
     ({"lag_s": -1.0}, "friction.lag_s"), ({"viscous": 1.0}, "friction.viscous"),
     ({"stick_velocity_m_s": 0.0}, "friction.stick_velocity_m_s")],
)
def test_build_errors_name_the_key(bad, key):
    with pytest.raises(ConfigError) as ei:
        build({**TV1, **bad})
    assert key in str(ei.value)


def test_spec_round_trip():
    dut = build({**TV1, "lag_s": 1e-3, "viscous_n_s_m": 2.0})
    again = build(dut.spec())
    assert again.params == dut.params
    assert dut.replace(fc_n=0.9).params.fc_n == 0.9
