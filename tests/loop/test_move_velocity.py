"""A move is planned inside the velocity limit (safety.move_velocity_fraction), or refused with one line: a move
at exactly max_velocity_m_s used to be accepted and then trip velocity_limit mid-move (seed stage, simulated)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml

from stagectl.app import build_stage
from stagectl.clock import SimClock
from stagectl.config import parse_app_config
from stagectl.recorder import Recorder
from stagectl.runtime.requests import MotionLimits, MoveRequest, RequestError

REPO = Path(__file__).resolve().parents[2]
SIM_YAML = REPO / "config" / "sim.yaml"


def _seed(**safety):
    data = yaml.safe_load(SIM_YAML.read_text())
    data["io"]["kind"] = "plant_io"
    data["safety"].update(safety)
    return parse_app_config(data, SIM_YAML)


def _move(cfg, v, distance=3e-3, duration_s=0.35):
    with build_stage(cfg, clock=SimClock()) as stage:
        rec = Recorder(stage.loop.columns, int(duration_s * 1000) + 10)
        stage.loop.add_sink(rec)
        fut = stage.loop.submit(MoveRequest(relative_m=distance, max_velocity_m_s=v))
        res = stage.loop.run(duration_s=duration_s)
        return fut.result(timeout=0), res, rec


def test_a_move_at_the_limit_is_refused_with_one_clear_line():
    cfg = _seed()
    assert cfg.safety.move_velocity_fraction == 0.9  # the default
    with build_stage(cfg, clock=SimClock()) as stage, pytest.raises(RequestError) as ei:
        stage.loop.submit(MoveRequest(relative_m=1e-3, max_velocity_m_s=cfg.safety.max_velocity_m_s))
    msg = str(ei.value)
    assert ei.value.field == "max_velocity_m_s" and "\n" not in msg
    assert msg.startswith("max_velocity_m_s: must be > 0 and <= 0.018 m/s (safety.move_velocity_fraction 0.9 of "
                          "max_velocity_m_s 0.02 m/s"), msg
    assert msg.endswith("(got 0.02 m/s)")


def test_a_move_at_the_planned_fraction_runs_through_below_the_limit():
    cfg = _seed()
    v_plan = cfg.safety.move_velocity_fraction * cfg.safety.max_velocity_m_s
    out, res, rec = _move(cfg, v_plan, distance=4.5e-3, duration_s=0.5)
    assert res.fault is None, res.fault
    assert out["target_m"] == pytest.approx(rec.col("x")[0] + 4.5e-3, abs=1e-6)
    v = rec.col("v")  # the supervisor's own filtered velocity estimate
    assert np.max(np.abs(rec.col("v_ref"))) == pytest.approx(v_plan, rel=1e-3)  # it really cruised at v_plan
    assert np.max(np.abs(v)) < cfg.safety.max_velocity_m_s
    assert abs(rec.col("x")[-1] - out["target_m"]) < 1e-6  # and arrived


def test_without_the_margin_a_move_at_the_limit_trips_mid_move():
    """Why the fraction exists: with move_velocity_fraction 1 the old behaviour comes back (accepted, then
    velocity_limit from the tracking overshoot)."""
    cfg = _seed(move_velocity_fraction=1.0)
    out, res, _ = _move(cfg, cfg.safety.max_velocity_m_s, distance=4.5e-3, duration_s=0.5)
    assert out["duration_s"] > 0.1  # accepted
    assert res.fault is not None and res.fault.name == "velocity_limit", res.fault


def test_default_velocity_never_exceeds_the_planned_fraction():
    cfg = _seed(max_velocity_m_s=5e-4)
    with build_stage(cfg, clock=SimClock()) as stage:
        assert stage.reference.default_velocity_m_s == pytest.approx(0.9 * 5e-4)
    lim = MotionLimits(-1.0, 1.0, 0.02, 0.5)
    assert lim.move_velocity_m_s == pytest.approx(0.01)
    MoveRequest(target_m=0.0, max_velocity_m_s=0.01).check_limits(lim)
    with pytest.raises(RequestError, match="max_velocity_m_s"):
        MoveRequest(target_m=0.0, max_velocity_m_s=0.0101).check_limits(lim)
    assert dataclasses.replace(lim, move_velocity_fraction=1.0).move_velocity_m_s == 0.02


def test_a_move_slower_than_a_day_is_refused_and_the_stage_holds():
    """``--max-velocity 1e-250`` (a typo) planned a ~1e244 s crawl; now one line naming the field, and the
    reference keeps its target. A slow but plausible crawl (1 µm at 1 nm/s: 1000 s) is still accepted."""
    cfg = _seed()
    with build_stage(cfg, clock=SimClock()) as stage:
        bad = stage.loop.submit(MoveRequest(relative_m=1e-6, max_velocity_m_s=1e-250))
        ok = stage.loop.submit(MoveRequest(relative_m=1e-6, max_velocity_m_s=1e-9))
        before = stage.reference.target_m
        stage.loop.run(duration_s=0.01)
        with pytest.raises(RequestError) as ei:
            bad.result(timeout=0)
        assert ei.value.field == "max_velocity_m_s" and "\n" not in str(ei.value)
        assert "would take 1e+244 s, more than 86400 s" in str(ei.value)
        assert ok.result(timeout=0)["duration_s"] == pytest.approx(1000.0, rel=0.01)
        assert stage.reference.target_m == pytest.approx(before + 1e-6, abs=1e-12)
