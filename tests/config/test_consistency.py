"""Every problem of a file at once (cross-checks run on the sections that parsed), the real drivers agreeing
with the simulated devices they talk to, and the simulated devices an ``embedded_canopen`` stage needs."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from stagectl.sim.interferometer import SimInterferometerConfig

from stagectl.app import build_stage, embedded_interferometer_config
from stagectl.clock import SimClock
from stagectl.config import parse_app_config
from stagectl.drivers.interferometer import InterferometerConfig
from stagectl.errors import ConfigError

from support import cli_in_process, config_problems, shipped_config_mapping

REPO = Path(__file__).resolve().parents[2]




def _check_config(tmp_path: Path, data: dict) -> tuple[int, list[str], str]:
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(data))
    r = cli_in_process(["check-config", str(p)])  # what check-config says, not a process start
    lines = [ln.removeprefix("stagectl: error: bad.yaml: ") for ln in r.stderr.splitlines()
             if ln.startswith("stagectl: error:")]
    return r.returncode, lines, r.stdout + r.stderr


# ------------------------------------------------------------------------------------ all problems at once
def test_an_unknown_key_does_not_hide_the_cross_checks(tmp_path):
    data = shipped_config_mapping("stage-canopen.yaml")
    data["loop"]["perod_s"] = 0.001  # schema problem in one section
    data["controller"]["max_force_n"] = 30.0  # force chain
    data["io"]["drive"]["can"]["bitrat"] = 1000000  # can: key
    rc, lines, out = _check_config(tmp_path, data)
    assert rc == 2 and "Traceback" not in out
    assert lines == [
        "loop.perod_s: unknown key (did you mean period_s?)",
        "io.drive.can.bitrat: unknown key for interface socketcan (did you mean bitrate?)",
        "controller.max_force_n: 30 N exceeds safety.max_force_n 10 N (the force limits must satisfy "
        "controller <= safety <= drive <= actuator)",
    ]


def test_cross_checks_skip_a_section_with_its_own_problems():
    data = shipped_config_mapping("sim.yaml")
    data["safety"]["max_forc_n"] = 1.0  # safety does not parse: no force-chain line about it
    data["controller"]["max_force_n"] = 15.0  # exceeds safety's 10 N, but safety did not parse
    data["demo"]["scenario"] = "cosin"
    probs = config_problems(data)
    assert probs == ["x.yaml: safety.max_forc_n: unknown key (did you mean max_force_n?)",
                     "x.yaml: demo.scenario: unknown scenario 'cosin' (known: cosine, triangle, steps, demo, hold)"]


def test_a_broken_sim_section_does_not_hide_the_other_checks():
    data = shipped_config_mapping("sim.yaml")
    data["sim"]["plant"]["mas"] = 1.0
    data["controller"]["max_force_n"] = 15.0
    probs = config_problems(data)
    assert probs == ["x.yaml: sim.plant.mas: unknown key (did you mean mass_kg?)",
                     "x.yaml: controller.max_force_n: 15 N exceeds safety.max_force_n 10 N (the force limits must "
                     "satisfy controller <= safety <= drive <= actuator)"]


def test_a_missing_model_file_still_has_no_follow_up_noise():
    data = shipped_config_mapping("sim.yaml")
    data["controller"]["feedforward"]["model_file"] = str(REPO / "config" / "models" / "nope.yaml")
    data["controller"]["mass_kg"] = None  # the model file would give it: no "mass_kg required" follow-up
    probs = config_problems(data)
    assert len(probs) == 1 and "controller.feedforward.model_file" in probs[0] and "nope.yaml" in probs[0]


# ------------------------------------------------------------------------------ drivers vs simulated devices
@pytest.mark.parametrize("name,path,value,expect", [
    ("hil-canopen.yaml", ("sim", "drive", "force_per_unit_n"), 0.01,
     "io.drive.force_per_unit_n: 0.001 N differs from sim.drive.force_per_unit_n 0.01 N"),
    ("hil-canopen.yaml", ("sim", "drive", "node_id"), 3, "io.drive.node_id: 1 differs from sim.drive.node_id 3"),
    ("hil-canopen.yaml", ("sim", "drive", "resolution_m"), 1e-8,
     "io.drive.resolution_m: 1e-09 m differs from sim.drive.resolution_m 1e-08 m"),
    ("hil-serial.yaml", ("sim", "interferometer", "resolution_m"), 1e-8,
     "io.interferometer.resolution_m: 1e-09 m differs from sim.interferometer.resolution_m 1e-08 m"),
    ("sim.yaml", ("io", "drive"), {"node_id": 1, "force_per_unit_n": 0.01, "resolution_m": 1e-9},
     "io.drive.force_per_unit_n: 0.01 N differs from sim.drive.force_per_unit_n 0.001 N"),
])
def test_driver_and_simulated_device_must_agree(tmp_path, name, path, value, expect):
    data = shipped_config_mapping(name)
    d = data
    for k in path[:-1]:
        d = d[k]
    d[path[-1]] = value
    rc, lines, out = _check_config(tmp_path, data)
    assert rc == 2 and "Traceback" not in out
    assert lines == [expect + " (the driver and the simulated device it talks to must agree)"]


def test_encoder_driver_and_simulated_encoder_must_agree():
    data = shipped_config_mapping("sim.yaml")
    data["io"]["sensor"] = "encoder"
    data["io"]["encoder"] = {"node_id": 3, "resolution_m": 5e-9}
    data["sim"]["encoder"] = {"node_id": 2, "resolution_m": 5e-9}
    assert config_problems(data) == ["x.yaml: io.encoder.node_id: 3 differs from sim.encoder.node_id 2 (the driver and "
                               "the simulated device it talks to must agree)"]
    data["io"]["encoder"] = {"node_id": 2, "resolution_m": 1e-9}
    assert config_problems(data) == ["x.yaml: io.encoder.resolution_m: 1e-09 m differs from sim.encoder.resolution_m "
                               "5e-09 m (the driver and the simulated device it talks to must agree)"]
    data["io"]["encoder"]["resolution_m"] = 5e-9
    assert parse_app_config(data, REPO / "config" / "x.yaml").io.encoder is not None


def test_shipped_configs_agree_with_their_simulated_devices():
    for p in sorted((REPO / "config").glob("*.yaml")):
        parse_app_config(shipped_config_mapping(p.name), REPO / "config" / p.name)


# ------------------------------------------------------------------------ embedded_canopen simulated devices
def _embedded(**changes: object) -> dict:
    data = shipped_config_mapping("sim.yaml")
    for dotted, value in changes.items():
        keys = dotted.split("__")
        d = data
        for k in keys[:-1]:
            d = d.setdefault(k, {})
        d[keys[-1]] = value
    return data


@pytest.mark.parametrize("changes,expect", [
    ({"io__sensor": "encoder"},
     "sim.encoder: required for io.sensor encoder with io.kind embedded_canopen (the simulated encoder the "
     "driver talks to; io.encoder is optional)"),
    ({"io__sensor": "encoder", "io__encoder": {"node_id": 2}},
     "sim.encoder: required for io.sensor encoder with io.kind embedded_canopen (the simulated encoder the "
     "driver talks to; io.encoder is optional)"),
    ({"io__sensor": "interferometer", "io__interferometer": {"url": "socket://127.0.0.1:1"}},
     "sim.interferometer: required for io.sensor interferometer with io.kind embedded_canopen (the simulated "
     "interferometer the driver reads; io.interferometer is optional)"),
    ({"io__sensor": "interferometer"},
     "sim.interferometer: required for io.sensor interferometer with io.kind embedded_canopen (the simulated "
     "interferometer the driver reads; io.interferometer is optional)"),
    ({"io__sensor": "encoder", "sim__encoder": {"node_id": 1}},
     "sim.encoder.node_id: 1 is also sim.drive.node_id (two CANopen nodes on one bus need distinct node ids)"),
    ({"sim__faults": [{"kind": "drive_fault", "device": "encoder"}]},
     "sim.faults[0].device: encoder is not configured (no sim.encoder)"),
])
def test_embedded_canopen_needs_its_simulated_devices(tmp_path, changes, expect):
    rc, lines, out = _check_config(tmp_path, _embedded(**changes))
    assert rc == 2 and "Traceback" not in out
    assert lines == [expect]


def test_simulated_sensor_alone_is_enough_for_both_sensor_kinds():
    enc = parse_app_config(_embedded(io__sensor="encoder", sim__encoder={"node_id": 2}),
                           REPO / "config" / "x.yaml")
    assert enc.io.encoder is None and enc.sim is not None and enc.sim.encoder is not None
    ifm_data = _embedded(io__sensor="interferometer",
                         sim__interferometer={"transport": "tcp", "trigger": "sync", "resolution_m": 1e-9})
    ifm = parse_app_config(ifm_data, REPO / "config" / "x.yaml")
    assert ifm.io.interferometer is None
    with build_stage(ifm, clock=SimClock()) as stage:
        stage.load_scenario("hold")
        result = stage.loop.run(duration_s=0.02)
        assert stage.sensor.name != stage.actuator.name
        assert result is not None


def test_interferometer_driver_config_follows_the_encoder_rule():
    sim = SimInterferometerConfig(resolution_m=5e-9)
    got = embedded_interferometer_config(None, sim, "socket://127.0.0.1:5")
    assert (got.url, got.resolution_m) == ("socket://127.0.0.1:5", 5e-9)
    mine = InterferometerConfig(url="/dev/ttyUSB0", resolution_m=5e-9, stale_cycles=9)
    got = embedded_interferometer_config(mine, sim, "socket://127.0.0.1:5")
    assert (got.url, got.stale_cycles) == ("socket://127.0.0.1:5", 9)
    with pytest.raises(ConfigError, match="sim.interferometer: required"):
        embedded_interferometer_config(mine, None, None)


def test_a_missing_required_section_has_no_follow_up_noise():
    probs = config_problems({"loop": {"perod_s": 0.001}})
    assert probs == ["x.yaml: safety: required key missing (limits and watchdogs)",
                     "x.yaml: controller: required key missing (controller tuning (pid, dob, feedforward))",
                     "x.yaml: loop.perod_s: unknown key (did you mean period_s?)",
                     "x.yaml: sim: required for io.kind plant_io (the simulated stage)"]


# ------------------------------------------------------------------------------------ HIL time base
@pytest.mark.parametrize("name", ["hil-canopen.yaml", "hil-serial.yaml"])
def test_a_sim_plant_stepped_per_sync_needs_device_time(name):
    """A HIL file whose own sim-plant steps its plant once per SYNC must run the loop on device time (on the
    wall clock each skipped slot puts the reference a period ahead of the stage); a sim-plant on the wall
    clock, or a drive elsewhere, needs no such thing."""
    data = shipped_config_mapping(name)
    parse_app_config(data, REPO / "config" / "x.yaml")  # fine as shipped
    data["loop"]["device_time"] = False
    probs = config_problems(data)
    assert len(probs) == 1 and "loop.device_time: false" in probs[0] and "set loop.device_time: true" in probs[0]
    wall = {**data, "loop": {**data["loop"], "pace_cycles": 0},  # (pacing needs device time)
            "sim": {**data["sim"], "drive": {**data["sim"]["drive"], "wall_clock_plant": True}}}
    parse_app_config(wall, REPO / "config" / "x.yaml")
    drive = {**data["io"]["drive"], "can": {**data["io"]["drive"]["can"], "port": 29999}}
    elsewhere = {**data, "loop": {**data["loop"], "pace_cycles": 0}, "io": {**data["io"], "drive": drive}}
    parse_app_config(elsewhere, REPO / "config" / "x.yaml")


def test_a_real_drive_refuses_device_time_and_pacing():
    """config/stage-canopen.yaml (SocketCAN: a real drive, whose stage moves on the clock) with the HIL's
    loop.device_time would run reference and controller steps on executed cycles (each skipped slot a period
    the stage moved and the loop did not count); pace_cycles without device_time is ignored by the loop. Both
    are refused, one line each naming the key; the shipped files stay valid."""
    data = shipped_config_mapping("stage-canopen.yaml")
    parse_app_config(data, REPO / "config" / "x.yaml")  # fine as shipped
    dt = {**data, "loop": {**data["loop"], "device_time": True}}
    probs = config_problems(dt)
    assert len(probs) == 1 and ("loop.device_time: true, but io.drive.can.interface "
                                                   "is 'socketcan'") in probs[0], probs
    paced = {**data, "loop": {**data["loop"], "pace_cycles": 1}}
    probs = config_problems(paced)
    assert len(probs) == 1 and ("loop.pace_cycles: 1 cycles does nothing without "
                                                   "loop.device_time: true") in probs[0], probs
    for name in ("hil-canopen.yaml", "hil-serial.yaml"):
        parse_app_config(shipped_config_mapping(name), REPO / "config" / "x.yaml")
