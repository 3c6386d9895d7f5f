"""Generalized Maxwell-slip (GMS) model, Al-Bender, Lampaert & Swevers, IEEE TAC 50(11), 2005.

Force formulation with a single attraction parameter C (docs/friction-models.md §3.1, §3.3, §3.5)::

    s(v) = sgn(v)·g(v),  g(v) = Fc + (Fs − Fc)·exp(−|v/Vs|^δ)        signed Stribeck curve [N]
    STICK (element i):  dF_i/dt = k_i·v
    SLIP  (element i):  dF_i/dt = sgn(v)·C·(α_i − F_i/s(v)) = C·(sgn(v)·α_i − F_i/g(v))
    F = Σ_i (F_i + σ1_i·dz_i/dt) + σ2·v,      dz_i/dt = (dF_i/dt)/k_i

Transition rules (implemented exactly, per element, with a mode flag in the state):

1. stick → slip only while loading in the direction of motion: ``sgn(v)·F_i >= α_i·g(v)``; on the
   step where the elastic update crosses the threshold, F_i is clamped to ``sgn(v)·α_i·g(v)``
   (no overshoot). An element being unloaded keeps sticking.
2. slip → stick when the velocity changes sign (the mode flag stores the slip direction).
3. ``v == 0`` exactly: every element holds (the slip law is singular at s(0) = 0).

The slip law is linear in F_i for v frozen over a step and is integrated exactly,
``F_i ← α_i·s(v) + (F_i − α_i·s(v))·exp(−C·dt/g(v))`` -- unconditionally stable for any C and dt.
Steady sliding gives ``F = Σα_i·s(v) + σ2·v`` (the Stribeck curve, with the sign of v); at v → 0 the
model is a Maxwell-slip model with ``W_i = α_i·Fs``.

The micro-damping term uses the instantaneous rate at the end of the step: ``dz_i/dt = v`` in stick,
``C·(sgn(v)·α_i − F_i/g)/k_i`` in slip (0 at v = 0), so :meth:`step` and :meth:`force` agree.

Symbols → parameters: k_i = ``k_n_m[i]`` [N/m], α_i = ``alpha[i]`` [–] (Σα ≈ 1), Fc = ``fc_n`` [N],
Fs = ``fs_n`` [N], Vs = ``vs_m_s`` [m/s], δ = ``delta`` [–], C = ``c_n_s`` [N/s],
σ1_i = ``sigma1_n_s_m`` [N·s/m] (scalar = same for every element), σ2 = ``viscous_n_s_m`` [N·s/m].
State: ``[F_1 … F_N, mode_1 … mode_N]`` with F_i [N] and mode ∈ {0 stick, +1 slip forward, −1 slip
backward}; relaxed = all zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from stagectl.errors import ConfigError, short
from stagectl.friction._numba import FloatArray, KernelModel, stribeck_excess
from stagectl.friction.base import register
from stagectl.jit import kernel
from stagectl.schema import param

# packed layout: [N, fc, fs, vs, delta, C, viscous, k_1..k_N, alpha_1..alpha_N, sigma1_1..sigma1_N,
#                 C/k_1..C/k_N]
_HDR = 7


@kernel(inline="always")
def _g(p: FloatArray, v: float) -> float:  # pragma: no cover - compiled
    g: float = p[1] + (p[2] - p[1]) * stribeck_excess(v, p[3], p[4])
    return g


@kernel
def _kstep(p: FloatArray, state: FloatArray, dx: float, v: float, dt: float) -> float:  # pragma: no cover
    n = np.int64(p[0])  # a cast; int() would compile numba's int overload (~0.03 s of a cold start)
    if v == 0.0:  # rule 3: hold
        tot = 0.0
        for i in range(n):
            tot += state[i]
        return tot
    # the scalar parameters read once, up front (read where used, the plant's GMS step was ~5 % slower)
    fc = p[1]
    fs = p[2]
    c = p[5]
    viscous = p[6]
    s = 1.0 if v > 0.0 else -1.0
    g = fc + (fs - fc) * stribeck_excess(v, p[3], p[4])
    inv_g = 1.0 / g
    # exp(−C·dt/g) once per step, before the element loop: computing it lazily on the first slipping element
    # put a hard-to-predict branch in the loop and cost ~12 % of a plant step
    decay = math.exp(-c * dt * inv_g)
    tot = 0.0
    for i in range(n):
        f = state[i]
        m = state[n + i]
        a = p[_HDR + n + i]
        lim = a * g
        if m != 0.0 and m != s:  # rule 2: velocity reversal -> stick
            m = 0.0
        if m == 0.0:
            if s * f >= lim:  # already at/over the (lowered) threshold while loading: slip from here
                m = s
                f = s * lim + (f - s * lim) * decay
            else:
                f = f + p[_HDR + i] * dx
                if s * f >= lim:  # rule 1 + clamp at break-away
                    f = s * lim
                    m = s
        else:
            f = s * lim + (f - s * lim) * decay  # exact exponential slip update
        state[i] = f
        state[n + i] = m
        sig1 = p[_HDR + 2 * n + i]
        if sig1 != 0.0:
            rate = v if m == 0.0 else p[_HDR + 3 * n + i] * (s * a - f * inv_g)  # C/k_i·(sgn(v)α_i − F_i/g)
            tot += f + sig1 * rate
        else:
            tot += f
    total: float = tot + viscous * v
    return total


@kernel
def _kforce(p: FloatArray, state: FloatArray, v: float) -> float:  # pragma: no cover
    n = np.int64(p[0])  # a cast, not int() (see _kstep)
    tot = 0.0
    if v == 0.0:
        for i in range(n):
            tot += state[i]
        return tot
    s = 1.0 if v > 0.0 else -1.0
    g = _g(p, v)
    c = p[5]
    for i in range(n):
        f = state[i]
        m = state[n + i]
        sig1 = p[_HDR + 2 * n + i]
        if sig1 != 0.0:
            if m == s:
                rate = c * (s * p[_HDR + n + i] - f / g) / p[_HDR + i]
            else:
                rate = v
            tot += f + sig1 * rate
        else:
            tot += f
    total: float = tot + p[6] * v
    return total


@kernel
def _ksets(PT: FloatArray, ST: FloatArray, dx: FloatArray, v: FloatArray, dt: float,
           out: FloatArray) -> None:  # pragma: no cover - compiled
    """:func:`_kstep` for many parameter sets at once, branch-free across sets (for batch runs).

    ``PT`` is the packed parameters transposed, one column per set (all with the same N); ``ST`` the states,
    one column per set; ``dx``, ``v``, ``out`` one entry per set. The same arithmetic as :func:`_kstep`, with
    the mode logic as selects, so the loop over the sets (innermost) has no data-dependent branches and the
    sets' dependency chains overlap. Results are bit-identical to :func:`_kstep` set by set.
    """
    n = np.int64(PT[0, 0])
    ns = PT.shape[1]
    for q in range(ns):
        out[q] = 0.0
    g = np.empty(ns)
    inv_g = np.empty(ns)
    sg = np.empty(ns)
    decay = np.empty(ns)
    for q in range(ns):
        vq = v[q]
        sg[q] = 1.0 if vq > 0.0 else (-1.0 if vq < 0.0 else 0.0)
        gq = PT[1, q] + (PT[2, q] - PT[1, q]) * stribeck_excess(vq, PT[3, q], PT[4, q])
        g[q] = gq
        inv_g[q] = 1.0 / gq
        decay[q] = math.exp(-PT[5, q] * dt * inv_g[q])
    for i in range(n):
        rk = _HDR + i
        ra = _HDR + n + i
        r1 = _HDR + 2 * n + i
        rc = _HDR + 3 * n + i
        for q in range(ns):
            vq = v[q]
            s = sg[q]
            f = ST[i, q]
            m = ST[n + i, q]
            a = PT[ra, q]
            lim = a * g[q]
            m = 0.0 if (m != 0.0 and m != s) else m
            slip_f = s * lim + (f - s * lim) * decay[q]
            f2 = f + PT[rk, q] * dx[q]
            over = s * f >= lim
            brk = s * f2 >= lim
            stick = m == 0.0
            fn = slip_f if (not stick or over) else (s * lim if brk else f2)
            mn = s if (not stick or over or brk) else 0.0
            hold = vq == 0.0  # rule 3: every element holds
            fn = f if hold else fn
            mn = ST[n + i, q] if hold else mn
            ST[i, q] = fn
            ST[n + i, q] = mn
            rate = vq if mn == 0.0 else PT[rc, q] * (s * a - fn * inv_g[q])
            sig1 = PT[r1, q]
            out[q] += fn if (hold or sig1 == 0.0) else fn + sig1 * rate
    for q in range(ns):
        out[q] += PT[6, q] * v[q]  # the viscous term last, as in _kstep (same rounding)


def _parse_float_or_tuple(value: Any, path: str, problems: list[str]) -> tuple[float, ...] | None:
    """Accept a number (same for every element) or a list of numbers [N·s/m], each >= 0 and finite."""
    items = list(value) if isinstance(value, (list, tuple)) else [value]
    out: list[float] = []
    for i, item in enumerate(items):
        where = f"{path}[{i}]" if isinstance(value, (list, tuple)) else path
        if isinstance(item, bool) or not isinstance(item, (int, float)):
            problems.append(f"{where}: expected a number N·s/m, got {short(item)}")
            return None
        f = float(item)
        if not math.isfinite(f) or f < 0.0:
            problems.append(f"{where}: must be >= 0 and finite N·s/m (got {short(item)})")
            return None
        out.append(f)
    return tuple(out)


@dataclass(frozen=True)
class GmsParams:
    """Parameters of the GMS model (SI units)."""

    k_n_m: tuple[float, ...] = param(unit="N/m", desc="element stiffnesses k_i", gt=0.0)
    alpha: tuple[float, ...] = param(unit="", desc="element fractions α_i of the Stribeck force (sum ≈ 1)",
                                     gt=0.0, le=1.0)
    fc_n: float = param(unit="N", desc="Coulomb level Fc", gt=0.0)
    fs_n: float = param(unit="N", desc="static (break-away) level Fs (below fc_n: friction rising with speed)",
                        gt=0.0)
    vs_m_s: float = param(1e-3, unit="m/s", desc="Stribeck velocity Vs", gt=0.0)
    delta: float = param(2.0, unit="", desc="Stribeck shape exponent δ", gt=0.0, le=10.0)
    c_n_s: float = param(1e4, unit="N/s", desc="attraction parameter C (slip relaxation rate)", gt=0.0)
    sigma1_n_s_m: tuple[float, ...] = param((0.0,), unit="N·s/m",
                                            desc="element micro-damping σ1_i (number = same for every element)",
                                            parse=_parse_float_or_tuple)
    viscous_n_s_m: float = param(0.0, unit="N·s/m", desc="viscous coefficient σ2", ge=0.0)

    def __post_init__(self) -> None:
        n = len(self.k_n_m)
        problems: list[str] = []
        if n == 0:
            problems.append("k_n_m: needs at least one element")
        if len(self.alpha) != n:
            problems.append(f"alpha: needs {n} entries like k_n_m (got {len(self.alpha)})")
        elif n and abs(sum(self.alpha) - 1.0) > 0.05:
            problems.append(f"alpha: must sum to 1 within 0.05 (got {sum(self.alpha):.6g})")
        if len(self.sigma1_n_s_m) == 1 and n > 1:
            object.__setattr__(self, "sigma1_n_s_m", tuple(self.sigma1_n_s_m) * n)
        elif len(self.sigma1_n_s_m) != n:
            problems.append(f"sigma1_n_s_m: needs 1 or {n} entries (got {len(self.sigma1_n_s_m)})")
        if problems:
            raise ConfigError(problems)


@register
class GmsFriction(KernelModel):
    """Generalized Maxwell-slip model (TAC 2005 form, single C); tag ``gms``."""

    tag = "gms"
    Params = GmsParams
    params: GmsParams
    _kstep = staticmethod(_kstep)
    _kforce = staticmethod(_kforce)
    #: many parameter sets per call, branch-free (the plant's batch runs use it)
    _ksets = staticmethod(_ksets)

    @staticmethod
    def _pack(params: GmsParams) -> FloatArray:
        q = params
        return np.array(
            [len(q.k_n_m), q.fc_n, q.fs_n, q.vs_m_s, q.delta, q.c_n_s, q.viscous_n_s_m,
             *q.k_n_m, *q.alpha, *q.sigma1_n_s_m, *(q.c_n_s / k for k in q.k_n_m)],
            dtype=np.float64,
        )

    @staticmethod
    def _relaxed(params: GmsParams) -> FloatArray:
        return np.zeros(2 * len(params.k_n_m))

    @property
    def stiffness_n_m(self) -> float:
        """Initial (pre-sliding) stiffness Σk_i [N/m]."""
        return float(sum(self.params.k_n_m))

    def stribeck(self, v: npt.ArrayLike) -> FloatArray:
        """Steady sliding force Σα_i·s(v) + σ2·v [N] for velocities ``v`` [m/s] (array)."""
        q = self.params
        va = np.asarray(v, dtype=np.float64)
        g = q.fc_n + (q.fs_n - q.fc_n) * np.exp(-(np.abs(va / q.vs_m_s) ** q.delta))
        return np.sign(va) * g * sum(q.alpha) + q.viscous_n_s_m * va

    def virgin(self, x: npt.ArrayLike) -> FloatArray:
        """Quasi-static virgin curve Σ min(k_i|x|, α_i·Fs)·sgn(x) [N] (v → 0, no viscous)."""
        xa = np.asarray(x, dtype=np.float64)
        k = np.asarray(self.params.k_n_m)[:, None]
        w = (np.asarray(self.params.alpha) * self.params.fs_n)[:, None]
        return np.asarray(np.sign(xa) * np.minimum(k * np.abs(xa)[None, :], w).sum(axis=0), dtype=np.float64)

    @property
    def damping_n_s_m(self) -> float:
        """Total linear damping σ2 + Σσ1_i [N·s/m] (for integrator step limits)."""
        return float(self.params.viscous_n_s_m + sum(self.params.sigma1_n_s_m))

    def derivative(self, state: FloatArray, v: float) -> FloatArray:
        """dF_i/dt for the current modes (mode flags have derivative 0)."""
        q = self.params
        n = len(q.k_n_m)
        out = np.zeros(2 * n)
        if v == 0.0:
            return out
        s = 1.0 if v > 0 else -1.0
        g = q.fc_n + (q.fs_n - q.fc_n) * math.exp(-(abs(v / q.vs_m_s) ** q.delta))
        for i in range(n):
            if state[n + i] == s:
                out[i] = q.c_n_s * (s * q.alpha[i] - state[i] / g)
            else:
                out[i] = q.k_n_m[i] * v
        return out

