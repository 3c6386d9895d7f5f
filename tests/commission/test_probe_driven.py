"""The sanity probe on a light, high-friction, heavily damped stage (found by an outside-in check of a stage the
code never saw): 1 kg, GMS friction with 3.2 N static and 2.5 N Coulomb, 40 N s/m viscous (m/c = 25 ms), a drive
at 10 mN per unit, behind the shipped seed-stage config (2 kg expected).

The probe's levels (4.3 N and 7 N, from the ~3 N breakaway) reach the speed cap within 7 and 3 cycles, too few for
two accelerations: the commissioning stopped in the sanity stage ("the accelerations under two force levels could
not be measured") on a healthy stage. The mass now comes from a fit of m·ẍ + c·ẋ + F_f = F over every cycle the
probe drove (levels and brake). The end-to-end run stops with an injected fault early in the FRF, right after the
probe (simulated time, ~3 s CPU).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from support import shipped_config_mapping  # noqa: E402

from stagectl.cli import main  # noqa: E402
from stagectl.commission.analysis import probe_driven_fit  # noqa: E402

PLANT = {"mass_kg": 1.0,
         "friction": {"model": "gms", "k_n_m": [2.0e5, 5.0e4, 1.5e4, 5.0e3], "alpha": [0.4, 0.3, 0.2, 0.1],
                      "fs_n": 3.2, "fc_n": 2.5, "vs_m_s": 0.002, "delta": 2, "c_n_s": 3.0e4,
                      "viscous_n_s_m": 40.0, "sigma1_n_s_m": [74.0, 18.5, 5.6, 1.9]}}


def test_a_damped_high_friction_stage_passes_the_probe_with_its_mass(tmp_path: Path) -> None:
    (tmp_path / "plant.yaml").write_text(yaml.safe_dump(PLANT))
    data = shipped_config_mapping("sim.yaml")
    data["sim"]["plant"]["model_file"] = str(tmp_path / "plant.yaml")
    data["sim"]["drive"]["force_per_unit_n"] = 0.01
    cfg = tmp_path / "stage.yaml"
    cfg.write_text(yaml.safe_dump(data))
    out = tmp_path / "o"
    rc = main(["commission", "--config", str(cfg), "--out", str(out), "--no-plots", "--quiet",
               "--inject-fault", "frf@0.05"])
    rep = json.loads((out / "report.json").read_text())
    assert rc == 1 and rep["aborted"]["experiment"] == "frf", rep["aborted"]   # past the probe (main: "sanity")
    s = rep["sanity"]
    assert s["mass_from"] == "driven", s
    assert abs(s["mass_kg"] / PLANT["mass_kg"] - 1) < 0.1, s
    for f in s["driven_fit"]:
        assert f["samples"] < 20   # the levels were short indeed: the two-acceleration mass had no data
        assert abs(f["viscous_n_s_m"] / 40.0 - 1) < 0.25 and abs(f["friction_n"] / 2.5 - 1) < 0.1, f


def _reference_drive(m: float, c: float, fc: float, delay: int, forces: list[tuple[float, int]], pre: float = 3.0,
                     T: float = 1e-3, noise_m: float = 0.5e-9, seed: int = 0) -> tuple[list[float], list[float]]:
    """Plain reference: m·ẍ + c·ẋ + fc = u(t − delay·T) (moving forward), exact zero-order-hold step per cycle,
    the probe's commanded forces held for the given cycle counts; before them ``pre`` acts (the ramp's breakaway),
    the stage starting at rest."""
    rng = np.random.default_rng(seed)
    a = c / m
    e = np.exp(-a * T)
    us = [f for f, k in forces for _ in range(k)]
    q = [pre] * delay
    x = v = 0.0
    xs, out = [], []
    for u in us:
        xs.append(x + noise_m * rng.standard_normal())
        out.append(u)
        q.append(u)
        f = q.pop(0) - fc
        vinf = f / c
        x += vinf * T + (v - vinf) * (1 - e) / a
        v = vinf + (v - vinf) * e
    return xs, out


@pytest.mark.parametrize("delay", [0, 1, 2])
def test_the_driven_fit_recovers_mass_viscous_and_friction(delay: int) -> None:
    # 1 kg, 40 N s/m, 2.5 N: 7 cycles at 4.3 N, 3 at 7 N, 5 of brake at -7 N (the stage still moves forward)
    xs, us = _reference_drive(1.0, 40.0, 2.5, delay, [(4.3, 7), (7.0, 3), (-7.0, 5)])
    f = probe_driven_fit(xs, us, 3.0, 1e-3)
    assert f is not None and f["delay_samples"] == delay
    assert f["mass_kg"] == pytest.approx(1.0, rel=0.02)
    assert f["viscous_n_s_m"] == pytest.approx(40.0, rel=0.1)
    assert f["friction_n"] == pytest.approx(2.5, rel=0.02)
    # the same motion in the - direction (forces and positions mirrored)
    g = probe_driven_fit([-x for x in xs], [-u for u in us], 3.0, 1e-3, sign=-1)
    assert g is not None and g["mass_kg"] == pytest.approx(f["mass_kg"], rel=1e-9)
    # too little to fit: one level only, or too few cycles
    assert probe_driven_fit(*_reference_drive(1.0, 40.0, 2.5, 1, [(4.3, 12)]), 3.0, 1e-3) is None
    assert probe_driven_fit(*_reference_drive(1.0, 40.0, 2.5, 1, [(4.3, 3), (7.0, 3), (-7.0, 2)]), 3.0, 1e-3) is None
