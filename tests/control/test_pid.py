"""PID law: anti-windup, bumpless enable/retune, derivative filter, clamp, dt checks (scripted dt)."""

from __future__ import annotations

import math

import pytest

from stagectl.control.pid import Pid, PidConfig
from stagectl.errors import ConfigError
from stagectl.schema import load

DT = 1e-3


def test_proportional_and_integral_in_physical_units():
    dut = Pid(PidConfig(kp_n_m=1e4, ki_n_m_s=1e5, kd_n_s_m=0.0))
    u = dut.step(DT, 1e-6, 0.0)  # e = 1 µm
    assert dut.state.p_n == pytest.approx(1e4 * 1e-6)
    assert dut.state.i_n == pytest.approx(1e5 * 1e-6 * DT)
    assert u == pytest.approx(0.01 + 1e-4)
    for _ in range(99):
        dut.step(DT, 1e-6, 0.0)
    assert dut.state.i_n == pytest.approx(1e5 * 1e-6 * 0.1)  # Ki·e·t


def test_anti_windup_freezes_integrator_in_error_direction_and_recovers():
    dut = Pid(PidConfig(kp_n_m=1e4, ki_n_m_s=1e6, kd_n_s_m=0.0))
    lim = 1.0
    # large positive error: P alone = 10 N > 1 N limit -> saturated in the error's direction
    for _ in range(50):
        u = dut.step(DT, 1e-3, 0.0, limit_n=lim)
    assert u == lim and dut.state.saturated == 1
    assert dut.state.i_n == 0.0  # never integrated while saturated in the error direction
    assert not dut.state.integrating
    # error reverses sign: integration resumes immediately (it now unwinds the output)
    dut.step(DT, -1e-6, 0.0, limit_n=lim)
    assert dut.state.integrating
    assert dut.state.i_n == pytest.approx(1e6 * -1e-6 * DT)
    # back inside the limit: output equals the unclamped PID again
    u = dut.step(DT, 1e-5, 0.0, limit_n=lim)
    assert dut.state.saturated == 0 and u == pytest.approx(dut.state.p_n + dut.state.i_n)


def test_anti_windup_counts_other_terms_for_saturation():
    dut = Pid(PidConfig(kp_n_m=1e3, ki_n_m_s=1e5, kd_n_s_m=0.0))
    # PID alone is small, but the feed-forward pushes the total over the limit in the error direction
    dut.step(DT, 1e-4, 0.0, u_other_n=5.0, limit_n=5.0)
    assert dut.state.i_n == 0.0 and dut.state.saturated == 1
    # opposite error with the same saturation: integration allowed (it reduces the output)
    dut.step(DT, -1e-4, 0.0, u_other_n=5.0, limit_n=5.0)
    assert dut.state.i_n < 0.0


def test_without_anti_windup_the_integrator_would_wind_up():
    # the same scenario with an unlimited output integrates: the test above can fail
    dut = Pid(PidConfig(kp_n_m=1e4, ki_n_m_s=1e6, kd_n_s_m=0.0))
    for _ in range(50):
        dut.step(DT, 1e-3, 0.0)
    assert dut.state.i_n == pytest.approx(1e6 * 1e-3 * 50 * DT)


def test_output_clamp_of_pid_term_and_total():
    dut = Pid(PidConfig(kp_n_m=1e4, ki_n_m_s=0.0, kd_n_s_m=0.0, max_force_n=2.0))
    u = dut.step(DT, -1e-3, 0.0, u_other_n=0.5)
    assert dut.state.u_pid_n == -2.0 and u == -1.5
    u = dut.step(DT, -1e-3, 0.0, u_other_n=-5.0, limit_n=3.0)
    assert u == -3.0 and dut.state.saturated == -1


def test_derivative_filter_step_response():
    fc = 100.0
    dut = Pid(PidConfig(kp_n_m=0.0, ki_n_m_s=0.0, kd_n_s_m=10.0, derivative_cutoff_hz=fc, derivative_on="error"))
    beta = math.exp(-2 * math.pi * fc * DT)
    dut.step(DT, 0.0, 0.0)
    u0 = dut.step(DT, 1e-6, 0.0)  # error step of 1 µm
    raw = 10.0 * 1e-6 / DT
    assert u0 == pytest.approx(raw * (1 - beta))
    u1 = dut.step(DT, 1e-6, 0.0)  # constant error afterwards: exponential decay
    assert u1 == pytest.approx(u0 * beta)
    for _ in range(200):
        u = dut.step(DT, 1e-6, 0.0)
    assert abs(u) < 1e-12


def test_derivative_on_measurement_ignores_reference_steps():
    dut = Pid(PidConfig(kp_n_m=0.0, ki_n_m_s=0.0, kd_n_s_m=10.0, derivative_on="measurement"))
    dut.step(DT, 0.0, 0.0)
    assert dut.step(DT, 5e-6, 0.0) == 0.0  # reference jumps, measurement still: no kick
    # the measurement moving at 1 mm/s with v_ref = 1 mm/s gives no derivative action either
    x = 0.0
    for _ in range(20):
        x += 1e-3 * DT
        u = dut.step(DT, x, x, v_ref_m_s=1e-3)
    assert abs(u) < 1e-12


def test_bumpless_enable_and_disable():
    dut = Pid(PidConfig())
    dut.disable()
    assert dut.step(DT, 1e-6, 0.0, u_other_n=0.25) == 0.25  # disabled: only the other terms
    assert dut.state.i_n == 0.0
    dut.enable(u_pid_now_n=0.8, error_m=2e-7)
    u = dut.step(DT, 2e-7, 0.0)
    # first output equals the held force plus one integration step
    assert u == pytest.approx(0.8 + PidConfig().ki_n_m_s * 2e-7 * DT, rel=1e-9)


def test_retune_is_bumpless():
    dut = Pid(PidConfig(kp_n_m=1e4, ki_n_m_s=1e5, kd_n_s_m=50.0))
    x = 0.0
    for k in range(100):
        x = 1e-6 * math.sin(k * 0.05)
        dut.step(DT, 2e-6, x)
    before = dut.step(DT, 2e-6, x)
    d_before = dut.state.deriv_m_s
    dut.retune(PidConfig(kp_n_m=4e4, ki_n_m_s=3e5, kd_n_s_m=200.0))
    after = dut.step(DT, 2e-6, x)
    # same error and measurement: the output changes only by one integration step of the new Ki and the
    # decay of the (gain-independent) filtered derivative -- not by the 4x jump of Kp·e
    expected = before + 3e5 * dut.state.error_m * DT + 200.0 * (dut.state.deriv_m_s - d_before)
    assert after == pytest.approx(expected, abs=1e-12)
    assert abs(after - before) < 0.1 * abs(3e4 * dut.state.error_m)


@pytest.mark.parametrize("dt", [0.0, -1e-3, math.nan, math.inf])
def test_bad_dt_raises(dt):
    with pytest.raises(ValueError, match="dt"):
        Pid(PidConfig()).step(dt, 0.0, 0.0)


def test_config_rejects_bad_values_with_units():
    with pytest.raises(ConfigError) as ei:
        load(PidConfig, {"kp_n_m": -1, "derivative_cutoff_hz": 0, "derivative_on": "setpoint", "kp": 3},
             "controller.pid")
    msg = str(ei.value)
    assert "controller.pid.kp_n_m: must be >= 0 N/m" in msg
    assert "controller.pid.derivative_cutoff_hz" in msg
    assert "controller.pid.derivative_on" in msg
    assert "controller.pid.kp: unknown key" in msg
