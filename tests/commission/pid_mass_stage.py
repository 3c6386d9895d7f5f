"""Shared oracle of the cogging tests: a plain simulation, independent of stagectl's plant and controller.

A rigid mass ``m`` with a smooth Coulomb + viscous friction ``F_c·tanh(v/v_s) + c·v``, a position force
``f(x)`` and an optional extra force, tracked by a PID (40 Hz, ζ 0.8, integral at 5 Hz) with inertia
feed-forward along a reference of constant-acceleration segments; 1 kHz, the plant sub-stepped ×10 (explicit
Euler). The recording carries what the slow-passes experiment records (x, u, x_ref, v_ref, a_ref).
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence

from stagectl.recorder import Recorder

T = 1e-3


def track(segs: Sequence[tuple[float, float]], *, mass_kg: float, fc_n: float, viscous_n_s_m: float,
          vs_m_s: float, position_force: Callable[[float], float], x0_m: float = 0.0,
          extra_force: Callable[[int, int], float] | None = None) -> Recorder:
    """Run the reference ``segs`` ((duration [s], acceleration [m/s²]) each) from rest at ``x0_m``;
    ``extra_force(i, k)`` [N] acts on the plant in sample ``k`` of segment ``i``."""
    kp = mass_kg * (2 * math.pi * 40) ** 2
    kd, ki = 2 * 0.8 * mass_kg * 2 * math.pi * 40, kp * 2 * math.pi * 5
    rec = Recorder(("t", "x", "u", "x_ref", "v_ref", "a_ref"), capacity=1 << 15)
    x, v, xr, vr, integ, t = x0_m, 0.0, x0_m, 0.0, 0.0, 0.0
    for i, (dur, ar) in enumerate(segs):
        for k in range(round(dur / T)):
            e = xr - x
            integ += e * T
            u = kp * e + kd * (vr - v) + ki * integ + mass_kg * ar
            rec.append((t, x, u, xr, vr, ar))
            extra = extra_force(i, k) if extra_force is not None else 0.0
            for _ in range(10):
                f = fc_n * math.tanh(v / vs_m_s) + viscous_n_s_m * v + position_force(x) + extra
                v += (u - f) / mass_kg * (T / 10)
                x += v * (T / 10)
            xr += vr * T + 0.5 * ar * T * T
            vr += ar * T
            if abs(vr) < 1e-12:
                vr = 0.0
            t += T
    return rec
