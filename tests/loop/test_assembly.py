"""The assembly's mechanisms: one timing value, one I/O builder per kind, the scenario registry in control/,
the fault aliases in sim/faults, and a typed driver configuration for the virtual drive."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from stagectl.drivers.cia402 import Cia402Config, Cia402Drive
from stagectl.sim.cia402_drive import SimDriveConfig
from stagectl.sim.cia406_encoder import SimEncoderConfig
from stagectl.sim.faults import FAULT_ALIASES, STALE_CYCLES, SimFault, world_fault

from stagectl.app import IO_BUILDERS, build_stage, embedded_drive_config, embedded_encoder_config
from stagectl.clock import SimClock, Timing
from stagectl.config import IoKind, load_app_config
from stagectl.control.reference import get_scenario, scenario_names
from stagectl.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]


def test_timing_derives_cycle_counts():
    dut = Timing(1e-3)
    assert dut.rate_hz == pytest.approx(1000.0)
    assert dut.cycles(0.2) == math.ceil(0.2 / 1e-3)
    assert dut.every(0.02) == 20 and dut.every(1e-6) == 1
    assert dut.per_cycle(2.0) == pytest.approx(2e-3)
    assert Timing.of(dut) is dut and Timing.of(5e-4) == Timing(5e-4)
    for bad in (0.0, -1e-3, math.nan, math.inf):
        with pytest.raises(ConfigError, match="period_s: must be > 0 s"):
            Timing(bad)


def test_consumers_take_the_one_timing_value():
    t = Timing(5e-4)
    drive = Cia402Drive(Cia402Config(node_id=1, heartbeat_timeout_s=0.2, controller_heartbeat_s=0.02), t)
    assert drive.timing is t and drive.period_s == 5e-4
    assert drive._hb_timeout_cycles == t.cycles(0.2) and drive._hb_every == t.every(0.02)


def test_one_io_builder_per_kind():
    assert set(IO_BUILDERS) == set(IoKind)


def test_stage_is_typed_and_shares_the_timing():
    cfg = load_app_config(REPO / "config" / "sim.yaml")
    with build_stage(cfg, clock=SimClock()) as stage:
        assert stage.timing == cfg.timing
        assert stage.safety.timing == cfg.timing
        assert stage.controller_config is cfg.controller
        assert stage.describe["period_s"] == cfg.loop.period_s and stage.simulated
        assert stage.world is not None and stage.plant is stage.world.plant


def test_virtual_drive_driver_config_is_an_explicit_derivation():
    can = {"interface": "virtual", "channel": "x"}
    sd = SimDriveConfig(node_id=3, resolution_m=2e-9, force_per_unit_n=0.001)
    got = embedded_drive_config(None, sd, can)
    assert (got.node_id, got.resolution_m, got.force_per_unit_n, got.can) == (3, 2e-9, 0.001, can)
    mine = Cia402Config(node_id=5, max_force_n=7.0)
    got = embedded_drive_config(mine, sd, can)
    assert got.node_id == 5 and got.max_force_n == 7.0 and got.can == can
    enc = embedded_encoder_config(None, SimEncoderConfig(node_id=4, resolution_m=5e-9), can)
    assert (enc.node_id, enc.resolution_m, enc.can) == (4, 5e-9, can)
    with pytest.raises(ConfigError, match="io.encoder"):
        embedded_encoder_config(None, None, can)


def test_scenario_registry_lives_in_control():
    assert scenario_names() == ("cosine", "triangle", "steps", "demo", "hold")
    assert get_scenario("hold") is None
    sc = get_scenario("demo")
    assert sc is not None and sc.name == "demo"
    with pytest.raises(ConfigError, match="demo.scenario: unknown scenario 'x'"):
        get_scenario("x", "demo.scenario")


def test_fault_aliases_map_loop_names_onto_virtual_device_faults():
    assert FAULT_ALIASES == {"emcy": SimFault.DRIVE_FAULT, "stale": SimFault.DROP_TPDO,
                             "heartbeat_lost": SimFault.HEARTBEAT_STOP}  # nan: plant_io only (fault vocabulary)
    assert world_fault("stale", {}) == {"kind": "drop_tpdo", "cycles": STALE_CYCLES}
    assert world_fault("stale", {"cycles": 3}) == {"kind": "drop_tpdo", "cycles": 3}
    assert world_fault("late_tpdo", {"cycles": 2}) == {"kind": "late_tpdo", "cycles": 2}


@pytest.mark.parametrize("kind", ["plant_io", "embedded_canopen"])
def test_inject_fault_aliases_on_both_simulated_stages(kind):
    import dataclasses

    cfg = load_app_config(REPO / "config" / "sim.yaml")
    cfg = dataclasses.replace(cfg, io=dataclasses.replace(cfg.io, kind=IoKind(kind)))
    with build_stage(cfg, clock=SimClock()) as stage:
        loop = stage.loop
        got: list[dict] = []
        loop.on_cycle = lambda: loop.cycle == 20 and got.append(stage.inject_fault("emcy"))
        loop.run(cycles=60)
        assert got and got[0]["injected"]
        assert loop.status().fault is not None
