"""review: the rest spring stiffness test's force witness (a second Q-filter observer on the whole command) is
retuned in place by a settings change, as the observer is, not rebuilt: with ``dob.nominal_mass_kg`` set its
mass is the nominal one, which never equals the controller's mass, so main rebuilt it (an allocation, and its
low-pass restarted from the command) at every retune, even one that changed nothing of the observer."""

from __future__ import annotations

import dataclasses
from typing import Any

PERIOD = 1e-3


def test_witness_is_retuned_in_place_with_a_nominal_mass(repo_root: Any) -> None:
    from stagectl.config import load_app_config
    from stagectl.control.controller import StageController
    from stagectl.control.trajectory import Reference

    cfg = load_app_config(repo_root / "config" / "sim.yaml")
    c = dataclasses.replace(cfg.controller, dob=dataclasses.replace(cfg.controller.dob, nominal_mass_kg=2.6))
    ctl = StageController(c, PERIOD)
    ctl.reset(0.0)
    rest = Reference(x_m=0.0, v_m_s=0.0, a_m_s2=0.0)
    for k in range(50):  # at rest, the stage 1 µm off: a force builds up
        ctl.step(PERIOD, -1e-6, rest)
    hw = ctl._hw
    assert hw.mass_kg == 2.6
    witness = (hw.state.d_hat_n, hw.state.w_n, hw._alpha)
    assert abs(witness[0]) > 1e-3  # the witness has been stepped: a force to keep
    ctl.retune(dataclasses.replace(c, velocity_cutoff_hz=200.0))  # nothing of the observer changes
    assert ctl._hw is hw and (hw.state.d_hat_n, hw.state.w_n, hw._alpha) == witness
    ctl.retune(dataclasses.replace(c, dob=dataclasses.replace(c.dob, bandwidth_hz=0.5 * c.dob.bandwidth_hz)))
    assert ctl._hw is hw and hw.cfg.bandwidth_hz == 0.5 * c.dob.bandwidth_hz and hw.mass_kg == 2.6
    assert hw.state.d_hat_n == witness[0] and hw._alpha > witness[2]  # bumpless; a slower low-pass
    ctl.retune(dataclasses.replace(c, dob=dataclasses.replace(c.dob, nominal_mass_kg=None)))
    assert ctl._hw is hw and hw.mass_kg == ctl.mass_kg
