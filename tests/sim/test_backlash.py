"""Backlash plant (motor + load through a deadband), checked against plain kinematics: lost motion at a
reversal equals the play, the load does not move while the play is open, and the rigid-body terminal speed
holds once it is closed."""

from __future__ import annotations

import numpy as np
import pytest
from stagectl.sim.backlash import BacklashPlant

PLANT = {"mass_kg": 2.0, "friction": {"model": "stribeck", "fc_n": 1.0, "fs_n": 1.0, "viscous_n_s_m": 10.0,
                                      "stick_velocity_m_s": 1e-6},
         "sensor": {"resolution_m": 1e-9}}


@pytest.mark.parametrize("friction_side,sensor_side", [("load", "motor"), ("motor", "load")])
def test_lost_motion_at_reversal_equals_the_play(friction_side: str, sensor_side: str) -> None:
    gap = 50e-6
    bl = {"gap_m": gap, "other_mass_kg": 0.5, "friction_side": friction_side, "sensor_side": sensor_side,
          "contact_stiffness_n_m": 2e5, "coupling_step_s": 1e-4}
    dut = BacklashPlant.from_mapping(PLANT, bl)
    dt = 1e-3
    for _ in range(2000):  # push +3 N: both bodies move together at the rigid-body terminal speed
        dut.step(3.0, dt)
    assert dut.v_m_s == pytest.approx((3.0 - 1.0) / 10.0, rel=0.02)
    k = 2e5
    f_load = 3.0 if friction_side == "load" else 0.0  # the contact carries the load's friction 1 + 10·0.2 N
    assert dut.x_motor_m - dut.x_load_m == pytest.approx(0.5 * gap + f_load / k, abs=0.1 * gap)  # + side
    # reverse: the contact opens, the motor crosses the play (lost motion), the contact closes on the other side
    d_open = d_close = None
    for i in range(12000):  # 0.2 s finely (the crossing takes a few ms), then 1.8 s at the control period
        was = dut.contact_force_n
        dut.step(-1.5, 2e-5 if i < 10000 else dt)
        d = dut.x_motor_m - dut.x_load_m
        if d_open is None and was > 0.0 and dut.contact_force_n == 0.0:
            d_open = d
        if d_open is not None and d_close is None and dut.contact_force_n < 0.0:
            d_close = d
    if friction_side == "load":
        assert d_open is not None and d_close is not None
        # the contact opens at +b/2 plus what is left of its elastic deflection, and closes at −b/2: the motor
        # crossed the whole play (lost motion b) with the load disengaged
        assert d_open >= 0.5 * gap
        assert d_close == pytest.approx(-0.5 * gap, abs=0.05 * gap)
    f_load = 1.5 if friction_side == "load" else 0.0
    assert dut.x_motor_m - dut.x_load_m == pytest.approx(-0.5 * gap - f_load / k, abs=0.1 * gap)  # − side
    assert dut.v_m_s == pytest.approx(-(1.5 - 1.0) / 10.0, rel=0.05)
    # the sensor reads the chosen side
    want = dut.x_motor_m if sensor_side == "motor" else dut.x_load_m
    assert dut.measure() == pytest.approx(want, abs=2e-9)


def test_zero_play_moves_as_one_body() -> None:
    dut = BacklashPlant.from_mapping(PLANT, {"gap_m": 0.0, "other_mass_kg": 0.5, "contact_stiffness_n_m": 2e5,
                                             "coupling_step_s": 1e-4})
    xs = []
    for k in range(300):
        dut.step(3.0 if k < 150 else -3.0, 1e-3)
        xs.append(dut.x_motor_m - dut.x_load_m)
    assert np.max(np.abs(xs)) < 1e-4


@pytest.mark.parametrize("friction_side", ["load", "motor"])
def test_compiled_loop_matches_the_python_reference(friction_side: str) -> None:
    """The fused numba loop integrates the same equations as the plain-Python reference over StagePlant.step
    (same coupling step, same sub-steps): with a static friction model (Karnopp band), a cogging force and a
    viscous asymmetry on the friction side, through reversals, the trajectories agree to rounding."""
    plant = {**PLANT, "effects": {"cogging": {"amplitude_n": 0.3, "wavelength_m": 2e-5, "phase_rad": 0.4},
                                  "viscous_asymmetry": {"difference_n_s_m": 2.0}}}
    bl = {"gap_m": 20e-6, "other_mass_kg": 0.5, "friction_side": friction_side, "contact_stiffness_n_m": 2e5,
          "coupling_step_s": 1e-4}
    fused = BacklashPlant.from_mapping(plant, bl)
    ref = BacklashPlant.from_mapping(plant, bl, fused=False)
    rng = np.random.default_rng(7)
    u = np.repeat(rng.uniform(-4.0, 4.0, 40), 25)  # 40 force levels held 25 ms each: stick, slip, reversals
    d = []
    for k, uk in enumerate(u):
        fused.step(float(uk), 1e-3)
        ref.step(float(uk), 1e-3)
        assert fused.contact_force_n == pytest.approx(ref.contact_force_n, abs=1e-6 + 1e-6 * abs(ref.contact_force_n))
        d.append(abs(fused.x_motor_m - ref.x_motor_m) + abs(fused.x_load_m - ref.x_load_m))
    assert max(d) < 1e-12 + 1e-9 * float(np.ptp([ref.x_motor_m, 0.0]))
    assert abs(ref.x_motor_m) > 1e-5  # it moved
    assert fused.friction_n == pytest.approx(ref.friction_n, abs=1e-9)
