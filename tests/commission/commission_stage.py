"""Shared helper: a stage configuration whose simulated plant is NOT the shipped model.

The commissioning config (controller, feed-forward model) says the seed stage (2 kg, Fc 0.8 N, 10 N s/m); the
plant behind it has mass 2.6 kg (+30 %), Coulomb 1.15 N (+44 %), viscous 14 N s/m (+40 %), static 1.3 N and a
hidden cogging force (0.15 N, 0.5 mm period). The commissioning reads only loop/io/safety/controller.
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = ROOT / "config" / "models" / "kamenar2016_gms.yaml"
HIDDEN = {"mass_kg": 2.6, "fc_n": 1.15, "viscous_n_s_m": 14.0, "cogging_wavelength_m": 0.5e-3}


def controller_and_safety_yaml() -> str:
    """The commissioning side's ``controller:`` and ``safety:`` sections: the seed stage's 40 Hz tuning and the
    shipped (wrong for the hidden plant) GMS model."""
    return f"""controller:
  mass_kg: 2.0
  max_force_n: 10.0
  pid: {{kp_n_m: 3.92e4, ki_n_m_s: 9.86e5, kd_n_s_m: 468.0, derivative_cutoff_hz: 200.0}}
  dob: {{kind: qfilter, bandwidth_hz: 100.0}}
  feedforward: {{kind: model, model_file: {SHIPPED}, inertia: true, lookahead_s: 0.0015}}
safety:
  min_position_m: -0.005
  max_position_m: 0.005
  following_error_m: 5.0e-5
  following_error_time_s: 0.01
  max_force_n: 10.0
  force_saturation_time_s: 0.5
  max_velocity_m_s: 0.02
  stale_cycles: 3
"""


def assert_identified(rep: dict, hidden: dict) -> None:
    """The commissioning's report found the hidden plant: complete, mass, Coulomb and viscous within 10 %, and
    the hidden cogging named."""
    assert rep["status"] == "complete"
    f = rep["fitted"]
    for key, true in (("mass_kg", hidden["mass_kg"]), ("coulomb_n", hidden["fc_n"]),
                      ("viscous_n_s_m", hidden["viscous_n_s_m"])):
        assert abs(f[key]["value"] / true - 1) < 0.10, (key, f[key], true)
    assert "cogging" in f["effects"]  # the hidden effect, named


def write_stage(path: Path, *, fc_n: float = 1.15, extra_plant: str = "") -> Path:
    models = SHIPPED
    path.write_text(f"""
description: commissioning test stage (hidden plant differs from the controller's model)
loop: {{period_s: 0.001}}
io: {{kind: plant_io, sensor: drive, delay_cycles: 1}}
sim:
  plant:
    model_file: {models}
    mass_kg: 2.6
    friction: {{fc_n: {fc_n}, fs_n: {fc_n + 0.15}, viscous_n_s_m: 14.0}}
    effects: {{cogging: {{amplitude_n: 0.15, wavelength_m: 0.0005}}}}
    sensor: {{resolution_m: 1.0e-9, noise_std_m: 0.5e-9}}
    actuator: {{max_force_n: 200.0}}
    seed: 3
{extra_plant}
""" + controller_and_safety_yaml())
    return path
