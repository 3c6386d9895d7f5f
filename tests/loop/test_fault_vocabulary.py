"""One name, one cause: the ``fault`` debug request's kinds latch the same fault on both simulated stages (the
directly wrapped plant and the virtual CANopen drive). Before: ``stale`` gave stale_position vs missed_frame,
``emcy`` emcy vs drive_fault, and ``nan`` meant a 5 mm jump latched as ``sensor_error`` on the CANopen stage
(now refused there)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from stagectl.sim.faults import NAN_ON_CANOPEN

from stagectl.app import build_stage
from stagectl.clock import SimClock
from stagectl.config import parse_app_config
from stagectl.loop import LoopState

REPO = Path(__file__).resolve().parents[2]
SIM_YAML = REPO / "config" / "sim.yaml"


@pytest.fixture(scope="module")
def cfgs():
    out = {}
    for kind in ("plant_io", "embedded_canopen"):
        data = yaml.safe_load(SIM_YAML.read_text())
        data["io"]["kind"] = kind
        out[kind] = parse_app_config(data, SIM_YAML)
    return out


@pytest.mark.parametrize("request_kind,fields,latched", [
    ("heartbeat_lost", {}, "heartbeat_lost"),
    ("stale", {}, "missed_frame"),
    ("emcy", {}, "drive_fault"),
    ("position_jump", {"jump_m": 30e-6, "cycles": 3}, "position_jump"),
])
def test_same_request_same_fault_on_both_simulated_stages(cfgs, request_kind, fields, latched):
    for io_kind, cfg in cfgs.items():
        with build_stage(cfg, clock=SimClock()) as stage:
            loop = stage.loop
            loop.on_cycle = lambda loop=loop, stage=stage: loop.cycle == 50 and stage.inject_fault(request_kind, **fields)
            loop.run(cycles=300)
            st = loop.status()
            assert st.state is LoopState.FAULT and st.fault.name == latched, (io_kind, st.fault)


def test_nan_is_refused_on_the_canopen_stage_with_one_line(cfgs):
    with build_stage(cfgs["embedded_canopen"], clock=SimClock()) as stage, pytest.raises(ValueError) as ei:
        stage.inject_fault("nan")
    assert str(ei.value) == NAN_ON_CANOPEN and "\n" not in NAN_ON_CANOPEN
    with build_stage(cfgs["plant_io"], clock=SimClock()) as stage:
        loop = stage.loop
        loop.on_cycle = lambda: loop.cycle == 20 and stage.inject_fault("nan")
        loop.run(cycles=40)
        assert loop.status().fault.name == "not_finite"
