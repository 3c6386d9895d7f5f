"""A reference that stops at once (v_ref jumps to 0: the end of a ``sine`` segment, a cosine of fractional cycles)
takes the feed-forward's look-ahead point back by the overshoot v·τ_a; that is no move back. The direction latch
keeps the last motion's direction, so the controller's stop synchronisation (``_rest_sync_where``) still judges the
stage "behind" the reference as behind (before: the latch reversed and the model was fed at the stage behind the
reference), and the Coulomb baseline keeps the sign of its force. Both directions of travel, sim.yaml settings."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from stagectl.control.api import Reference
from stagectl.control.friction_ff import CoulombFeedforward
from stagectl.control.trajectory import Cosine, Sine, TrajectoryGenerator

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("sgn", [1.0, -1.0])
@pytest.mark.parametrize("seg", ["sine", "cosine"])
def test_abrupt_stop_keeps_the_direction_and_the_rest_sync_side(sgn: float, seg: str) -> None:
    from stagectl.config import load_app_config
    from stagectl.control.controller import StageController

    cfg = load_app_config(REPO / "config" / "sim.yaml")
    c = cfg.controller
    c = dataclasses.replace(c, settle=dataclasses.replace(c.settle, move_s=0.0))  # (no settle move: rest sync)
    ctl = StageController(c, cfg.timing)
    dt = cfg.loop.period_s
    ctl.reset(0.0)
    ff = ctl.ff
    assert ff.lookahead_s > 0.0
    gen = TrajectoryGenerator(0.0)
    # a sine ends moving at v = 2πfA (12.6 µm/s: overshoot 19 nm > the 5 nm threshold); a quarter raised cosine
    # at its fastest, πfA (31 µm/s)
    gen.replace(Sine(amplitude_m=1e-6 * sgn, frequency_hz=2.0, cycles=1) if seg == "sine"
                else Cosine(amplitude_m=10e-6 * sgn, frequency_hz=1.0, cycles=0.25))
    n_rev = 2 if seg == "sine" else 0
    ref = gen.sample()
    while gen.state.segment != "hold":
        ref = gen.step(dt)
        ctl.step(dt, ref.x_m - 10e-9 * sgn, ref)  # the stage 10 nm behind
        last_v = ref.v_m_s if ref.v_m_s != 0.0 else last_v
    assert sgn * last_v > 1e-5  # it did stop at once, moving in direction sgn
    x = ref.x_m
    for _ in range(50):  # then held; the stage stuck 1 µm behind: no sync, the model stays at the reference
        ref = gen.step(dt)
        ctl.step(dt, x - 1e-6 * sgn, ref)
    assert ff.latch.direction == sgn
    assert ff.state.reversals == n_rev
    assert ff.state.x_fed_m == pytest.approx(x, abs=1e-12)
    for _ in range(50):  # stuck 1 µm ahead: fed at the stage
        ctl.step(dt, x + 1e-6 * sgn, Reference(x))
    assert ff.state.x_fed_m == pytest.approx(x + 1e-6 * sgn, abs=1e-12)


@pytest.mark.parametrize("sgn", [1.0, -1.0])
def test_coulomb_baseline_keeps_its_sign_at_an_abrupt_stop(sgn: float) -> None:
    ff = CoulombFeedforward(0.8, lookahead_s=1.5e-3)
    ff.reset(0.0)
    dt, v, x = 1e-3, 2e-5 * sgn, 0.0
    for _ in range(20):
        x += v * dt
        u = ff.step(dt, Reference(x, v))
    assert u == pytest.approx(0.8 * sgn)
    for _ in range(5):  # held at once: the look-ahead steps back by v·τ_a = 30 nm
        u = ff.step(dt, Reference(x))
    assert u == pytest.approx(0.8 * sgn)
    assert ff.state.reversals == 0
    for k in range(1, 4):  # a real move back from the stop is still a reversal
        u = ff.step(dt, Reference(x - 4e-9 * k * sgn))
    assert u == pytest.approx(-0.8 * sgn)
