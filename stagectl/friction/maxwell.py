"""Maxwell-slip model: N rate-independent elasto-slip (Jenkins) elements in parallel.

Equations (docs/friction-models.md §2)::

    element i: spring k_i in series with a block that slips at |F_i| = W_i
    exact discrete update (any step size):  F_i ← clip(F_i + k_i·Δx, −W_i, +W_i)
    F = Σ_i F_i + σ2·v

Virgin curve ``F_v(x) = Σ min(k_i|x|, W_i)·sgn(x)``, Masing branches ``F = F_r − 2·F_v((x_r − x)/2)``,
energy per symmetric cycle ``E(A) = Σ 4·W_i·max(A − W_i/k_i, 0)``; non-local memory and wipe-out follow
from the clipping update (no reversal stack).

Symbols → parameters: k_i = ``k_n_m[i]`` [N/m]; W_i = ``w_n[i]`` [N], or ``alpha[i]·fs_n`` when given as
fractions α_i [–] of a total slip force Fs = ``fs_n`` [N]; σ2 = ``viscous_n_s_m`` [N·s/m].
State: ``[F_1 … F_N]`` [N], relaxed = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stagectl.friction._numba import FloatArray, KernelModel
from stagectl.friction.base import register
from stagectl.jit import kernel
from stagectl.schema import param

# packed layout: [N, viscous, k_1..k_N, W_1..W_N]


@kernel
def _kstep(p: FloatArray, state: FloatArray, dx: float, v: float, dt: float) -> float:  # pragma: no cover
    n = np.int64(p[0])  # a cast; int() would compile numba's int overload (~0.03 s of a cold start)
    tot = 0.0
    for i in range(n):
        w = p[2 + n + i]
        f = state[i] + p[2 + i] * dx
        if f > w:
            f = w
        elif f < -w:
            f = -w
        state[i] = f
        tot += f
    total: float = tot + p[1] * v
    return total


@kernel
def _kforce(p: FloatArray, state: FloatArray, v: float) -> float:  # pragma: no cover
    n = np.int64(p[0])  # a cast, not int() (see _kstep)
    tot = 0.0
    for i in range(n):
        tot += state[i]
    total: float = tot + p[1] * v
    return total


@dataclass(frozen=True)
class MaxwellSlipParams:
    """Parameters of the Maxwell-slip model (SI units). Give ``w_n``, or ``alpha`` with ``fs_n``."""

    k_n_m: tuple[float, ...] = param(unit="N/m", desc="element stiffnesses k_i", gt=0.0)
    w_n: tuple[float, ...] | None = param(None, unit="N", desc="element slip forces W_i", gt=0.0)
    alpha: tuple[float, ...] | None = param(None, unit="", desc="element fractions α_i of fs_n (W_i = α_i·Fs)",
                                            gt=0.0, le=1.0)
    fs_n: float | None = param(None, unit="N", desc="total slip force Fs used with alpha", gt=0.0)
    viscous_n_s_m: float = param(0.0, unit="N·s/m", desc="viscous coefficient σ2", ge=0.0)

    def __post_init__(self) -> None:
        n = len(self.k_n_m)
        if n == 0:
            raise ValueError("k_n_m: needs at least one element")
        if self.w_n is not None:
            if self.alpha is not None or self.fs_n is not None:
                raise ValueError("w_n: give either w_n or alpha + fs_n, not both")
            if len(self.w_n) != n:
                raise ValueError(f"w_n: needs {n} entries like k_n_m (got {len(self.w_n)})")
        else:
            if self.alpha is None or self.fs_n is None:
                raise ValueError("w_n: required (or give alpha and fs_n)")
            if len(self.alpha) != n:
                raise ValueError(f"alpha: needs {n} entries like k_n_m (got {len(self.alpha)})")

    @property
    def slip_forces_n(self) -> tuple[float, ...]:
        """W_i [N]."""
        if self.w_n is not None:
            return self.w_n
        fs = self.fs_n if self.fs_n is not None else 0.0  # both set: checked in __post_init__
        return tuple(a * fs for a in (self.alpha or ()))


@register
class MaxwellSlipFriction(KernelModel):
    """Maxwell-slip (Iwan) model; tag ``maxwell_slip``."""

    tag = "maxwell_slip"
    Params = MaxwellSlipParams
    params: MaxwellSlipParams
    _kstep = staticmethod(_kstep)
    _kforce = staticmethod(_kforce)

    @staticmethod
    def _pack(params: MaxwellSlipParams) -> FloatArray:
        k = params.k_n_m
        return np.array([len(k), params.viscous_n_s_m, *k, *params.slip_forces_n], dtype=np.float64)

    @staticmethod
    def _relaxed(params: MaxwellSlipParams) -> FloatArray:
        return np.zeros(len(params.k_n_m))

    @property
    def stiffness_n_m(self) -> float:
        """Initial (pre-sliding) stiffness Σk_i [N/m]."""
        return float(sum(self.params.k_n_m))

    def virgin(self, x: np.ndarray) -> np.ndarray:
        """Closed-form virgin curve F_v(x) = Σ min(k_i|x|, W_i)·sgn(x) [N] (quasi-static, no viscous)."""
        xa = np.asarray(x, dtype=np.float64)
        k = np.asarray(self.params.k_n_m)[:, None]
        w = np.asarray(self.params.slip_forces_n)[:, None]
        return np.asarray(np.sign(xa) * np.minimum(k * np.abs(xa)[None, :], w).sum(axis=0), dtype=np.float64)

    def cycle_energy(self, amplitude_m: float) -> float:
        """Energy dissipated per symmetric cycle of amplitude A: Σ 4·W_i·max(A − W_i/k_i, 0) [J]."""
        k = np.asarray(self.params.k_n_m)
        w = np.asarray(self.params.slip_forces_n)
        return float(np.sum(4.0 * w * np.maximum(amplitude_m - w / k, 0.0)))

    @property
    def damping_n_s_m(self) -> float:
        """Viscous coefficient σ2 [N·s/m] (for integrator step limits)."""
        return float(self.params.viscous_n_s_m)

    def derivative(self, state: FloatArray, v: float) -> FloatArray:
        k = np.asarray(self.params.k_n_m)
        w = np.asarray(self.params.slip_forces_n)
        d = k * v
        slipping = (np.abs(state) >= w) & (np.sign(state) == np.sign(v))
        d[slipping] = 0.0
        return d
