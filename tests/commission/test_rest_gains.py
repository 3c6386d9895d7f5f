"""Commissioning chooses the rest loop's gains (``choose_rest_gains``) when it advises the rest spring: the
stage.yaml it writes carries gains whose rest loop on the stuck stage meets the 40° / 8 dB floor by ``tune``'s own
analysis (before, it wrote the spring with the controller's own rest gains: PM 29°, GM 5.7 dB on config/sim.yaml's
stage)."""

from __future__ import annotations

from pathlib import Path

import yaml

from stagectl.commands.tune import _rest_loops
from stagectl.commission.sequence import REST_SPRING, choose_rest_gains, controller_mapping
from stagectl.config.loader import parse_app_config
from stagectl.control.pid import PidConfig

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "config" / "models" / "kamenar2016_gms.yaml"


def test_commissioned_rest_gains_meet_the_floor_by_tunes_analysis() -> None:
    T, nd, m = 1e-3, 1, 1.95
    # the gains commissioning chose for config/sim.yaml's stage (22 Hz PID, 110 Hz Q-filter observer)
    pid = {"kp_n_m": 11633.0, "ki_n_m_s": 160802.0, "kd_n_s_m": 252.5, "derivative_cutoff_hz": 110.0}
    mapping = {"loop": {"period_s": T}, "io": {"kind": "plant_io", "sensor": "drive", "delay_cycles": nd},
               "sim": {"plant": {"model_file": str(MODEL)}},
               "safety": yaml.safe_load((ROOT / "config" / "sim.yaml").read_text())["safety"]}
    plant_fr = parse_app_config({**mapping, "controller": {"mass_kg": m, "feedforward": {"kind": "none"}}}, ROOT / "x.yaml").sim.plant.friction
    k, c = float(plant_fr.stiffness_n_m), float(plant_fr.damping_n_s_m)  # type: ignore[union-attr]
    phi = float(REST_SPRING["rest_stiffness_fraction"])
    choice = choose_rest_gains(m, T, PidConfig(**pid), nd, 110.0, k, c, phi * k)
    assert choice["summary"]["chosen"] == "grid" and choice["loops"]["rest/stuck"]["healthy"]

    def tune_stuck(rest_gains: dict[str, float]) -> dict[str, float]:
        entry = {"pid": pid, "dob_kind": "qfilter", "dob_bandwidth_hz": 110.0,
                 "rest": {"enabled": True, **REST_SPRING, **rest_gains}}
        ctl = controller_mapping(entry, m, nd, T, nd * T, None, 10.0, str(MODEL))
        app = parse_app_config({**mapping, "controller": ctl}, ROOT / "x.yaml")
        rest = _rest_loops(app, app.controller, m, m, T, nd)
        assert rest is not None
        return rest["loops"]["rest/stuck"]  # type: ignore[no-any-return]

    stuck = tune_stuck(choice["gains"])
    assert stuck["closed_loop_stable"] and stuck["phase_margin_deg"] >= 40.0 and stuck["gain_margin_db"] >= 8.0
    assert abs(stuck["phase_margin_deg"] - choice["loops"]["rest/stuck"]["phase_margin_deg"]) < 0.5
    # the controller's own rest gains (what stage.yaml carried before) do not meet it on this stage
    own = tune_stuck({"rest_kd_fraction": 1.0, "rest_dob_bandwidth_fraction": 1.0, "rest_spring_section_count": 1})
    assert own["phase_margin_deg"] < 40.0 or own["gain_margin_db"] < 8.0
