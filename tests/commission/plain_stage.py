"""Shared oracle of the commissioning pass tests: a plain stage written from the physics (not the simulator), and
the sequence's constant-velocity pass layout.

The stage: mass ``m``; one elastoplastic Maxwell-slip element of stiffness ``K`` whose force ``K·z`` slips at the
Stribeck level ``F_c + (F_s − F_c)·exp(−(v/v_s)²)``; viscous ``c·v``; an optional position force ``f(x)`` (a
cogging); one cycle of I/O delay (the force commanded in a period acts in the next); explicit Euler in 10
sub-steps a period.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from stagectl.commission import sequence as seq
from stagectl.control.trajectory import Dwell, Move


class MaxwellSlipStage:
    """The plain stage (module docstring). ``st`` holds ``mass`` [kg], ``fs``, ``fc`` [N], ``visc`` [N s/m],
    ``vs`` [m/s] and ``k`` [N/m]; ``x`` [m] is its position."""

    def __init__(self, st: dict[str, Any], x0_m: float = 0.0,
                 position_force: Callable[[float], float] | None = None, sub: int = 10) -> None:
        self.m, self.fs, self.fc, self.visc, self.vs, self.k = (st[k] for k in ("mass", "fs", "fc", "visc", "vs", "k"))
        self.position_force = position_force
        self.sub = sub
        self.x = x0_m
        self.vel = self.z = self.u_applied = 0.0

    def period(self, u_n: float, period_s: float) -> None:
        """One period under the force commanded a period ago; ``u_n`` [N] acts in the next."""
        m, fs, fc, visc, vs, K = self.m, self.fs, self.fc, self.visc, self.vs, self.k
        f_x = self.position_force
        x, vel, z, u_applied = self.x, self.vel, self.z, self.u_applied
        h = period_s / self.sub
        for _ in range(self.sub):
            z += vel * h
            f_slide = fc + (fs - fc) * math.exp(-((vel / vs) ** 2))
            if abs(K * z) > f_slide:
                z = math.copysign(f_slide / K, z)
            if f_x is None:
                vel += (u_applied - K * z - visc * vel) / m * h
            else:
                vel += (u_applied - K * z - visc * vel - f_x(x)) / m * h
            x += vel * h
        self.x, self.vel, self.z, self.u_applied = x, vel, z, u_n


def pass_segments(budget: seq.RampBudget, m_est_kg: float, v_rep_m_s: float, a_rep_m_s2: float, period_s: float,
                  v_max_m_s: float, stroke_m: float, max_force_n: float = 7.0) -> list[Move | Dwell]:
    """The sequence's constant-velocity passes: ``seq.CV_SPEEDS`` log-spaced speeds up to ``v_max_m_s``, each a
    reposition move, then out and back over ``min(stroke, max(v·CV_PASS_S, 0.05·stroke))`` with ramps from the
    error budget and the readability floor, 0.1 s dwells between."""
    segs: list[Move | Dwell] = []
    for v in np.geomspace(v_max_m_s / seq.CV_SPAN, v_max_m_s, seq.CV_SPEEDS).tolist():
        L = min(stroke_m, max(v * seq.CV_PASS_S, 0.05 * stroke_m))
        a = seq.pass_acceleration(max(min(max(v * v / (0.1 * L), 0.02), 0.3 * max_force_n / m_est_kg), 1e-6), v,
                                  budget, seq.readable_acceleration(v, L, period_s))
        segs += [Move(to_m=-L / 2, max_velocity_m_s=v_rep_m_s, max_acceleration_m_s2=a_rep_m_s2,
                      max_jerk_m_s3=100 * a_rep_m_s2),
                 Dwell(0.1),
                 Move(to_m=L / 2, max_velocity_m_s=v, max_acceleration_m_s2=a, max_jerk_m_s3=a * 100), Dwell(0.1),
                 Move(to_m=-L / 2, max_velocity_m_s=v, max_acceleration_m_s2=a, max_jerk_m_s3=a * 100), Dwell(0.1)]
    return segs


def run_passes(ctl: Any, budget: seq.RampBudget, m_est_kg: float, v_rep_m_s: float, stage: Any, period_s: float,
               v_max_m_s: float, stroke_m: float) -> float:
    """The sequence's passes (:func:`pass_segments`, repositioning at ``v_rep_m_s`` with ``v_rep²/(0.02·stroke)``)
    run by the controller ``ctl`` (a ``CommissionController`` with its speed ladder closed) on ``stage``
    (``.x`` [m], ``.period(u, T)``), from rest at 0; returns the largest |x_ref − x| [m]."""
    from stagectl.control.trajectory import Scenario, TrajectoryGenerator

    segs = pass_segments(budget, m_est_kg, v_rep_m_s, v_rep_m_s ** 2 / (0.1 * 0.2 * stroke_m), period_s, v_max_m_s,
                         stroke_m)
    gen = TrajectoryGenerator(0.0)
    gen.load(Scenario(name="cv", segments=tuple(segs)))
    ctl.reset(0.0)
    peak = 0.0
    while not gen.done:
        ref = gen.step(period_s)
        u = ctl.step(period_s, stage.x, ref).force_n
        peak = max(peak, abs(ref.x_m - stage.x))
        stage.period(u, period_s)
    return peak
