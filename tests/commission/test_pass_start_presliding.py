"""A constant-velocity pass that starts from a stuck stage with long pre-sliding, a spring and an offset: the
start's force step comes in along the reference's travel over the stage's pre-sliding length.

Oracle: a plain stage written here (mass; four elastoplastic Maxwell-slip elements, stiffnesses 2e5…5e3 N/m,
each slipping at its share of the Stribeck level F_c + (F_s − F_c)·exp(−(v/v_s)²), with micro-damping while it
sticks; viscous c·v; a 150 N/m spring and a 0.35 N offset; one cycle of I/O delay, 10 sub-steps a period), not
the simulator. It is the outside stage of docs/commissioning.md (*Pass starts on a stage with long
pre-sliding*), which faulted in friction_cv on main (following error 50.4 µm at the start of a 1 mm/s pass):
the force step at a start (the observer's released pre-sliding force, 2–3 N, and the Coulomb term, 1.96 N)
came in at once, the softest elements (5e3 N/m, slip at 0.32 N: 64 µm) let the stage leap ~30 µm ahead of the
standing reference through its pre-sliding reversal, the observer wound up to pull it back, and the stage stuck
while the reference ran away. The passes run the sequence's layout through the real
:class:`CommissionController` with the stiffer experiments' tuning (26 Hz) and a :class:`SpeedLadderFeedforward`,
with what the sequence knew on that stage (its report.json: probe mass 1.08 kg, break-aways 3.66 / 2.44 N, FRF
pre-sliding stiffness 2.67e5 N/m).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

from stagectl.commission import sequence as seq
from stagectl.commission.controllers import CommissionController, SpeedLadderFeedforward
from stagectl.control.controller import StageController
from stagectl.control.friction_ff import CoulombFeedforward

sys.path.insert(0, str(Path(__file__).parent))
from plain_stage import run_passes

T = 1e-3
E_MAX = 50e-6
V_MAX = 0.016
S = 9e-3   # the outside stage's passes: ±4.5 mm
#: the outside stage (mass, GMS-like elements, Stribeck, viscous, spring + offset) ...
PLANT: dict[str, Any] = {"mass": 1.0, "k": (2e5, 5e4, 1.5e4, 5e3), "alpha": (0.4, 0.3, 0.2, 0.1), "sigma1": (74.0, 18.5, 5.6, 1.9),
         "fs": 3.2, "fc": 2.5, "vs": 2e-3, "visc": 40.0, "spring": 150.0, "x0": -2e-3, "offset": 0.35}
#: ... and what the sequence knew when its passes ran
KNOWN: dict[str, Any] = {"m_exp": 1.081, "m_std": 6.4e-4, "ff": 1.9558, "breakaway": [3.6557, 2.4447], "k_ps": 2.67e5,
         "xp": 0.026, "v_rep": 1.804e-3}


class MultiSlipStage:
    """The plain stage of the module docstring; ``x`` [m] is its position."""

    def __init__(self, p: dict[str, Any], sub: int = 10) -> None:
        self.p = p
        self.sub = sub
        self.x = self.vel = self.u_applied = 0.0
        self.z = [0.0] * len(p["k"])

    def period(self, u_n: float, period_s: float) -> None:
        """One period under the force commanded a period ago; ``u_n`` [N] acts in the next."""
        p = self.p
        ks, al, s1 = p["k"], p["alpha"], p["sigma1"]
        fs, fc, vs = float(p["fs"]), float(p["fc"]), float(p["vs"])
        m, visc = float(p["mass"]), float(p["visc"])
        load_k, x0, off = float(p["spring"]), float(p["x0"]), float(p["offset"])
        x, vel, z, h = self.x, self.vel, self.z, period_s / self.sub
        for _ in range(self.sub):
            f_slide = fc + (fs - fc) * math.exp(-((vel / vs) ** 2))
            f_fr = 0.0
            for i, (k, a, c) in enumerate(zip(ks, al, s1)):
                zi = z[i] + vel * h
                w = a * f_slide
                if abs(k * zi) > w:
                    z[i] = math.copysign(w / k, zi)
                    f_fr += k * z[i]
                else:
                    z[i] = zi
                    f_fr += k * zi + c * vel
            vel += (self.u_applied - f_fr - visc * vel - off - load_k * (x - x0)) / m * h
            x += vel * h
        self.x, self.vel, self.u_applied = x, vel, u_n


def _run(presliding_length_m: float) -> tuple[SpeedLadderFeedforward, float]:
    """The passes on the oracle; returns the ladder and the peak |x_ref − x| over the passes [m]."""
    k = KNOWN
    cfg = seq.commission_tuning(k["m_exp"], T, 10.0, k["ff"], crossover_x_period=k["xp"])
    inner = StageController(cfg, T)
    assert isinstance(inner.ff, CoulombFeedforward)
    budget = seq.pass_budget(cfg, T, 1, k["m_exp"], k["m_std"], max(k["breakaway"]), 0.0, E_MAX)
    ladder = SpeedLadderFeedforward(inner.ff, seq.LADDER_SETTLE_X_CROSSOVER_PERIOD / (2 * math.pi * k["xp"] / T),
                                    hold_limit_n=budget.error_m / budget.g_step_m_n,
                                    presliding_length_m=presliding_length_m)
    ctl = CommissionController(inner)
    ctl.set_closed(inner, ladder=ladder)
    peak = run_passes(ctl, budget, k["m_exp"], float(k["v_rep"]), MultiSlipStage(PLANT), T, V_MAX, S)
    return ladder, peak


def test_pass_starts_on_a_stage_with_long_presliding_stay_within_the_following_error_limit() -> None:
    assert 10e-6 < seq.presliding_length(KNOWN["breakaway"], KNOWN["k_ps"]) < 13e-6   # 3.05 N over 2.67e5 N/m
    L = seq.presliding_length(KNOWN["breakaway"], KNOWN["k_ps"], seq.PRESLIDING_LENGTH_X_BUDGET * 0.5 * E_MAX)
    assert L == seq.PRESLIDING_LENGTH_X_BUDGET * 0.5 * E_MAX   # the sequence's cap: 8.3 µm
    ladder, peak = _run(L)
    _, peak_step = _run(0.0)   # main: the start's force step at once (52 µm; blended: 20 µm)
    assert peak < 0.5 * E_MAX < E_MAX < peak_step, (peak, peak_step)
    assert ladder.releases     # the held force still goes, along the travel
    assert max(abs(f) for f in ladder.releases) <= 1.05 * (PLANT["fs"] + 0.35 + 150 * 4.5e-3), ladder.releases


def test_no_presliding_length_without_a_stiffness_or_breakaway() -> None:
    assert seq.presliding_length([3.0], math.nan) == 0.0
    assert seq.presliding_length([], 1e5) == 0.0
    assert seq.presliding_length([1.0, 3.0], 1e5) == 2e-5
    assert seq.presliding_length([1.0, 3.0], 1e3, 25e-6) == 25e-6   # capped at the passes' error budget
