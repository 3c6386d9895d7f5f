"""A reset is refused, with one line naming the cause, while the cause of the fault persists (heartbeat still
missing, bus-off, link closed, stage outside the soft limits); it is accepted once the cause is gone. A refused
reset costs the loop nothing (no fault-reset handshake against a silent drive)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from stagectl.app import build_stage
from stagectl.clock import SimClock
from stagectl.config import parse_app_config
from stagectl.drivers.base import FaultKind
from stagectl.loop import LoopState, LoopStateError
from stagectl.runtime.requests import MoveRequest, ResetRequest

REPO = Path(__file__).resolve().parents[2]
SIM_YAML = REPO / "config" / "sim.yaml"


def _reset(loop, cycles=3):
    fut = loop.submit(ResetRequest())
    loop.run(cycles=cycles)
    return fut


def test_plant_io_persisting_device_cause(make, caplog):
    loop, io, plant, ctl, clock = make()
    loop.on_cycle = lambda: loop.cycle == 20 and io.inject_fault(FaultKind.HEARTBEAT_LOST, "no heartbeat",
                                                                   persist=True)
    loop.run(cycles=40)
    loop.on_cycle = None
    assert loop.status().fault.name == "heartbeat_lost"
    fut = _reset(loop)
    with pytest.raises(LoopStateError) as ei:
        fut.result(timeout=0)
    msg = str(ei.value)
    assert msg == ("reset refused: cause still present: plant_io: heartbeat_lost: no heartbeat; "
                   "the fault stays latched"), msg
    assert loop.status().state is LoopState.FAULT and loop.status().fault.name == "heartbeat_lost"
    assert any("reset refused" in r.getMessage() for r in caplog.records)
    assert io.applied_force_n == 0.0
    io.remove_cause()
    assert _reset(loop).result(timeout=0)["state"] == "active"
    assert loop.status().fault is None


def test_outside_the_soft_limits_reset_is_refused_until_the_stage_is_back(make):
    loop, io, plant, ctl, clock = make(safety={"max_velocity_m_s": 100.0})
    loop.run(cycles=10)
    plant.x_m = 0.0102  # pushed past the 10 mm soft limit (by hand, a collision)
    loop.run(cycles=5)
    assert loop.status().fault.name == "position_limit"
    with pytest.raises(LoopStateError, match=r"position_limit: x = 0.0102 m outside soft limits \[-0.01, 0.01\] m"):
        _reset(loop).result(timeout=0)
    plant.x_m, plant.v_m_s = 0.0095, 0.0
    assert _reset(loop).result(timeout=0)["cleared"]["name"] == "position_limit"


@pytest.fixture(scope="module")
def seed_canopen():
    data = yaml.safe_load(SIM_YAML.read_text())
    data["io"]["kind"] = "embedded_canopen"
    return parse_app_config(data, SIM_YAML)


def test_heartbeat_loss_persisting_then_gone_on_the_seed_stage(seed_canopen):
    with build_stage(seed_canopen, clock=SimClock()) as stage:
        loop, world = stage.loop, stage.world
        loop.on_cycle = lambda: loop.cycle == 50 and world.inject_fault("heartbeat_stop")  # for ever
        loop.run(cycles=300)
        loop.on_cycle = None
        assert loop.status().fault.name == "heartbeat_lost"
        with pytest.raises(LoopStateError, match="reset refused: cause still present: .*heartbeat_lost: no drive "
                                                 "heartbeat for"):
            _reset(loop).result(timeout=0)
        assert loop.status().state is LoopState.FAULT
        world.clear_faults()  # the drive beats again (its producer time: 0.1 s)
        loop.run(cycles=150)
        assert _reset(loop, 5).result(timeout=0)["state"] == "active"
        mv = loop.submit(MoveRequest(relative_m=2e-6))
        loop.run(cycles=300)
        assert mv.result(timeout=0)["target_m"] == pytest.approx(loop.status().x_ref_m)
        assert loop.status().fault is None


def test_reset_against_a_bus_off_drive_is_refused_without_touching_the_bus(seed_canopen):
    """The old reset ran the CiA 402 fault-reset handshake against the silent drive inside the loop's cycle
    (0.5 s per try). Now: refused in the cycle it arrives, the loop keeps its one SYNC per cycle."""
    with build_stage(seed_canopen, clock=SimClock()) as stage:
        loop, world = stage.loop, stage.world
        loop.on_cycle = lambda: loop.cycle == 50 and world.inject_fault("bus_off")
        loop.run(cycles=100)
        loop.on_cycle = None
        assert loop.status().fault.name == "bus_off"
        seen: list[int] = []
        loop.on_cycle = lambda: seen.append(world.drive.sync_count)
        fut = _reset(loop, cycles=4)
        with pytest.raises(LoopStateError, match="bus_off: no frame from the drive"):
            fut.result(timeout=0)
        # one SYNC per loop cycle, none for a handshake, in the cycle that served the reset too
        assert [b - a for a, b in zip(seen, seen[1:])] == [1, 1, 1], seen
