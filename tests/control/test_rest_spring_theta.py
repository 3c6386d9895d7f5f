"""The rest spring and the feed-forward's adapted scale θ (controller docstring, "Rest spring"): the spring
follows θ only up to 1 (a larger spring thins the rest loop's margins), and ``stagectl tune`` reports the rest
loop worst case over the θ range the configuration allows, saying so when the design fails there."""

from __future__ import annotations

import dataclasses
import json

import pytest

from stagectl.cli import main


@pytest.fixture(scope="module")
def seed(repo_root):
    from stagectl.config import load_app_config

    return load_app_config(repo_root / "config" / "sim.yaml")


def _spring_force(seed, theta: float) -> float:
    """The rest spring's force [N] after 0.3 s at rest 150 nm off the reference with the model scale θ."""
    from stagectl.control.api import Reference
    from stagectl.control.controller import StageController

    # the full spring at once (a synthetic position: no force to see the stage held by)
    ctl = StageController(dataclasses.replace(seed.controller, rest_spring_unconfirmed_kp_fraction=1e9), seed.timing)
    ctl.reset(0.0)
    ctl.ff_scale = theta
    for _ in range(300):
        ctl.step(seed.loop.period_s, 150e-9, Reference(0.0, 0.0, 0.0))
    return ctl._s_rest


def _write(data, tmp_path, name):
    import yaml

    p = tmp_path / name
    p.write_text(yaml.safe_dump(data))
    return p


def test_the_rest_spring_follows_theta_only_up_to_one(seed):
    c = seed.controller
    k_v = c.rest_stiffness_fraction * c.feedforward.model.friction.stiffness_n_m
    assert _spring_force(seed, 1.0) == pytest.approx(k_v * 150e-9, rel=1e-3)
    assert _spring_force(seed, 1.5) == pytest.approx(k_v * 150e-9, rel=1e-3)  # not 1.5x: capped
    assert _spring_force(seed, 0.6) == pytest.approx(0.6 * k_v * 150e-9, rel=1e-3)


def test_tune_reports_the_rest_loop_worst_case_over_theta(repo_root, capsys, seed):
    """config/sim.yaml adapts θ within 1 ± 0.5: tune sweeps the spring's θ over 0.5..1 (capped), the stuck-plant
    figures are the sweep's worst (with the rest gains of config/sim.yaml at θ = 0.5: there the margins rise with
    the spring), each sweep point equal to design.analyse_rest at that θ (the oracle); with the learning off θ
    stays 1."""
    from stagectl.control.design import analyse_rest

    main(["tune", "--config", str(repo_root / "config" / "sim.yaml"), "--bandwidth-hz", "200", "--json"])
    rest = json.loads(capsys.readouterr().out)["configured"]["rest"]
    assert rest["theta_range"] == [0.5, 1.0]
    sweep = rest["theta_sweep"]
    assert len(sweep) == 5 and not rest["stuck_unstable_at_theta"]
    pms = [r["phase_margin_deg"] for r in sweep]
    assert pms == sorted(pms) and pms[-1] - pms[0] > 1.0  # the margin depends on the spring's θ
    c = seed.controller
    fr = seed.sim.plant.friction
    for r in (sweep[0], sweep[-1]):
        stuck, _ = analyse_rest(2.0, seed.loop.period_s, c.pid, seed.io.delay_cycles, c.dob.bandwidth_hz,
                                c.dob.command_delay_samples, fr.stiffness_n_m, fr.damping_n_s_m,
                                r["theta"] * rest["rest_spring_n_m"], c.velocity_cutoff_hz,
                                kd_fraction=c.rest_kd_fraction, dob_bandwidth_fraction=c.rest_dob_bandwidth_fraction,
                                spring_sections=c.rest_spring_section_count)
        assert r["phase_margin_deg"] == pytest.approx(stuck.phase_margin_deg)
        assert r["gain_margin_db"] == pytest.approx(stuck.gain_margin_db)
    worst = rest["loops"]["rest/stuck"]
    assert worst["phase_margin_deg"] == min(pms) and worst["theta"] == 0.5
    assert worst["gain_margin_db"] == min(r["gain_margin_db"] for r in sweep)


def test_tune_says_when_the_rest_loop_fails_within_the_theta_range(tmp_path, capsys):
    """A stage whose pre-sliding stiffness is 0.3x its model's: the rest loop on the stuck stage is stable at
    θ = 0.5 but unstable at θ = 1; tune names the θ values, prints it and exits 1."""
    import yaml

    from stagectl.config import load_app_config
    from tests.support import shipped_config_mapping

    data = shipped_config_mapping("sim.yaml")
    cfg = load_app_config(_write(data, tmp_path, "base.yaml"))
    spec = dict(cfg.sim.plant.friction.spec())
    spec["k_n_m"] = [0.3 * k for k in spec["k_n_m"]]
    spec["sigma1_n_s_m"] = [0.3 * c for c in spec["sigma1_n_s_m"]]
    model = tmp_path / "soft.yaml"
    model.write_text(yaml.safe_dump({"mass_kg": cfg.sim.plant.mass_kg, "friction": spec}))
    data["sim"]["plant"]["model_file"] = str(model)
    path = _write(data, tmp_path, "soft_stage.yaml")
    assert main(["tune", "--config", str(path), "--bandwidth-hz", "200", "--json"]) == 1
    rest = json.loads(capsys.readouterr().out)["configured"]["rest"]
    at = rest["stuck_unstable_at_theta"]
    assert 1.0 in at and 0.5 not in at
    assert rest["theta_sweep"][0]["closed_loop_stable"] is True
    assert rest["loops"]["rest/stuck"]["closed_loop_stable"] is False
    main(["tune", "--config", str(path), "--bandwidth-hz", "200"])
    assert "the rest loop is UNSTABLE on the stuck stage at theta" in capsys.readouterr().out


def test_a_config_without_learning_keeps_theta_one(tmp_path, capsys):
    from tests.support import shipped_config_mapping

    data = shipped_config_mapping("sim.yaml")
    data["controller"]["feedforward"]["adapt_bandwidth_hz"] = 0.0
    data["controller"]["feedforward"]["learn_moves_fraction"] = 0.0
    main(["tune", "--config", str(_write(data, tmp_path, "fixed.yaml")), "--bandwidth-hz", "200", "--json"])
    rest = json.loads(capsys.readouterr().out)["configured"]["rest"]
    assert rest["theta_range"] == [1.0, 1.0] and len(rest["theta_sweep"]) == 1
