"""``model_file`` is read by the configuration loader only: every other parse route of a plant refuses it
(instead of silently ignoring the file), and the loader's route keeps it with the resolved model."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from stagectl.config import AppConfig, load_app_config
from stagectl.errors import ConfigError
from stagectl.friction import load_model_file
from stagectl.schema import load
from stagectl.sim.plant import PlantConfig
from stagectl.sim.world import SimWorldConfig

from support import cli_in_process

REPO = Path(__file__).resolve().parents[2]
MODEL = REPO / "config" / "models" / "kamenar2016_gms.yaml"
NOT_LOADED = "model_file: does/not/exist.yaml is not loaded"


@pytest.mark.parametrize("route", [
    lambda d: load(SimWorldConfig, {"plant": d}, "sim"),
    lambda d: load(PlantConfig, d, "sim.plant"),
    lambda d: SimWorldConfig.from_mapping({"plant": d}),
    lambda d: PlantConfig.from_mapping(d, "sim.plant"),
    lambda d: load(AppConfig, {"sim": {"plant": d}, "safety": {}, "controller": {}}),
])
def test_every_route_refuses_an_unresolved_model_file(route):
    plant = {"model_file": "does/not/exist.yaml", "mass_kg": 2.0,
             "friction": {"model": "stribeck", "fc_n": 1.0, "fs_n": 1.5, "vs_m_s": 1e-3}}
    with pytest.raises(ConfigError) as ei:
        route(plant)
    assert any(f"sim.plant.{NOT_LOADED}" in p for p in ei.value.problems), ei.value.problems


def test_the_resolved_model_is_taken_and_the_key_kept():
    model = load_model_file(MODEL)
    got = PlantConfig.from_mapping({"model_file": "models/x.yaml"}, "sim.plant", model)
    assert got.model_file == "models/x.yaml" and got.mass_kg == model.mass_kg and got.friction == model.friction
    cfg = load_app_config(REPO / "config" / "sim.yaml")
    assert cfg.sim is not None and cfg.sim.plant.model_file == "models/kamenar2016_gms.yaml"


def test_check_config_still_reads_the_model_file(tmp_path):
    data = yaml.safe_load((REPO / "config" / "sim.yaml").read_text())
    data["sim"]["plant"]["model_file"] = "does/not/exist.yaml"
    data["controller"]["feedforward"]["model_file"] = str(MODEL)
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(data))
    r = cli_in_process(["check-config", str(p)])  # what check-config says, not a process start
    assert r.returncode == 2 and "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("stagectl: error:")]
    assert len(lines) == 1 and "sim.plant.model_file:" in lines[0] and "exist.yaml" in lines[0]


@pytest.mark.parametrize("command", [["check-config"], ["simulate", "--scenario", "cosine", "--out", "OUT", "--config"]])
def test_a_model_file_given_as_a_stage_config_is_one_line(command, tmp_path):
    # the reverse of `model plot STAGE.yaml`: a user passes the model file where the stage config belongs
    argv = [a.replace("OUT", str(tmp_path / "out")) for a in command] + [str(MODEL)]
    r = cli_in_process(argv)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("stagectl: error:")]
    assert len(lines) == 1, r.stderr
    assert "is a friction model file, not a stage config" in lines[0] and "model_file" in lines[0], lines[0]
