"""Static friction: Coulomb + viscous + Stribeck, with a Karnopp band and an optional frictional lag.

Equations (docs/friction-models.md §1)::

    g(v)  = Fc + (Fs − Fc)·exp(−|v/Vs|^δ)               Stribeck magnitude [N]
    F(v)  = sgn(v)·(Fc + e) + σ2·v,   e = e_ss(v) = (Fs − Fc)·exp(−|v/Vs|^δ)

Frictional lag (``lag_s`` = T_l > 0): the Stribeck excess ``e`` follows its steady value through a
first-order lag, ``de/dt = (e_ss(v) − e)/T_l``, integrated exactly for v frozen over a step:
``e ← e_ss + (e − e_ss)·exp(−dt/T_l)``. The relaxed state is ``e = Fs − Fc`` (at rest). With
``lag_s = 0`` the model has **no state** (``n_states == 0``) and is exactly the static map; with
``lag_s > 0`` it has one state ``[e]``.

Symbols → parameters: Fc = ``fc_n`` [N], Fs = ``fs_n`` [N], Vs = ``vs_m_s`` [m/s],
δ = ``delta`` [–], σ2 = ``viscous_n_s_m`` [N·s/m], T_l = ``lag_s`` [s].
``fs_n = fc_n`` gives plain Coulomb + viscous. Fs > Fc is the Stribeck dip (friction falls with speed);
Fs < Fc a friction that rises with speed from a lower break-away level, as measured on rolling contacts
(ball screws, rolling guides: no dip, the force builds up over the first tens of mm/s).

At v = 0 the map returns 0 (sgn(0) = 0); a plant needs a stick treatment there. The kernel reports
``breakaway_n = Fs`` and ``stick_velocity_m_s`` (Karnopp band half-width DV): inside ``|v| < DV`` the
plant holds the stage while ``|F_ext| <= Fs`` and the friction balances ``F_ext`` (§1.2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stagectl.friction._numba import FloatArray, KernelModel, sgn, stribeck_excess
from stagectl.friction.base import register
from stagectl.jit import kernel
from stagectl.schema import param

# packed layout: [fc, fs, vs, delta, viscous, lag_s, stick_v]


@kernel
def _kstep(p: FloatArray, state: FloatArray, dx: float, v: float, dt: float) -> float:  # pragma: no cover
    fc = p[0]
    ess = (p[1] - fc) * stribeck_excess(v, p[2], p[3])
    lag = p[5]
    if lag > 0.0:
        # exact first-order lag of the Stribeck excess for v frozen over dt
        e = ess + (state[0] - ess) * math.exp(-dt / lag)
        state[0] = e
    else:
        e = ess
    f: float = sgn(v) * (fc + e) + p[4] * v
    return f


@kernel
def _kforce(p: FloatArray, state: FloatArray, v: float) -> float:  # pragma: no cover
    fc = p[0]
    if p[5] > 0.0:
        e = state[0]
    else:
        e = (p[1] - fc) * stribeck_excess(v, p[2], p[3])
    f: float = sgn(v) * (fc + e) + p[4] * v
    return f


@dataclass(frozen=True)
class StribeckParams:
    """Parameters of the static Coulomb + viscous + Stribeck model (SI units)."""

    fc_n: float = param(unit="N", desc="Coulomb (kinetic) friction level Fc", ge=0.0)
    fs_n: float = param(unit="N", desc="static (break-away) level Fs (below fc_n: friction rising with speed)",
                        ge=0.0)
    vs_m_s: float = param(1e-3, unit="m/s", desc="Stribeck velocity Vs", gt=0.0)
    delta: float = param(2.0, unit="", desc="Stribeck shape exponent δ", gt=0.0, le=10.0)
    viscous_n_s_m: float = param(0.0, unit="N·s/m", desc="viscous coefficient σ2", ge=0.0)
    stick_velocity_m_s: float = param(1e-6, unit="m/s", desc="Karnopp zero-velocity band half-width DV",
                                      gt=0.0)
    lag_s: float = param(0.0, unit="s", desc="frictional lag time constant of the Stribeck excess (0 = none)",
                         ge=0.0)


@register
class StribeckFriction(KernelModel):
    """Coulomb + viscous + Stribeck (+ optional frictional lag); tag ``stribeck``."""

    tag = "stribeck"
    Params = StribeckParams
    params: StribeckParams
    _kstep = staticmethod(_kstep)
    _kforce = staticmethod(_kforce)

    @staticmethod
    def _pack(params: StribeckParams) -> FloatArray:
        q = params
        return np.array([q.fc_n, q.fs_n, q.vs_m_s, q.delta, q.viscous_n_s_m, q.lag_s, q.stick_velocity_m_s])

    @staticmethod
    def _relaxed(params: StribeckParams) -> FloatArray:
        if params.lag_s > 0.0:
            return np.array([params.fs_n - params.fc_n])
        return np.zeros(0)

    def _stick(self) -> tuple[float, float]:
        return float(self.params.fs_n), float(self.params.stick_velocity_m_s)

    def stribeck(self, v: float) -> float:
        """Steady-state friction F(v) = sgn(v)·g(v) + σ2·v [N] at velocity ``v`` [m/s]."""
        return float(_kforce(self._p, np.zeros(0) if self.n_states == 0 else np.array([self._ess(v)]), float(v)))

    def _ess(self, v: float) -> float:
        q = self.params
        return (q.fs_n - q.fc_n) * math.exp(-(abs(v / q.vs_m_s) ** q.delta))

    @property
    def damping_n_s_m(self) -> float:
        """Viscous coefficient σ2 [N·s/m] (for integrator step limits)."""
        return float(self.params.viscous_n_s_m)

    def derivative(self, state: FloatArray, v: float) -> FloatArray:
        if self.n_states == 0:
            return np.zeros(0)
        return np.array([(self._ess(v) - state[0]) / self.params.lag_s])
