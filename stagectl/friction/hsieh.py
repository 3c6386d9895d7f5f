"""Hsieh & Pan (2000) pre-sliding model (HM) with a sliding model and a force-continuous switch.

Pre-sliding (docs/friction-models.md §4.1, the equations as Kamenar & Zelenika give them)
----------------------------------------------------------------------------------
The displacement splits into an elastic part x_s (spring module) and a plastic part x_p (plastic module)
in series, ``x = x_s + x_p``. With (x_r, σ_r) the start of the current branch (last reversal point)::

    F_el(x_s) = σ_r + k1s·(x_s − x_r) + sgn(x_s − x_r)·(k2s/β)·(1 − exp(−β·|x_s − x_r|))   [N]
    F        = F_el + Cv·dx_s/dt                                                           [N]
    dx_h/dt  = ρ·(|F_el|^a/ψ − x_h)   if |F_el|^a/ψ > x_h,  else 0        (work hardening, ratchet)
    dx_p/dt  = sgn(F_el)·dx_h/dt                                          (creep / plastic flow)

Both branch formulas of §4.1 (x_s ≥ x_r and x_s < x_r) are the one odd function written above.

Symbols → parameters: k1s = ``k1s_n_m`` [N/m] (linear spring), k2s = ``k2s_n_m`` [N/m] (initial stiffness
of the saturating spring, which saturates at k2s/β), β = ``beta_1_m`` [1/m], Cv = ``cv_n_s_m`` [N·s/m]
(damper on dx_s/dt), ρ = ``rho_1_s`` [1/s] (plastic rate constant), ψ = ``psi`` [N^a/m] (plastic
compliance scale: equilibrium x_h = |F|^a/ψ), a = ``a`` [–] (plastic exponent), x_h [m] hardening
variable (largest equilibrium plastic displacement reached so far).

**Algebraic loop.** Cv·dx_s/dt depends on dx_p/dt, which depends on the force. As docs/friction-models.md §4.3
suggests, the plastic law is driven by the *elastic* force F_el (not by F including the damper), which
breaks the loop. Per step, with the total displacement prescribed (``x_s + x_p`` advances by Δx), the
plastic increment is solved *implicitly* with the exact exponential factor c = 1 − exp(−ρ·dt)::

    y = x_p' :   y − x_p = sgn(F_el(x_s'))·c·max(0, |F_el(x_s')|^a/ψ − x_h),   x_s' = x_s + x_p + Δx − y

The right-hand side is non-increasing in y, so the root is unique and bracketed by
[x_p, x_p + φ(F_el(x_s + Δx))]; it is found by safeguarded Newton (bisection fallback). The update is
unconditionally stable for any dt (ρ·dt → ∞ gives the quasi-static equilibrium x_h = |F_el|^a/ψ), and
x_h' = x_h + |y − x_p| keeps the ratchet exact. The damper uses the step's elastic rate,
``dx_s/dt = v − (x_p' − x_p)/dt`` (= Δx_s/dt when v = Δx/dt, as in ``force_along``).
Note: docs/friction-models.md §4.4 quotes F = 0.9025 N at the end of a 0.5 µm/s ramp to 28.07 µm; that is
0.9 N + Cv·dx/dt, a damper on the *total* rate. Following the seed's Cv·dx_s/dt this module gives
0.9004 N there (most of the motion is plastic); the unloading zero crossing at 22.88 µm agrees.

**Reversal memory with wipe-out.** A stack of branch starts P_0 … P_{n−1} (P_0 = the virgin origin or the
point where pre-sliding was re-entered). When x_s reverses, (x_s, F_el) is pushed and a new branch of the
virgin shape starts there. When the current branch (started at P_{n−1}) reaches the reversal point
P_{n−2} where the previous motion in the same direction stopped (requires n − 1 ≥ 2), the inner loop is
closed: P_{n−1}, P_{n−2} are popped and the older branch from P_{n−3} continues (it passes exactly through
P_{n−2}, because the branch shape is odd: loops close exactly and F stays continuous). The stack lives
inside the state vector with a fixed capacity of 64 points; when it is full the two *oldest* reversal
points above P_0 are discarded (the current branch, hence the force, is unchanged; only the memory of
the outermost loop is lost).

Sliding model and switching (docs/friction-models.md §4.5)
-----------------------------------------------------
::

    g(v)   = Fc + (Fs − Fc)·exp(−|v/Vs|^δ),    F_sl(v) = sgn(v)·g(v) + σ2·v                   [N]

* **pre-sliding → sliding** when, moving in direction d = sgn(Δx), the elastic force reaches the
  break-away level, ``d·F_el ≥ F_ba``, or the displacement since the last reversal (or since re-entering
  pre-sliding) reaches the pre-sliding distance, ``d·Δx_ps ≥ x_ps``. At the switch the force offset
  ``ΔF = F_pre − F_sl(v)`` is recorded; while sliding ``F = F_sl(v) + ΔF·exp(−s/ℓ)`` with s the
  distance slid since the switch. The force is therefore continuous at the switch, and the offset
  (e.g. the large Cv·v term of the HM) fades over the transition length ℓ.
* **sliding → pre-sliding** at a velocity reversal or a stop (Δx·d ≤ 0): the stack is reset to one
  point (x_r, σ_r) = (current x_s, last force F) (gross sliding erases the pre-sliding memory), so the
  new branch starts at the force the sliding model had: continuous up to the step's own increment
  (≤ (k1s + k2s)·|Δx| + Cv·|v|). x_h is raised to at least |σ_r|^a/ψ (the contact is hardened to the
  sliding level, so no spurious creep starts at rest).

Symbols → parameters: Fc = ``fc_n`` [N], Fs = ``fs_n`` [N], Vs = ``vs_m_s`` [m/s], δ = ``delta`` [–],
σ2 = ``viscous_n_s_m`` [N·s/m], F_ba = ``breakaway_n`` [N] (default Fs), x_ps = ``presliding_distance_m``
[m] (default ``.inf`` = off), ℓ = ``transition_m`` [m].

State vector (float64, length 140; see the ``S_*`` index constants): mode (0 pre-sliding, 1 sliding),
x_s, x_p, x_h, branch direction, stack depth, last force, sliding direction, switch offset ΔF, distance
slid s, displacement since the last reversal, F_el, then 64 × (x_r, σ_r).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from stagectl.friction._numba import FloatArray, KernelModel, sgn, stribeck_g
from stagectl.friction.base import register
from stagectl.jit import kernel
from stagectl.schema import param

# packed layout
P_K1S, P_K2S, P_BETA, P_CV, P_RHO, P_PSI, P_A = 0, 1, 2, 3, 4, 5, 6
P_FC, P_FS, P_VS, P_DELTA, P_SIGMA2, P_FBA, P_DPS, P_LTR = 7, 8, 9, 10, 11, 12, 13, 14
N_PACKED = 15

# state layout
S_MODE = 0  # 0 = pre-sliding, 1 = sliding
S_XS = 1  # elastic displacement x_s [m]
S_XP = 2  # plastic displacement x_p [m]
S_XH = 3  # hardening variable x_h [m]
S_DIR = 4  # direction of the current branch (−1, 0 = not yet moved, +1)
S_DEPTH = 5  # number of points on the reversal stack (>= 1)
S_FPREV = 6  # last returned force [N]
S_SLDIR = 7  # sliding direction (±1)
S_OFFSET = 8  # force offset ΔF recorded at the switch to sliding [N]
S_SLID = 9  # distance slid since the switch [m]
S_TRAVEL = 10  # displacement since the last reversal / re-entry [m]
S_FEL = 11  # elastic force F_el [N]
S_STACK = 12  # stack: x_r at S_STACK + 2j, σ_r at S_STACK + 2j + 1
STACK_CAP = 64
N_STATE = S_STACK + 2 * STACK_CAP

_NEWTON_MAXIT = 60


@kernel(inline="always")
def _branch(p: FloatArray, xr: float, sr: float, xs: float) -> tuple[float, float]:  # pragma: no cover
    """Branch force and slope dF_el/dx_s from start (xr, sr)."""
    d = xs - xr
    ad = abs(d)
    e = math.exp(-p[P_BETA] * ad)
    f = sr + p[P_K1S] * d + sgn(d) * (p[P_K2S] / p[P_BETA]) * (1.0 - e)
    return f, p[P_K1S] + p[P_K2S] * e


@kernel
def _el_eval(p: FloatArray, state: FloatArray, n: int, dirn: float, xs0: float, f0: float,
             xs: float) -> tuple[float, float, int]:  # pragma: no cover
    """Elastic force at ``xs`` reached monotonically from ``xs0`` within this step (lookahead).

    Returns (F_el, slope, k): k is the index of the active branch start on the (possibly virtual) stack;
    k == n means the virtual reversal point (xs0, f0) pushed at this step.
    """
    if dirn == 0.0 or (xs - xs0) * dirn >= 0.0:
        top = n - 1
        d = dirn
    else:
        top = n  # virtual reversal point at (xs0, f0)
        d = -dirn
    k = top
    while k >= 2:
        j = k - 1  # reversal point where the previous motion in direction d stopped
        xj = xs0 if j == n else state[S_STACK + 2 * j]
        if (xs - xj) * d >= 0.0:
            k -= 2
        else:
            break
    if k == n:
        xr, sr = xs0, f0
    else:
        xr = state[S_STACK + 2 * k]
        sr = state[S_STACK + 2 * k + 1]
    f, sl = _branch(p, xr, sr, xs)
    return f, sl, k


@kernel(inline="always")
def _phi(p: FloatArray, f: float, xh: float, c: float) -> tuple[float, float]:  # pragma: no cover
    """Plastic increment φ(F) = sgn(F)·c·max(0, |F|^a/ψ − x_h) and dφ/dF."""
    af = abs(f)
    h = af ** p[P_A] / p[P_PSI]
    if h <= xh or c == 0.0:
        return 0.0, 0.0
    dphi = c * p[P_A] * af ** (p[P_A] - 1.0) / p[P_PSI] if af > 0.0 else 0.0
    return sgn(f) * c * (h - xh), dphi


@kernel
def _sliding_force(p: FloatArray, v: float) -> float:  # pragma: no cover
    f: float = sgn(v) * stribeck_g(v, p[P_FC], p[P_FS], p[P_VS], p[P_DELTA]) + p[P_SIGMA2] * v
    return f


@kernel
def _top_force(p: FloatArray, state: FloatArray) -> float:  # pragma: no cover
    n = int(state[S_DEPTH])
    xr = state[S_STACK + 2 * (n - 1)]
    sr = state[S_STACK + 2 * (n - 1) + 1]
    return _branch(p, xr, sr, state[S_XS])[0]


@kernel
def _presliding_step(p: FloatArray, state: FloatArray, dx: float, v: float,
                     dt: float) -> float:  # pragma: no cover
    n = int(state[S_DEPTH])
    dirn = state[S_DIR]
    xs0 = state[S_XS]
    xp0 = state[S_XP]
    xh = state[S_XH]
    f0 = _top_force(p, state)
    xtot = xs0 + xp0 + dx
    c = 1.0 - math.exp(-p[P_RHO] * dt) if (p[P_RHO] > 0.0 and dt > 0.0) else 0.0

    # implicit plastic increment: r(y) = y − xp0 − φ(F_el(xtot − y)) = 0, r strictly increasing
    y = xp0
    fa, sla, ka = _el_eval(p, state, n, dirn, xs0, f0, xtot - xp0)
    phi0, dphi0 = _phi(p, fa, xh, c)
    if phi0 != 0.0:
        lo = min(xp0, xp0 + phi0)
        hi = max(xp0, xp0 + phi0)
        r = -phi0
        dr = 1.0 + dphi0 * sla
        for _ in range(_NEWTON_MAXIT):
            # keep the bracket: r(lo) <= 0 <= r(hi)
            if r < 0.0:
                lo = y
            else:
                hi = y
            yn = y - r / dr
            if not (lo < yn < hi):
                yn = 0.5 * (lo + hi)
            if abs(yn - y) <= 1e-17 + 1e-13 * abs(yn - xp0):
                y = yn
                break
            y = yn
            fy, sly, _k = _el_eval(p, state, n, dirn, xs0, f0, xtot - y)
            ph, dph = _phi(p, fy, xh, c)
            r = y - xp0 - ph
            dr = 1.0 + dph * sly
            if r == 0.0:
                break
    xs1 = xtot - y
    f1, _sl, k = _el_eval(p, state, n, dirn, xs0, f0, xs1)

    # commit plastic state (ratchet)
    state[S_XH] = xh + abs(y - xp0)
    state[S_XP] = y
    state[S_XS] = xs1

    # commit the reversal stack
    dxs = xs1 - xs0
    if dxs != 0.0:
        d = sgn(dxs)
        if dirn == 0.0:
            state[S_DIR] = d
        elif d != dirn:
            state[S_DIR] = d
            state[S_TRAVEL] = 0.0
            if k == n:  # the reversal point (xs0, f0) survives: push it
                if n == STACK_CAP:  # full: drop the two oldest reversal points above P_0
                    for j in range(1, n - 2):
                        state[S_STACK + 2 * j] = state[S_STACK + 2 * (j + 2)]
                        state[S_STACK + 2 * j + 1] = state[S_STACK + 2 * (j + 2) + 1]
                    n -= 2
                state[S_STACK + 2 * n] = xs0
                state[S_STACK + 2 * n + 1] = f0
                n += 1
            else:
                n = k + 1
        else:
            n = k + 1
        state[S_DEPTH] = n
    state[S_TRAVEL] += dx
    state[S_FEL] = f1

    vs_el = v - (y - xp0) / dt if dt > 0.0 else v
    f: float = f1 + p[P_CV] * vs_el
    return f


@kernel
def _kstep(p: FloatArray, state: FloatArray, dx: float, v: float, dt: float) -> float:  # pragma: no cover
    if state[S_MODE] == 1.0:
        sd = state[S_SLDIR]
        if dx * sd > 0.0:
            s = state[S_SLID] + abs(dx)
            state[S_SLID] = s
            f: float = _sliding_force(p, v) + state[S_OFFSET] * math.exp(-s / p[P_LTR])
            state[S_FPREV] = f
            return f
        # stop or velocity reversal: re-enter pre-sliding at the current force
        sr = state[S_FPREV]
        state[S_MODE] = 0.0
        state[S_DEPTH] = 1.0
        state[S_DIR] = 0.0
        state[S_TRAVEL] = 0.0
        state[S_STACK] = state[S_XS]
        state[S_STACK + 1] = sr
        state[S_FEL] = sr
        h = abs(sr) ** p[P_A] / p[P_PSI]
        if h > state[S_XH]:
            state[S_XH] = h
    f = _presliding_step(p, state, dx, v, dt)
    d = sgn(dx)
    if d != 0.0 and (state[S_FEL] * d >= p[P_FBA] or state[S_TRAVEL] * d >= p[P_DPS]):
        state[S_MODE] = 1.0
        state[S_SLDIR] = d
        state[S_OFFSET] = f - _sliding_force(p, v)
        state[S_SLID] = 0.0
    state[S_FPREV] = f
    return f


@kernel
def _kforce(p: FloatArray, state: FloatArray, v: float) -> float:  # pragma: no cover
    if state[S_MODE] == 1.0:
        if v * state[S_SLDIR] > 0.0:
            f: float = _sliding_force(p, v) + state[S_OFFSET] * math.exp(-state[S_SLID] / p[P_LTR])
            return f
        f_last: float = state[S_FPREV]
        return f_last
    fel = _top_force(p, state)
    h = abs(fel) ** p[P_A] / p[P_PSI]
    vp = sgn(fel) * p[P_RHO] * (h - state[S_XH]) if h > state[S_XH] else 0.0
    f_total: float = fel + p[P_CV] * (v - vp)
    return f_total


@dataclass(frozen=True)
class HsiehParams:
    """Parameters of the Hsieh & Pan model with its sliding model and switch (SI units)."""

    k1s_n_m: float = param(unit="N/m", desc="linear spring k1s of the spring module", gt=0.0)
    k2s_n_m: float = param(unit="N/m", ge=0.0,
                           desc="initial stiffness k2s of the saturating spring (saturates at k2s/beta)")
    beta_1_m: float = param(unit="1/m", desc="decay rate beta of the saturating spring", gt=0.0)
    cv_n_s_m: float = param(unit="N·s/m", desc="damping Cv on the elastic rate dx_s/dt", ge=0.0)
    rho_1_s: float = param(unit="1/s", desc="plastic rate constant rho (0 = no plastic flow)", ge=0.0)
    psi: float = param(unit="N^a/m", desc="plastic compliance scale psi: equilibrium x_h = |F|^a/psi", gt=0.0)
    a: float = param(unit="", desc="plastic exponent a", gt=0.0, le=20.0)
    fc_n: float = param(unit="N", desc="sliding model: Coulomb level Fc", gt=0.0)
    fs_n: float = param(unit="N", desc="sliding model: static level Fs, >= fc_n", gt=0.0)
    vs_m_s: float = param(1e-3, unit="m/s", desc="sliding model: Stribeck velocity Vs", gt=0.0)
    delta: float = param(2.0, unit="", desc="sliding model: Stribeck shape exponent delta", gt=0.0, le=10.0)
    viscous_n_s_m: float = param(0.0, unit="N·s/m", desc="sliding model: viscous coefficient sigma2", ge=0.0)
    breakaway_n: float | None = param(None, unit="N", gt=0.0, allow_inf=True,
                                      desc="switch to sliding when the elastic force reaches this level "
                                           "(default fs_n; .inf = never)")
    presliding_distance_m: float = param(math.inf, unit="m", gt=0.0, allow_inf=True,
                                         desc="switch to sliding after this displacement since the last "
                                              "reversal (.inf = off)")
    transition_m: float = param(1e-6, unit="m", gt=0.0,
                                desc="sliding distance over which the force offset at the switch fades")

    def __post_init__(self) -> None:
        if self.fs_n < self.fc_n:
            raise ValueError(f"fs_n: must be >= fc_n ({self.fc_n:g} N) (got {self.fs_n:g} N)")

    @property
    def breakaway_level_n(self) -> float:
        """The break-away level F_ba actually used [N]."""
        return float(self.fs_n if self.breakaway_n is None else self.breakaway_n)


@register
class HsiehFriction(KernelModel):
    """Hsieh & Pan pre-sliding model + sliding model with force-continuous switching; tag ``hsieh``."""

    tag = "hsieh"
    Params = HsiehParams
    params: HsiehParams
    _kstep = staticmethod(_kstep)
    _kforce = staticmethod(_kforce)

    @staticmethod
    def _pack(params: HsiehParams) -> FloatArray:
        q = params
        return np.array([q.k1s_n_m, q.k2s_n_m, q.beta_1_m, q.cv_n_s_m, q.rho_1_s, q.psi, q.a,
                         q.fc_n, q.fs_n, q.vs_m_s, q.delta, q.viscous_n_s_m, q.breakaway_level_n,
                         q.presliding_distance_m, q.transition_m], dtype=np.float64)

    @staticmethod
    def _relaxed(params: HsiehParams) -> FloatArray:
        s = np.zeros(N_STATE)
        s[S_DEPTH] = 1.0  # P_0 = virgin origin (0, 0)
        return s

    @property
    def stiffness_n_m(self) -> float:
        """Initial spring-module stiffness k1s + k2s [N/m] (for integrator step limits)."""
        return float(self.params.k1s_n_m + self.params.k2s_n_m)

    @property
    def damping_n_s_m(self) -> float:
        """Largest linear damping Cv + σ2 [N·s/m] (for integrator step limits)."""
        return float(self.params.cv_n_s_m + self.params.viscous_n_s_m)

    # ------------------------------------------------------------------ closed forms and inspection
    def virgin_force(self, xs: npt.ArrayLike) -> FloatArray:
        """Spring-module virgin curve F_el(x_s) [N] for elastic displacement ``xs`` [m]."""
        q = self.params
        x = np.asarray(xs, dtype=np.float64)
        sat = (q.k2s_n_m / q.beta_1_m) * (1.0 - np.exp(-q.beta_1_m * np.abs(x)))
        return np.asarray(q.k1s_n_m * x + np.sign(x) * sat, dtype=np.float64)

    def quasi_static_virgin(self, force_n: npt.ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Quasi-static, force-driven virgin curve (x_h at equilibrium), docs/friction-models.md §4.4.

        For each force F [N]: x_s solves F_el(x_s) = F on the virgin branch, x_p = sgn(F)·|F|^a/ψ.
        Returns ``(x_s, x_p, x = x_s + x_p)`` in metres.
        """
        q = self.params
        f = np.atleast_1d(np.asarray(force_n, dtype=np.float64))
        af = np.abs(f)
        # Newton on the monotone, concave virgin curve, started from the linear asymptote (converges
        # from above, since the curve is concave for x_s > 0)
        x = af / q.k1s_n_m
        for _ in range(100):
            e = np.exp(-q.beta_1_m * x)
            r = q.k1s_n_m * x + (q.k2s_n_m / q.beta_1_m) * (1.0 - e) - af
            x = x - r / (q.k1s_n_m + q.k2s_n_m * e)
        xs = np.sign(f) * x
        xp = np.sign(f) * af ** q.a / q.psi
        return xs, xp, xs + xp

    def loop_width(self, amplitude_n: float) -> float:
        """Spring-module width Δ [m] of a symmetric force loop ±F_a: k1s·Δ + (k2s/β)(1 − e^{−βΔ}) = 2F_a."""
        return float(self.quasi_static_virgin(2.0 * amplitude_n)[0][0])

    @staticmethod
    def stack_depth(state: FloatArray) -> int:
        """Number of points on the reversal stack (1 = only the branch origin)."""
        return int(state[S_DEPTH])

    @staticmethod
    def sliding(state: FloatArray) -> bool:
        """True while the sliding model is active."""
        return bool(state[S_MODE] == 1.0)

    @staticmethod
    def parts(state: FloatArray) -> dict[str, float]:
        """Named internal quantities: x_s, x_p, x_h [m], F_el [N], depth, sliding."""
        return {"x_s_m": float(state[S_XS]), "x_p_m": float(state[S_XP]), "x_h_m": float(state[S_XH]),
                "f_el_n": float(state[S_FEL]), "depth": int(state[S_DEPTH]),
                "sliding": bool(state[S_MODE] == 1.0)}

    def sliding_force(self, v: float) -> float:
        """Steady sliding-model force F_sl(v) = sgn(v)·g(v) + σ2·v [N]."""
        return float(_sliding_force(self._p, float(v)))
