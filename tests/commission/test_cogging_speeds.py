"""A ripple periodic in time at the slow passes' speed is not a cogging (issue 11: no effect the plant lacks is named).

A 1 kg GMS stage with a spring and no cogging limit-cycled at 35 Hz in its 1.5 mm/s slow passes (its Stribeck
slope is unstable at 1-2 mm/s); the scan read the 115 mN ripple as a 40 µm cogging in both directions (phases
10° apart), ratio 82, "high", and the constant-velocity passes' moves at the same speed confirmed it. The
recording's slower moves to and from the passes (0.3 mm/s, over 4.4 mm) showed 0.03 mN of it: a force of
position is there at every speed, a ripple periodic in time reads as λ = v/f at one speed only.

Oracle: a plain simulation independent of stagectl's plant and controller (a rigid mass, smooth Coulomb +
viscous friction, PID at 1 kHz, sub-stepped ×10): a move to one end at 0.3 mm/s, a pass each way at 1.5 mm/s,
a move back at 0.3 mm/s. The speed-driven ripple ``A·sin(2πf(t − t₀))`` runs during each fast cruise from its
start ``t₀``; ``f`` is chosen so that the two directions agree in phase, as on the measured stage, so that the
direction check alone does not refuse it. A true cogging on the same moves stays named.
"""
from __future__ import annotations

import math
import sys
from collections.abc import Callable
from pathlib import Path

from stagectl.commission.fit import cogging_evidence
from stagectl.recorder import Recorder

sys.path.insert(0, str(Path(__file__).parent))
from pid_mass_stage import T, track

STROKE, V_SLOW, V_FAST, RAMP, MASS = 2e-3, 3e-4, 1.5e-3, 0.05, 1.0


def _passes(position_force: Callable[[float], float], ripple_n: float, ripple_hz: float) -> Recorder:
    h = STROKE / 2
    moves = [(-h, V_SLOW), (h, V_FAST), (-h, V_FAST), (0.0, V_SLOW)]
    segs: list[tuple[float, float]] = [(0.2, 0.0)]  # (duration, acceleration)
    fast: list[bool] = [False]  # the segment is a fast cruise
    pos = 0.0
    for target, v in moves:
        d = target - pos
        s = math.copysign(1.0, d)
        segs += [(RAMP, s * v / RAMP), ((abs(d) - v * RAMP) / v, 0.0), (RAMP, -s * v / RAMP), (0.2, 0.0)]
        fast += [False, v == V_FAST, False, False]
        pos = target

    def ripple(i: int, k: int) -> float:
        return ripple_n * math.sin(2 * math.pi * ripple_hz * k * T) if fast[i] else 0.0

    return track(segs, mass_kg=MASS, fc_n=0.5, viscous_n_s_m=40.0, vs_m_s=2e-5, position_force=position_force,
                 extra_force=ripple)


def test_a_ripple_at_one_speed_is_not_named_a_cogging() -> None:
    # the fast cruises start at ∓(h − v·RAMP/2); their phases agree in x when the distance between the starts
    # holds a whole number of wavelengths and a half
    span = STROKE - V_FAST * RAMP
    f = V_FAST * 40.5 / span  # λ = span / 40.5 ≈ 48 µm, f ≈ 31 Hz
    ev = cogging_evidence(_passes(lambda x: 0.0, 0.1, f), MASS, T)
    assert ev["ratio"] >= 5.0 and ev["directions_phase_deg"] < 45.0, ev  # what main named
    assert abs(ev["wavelength_m"] / (V_FAST / f) - 1.0) < 0.05, ev
    assert not ev["present"], ev
    by = {round(s["speed_m_s"], 5): s for s in ev["speeds"]}
    assert by[V_SLOW]["fraction"] < 0.1 and by[V_FAST]["fraction"] > 0.5, by
    assert "not a force of position" in ev["reason"]


def test_a_cogging_on_the_same_moves_is_named_at_both_speeds() -> None:
    amp, lam = 0.03, 0.31e-3
    ev = cogging_evidence(_passes(lambda x: amp * math.sin(2 * math.pi * x / lam + 0.4), 0.0, 1.0), MASS, T)
    assert ev["present"], ev
    assert abs(ev["wavelength_m"] / lam - 1) < 0.02 and abs(ev["amplitude_n"] / amp - 1) < 0.1, ev
    assert all(abs(s["fraction"] - 1.0) < 0.15 for s in ev["speeds"]) and len(ev["speeds"]) == 2, ev
