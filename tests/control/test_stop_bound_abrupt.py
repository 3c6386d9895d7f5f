"""The look-ahead bound (``stop_m``, :func:`stagectl.control.friction_ff.bounded_ahead`) together with the abrupt-stop
rule (:meth:`DirectionLatch.stop_at`) at a reference that stops at once: a ``sine`` / a cosine of fractional cycles
that ends moving, followed by a dwell (the reference's v steps to 0 where the segment ended).

Without the bound the look-ahead point x + v·τ_a runs past that stop in the last samples, the model copy is stepped
there, and ``stop_at`` only moves the fed position back afterwards: the model holds the state of a travel the
reference never made. With the bound the model is never fed past the stop, the reversals are the reference's own
turns, and the force held at rest is nearer that of the model fed the reference itself (no look-ahead; the
independent oracle: the look-ahead shifts the model's path in time, it must not lengthen it)."""

from __future__ import annotations

import math
from itertools import pairwise
from pathlib import Path

import pytest

from stagectl.control.friction_ff import FrictionFeedforward
from stagectl.control.trajectory import Cosine, Dwell, Sine, TrajectoryGenerator

REPO = Path(__file__).resolve().parents[2]
T = 1e-3
CASES = {
    "sine 1.3": [Sine(amplitude_m=1e-6, frequency_hz=5.0, cycles=1.3), Dwell(0.02)],
    "sine 1.1": [Sine(amplitude_m=1e-6, frequency_hz=5.0, cycles=1.1), Dwell(0.02)],
    "cosine 1.2": [Cosine(amplitude_m=2e-6, frequency_hz=5.0, cycles=1.2), Dwell(0.02)],
    "cosine -0.8": [Cosine(amplitude_m=-3e-6, frequency_hz=2.0, cycles=0.8), Dwell(0.02)],
}


@pytest.fixture(scope="module")
def model():  # type: ignore[no-untyped-def]
    from stagectl.config import load_app_config
    from stagectl.control.controller import StageController

    cfg = load_app_config(REPO / "config" / "sim.yaml")
    ff = StageController(cfg.controller, cfg.timing).ff
    assert isinstance(ff, FrictionFeedforward)
    return ff.model


def _run(model, segs, lookahead_s: float, bounded: bool):  # type: ignore[no-untyped-def]
    """Step a feed-forward along the segments; returns per sample (x_ref, v_ref, fed position after the step) and
    the feed-forward's final force and reversal count."""
    ff = FrictionFeedforward(model, lookahead_s=lookahead_s)
    gen = TrajectoryGenerator(0.0)
    gen.replace(segs)
    ff.reset(0.0)
    rows = []
    u = 0.0
    while not gen.done:
        ref = gen.step(T)
        u = ff.step(T, ref, gen.stop_m() if bounded else math.nan)
        rows.append((ref.x_m, ref.v_m_s, ff.state.x_fed_m, ff.latch.direction))
    return rows, u, ff.state.reversals


@pytest.mark.parametrize("name", sorted(CASES))
def test_an_abrupt_stop_is_not_overfed_and_keeps_the_turns(model, name: str) -> None:  # type: ignore[no-untyped-def]
    segs = CASES[name]
    rows, u_b, rev_b = _run(model, segs, 1.5e-3, bounded=True)
    _, u_free, _ = _run(model, segs, 1.5e-3, bounded=False)
    _, u_0, rev_0 = _run(model, segs, 0.0, bounded=False)
    v = [r[1] for r in rows]
    turns = sum(1 for a, b in pairwise(v) if a * b < 0.0)
    assert rev_b == turns == rev_0, (rev_b, turns, rev_0)
    # the last leg: from the last turn to the stop; the model is never fed past the stop in its direction
    i_stop = next(i for i, r in enumerate(rows) if r[1] == 0.0 and i > 0 and rows[i - 1][1] != 0.0)
    x_stop = rows[i_stop][0]
    d = 1 if rows[i_stop - 1][1] > 0.0 else -1
    last_turn = max(i for i in range(1, i_stop) if v[i - 1] * v[i] < 0.0)
    assert all((r[2] - x_stop) * d <= 1e-15 for r in rows[last_turn:]), name
    assert rows[-1][2] == pytest.approx(x_stop, abs=1e-15) and rows[-1][3] == d
    # the force held at rest: nearer the model fed the reference itself than with the unbounded look-ahead
    assert abs(u_b - u_0) < abs(u_free - u_0), (u_b, u_free, u_0)
