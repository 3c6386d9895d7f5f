"""Cogging whose period is close to the stroke (the period scan's longest period).

Oracle: a plain simulation, independent of stagectl's plant and controller: a rigid mass with a smooth
Coulomb + viscous friction and a position force, tracked by a PD + integral loop along slow passes of
constant velocity both ways (1 kHz, the plant sub-stepped ×10, explicit Euler). The recording carries what
the slow-passes experiment records (x, u, v_ref, a_ref), and :func:`stagectl.commission.fit.cogging_evidence`
must name a 1.41 mm cogging over the 2 mm stroke (generated plant 44's; main refused it as a trend, and
the commissioned stage tracked the cosine 21× and the triangle 7× the exact model's), while a smooth force
of the same size along the stroke (an exponential, same in both directions) stays a trend.
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


def _slow_passes(position_force: Callable[[float], float], stroke_m: float = 2e-3, v_m_s: float = 4.6e-4,
                 mass_kg: float = 0.79) -> Recorder:
    """Two passes each way over ``stroke_m`` at ``v_m_s`` (ramps of 0.05 s, dwells of 0.2 s)."""
    ramp = 0.05
    a = v_m_s / ramp
    # reference: piecewise constant-acceleration moves between the ends
    segs: list[tuple[float, float]] = []  # (duration, acceleration)
    cruise = (stroke_m - v_m_s * ramp) / v_m_s
    for sgn in (1, -1, 1, -1):
        segs += [(0.2, 0.0), (ramp, sgn * a), (cruise, 0.0), (ramp, -sgn * a)]
    segs.append((0.2, 0.0))
    return track(segs, mass_kg=mass_kg, fc_n=0.48, viscous_n_s_m=35.0, vs_m_s=2e-5, position_force=position_force,
                 x0_m=-stroke_m / 2)


def test_cogging_near_the_stroke_is_named() -> None:
    amp, lam = 0.1133, 1.412e-3
    ev = cogging_evidence(_slow_passes(lambda x: amp * math.sin(2 * math.pi * x / lam + 0.4)), 0.79, T)
    assert ev["present"], ev
    assert abs(ev["wavelength_m"] / lam - 1) < 0.02, ev
    assert abs(ev["amplitude_n"] / amp - 1) < 0.05, ev


def test_smooth_trend_at_the_scan_edge_is_not_cogging() -> None:
    # a force rising smoothly along the stroke (as large as the cogging above), the same both ways
    ev = cogging_evidence(_slow_passes(lambda x: 0.12 * math.exp(x / 0.5e-3) / math.exp(2.0)), 0.79, T)
    assert not ev["present"], ev
    assert ev["wavelength_m"] > 0.9 * ev["scan_m"][1], ev  # the trend peaked at the scan's edge


def test_a_force_whose_period_runs_to_the_travel_is_not_cogging() -> None:
    """A cable carrier's pull that saturates along the stroke and a V-shaped force (0.1 N over the stroke,
    the same both ways): neither is periodic, the least-squares period runs to the whole travel, and the
    cubic does not take them (they are not polynomials). Both were named cogging by the edge rule alone."""
    for name, force in (("saturating pull", lambda x: 0.1 * (1.0 - math.exp(-(x + 1e-3) / 0.3e-3))),
                        ("|x|", lambda x: 100.0 * abs(x))):
        ev = cogging_evidence(_slow_passes(force), 0.79, T)
        assert ev["ratio"] >= 5.0, (name, ev)  # the scan's peak is strong: only the period's bound refuses it
        assert not ev["present"], (name, ev)
