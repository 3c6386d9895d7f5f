"""Cross-checks of the loading pipeline: the force-limit chain, the ``can:`` keys of the chosen python-can
interface, model files resolved once, and check-config running exactly the daemon's validation."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
import yaml
from stagectl.drivers.canbus import accepted_bus_keys, can_key_problems

from stagectl.config import AppConfig, load_app_config, parse_app_config
from stagectl.config.checks import force_chain_problems
from stagectl.errors import ConfigError

from support import cli_in_process, config_problems, shipped_config_mapping

REPO = Path(__file__).resolve().parents[2]




def _check_config(tmp_path: Path, data: dict) -> subprocess.CompletedProcess[str]:
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(data))
    return cli_in_process(["check-config", str(p)])  # what check-config says, not a process start


def _error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("stagectl: error:")]


# ------------------------------------------------------------------------------------------ force chain
@pytest.mark.parametrize("name", sorted(p.name for p in (REPO / "config").glob("*.yaml")))
def test_shipped_configs_satisfy_the_force_chain(name):
    assert force_chain_problems(load_app_config(REPO / "config" / name)) == []


@pytest.mark.parametrize("name,keys,expect", [
    ("sim.yaml", {("controller", "max_force_n"): 15.0},
     "controller.max_force_n: 15 N exceeds safety.max_force_n 10 N"),
    ("stage-canopen.yaml", {("safety", "max_force_n"): 12.0, ("controller", "max_force_n"): 12.0},
     "safety.max_force_n: 12 N exceeds io.drive.max_force_n 10 N"),
    ("hil-canopen.yaml", {("io", "drive", "max_force_n"): 30.0, ("safety", "max_force_n"): 25.0,
                          ("controller", "max_force_n"): 25.0},
     "io.drive.max_force_n: 30 N exceeds sim.plant.actuator.max_force_n 20 N"),
    ("sim.yaml", {("sim", "plant", "actuator", "max_force_n"): 5.0},
     "safety.max_force_n: 10 N exceeds sim.plant.actuator.max_force_n 5 N"),
    ("sim.yaml", {("sim", "drive", "force_per_unit_n"): 1e-4},
     "safety.max_force_n: 10 N exceeds the drive's torque range 32767 x sim.drive.force_per_unit_n 3.2767 N"),
])
def test_each_broken_link_of_the_force_chain_is_one_line(name, keys, expect):
    data = shipped_config_mapping(name)
    for path, value in keys.items():
        d = data
        for k in path[:-1]:
            d = d.setdefault(k, {})
        d[path[-1]] = value
    probs = config_problems(data)
    assert len(probs) == 1, probs
    assert expect in probs[0] and probs[0].startswith("x.yaml: ")


def test_force_chain_through_check_config(tmp_path):
    data = shipped_config_mapping("stage-canopen.yaml")
    data["controller"]["max_force_n"] = 30.0
    r = _check_config(tmp_path, data)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    lines = _error_lines(r.stderr)
    assert lines == ["stagectl: error: bad.yaml: controller.max_force_n: 30 N exceeds safety.max_force_n 10 N "
                     "(the force limits must satisfy controller <= safety <= drive <= actuator)"]


# ------------------------------------------------------------------------------------------ can: keys
def test_can_typo_rejected_by_check_config_with_did_you_mean(tmp_path):
    data = shipped_config_mapping("stage-canopen.yaml")
    data["io"]["drive"]["can"] = {"interface": "socketcan", "channel": "can0", "bitrat": 1000000}
    r = _check_config(tmp_path, data)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    assert _error_lines(r.stderr) == [
        "stagectl: error: bad.yaml: io.drive.can.bitrat: unknown key for interface socketcan (did you mean bitrate?)"]


def test_can_keys_come_from_python_can():
    socketcan = accepted_bus_keys("socketcan")
    assert socketcan is not None
    assert {"channel", "bitrate", "receive_own_messages", "local_loopback", "fd"} <= socketcan
    socketcand = accepted_bus_keys("socketcand")
    assert socketcand is not None and {"host", "port", "tcp_tune"} <= socketcand
    assert accepted_bus_keys("no_such_interface") is None
    assert can_key_problems({"interface": "socketcand", "channel": "can0", "host": "h", "prot": 1},
                            path="io.drive.can") == [
        "io.drive.can.prot: unknown key for interface socketcand (did you mean port?)"]
    assert can_key_problems({"interface": "socketcn", "channel": "can0"}, path="c") == [
        "c.interface: unknown python-can interface 'socketcn' (did you mean socketcan?)"]
    assert can_key_problems({"interface": "virtual", "channel": "x", "receive_own_messages": True}) == []


def test_can_typo_in_every_can_section(tmp_path):
    data = shipped_config_mapping("hil-canopen.yaml")
    data["io"]["drive"]["can"]["hots"] = "127.0.0.1"
    probs = "\n".join(config_problems(data))
    assert "io.drive.can.hots: unknown key for interface socketcand (did you mean host?)" in probs


# ------------------------------------------------------------------------------------------ pipeline
def test_model_file_loaded_once_and_handed_to_plant_and_controller(monkeypatch):
    import stagectl.config.loader as loader

    calls: list[Path] = []
    real = loader.load_model_file

    def counting(path):
        calls.append(Path(path))
        return real(path)

    monkeypatch.setattr(loader, "load_model_file", counting)
    cfg = load_app_config(REPO / "config" / "sim.yaml")
    assert len(calls) == 1  # sim.plant and controller.feedforward name the same file
    model = cfg.controller.feedforward.model
    assert model is not None and model.mass_kg == 2.0 and model.friction.tag == "gms"
    assert cfg.sim is not None and cfg.sim.plant.friction == model.friction


def test_check_config_designs_no_controller(monkeypatch):
    import stagectl.control.controller as controller

    def forbidden(*a, **kw):
        raise AssertionError("check-config must not build a StageController")

    monkeypatch.setattr(controller.StageController, "__init__", forbidden)
    for p in sorted((REPO / "config").glob("*.yaml")):
        assert isinstance(load_app_config(p), AppConfig)


def test_controller_needs_checked_on_the_resolved_model():
    data = shipped_config_mapping("stage-canopen.yaml")
    del data["controller"]["mass_kg"]
    del data["controller"]["feedforward"]["model_file"]
    probs = "\n".join(config_problems(data))
    assert "controller.feedforward: kind 'model' needs friction:, model_file:" in probs
    assert "controller.mass_kg: required key missing" in probs


def test_the_resolved_model_is_not_a_yaml_key():
    data = shipped_config_mapping("stage-canopen.yaml")
    data["controller"]["feedforward"]["model"] = {"model": "gms"}
    probs = "\n".join(config_problems(data))
    assert "controller.feedforward.model: unknown key" in probs


# ------------------------------------------------------------------------------------------ device time
@pytest.mark.parametrize("name", sorted(p.name for p in (REPO / "config").glob("*.yaml")))
def test_shipped_configs_check_without_a_note(tmp_path, name):
    r = _check_config(tmp_path, shipped_config_mapping(name))
    assert r.returncode == 0 and "note:" not in r.stderr, r.stderr


def test_a_hil_file_without_its_sim_section_is_told_pacing_is_for_a_sim_plant(tmp_path):
    """A stage-PC file made from a HIL file keeps device time and pacing: on a real drive the loop would stop
    sending forces while the stage moves on. The file cannot tell a real drive from a sim-plant elsewhere, so it
    is valid, with one note naming both keys and what to set (review12, finding 4)."""
    data = shipped_config_mapping("hil-canopen.yaml")
    assert data["loop"]["device_time"] is True and data["loop"]["pace_cycles"] > 0
    del data["sim"]
    r = _check_config(tmp_path, data)
    assert r.returncode == 0 and "OK" in r.stdout
    notes = [ln for ln in r.stderr.splitlines() if ln.startswith("stagectl: note:")]
    assert len(notes) == 1 and "loop.device_time and loop.pace_cycles" in notes[0], r.stderr
    assert "loop.device_time: false and loop.pace_cycles: 0" in notes[0]
    data["loop"].update(device_time=False, pace_cycles=0)
    r = _check_config(tmp_path, data)
    assert r.returncode == 0 and "note:" not in r.stderr
