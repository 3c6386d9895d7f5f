"""Every shipped configuration loads; typos and bad values are rejected with their key path, all at once."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from stagectl.commands.check_config import run as check_config_run
from stagectl.config import IoKind, SensorSource, load_app_config, parse_app_config
from stagectl.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]
SHIPPED = sorted((REPO / "config").glob("*.yaml"))


def test_the_four_configs_are_shipped():
    names = {p.name for p in SHIPPED}
    assert {"sim.yaml", "hil-canopen.yaml", "hil-serial.yaml", "stage-canopen.yaml"} <= names


@pytest.mark.parametrize("path", SHIPPED, ids=[p.name for p in SHIPPED])
def test_every_shipped_config_loads(path):
    cfg = load_app_config(path)
    assert cfg.path == path.resolve()
    assert cfg.loop.period_s == pytest.approx(1e-3)
    assert cfg.controller is not None
    assert cfg.safety.min_position_m < 0 < cfg.safety.max_position_m
    if cfg.io.kind is IoKind.CANOPEN:
        assert cfg.io.drive is not None


def test_sim_yaml_is_the_seed_stage():
    cfg = load_app_config(REPO / "config" / "sim.yaml")
    assert cfg.io.kind is IoKind.EMBEDDED_CANOPEN  # the real CiA 402 driver against the virtual drive
    assert cfg.sim is not None and cfg.sim.transport.kind == "virtual"
    plant = cfg.sim.plant
    assert plant.mass_kg == 2.0
    assert plant.sensor.resolution_m == 1e-9
    fr = plant.friction
    assert fr.tag == "gms"
    assert fr.params.fs_n == pytest.approx(0.9)
    assert tuple(fr.params.k_n_m)[0] == pytest.approx(454610.0)


def _sim_mapping():
    """config/sim.yaml with its model paths made absolute (so a copy can live in tmp_path)."""
    data = yaml.safe_load((REPO / "config" / "sim.yaml").read_text())
    model = str(REPO / "config" / "models" / "kamenar2016_gms.yaml")
    data["sim"]["plant"]["model_file"] = model
    data["controller"]["feedforward"]["model_file"] = model
    return data


def _problems(data, tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as ei:
        load_app_config(p)
    return ei.value.problems


def test_typos_rejected_with_their_path_all_at_once(tmp_path):
    data = _sim_mapping()
    data["loop"]["perod_s"] = 0.001
    data["safety"]["max_force_N"] = 3
    data["controller"]["pid"]["kp_n_m"] = -5.0
    data["io"]["kind"] = "ethercat"
    data["sim"]["plant"]["sensor"]["resolution"] = 1e-9
    data["telemetry"] = {}
    probs = _problems(data, tmp_path)
    text = "\n".join(probs)
    assert "bad.yaml: loop.perod_s: unknown key (did you mean period_s?)" in text
    assert "safety.max_force_N: unknown key (did you mean max_force_n?)" in text
    assert "controller.pid.kp_n_m: must be >= 0 N/m (got -5 N/m)" in text
    assert "io.kind: must be one of plant_io, embedded_canopen, canopen (got 'ethercat')" in text
    assert "sim.plant.sensor.resolution: unknown key" in text
    assert "telemetry: unknown key" in text
    assert len(probs) >= 6


def test_cross_section_checks(tmp_path):
    data = _sim_mapping()
    data["safety"]["min_position_m"] = 0.01
    data["io"] = {"kind": "canopen", "sensor": "interferometer"}
    del data["controller"]
    probs = "\n".join(_problems(data, tmp_path))
    assert "io.drive: required for io.kind canopen" in probs
    assert "io.interferometer: required for io.sensor interferometer" in probs
    assert "safety.max_position_m: must be > min_position_m" in probs
    assert "controller: required key missing" in probs


def test_socketcand_bus_needs_host_and_port(tmp_path):
    data = yaml.safe_load((REPO / "config" / "hil-canopen.yaml").read_text())
    del data["io"]["drive"]["can"]["port"]
    data["controller"]["feedforward"]["model_file"] = str(REPO / "config" / "models" / "kamenar2016_gms.yaml")
    data["sim"]["plant"]["model_file"] = str(REPO / "config" / "models" / "kamenar2016_gms.yaml")
    probs = "\n".join(_problems(data, tmp_path))
    assert "io.drive.can.port: required for interface socketcand" in probs


def test_model_file_paths_are_relative_to_the_yaml(tmp_path):
    data = _sim_mapping()
    data["sim"]["plant"]["model_file"] = "models/nowhere.yaml"
    probs = "\n".join(_problems(data, tmp_path))
    assert "sim.plant.model_file" in probs and "nowhere.yaml" in probs


def test_yaml_syntax_and_top_level_errors(tmp_path):
    p = tmp_path / "broken.yaml"
    p.write_text("loop: {period_s: 0.001\n")
    with pytest.raises(ConfigError, match="YAML syntax error at line"):
        load_app_config(p)
    with pytest.raises(ConfigError, match="expected a mapping"):
        parse_app_config([1, 2], tmp_path / "x.yaml")


def test_check_config_command_ok_and_errors(tmp_path, capsys):
    import argparse

    assert check_config_run(argparse.Namespace(file=str(REPO / "config" / "sim.yaml"), quiet=False)) == 0
    assert "OK" in capsys.readouterr().out
    data = _sim_mapping()
    data["loop"]["period_s"] = "fast"
    data["safety"]["stale_cycles"] = 0
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(data))
    assert check_config_run(argparse.Namespace(file=str(p), quiet=False)) == 2
    err = capsys.readouterr().err
    assert "2 problems" in err
    assert "loop.period_s: expected a number s, got 'fast'" in err
    assert "safety.stale_cycles: must be >= 1" in err


def test_check_config_cli_exit_code(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("safety: {min_position_m: 0, max_position_m: 1, bogus: 1}\n")
    r = subprocess.run([sys.executable, "-m", "stagectl.cli", "check-config", str(p)], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2
    assert "safety.bogus: unknown key" in r.stderr
    assert "Traceback" not in r.stderr
    # the same file as the other commands take it (--config), and a file given twice refused
    r2 = subprocess.run([sys.executable, "-m", "stagectl.cli", "check-config", "--config", str(p)],
                        capture_output=True, text=True, timeout=120)
    assert (r2.returncode, r2.stderr) == (r.returncode, r.stderr)
    r3 = subprocess.run([sys.executable, "-m", "stagectl.cli", "check-config", str(p), "--config", str(p)],
                        capture_output=True, text=True, timeout=120)
    assert r3.returncode == 2 and r3.stderr.count("\n") == 1 and "give the file once" in r3.stderr


def test_sensor_choice_for_plant_io_rejected(tmp_path):
    data = _sim_mapping()
    data["io"]["kind"] = "plant_io"
    data["io"]["sensor"] = "interferometer"
    probs = "\n".join(_problems(data, tmp_path))
    assert "io.sensor: plant_io measures through the plant itself" in probs
    assert SensorSource("drive") is SensorSource.DRIVE


def test_missing_model_file_named_for_each_key_without_follow_up_noise(tmp_path):
    data = _sim_mapping()
    data["sim"]["plant"]["model_file"] = "models/nope.yaml"
    data["controller"]["feedforward"]["model_file"] = "models/nope.yaml"
    probs = _problems(data, tmp_path)
    assert any(p.startswith("bad.yaml: sim.plant.model_file:") and "nope.yaml" in p for p in probs)
    assert any("controller.feedforward.model_file:" in p and "nope.yaml" in p for p in probs)
    assert not any("sim: required" in p for p in probs)  # the sim section was given; its own error says why


def test_demo_scenario_is_validated(tmp_path):
    data = _sim_mapping()
    data["demo"] = {"scenario": "dmeo"}
    probs = "\n".join(_problems(data, tmp_path))
    assert "demo.scenario: unknown scenario 'dmeo' (known: cosine, triangle, steps, demo, hold)" in probs


@pytest.mark.parametrize("command", ["simulate", "run"])
def test_cli_bad_scenario_and_unwritable_out_fail_before_running(tmp_path, capsys, command):
    from stagectl.cli import main

    cfg = str(REPO / "config" / "sim.yaml")
    assert main([command, "--config", cfg, "--scenario", "nope", "--out", str(tmp_path / "o")]) == 2
    assert "stagectl: error: --scenario: unknown scenario 'nope'" in capsys.readouterr().err
    blocker = tmp_path / "afile"
    blocker.write_text("")
    assert main([command, "--config", cfg, "--scenario", "hold", "--duration", "0.05",
                 "--out", str(blocker / "sub")]) == 2
    err = capsys.readouterr().err
    assert "stagectl: error: --out: cannot write to directory" in err and "Not a directory" in err
    assert not (tmp_path / "o").exists()  # nothing was run or written
