"""Dahl friction model (Dahl 1968/1976), rate-independent, plus an optional viscous term.

Equations (docs/friction-models.md §5.2)::

    u      = 1 − (F_d/Fc)·sgn(v)                          normalised distance to saturation [–]
    dF_d/dx = σ0·|u|^i·sgn(u)                              (i = 1:  dF_d/dt = σ0·(v − |v|·F_d/Fc))
    F      = F_d + σ2·v                                    friction force [N], opposes motion
    virgin curve (i = 1): F_d(x) = Fc·(1 − exp(−σ0·x/Fc)),  saturation F_d → ±Fc

Discrete update over a displacement Δx (exact for any |Δx|, so unconditionally stable; the model is
rate-independent, so only Δx matters, not dt), with d = sgn(Δx), s = |Δx|, k = σ0/Fc::

    i = 1:   u ← u·exp(−k·s)
    i > 1:   |u| ← (|u|^(1−i) + (i − 1)·k·s)^(−1/(i−1))
    i < 1:   |u| ← max(0, |u|^(1−i) − (1 − i)·k·s)^(1/(1−i))        (sgn(u) kept)
    F_d ← d·Fc·(1 − u)

Symbols → parameters: σ0 = ``sigma0_n_m`` [N/m] (rest stiffness), Fc = ``fc_n`` [N] (Coulomb level),
i = ``exponent`` [–] (shape, 1 = classic Dahl), σ2 = ``viscous_n_s_m`` [N·s/m].
State: ``[F_d]`` [N], relaxed F_d = 0. No Stribeck effect, no stiction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stagectl.friction._numba import FloatArray, KernelModel, sgn
from stagectl.friction.base import register
from stagectl.jit import kernel
from stagectl.schema import param

# packed layout: [sigma0, fc, exponent, sigma2]


@kernel
def _kstep(p: FloatArray, state: FloatArray, dx: float, v: float, dt: float) -> float:  # pragma: no cover
    fc = p[1]
    if dx != 0.0:
        d = sgn(dx)
        k = p[0] / fc
        s = abs(dx)
        i = p[2]
        u = 1.0 - state[0] * d / fc
        if u != 0.0:
            au = abs(u)
            if i == 1.0:
                au = au * math.exp(-k * s)
            elif i > 1.0:
                au = (au ** (1.0 - i) + (i - 1.0) * k * s) ** (-1.0 / (i - 1.0))
            else:
                w = au ** (1.0 - i) - (1.0 - i) * k * s
                au = w ** (1.0 / (1.0 - i)) if w > 0.0 else 0.0
            u = au if u > 0.0 else -au
        state[0] = d * fc * (1.0 - u)
    f: float = state[0] + p[3] * v
    return f


@kernel
def _kforce(p: FloatArray, state: FloatArray, v: float) -> float:  # pragma: no cover
    f: float = state[0] + p[3] * v
    return f


@dataclass(frozen=True)
class DahlParams:
    """Parameters of the Dahl model (SI units)."""

    sigma0_n_m: float = param(unit="N/m", desc="rest stiffness σ0 (slope of the virgin curve at 0)", gt=0.0)
    fc_n: float = param(unit="N", desc="Coulomb level Fc (saturation force)", gt=0.0)
    exponent: float = param(1.0, unit="", desc="shape exponent i of the Dahl law (1 = classic)",
                            ge=0.0, le=10.0)
    viscous_n_s_m: float = param(0.0, unit="N·s/m", desc="viscous coefficient σ2", ge=0.0)


@register
class DahlFriction(KernelModel):
    """Dahl model; tag ``dahl``. One state ``[F_d]`` (N)."""

    tag = "dahl"
    Params = DahlParams
    params: DahlParams
    _kstep = staticmethod(_kstep)
    _kforce = staticmethod(_kforce)

    @staticmethod
    def _pack(params: DahlParams) -> FloatArray:
        q = params
        return np.array([q.sigma0_n_m, q.fc_n, q.exponent, q.viscous_n_s_m], dtype=np.float64)

    @staticmethod
    def _relaxed(params: DahlParams) -> FloatArray:
        return np.zeros(1)

    @property
    def stiffness_n_m(self) -> float:
        """Rest stiffness σ0 [N/m] (for integrator step limits)."""
        return float(self.params.sigma0_n_m)

    @property
    def damping_n_s_m(self) -> float:
        """Viscous coefficient σ2 [N·s/m] (for integrator step limits)."""
        return float(self.params.viscous_n_s_m)

    def virgin(self, x: np.ndarray) -> np.ndarray:
        """Virgin curve F_d(x) [N] from the relaxed state (exponent i = 1): Fc·(1 − exp(−σ0|x|/Fc))·sgn(x)."""
        if self.params.exponent != 1.0:
            raise ValueError("exponent: the closed-form virgin curve is for exponent = 1")
        q = self.params
        xa = np.asarray(x, dtype=np.float64)
        return np.sign(xa) * q.fc_n * (1.0 - np.exp(-q.sigma0_n_m * np.abs(xa) / q.fc_n))

    def derivative(self, state: FloatArray, v: float) -> FloatArray:
        """``[dF_d/dt]`` = v·σ0·|u|^i·sgn(u), u = 1 − (F_d/Fc)·sgn(v) [N/s]."""
        q = self.params
        s = math.copysign(1.0, v) if v != 0.0 else 0.0
        u = 1.0 - state[0] * s / q.fc_n
        su = 1.0 if u > 0 else -1.0 if u < 0 else 0.0
        return np.array([v * q.sigma0_n_m * abs(u) ** q.exponent * su])
