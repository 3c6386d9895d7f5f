"""position_jump: the per-cycle position bound comes from the physics (velocity limit, force limit, mass,
period), so a 30 µm glitch that the drivers' 2 mm glitch check lets through latches on the seed stage."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import yaml

from stagectl.app import build_stage
from stagectl.clock import SimClock
from stagectl.config import parse_app_config
from stagectl.loop import LoopState
from stagectl.runtime.requests import MoveRequest
from stagectl.safety import Safety, SafetyConfig

REPO = Path(__file__).resolve().parents[2]
SIM_YAML = REPO / "config" / "sim.yaml"


def _seed(kind: str):
    data = yaml.safe_load(SIM_YAML.read_text())
    data["io"]["kind"] = kind
    return parse_app_config(data, SIM_YAML)


def test_bound_is_the_physical_one():
    cfg = SafetyConfig(min_position_m=-5e-3, max_position_m=5e-3, max_force_n=10.0, max_velocity_m_s=0.02,
                       jump_margin_m=1e-6)
    s = Safety(cfg, 1e-3, mass_kg=2.0)
    T = 1e-3
    # plain reference: v_max·T + F/m·T²/2 + margin
    assert s.max_step_m(T) == pytest.approx(0.02 * T + 0.5 * (10.0 / 2.0) * T * T + 1e-6, rel=1e-12)
    assert s.max_step_m(T) == pytest.approx(23.5e-6, rel=1e-9)
    assert s.max_step_m(2 * T) == pytest.approx(0.02 * 2 * T + 0.5 * 5.0 * 4 * T * T + 1e-6, rel=1e-12)
    assert Safety(cfg, T).max_step_m(T) == math.inf  # no mass: no jump check


def test_unit_jump_latches_and_a_legal_step_does_not():
    cfg = SafetyConfig(min_position_m=-5e-3, max_position_m=5e-3, max_force_n=10.0, max_velocity_m_s=0.02)
    s = Safety(cfg, 1e-3, mass_kg=2.0)
    s.restart(0.0, 0.0)
    # moving at 19 mm/s: 19 µm per cycle is inside the bound, for 5 cycles
    x = 0.0
    for k in range(1, 6):
        x += 19e-6
        assert not s.check_measurement(k * 1e-3, k, x, True, None), s.fault
    # after a stale cycle the next sample may cover two periods
    assert not s.check_measurement(6e-3, 6, x, False, None)
    x += 2 * 19e-6
    assert not s.check_measurement(7e-3, 7, x, True, None), s.fault
    k = 8
    for _ in range(20):  # come to rest (v̂ decays)
        assert not s.check_measurement(k * 1e-3, k, x, True, None), s.fault
        k += 1
    x += 23e-6
    assert not s.check_measurement(k * 1e-3, k, x, True, None), s.fault  # 23 µm: still inside 23.5 µm
    k += 1
    for _ in range(20):
        assert not s.check_measurement(k * 1e-3, k, x, True, None), s.fault
        k += 1
    assert s.check_measurement(k * 1e-3, k, x + 30e-6, True, None)
    assert s.fault.name == "position_jump" and "at most 2.35e-05 m" in s.fault.cause, s.fault


@pytest.mark.parametrize("io_kind", ["embedded_canopen", "plant_io"])
def test_30_um_jump_for_3_cycles_latches_on_the_seed_stage(io_kind):
    """config/sim.yaml, simulated time: hold, then a 30 µm sensor glitch lasting 3 cycles (the issue's case: the
    old 2 mm plausibility limit missed it). It latches position_jump in the cycle it appears."""
    cfg = _seed(io_kind)
    with build_stage(cfg, clock=SimClock()) as stage:
        loop = stage.loop
        at = 300
        if io_kind == "embedded_canopen":
            stage.world.inject_fault("position_jump", jump_m=30e-6, at_cycle=at, cycles=3)
        else:
            io = stage.plant_io

            def hook():
                if at - 3 <= loop.cycle < at:  # the glitched samples of three cycles
                    io.glitch(stage.plant.measure() + 30e-6)
            loop.on_cycle = hook
        res = loop.run(duration_s=0.6)
        st = loop.status()
        assert st.state is LoopState.FAULT and res.fault is not None
        assert res.fault.name == "position_jump", res.fault
        assert 3e-5 * 0.9 < float(res.fault.cause.split()[2]) < 3e-5 * 1.1  # "position moved <dx> m ..."
        assert at - 10 <= res.fault.cycle <= at + 2, res.fault  # (the drive counts its start-up SYNCs too)


def test_seed_stage_moves_near_the_limit_without_a_false_jump():
    """The bound is not a hair trigger: a move at the planned fraction of the velocity limit on the seed
    stage runs through without any fault."""
    cfg = _seed("plant_io")
    with build_stage(cfg, clock=SimClock()) as stage:
        v = cfg.safety.move_velocity_fraction * cfg.safety.max_velocity_m_s
        stage.loop.submit(MoveRequest(target_m=2e-3, max_velocity_m_s=v))
        res = stage.loop.run(duration_s=0.4)
        assert res.fault is None, res.fault
        assert stage.loop.status().x_m > 2e-3 * 0.9 * 0.5  # it really moved fast
