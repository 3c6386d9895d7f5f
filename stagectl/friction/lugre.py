"""LuGre friction model (Canudas de Wit, Olsson, Åström, Lischinsky, IEEE TAC 40(3), 1995).

Equations (docs/friction-models.md §5.1)::

    g(v)   = Fc + (Fs − Fc)·exp(−|v/Vs|^δ)             Stribeck magnitude [N]
    dz/dt  = v − σ0·|v|·z / g(v)                         bristle deflection rate [m/s]
    σ1(v)  = σ1·exp(−(v/Vd)²)                           bristle damping (Vd = ∞: constant σ1)
    F      = σ0·z + σ1(v)·dz/dt + σ2·v                  friction force [N], opposes motion
    steady state: z_ss = sgn(v)·g(v)/σ0,   F_ss = sgn(v)·g(v) + σ2·v

Discrete update (v frozen over the step, exact, unconditionally stable for any ``dt``)::

    z ← z_ss + (z − z_ss)·exp(−σ0·|v|·dt / g(v))       (v = 0: z unchanged)

``step`` returns ``F`` evaluated with the *new* z and the instantaneous dz/dt at velocity v, i.e. exactly
what ``force(state, v)`` returns afterwards.

Symbols → parameters: σ0 = ``sigma0_n_m`` [N/m], σ1 = ``sigma1_n_s_m`` [N·s/m], σ2 = ``viscous_n_s_m``
[N·s/m], Fc = ``fc_n`` [N], Fs = ``fs_n`` [N] (≥ Fc), Vs = ``vs_m_s`` [m/s], δ = ``delta`` [–],
Vd = ``sigma1_decay_m_s`` [m/s] (``.inf`` = off). State: ``[z]`` [m], relaxed z = 0.

Known property: LuGre drifts under oscillating forces below break-away (no non-local memory), and the
hysteresis loops are not Masing-like. Use GMS when that matters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stagectl.friction._numba import FloatArray, KernelModel, sgn, stribeck_g
from stagectl.friction.base import register
from stagectl.jit import kernel
from stagectl.schema import param

# packed layout: [sigma0, sigma1, sigma2, fc, fs, vs, delta, vd]


@kernel(inline="always")
def _sigma1(p: FloatArray, v: float) -> float:  # pragma: no cover - compiled
    vd = p[7]
    s1: float = p[1]
    if math.isinf(vd):
        return s1
    return s1 * math.exp(-((v / vd) ** 2))


@kernel
def _kstep(p: FloatArray, state: FloatArray, dx: float, v: float, dt: float) -> float:  # pragma: no cover
    s0 = p[0]
    g = stribeck_g(v, p[3], p[4], p[5], p[6])
    z = state[0]
    if v != 0.0:
        zss = sgn(v) * g / s0
        # exact solution of dz/dt = v − σ0|v|z/g for frozen v
        z = zss + (z - zss) * math.exp(-s0 * abs(v) * dt / g)
        state[0] = z
    zdot = v - s0 * abs(v) * z / g
    f: float = s0 * z + _sigma1(p, v) * zdot + p[2] * v
    return f


@kernel
def _kforce(p: FloatArray, state: FloatArray, v: float) -> float:  # pragma: no cover
    s0 = p[0]
    g = stribeck_g(v, p[3], p[4], p[5], p[6])
    z = state[0]
    zdot = v - s0 * abs(v) * z / g
    f: float = s0 * z + _sigma1(p, v) * zdot + p[2] * v
    return f


@dataclass(frozen=True)
class LuGreParams:
    """Parameters of the LuGre model (SI units). Defaults of δ, σ2 and Vd: 2, 0 and off."""

    sigma0_n_m: float = param(unit="N/m", desc="bristle stiffness σ0", gt=0.0)
    sigma1_n_s_m: float = param(unit="N·s/m", desc="bristle damping σ1", ge=0.0)
    fc_n: float = param(unit="N", desc="Coulomb (kinetic) friction level Fc", gt=0.0)
    fs_n: float = param(unit="N", desc="static (break-away) level Fs, >= fc_n", gt=0.0)
    vs_m_s: float = param(1e-3, unit="m/s", desc="Stribeck velocity Vs", gt=0.0)
    delta: float = param(2.0, unit="", desc="Stribeck shape exponent δ", gt=0.0, le=10.0)
    viscous_n_s_m: float = param(0.0, unit="N·s/m", desc="viscous coefficient σ2", ge=0.0)
    sigma1_decay_m_s: float = param(math.inf, unit="m/s", allow_inf=True, gt=0.0,
                                    desc="velocity Vd of σ1(v) = σ1·exp(-(v/Vd)^2) (.inf = constant σ1)")

    def __post_init__(self) -> None:
        if self.fs_n < self.fc_n:
            raise ValueError(f"fs_n: must be >= fc_n ({self.fc_n:g} N) (got {self.fs_n:g} N)")


@register
class LuGreFriction(KernelModel):
    """LuGre single-state bristle model; tag ``lugre``. One state ``[z]`` (bristle deflection, m)."""

    tag = "lugre"
    Params = LuGreParams
    params: LuGreParams
    _kstep = staticmethod(_kstep)
    _kforce = staticmethod(_kforce)

    @staticmethod
    def _pack(params: LuGreParams) -> FloatArray:
        q = params
        return np.array([q.sigma0_n_m, q.sigma1_n_s_m, q.viscous_n_s_m, q.fc_n, q.fs_n, q.vs_m_s, q.delta,
                         q.sigma1_decay_m_s], dtype=np.float64)

    @staticmethod
    def _relaxed(params: LuGreParams) -> FloatArray:
        return np.zeros(1)

    @property
    def stiffness_n_m(self) -> float:
        """Bristle (pre-sliding) stiffness σ0 [N/m] (for integrator step limits)."""
        return float(self.params.sigma0_n_m)

    @property
    def damping_n_s_m(self) -> float:
        """Largest linear damping σ1 + σ2 [N·s/m] (for integrator step limits)."""
        return float(self.params.sigma1_n_s_m + self.params.viscous_n_s_m)

    def g(self, v: float) -> float:
        """Unsigned Stribeck magnitude g(v) [N]."""
        q = self.params
        return q.fc_n + (q.fs_n - q.fc_n) * math.exp(-(abs(v / q.vs_m_s) ** q.delta))

    def steady_state(self, v: float) -> tuple[float, float]:
        """Steady sliding at constant ``v`` [m/s]: ``(z_ss [m], F_ss [N])``."""
        g = self.g(v)
        s = math.copysign(1.0, v) if v != 0.0 else 0.0
        return s * g / self.params.sigma0_n_m, s * g + self.params.viscous_n_s_m * v

    def derivative(self, state: FloatArray, v: float) -> FloatArray:
        """``[dz/dt]`` = v − σ0|v|z/g(v) [m/s]."""
        return np.array([v - self.params.sigma0_n_m * abs(v) * state[0] / self.g(v)])
