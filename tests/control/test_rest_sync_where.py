"""Where the stop synchronisation feeds the model (``StageController._rest_sync_where``), both directions of
travel: with the stage stuck ahead of its reference beyond ``rest_spring_range_m`` the model is fed at the stage;
once the stage has left that position for one behind the reference (or is sliding) the model is fed at x_r again,
so that the next move's reference travel is not skipped by the model as if the stage were still ahead."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from stagectl.control.api import Reference

REPO = Path(__file__).resolve().parents[2]


def _quintic(d_m: float, t_s: float, t: float) -> tuple[float, float, float]:
    s = t / t_s
    return (d_m * (10 * s**3 - 15 * s**4 + 6 * s**5), d_m / t_s * (30 * s**2 - 60 * s**3 + 30 * s**4),
            d_m / t_s**2 * (60 * s - 180 * s**2 + 120 * s**3))


@pytest.mark.parametrize("sgn", [1.0, -1.0])
def test_model_leaves_the_stage_position_when_the_stage_goes_behind(sgn: float) -> None:
    from stagectl.config import load_app_config
    from stagectl.control.controller import StageController

    cfg = load_app_config(REPO / "config" / "sim.yaml")
    c = cfg.controller
    c = dataclasses.replace(c, settle=dataclasses.replace(c.settle, move_s=0.0))  # (no settle move: rest sync)
    ctl = StageController(c, cfg.timing)
    dt, n = cfg.loop.period_s, 100
    x = 0.0
    for k in range(n + 1):  # a 20 µm move in direction sgn, the stage 20 nm behind
        x, v, a = _quintic(20e-6 * sgn, n * dt, k * dt)
        ctl.step(dt, x - 20e-9 * sgn * (k > 0), Reference(x, v, a))
    ff = ctl.ff
    assert ff.latch.direction == sgn
    for _ in range(50):  # stuck 1 µm ahead: fed at the stage
        ctl.step(dt, x + 1e-6 * sgn, Reference(x, 0.0, 0.0))
    assert ff.state.x_fed_m == pytest.approx(x + 1e-6 * sgn, abs=1e-12)
    for _ in range(50):  # then still 1 µm behind: no sync, the model at the reference (not at the stage ahead)
        ctl.step(dt, x - 1e-6 * sgn, Reference(x, 0.0, 0.0))
    assert ff.state.x_fed_m == pytest.approx(x, abs=1e-12)
    # the next move's first 0.5 µm feed the model (it is not held until the reference passes the old stage position)
    f0 = ff.model_force_n
    for k in range(1, 21):
        xk, vk, ak = _quintic(0.5e-6 * sgn, 20 * dt, k * dt)
        ctl.step(dt, x - 1e-6 * sgn, Reference(x + xk, vk, ak))
    assert not ff.state.holding
    assert sgn * (ff.model_force_n - f0) > 0.0
