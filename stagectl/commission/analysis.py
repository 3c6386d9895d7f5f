"""The analyses of the commissioning experiments (pure numpy/scipy; SI units).

**Sanity** (:func:`evaluate_probe`): per direction, quadratic fits ``x(τ) = x0 + v0·τ + a·τ²/2`` over the two
constant-force phases give ``a1, a2``; ``m = (F2 − F1)/(a2 − a1)`` (a force-independent friction cancels).
A viscous force ``c·v`` does not cancel: it grows with the speed the higher level reaches, shrinks
``a2 − a1`` and inflates ``m`` (×6 on a 0.67 kg stage with 89 N·s/m). So :func:`probe_joint_fit` also fits
``m·ẍ + c·ẋ + F_f = F(t)`` over both phases at once (the position series is continuous across the level
switch), integrated twice so that no velocity or acceleration is differentiated from the samples::

    m·x(t) + c·∫x dt + F_f·t²/2 − p − q·t = ∬F dt²      (p, q: the unknown initial position and speed terms)

linear least squares in ``(m, c, F_f, p, q)``, with the level switch's timing (0–3 samples of I/O delay)
chosen by the smallest residual; standard errors ``s²·(AᵀA)⁻¹``. It replaces the quadratic mass only where
it is credible (``m > 0``, ``c > 0``, relative standard error under :data:`PROBE_JOINT_MAX_REL_STD`) and the
viscous force it finds matters (``c·(v̄2 − v̄1) ≥ PROBE_VISCOUS_SHARE·(F2 − F1)``, the quadratic estimate's bias);
elsewhere (a Stribeck drop looks like ``c < 0``, short phases cannot separate ``m`` from ``c``) the
quadratic mass stands, as before.

Where the levels are too short for two accelerations (fewer than 4 samples: a light stage with a high
breakaway reaches the speed cap within a few cycles of each level, e.g. 1 kg with 3.2 N static and 40 N·s/m
under 4.3 N and 7 N), :func:`probe_driven_fit` fits the same model over every cycle the probe drove after the
breakaway, levels and brake alike (the brake's ``−F2`` is a third, large force level; the friction keeps its
sign while the stage still moves forward), with the commanded force as recorded, cycle by cycle
(``mass_from: driven``). The probe stops only when that fit is not credible either.

**FRF** (:func:`estimate_frf`): the force excitation ``d`` is periodic with ``N`` samples; after one period of
transient the recorded ``x`` and ``u`` (the total commanded force, excitation included) are cut into ``P``
periods and averaged; at the excited bins ``P(ω_k) = X̄_k / Ū_k`` (closed loop, both driven by the same known
``d``: the indirect estimate, unbiased by the controller). Its standard deviation comes from the spread of the
``P`` per-period ratios (/√P).

**Plant fit** (:func:`fit_plant`): ``G(z) = ZOH{1/(m·s² + c·s + k)}·e^{−jωτ}`` (exact zero-order-hold
discretisation at the loop period, ``τ`` the I/O delay), least squares on ``ln(P_meas/G)`` (log-magnitude and
phase equally), weighted by the per-line uncertainty. ``k`` is the pre-sliding (friction) stiffness the stage
stands on while excited around a position, so ``f0 = √(k/m)/2π`` is reported as the pre-sliding resonance.
Parameter standard errors: ``s²·(JᵀJ)⁻¹``. Lines where ``|P_meas/G|`` exceeds ``RESONANCE_RATIO`` are
reported as unmodelled resonances, unless nonlinear distortion dominates them (:func:`frf_distortion`).

**Friction from constant-velocity passes** (:func:`cv_friction`): the mean force of each steady segment vs its
speed, per direction. The two directions of a speed are paired, and the fit reads their odd part
``(F₊ − F₋)/2`` at ``(|v₊| + |v₋|)/2`` only; the even part ``(F₊ + F₋)/2`` is the offset. Regression
``F_odd = Fc + Fv·|v|`` with the Stribeck excess of the curve fitted by
:func:`stagectl.ident.identify.fit_stribeck_curve` removed first (standard errors from the regression).

**Margins on the measured FRF** (:func:`measured_margins`): ``L(jω) = P_meas(jω)·K(e^{jωT})`` with ``K`` the
equivalent controller ``(C + H_y)/(1 − H_u)`` of PID + disturbance observer (``stagectl.control.design``),
on the lines but those both dominated by the friction's nonlinear distortion (:func:`frf_distortion`) and
impossible for a passive stage (:meth:`Frf.margin_lines`). A stage excited under its breakaway stands on its
pre-sliding spring: the lines near ``√(Σk/m)/2π`` see it as a real, linear and cleanly measured resonance
of the stage at rest (it stays in the check); the low-frequency lines, where the elements slip and re-stick,
hold intermodulation products of the other lines and can show any phase (plant gen 29: +45° at 11 Hz, which
alone had ruled out 22–35 Hz PIDs).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy import signal
from scipy.optimize import least_squares

from stagectl.commission.controllers import PROBE_MIN_LEVEL_RATIO, ProbeDirection
from stagectl.errors import StageError

FloatArray = npt.NDArray[np.float64]
ComplexArray = npt.NDArray[np.complex128]

RESONANCE_RATIO = 2.0
FIT_ABOVE_F0 = 1.5
#: the mass fit uses at least the lines above this × sample rate (the smallest displacements: there the
#: pre-sliding friction is its initial, linear stiffness; lower lines see partial slip, a hysteretic
#: describing function that biased the mass by -20 % on config/sim.yaml)
MASS_BAND_X_PERIOD = 0.15


#: the probe's joint mass + viscous fit is used when its mass's relative standard error is under this
PROBE_JOINT_MAX_REL_STD = 0.25
#: ... and its viscous force difference between the two levels is at least this share of ``F2 − F1``
PROBE_VISCOUS_SHARE = 0.1
#: singular values of the joint fit's column-scaled design below this fraction of the largest count as zero
#: (one force level makes the model's own equation a column dependency: ~1e-16 there, ~1e-3 on a real probe)
PROBE_JOINT_RCOND = 1e-9
#: the driven fit (:func:`probe_driven_fit`) needs at least this many cycles ...
PROBE_DRIVEN_MIN_SAMPLES = 10
#: ... with at least two force levels held this many cycles each
PROBE_DRIVEN_MIN_LEVEL_SAMPLES = 3


class SanityError(StageError):
    """The stage failed the sanity probe (wrong sign, no motion, implausible scale)."""


# ================================================================================================ sanity
@dataclass
class SanityResult:
    mass_kg: float
    mass_by_direction_kg: list[float]
    breakaway_n: list[float]
    notes: list[str] = field(default_factory=list)
    #: the mass's standard error [kg] (the joint fit's, or half the directions' spread + 5 %)
    mass_std_kg: float = math.nan
    #: "quadratic" (two accelerations, friction cancels) or "joint" (mass + viscous + friction fit)
    mass_from: str = "quadratic"
    #: the quadratic estimate per direction (kept when the joint fit replaced it) [kg]
    quadratic_mass_kg: list[float] = field(default_factory=list)
    #: the joint fit per direction: mass, its std, viscous [N s/m], friction [N] (None where it failed)
    joint: list[dict[str, Any] | None] = field(default_factory=list)
    #: the joint fit's mass and standard error [kg] where every direction's is credible (``m > 0``, ``c > 0``,
    #: relative std under :data:`PROBE_JOINT_MAX_REL_STD`) whatever its viscous share, else nan: the reference
    #: the FRF's mass is judged against (:func:`frf_mass_consistent`)
    joint_mass_kg: float = math.nan
    joint_mass_std_kg: float = math.nan
    #: the driven fit per direction (:func:`probe_driven_fit`), only where the levels were too short for the
    #: two-acceleration mass (then ``mass_from`` is "driven")
    driven: list[dict[str, Any] | None] = field(default_factory=list)

    @property
    def tuning_mass_kg(self) -> float:
        """The two-acceleration mass (median over directions), what the FRF's tuning is designed for: the
        mass the probe's motion looks like, at least the true one when a viscous force biases it."""
        return float(np.median(self.quadratic_mass_kg)) if self.quadratic_mass_kg else self.mass_kg

    def as_dict(self) -> dict[str, Any]:
        return {"mass_kg": self.mass_kg, "mass_std_kg": self.mass_std_kg, "mass_from": self.mass_from,
                "mass_by_direction_kg": self.mass_by_direction_kg, "quadratic_mass_kg": self.quadratic_mass_kg,
                "tuning_mass_kg": self.tuning_mass_kg,
                "joint_fit": self.joint, "joint_mass_kg": self.joint_mass_kg,
                "joint_mass_std_kg": self.joint_mass_std_kg, "breakaway_n": self.breakaway_n, "notes": self.notes,
                **({"driven_fit": self.driven} if self.driven else {})}


#: a delay whose residual sum of squares is within this factor of the best delay's fits the probe about as well
#: (:func:`_fit_over_delays`): the data do not decide between them, and the mass differs by 10-15 % a cycle
#: (fresh plant k125 of tests/commission/plant_kinds.py, 5.00 kg, 89 N s/m, 35 + 31 samples: 4.91 kg at the
#: true delay of one cycle, 4.28 kg at two, whose sum of squares was 0.6x as large because the pre-sliding
#: friction still built up over the first samples; the ones where one delay fits, 30-1000x smaller)
PROBE_DELAY_AMBIGUITY = 4.0


def _fit_over_delays(A: FloatArray, g_of: Callable[[int], FloatArray]
                     ) -> tuple[FloatArray, FloatArray, int, list[tuple[int, FloatArray, FloatArray]]] | None:
    """Least squares ``A·θ = G(d)`` for each I/O delay ``d`` = 0–3 cycles (the columns scaled to 1 once: the
    design does not depend on the delay, only the force's double integral ``G`` does); the best-fitting delay's
    ``(θ, sd(θ), d, alternatives)``, or ``None`` when the columns are not separable (singular values under
    :data:`PROBE_JOINT_RCOND` of the largest: no motion, one force level) at every delay. A negative variance
    (rounding in a near-singular design) is unknown, NaN (it fails the credibility gates), not 0.

    ``alternatives``: ``(d, θ, sd(θ))`` of every delay whose residual sum of squares is within
    :data:`PROBE_DELAY_AMBIGUITY` of the best one's (the best included, first). Where there are several, the data
    do not decide the delay and ``θ`` trades with it: ``sd(θ)`` then also counts half their range of each
    parameter (in quadrature); :func:`probe_at_delay` picks one once the FRF has measured the delay."""
    sc = np.maximum(np.abs(A).max(axis=0), 1e-300)
    An = A / sc
    fits: list[tuple[float, FloatArray, int]] = []
    for dly in range(4):
        G = g_of(dly)
        th, _, rank, _ = np.linalg.lstsq(An, G, rcond=PROBE_JOINT_RCOND)
        if rank < A.shape[1]:
            continue
        res = G - An @ th
        fits.append((float(res @ res), th / sc, dly))
    if not fits:
        return None
    dof = max(An.shape[0] - An.shape[1], 1)
    try:
        inv = np.linalg.inv(An.T @ An)
    except np.linalg.LinAlgError:
        return None

    def sd_of(ss: float) -> FloatArray:
        var = np.diag((ss / dof) * inv)
        return np.asarray(np.sqrt(np.where(var >= 0.0, var, np.nan)) / sc, np.float64)

    fits.sort(key=lambda f: f[0])
    ss, th, dly = fits[0]
    alts = [(d, t, sd_of(s)) for s, t, d in fits if s <= PROBE_DELAY_AMBIGUITY * ss]
    sd = sd_of(ss)
    if len(alts) > 1:  # (alts[0][2] keeps the best delay's own)
        span = np.ptp(np.array([t for _, t, _ in alts]), axis=0)
        sd = np.sqrt(sd ** 2 + (span / 2) ** 2)
    return th, sd, dly, alts


def _delay_alternatives(alts: list[tuple[int, FloatArray, FloatArray]]) -> list[dict[str, float]]:
    return [{"delay_samples": float(d), "mass_kg": float(t[0]), "mass_std_kg": float(s[0]),
             "viscous_n_s_m": float(t[1]), "viscous_std_n_s_m": float(s[1]), "friction_n": float(t[2])}
            for d, t, s in alts] if len(alts) > 1 else []


def probe_joint_fit(x1: list[float], x2: list[float], f1_n: float, f2_n: float, dt_s: float,
                    sign: int = 1) -> dict[str, Any] | None:
    """Mass, viscous coefficient and friction from one probe direction's two constant-force phases.

    ``x1``, ``x2``: the positions [m] sampled every ``dt_s`` under ``sign·f1_n`` then ``sign·f2_n`` (contiguous:
    ``x2[0]`` one period after ``x1[-1]``). Model ``m·ẍ + c·ẋ + F_f = F`` in the direction of motion, integrated
    twice (module docstring); the switch to ``F2`` is taken 0–3 samples after the last ``x1`` sample (the I/O
    delay), whichever fits best. Returns ``{"mass_kg", "mass_std_kg", "viscous_n_s_m", "viscous_std_n_s_m",
    "friction_n", "delay_samples", "dv_m_s"}`` (``dv_m_s``: the mean speed's rise from the first phase to the
    second) or ``None`` when there are too few samples, a non-finite input, one force level (``f1_n = f2_n``) or
    a design whose columns are not separable (singular values under :data:`PROBE_JOINT_RCOND` of the largest:
    no motion) at every delay."""
    n1, n2 = len(x1), len(x2)
    if n1 < 4 or n2 < 4:
        return None
    if not (math.isfinite(f1_n) and math.isfinite(f2_n) and f2_n != f1_n and dt_s > 0.0 and math.isfinite(dt_s)
            and all(math.isfinite(v) for v in x1) and all(math.isfinite(v) for v in x2)):
        return None  # one force level (the model's equation is then a column dependency), or non-finite data
    xs = sign * np.asarray([*x1, *x2], dtype=np.float64)
    xs = xs - xs[0]
    t = dt_s * np.arange(1, n1 + n2 + 1, dtype=np.float64)
    X1 = np.concatenate([[0.0], np.cumsum(0.5 * (xs[1:] + xs[:-1])) * dt_s])
    # the design does not depend on the delay (only the force's double integral G does): built and scaled once
    A = np.column_stack([xs, X1, t ** 2 / 2, -np.ones_like(t), -t])
    fit = _fit_over_delays(A, lambda dly: f1_n * t ** 2 / 2
                           + (f2_n - f1_n) * np.maximum(t - (n1 + dly) * dt_s, 0.0) ** 2 / 2)
    if fit is None:
        return None
    th, sd, dly, alts = fit
    v1 = (xs[n1 - 1] - xs[0]) / ((n1 - 1) * dt_s)
    v2 = (xs[-1] - xs[n1]) / ((n2 - 1) * dt_s)
    return {"mass_kg": float(th[0]), "mass_std_kg": float(sd[0]), "viscous_n_s_m": float(th[1]),
            "viscous_std_n_s_m": float(sd[1]), "friction_n": float(th[2]), "delay_samples": float(dly),
            "dv_m_s": float(v2 - v1), "force_step_n": float(f2_n - f1_n),
            "mass_std_at_delay_kg": float(alts[0][2][0]), "delay_alternatives": _delay_alternatives(alts)}


def probe_driven_fit(x: list[float], u: list[float], pre_force_n: float, dt_s: float,
                     sign: int = 1) -> dict[str, Any] | None:
    """Mass, viscous coefficient and friction from every cycle the probe drove in one direction.

    ``x[i]``: the position [m] at cycle ``i`` (from the breakaway's detection to the end of the brake), ``u[i]``
    the force [N, signed] commanded at that cycle, applied over ``[t_{i+d}, t_{i+d+1})`` after ``d`` = 0–3
    cycles of I/O delay (the best fit's); before ``u[0]`` arrives the ramp's ``sign·pre_force_n`` acts. In the
    direction of motion ``m·ẍ + c·ẋ + F_f = F`` holds while the stage moves forward (the brake's ``−F2``
    included: the friction keeps its sign; the cycles from the first position not ahead of its predecessor on
    are left out), integrated twice as :func:`probe_joint_fit`::

        m·x(t_i) + c·∫x dt + F_f·t_i²/2 − p − q·t_i = G_i,    G_{i+1} = G_i + V_i·T + F_i·T²/2,  V_{i+1} = V_i + F_i·T

    (``G``: the applied force's exact double integral over the zero-order-held cycles). Returns the keys of
    :func:`probe_joint_fit` but ``dv_m_s``, plus ``"samples"``, or ``None`` with fewer than
    :data:`PROBE_DRIVEN_MIN_SAMPLES` cycles, fewer than two force levels held
    :data:`PROBE_DRIVEN_MIN_LEVEL_SAMPLES` cycles each, non-finite input or an inseparable design."""
    n = len(x)
    if n < PROBE_DRIVEN_MIN_SAMPLES or len(u) != n or not (dt_s > 0.0 and math.isfinite(dt_s)):
        return None
    if not (math.isfinite(pre_force_n) and all(math.isfinite(v) for v in x) and all(math.isfinite(v) for v in u)):
        return None
    xs = sign * np.asarray(x, dtype=np.float64)
    # the model holds while the stage moves forward: up to the last position before the first one that is not
    # ahead of its predecessor (the brake reversed or stuck it; the friction changes sign or becomes static)
    back = np.flatnonzero(np.diff(xs) <= 0.0)
    if back.size:
        n = int(back[0]) + 1
        if n < PROBE_DRIVEN_MIN_SAMPLES:
            return None
        xs = xs[:n]
    us = sign * np.asarray(u[:n], dtype=np.float64)
    _, counts = np.unique(np.round(us[:-1], 12), return_counts=True)
    if int(np.sum(counts >= PROBE_DRIVEN_MIN_LEVEL_SAMPLES)) < 2:
        return None
    xs = xs - xs[0]
    t = dt_s * np.arange(n, dtype=np.float64)
    X1 = np.concatenate([[0.0], np.cumsum(0.5 * (xs[1:] + xs[:-1])) * dt_s])
    A = np.column_stack([xs, X1, t ** 2 / 2, -np.ones_like(t), -t])

    def g_of(dly: int) -> FloatArray:
        fa = np.concatenate([np.full(dly, pre_force_n), us])[:n - 1]   # the force over [t_i, t_{i+1})
        vel = np.concatenate([[0.0], np.cumsum(fa) * dt_s])[:-1]
        return np.concatenate([[0.0], np.cumsum(vel * dt_s + fa * dt_s ** 2 / 2)])

    fit = _fit_over_delays(A, g_of)
    if fit is None:
        return None
    th, sd, dly, alts = fit
    return {"mass_kg": float(th[0]), "mass_std_kg": float(sd[0]), "viscous_n_s_m": float(th[1]),
            "viscous_std_n_s_m": float(sd[1]), "friction_n": float(th[2]), "delay_samples": float(dly),
            "samples": float(n), "mass_std_at_delay_kg": float(alts[0][2][0]),
            "delay_alternatives": _delay_alternatives(alts)}


def _credible_std(f: dict[str, Any]) -> float:
    """The standard error a fit's credibility is judged on: its own at the delay it chose (``mass_std_kg``
    also counts the delays that fit about as well, :func:`_fit_over_delays`; that uncertainty is reported and
    weighed, and :func:`probe_at_delay` resolves it, but it does not make the probe refuse a fit)."""
    return float(f.get("mass_std_at_delay_kg", f["mass_std_kg"]))


def _driven_credible(f: dict[str, Any] | None) -> bool:
    return (f is not None and f["mass_kg"] > 0.0 and math.isfinite(_credible_std(f))
            and _credible_std(f) <= PROBE_JOINT_MAX_REL_STD * f["mass_kg"])


def _accel(t: list[float], x: list[float]) -> float:
    if len(t) < 4:
        return math.nan
    c = np.polyfit(np.asarray(t), np.asarray(x), 2)
    return float(2.0 * c[0])


def _joint_credible(joint: list[dict[str, Any] | None]
                    ) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
    """The joint fits' (mass, std) that are credible (``m > 0``, ``c > 0``, relative std under
    :data:`PROBE_JOINT_MAX_REL_STD`), and those of them whose viscous force difference between the levels is at
    least :data:`PROBE_VISCOUS_SHARE` of ``F2 − F1`` (it biases the two-acceleration mass)."""
    cred: list[tuple[float, float]] = []
    visc: list[tuple[float, float]] = []
    for jf in joint:
        if (jf is not None and jf["mass_kg"] > 0 and jf["viscous_n_s_m"] > 0
                and _credible_std(jf) <= PROBE_JOINT_MAX_REL_STD * jf["mass_kg"]):
            cred.append((jf["mass_kg"], jf["mass_std_kg"]))
            if jf["viscous_n_s_m"] * jf["dv_m_s"] >= PROBE_VISCOUS_SHARE * jf["force_step_n"]:
                visc.append((jf["mass_kg"], jf["mass_std_kg"]))
    return cred, visc


def _joint_mass(fits: list[tuple[float, float]]) -> tuple[float, float]:
    """The median of the directions' joint masses and its standard error: their combined one or half their
    spread, whichever is larger."""
    mj = [v for v, _ in fits]
    return float(np.median(mj)), max(math.sqrt(sum(s ** 2 for _, s in fits)) / len(fits), (max(mj) - min(mj)) / 2)


#: the FRF's delay picks one of the probe's delay alternatives (:func:`probe_at_delay`) when the nearest is
#: nearer than this many cycles, FRF standard error counted twice
PROBE_DELAY_PICK_CYCLES = 0.5


def probe_at_delay(s: SanityResult, delay_cycles: float, delay_std_cycles: float) -> SanityResult:
    """The probe's result with each joint fit whose delay the probe's data did not decide (several
    ``delay_alternatives``, :func:`_fit_over_delays`) taken at the delay the FRF measured: the alternative
    nearest ``delay_cycles`` (the FRF's I/O delay [cycles]), where ``|d − τ| + 2·σ_τ <
    PROBE_DELAY_PICK_CYCLES`` (it tells the whole cycles apart), with that delay's own standard errors. The joint
    mass and, where the probe took it (``mass_from == "joint"``), the probe's mass are recomputed from them.
    Unchanged where nothing is ambiguous or the FRF's delay does not decide."""
    if not (math.isfinite(delay_cycles) and math.isfinite(delay_std_cycles)):
        return s
    joint: list[dict[str, Any] | None] = []
    picked: list[str] = []
    for j in s.joint:
        alts = (j or {}).get("delay_alternatives") or []
        if j is None or not alts:
            joint.append(j)
            continue
        a = min(alts, key=lambda a: abs(a["delay_samples"] - delay_cycles))
        if abs(a["delay_samples"] - delay_cycles) + 2.0 * delay_std_cycles >= PROBE_DELAY_PICK_CYCLES:
            joint.append(j)
            continue
        picked.append(f"{j['mass_kg']:.4g} ± {j['mass_std_kg']:.2g} kg at {j['delay_samples']:g} -> "
                      f"{a['mass_kg']:.4g} ± {a['mass_std_kg']:.2g} kg at {a['delay_samples']:g}")
        joint.append({**j, **a, "mass_std_at_delay_kg": a["mass_std_kg"], "delay_alternatives": [],
                      "delay_from": "frf", "probe_delay_alternatives": alts})
    if not picked:
        return s
    joint_c, joint_m = _joint_credible(joint)
    n = len(s.quadratic_mass_kg) or len(s.mass_by_direction_kg)
    jm = js = math.nan
    if joint_c and len(joint_c) == n:
        jm, js = _joint_mass(joint_c)
    out = dataclasses.replace(s, joint=joint, joint_mass_kg=jm, joint_mass_std_kg=js,
                              notes=[*s.notes, "the probe's delay was ambiguous (two or more delays fitted about as "
                                     f"well); taken at the FRF's {delay_cycles:.3g} ± {delay_std_cycles:.2g} cycles: "
                                     + "; ".join(picked)])
    if s.mass_from == "joint" and joint_m and len(joint_m) == n:
        m, sd = _joint_mass(joint_m)
        out = dataclasses.replace(out, mass_kg=m, mass_std_kg=sd, mass_by_direction_kg=[v for v, _ in joint_m])
    return out


def evaluate_probe(dirs: list[ProbeDirection], f_lim_n: float, d_detect_m: float,
                   expected_mass_kg: float | None, v_stop_m_s: float | None = None) -> SanityResult:
    """Check the probe's outcome and estimate the mass (see the module docstring). ``v_stop_m_s``: the speed
    that ends the second acceleration level (0.9 × the envelope's velocity, which ``--max-velocity`` lowers),
    named when no mass could be measured.

    Raises
    ------
    SanityError
        One line naming what is wrong and what to check (sign, scaling, stuck axis / sensor).
    """
    masses: list[float] = []
    brk: list[float] = []
    notes: list[str] = []
    joint: list[dict[str, Any] | None] = []
    for d in dirs:
        name = "+" if d.sign > 0 else "-"
        if d.outcome == "wrong_sign":
            raise SanityError(f"sanity: a {name} force moved the stage the other way ({d_detect_m * 1e6:.3g} um): "
                              "wrong sign; check io.drive polarity (force_per_unit_n sign) and the sensor direction")
        if d.outcome == "no_motion":
            raise SanityError(f"sanity: no motion beyond {d_detect_m * 1e6:.3g} um with up to {f_lim_n:.3g} N "
                              f"in the {name} direction: stuck axis (brake, end stop) or the sensor does not move; "
                              "check io.sensor and io.drive.resolution_m, or allow more force (the probe goes up to "
                              "0.7 x the lowest of safety.max_force_n, controller.max_force_n and --max-force, and "
                              "never above the drive's limit: io.drive.max_force_n, its max torque 0x6072)")
        if d.outcome != "ok":
            raise SanityError(f"sanity: the {name} probe did not finish ({d.outcome})")
        brk.append(d.breakaway_n)
        a1, a2 = _accel(d.t1, d.x1) * d.sign, _accel(d.t2, d.x2) * d.sign
        if a1 < 0 and a2 < 0:
            raise SanityError(f"sanity: the stage decelerated under a {name} force ({a1:.3g}, {a2:.3g} m/s^2): "
                              "wrong sign; check io.drive polarity and the sensor direction")
        if math.isfinite(a1) and math.isfinite(a2) and a2 > a1 > -math.inf and d.f2_n > d.f1_n:
            masses.append((d.f2_n - d.f1_n) / (a2 - a1))
            dt = (d.t1[-1] - d.t1[0]) / (len(d.t1) - 1) if len(d.t1) > 1 else math.nan
            jf = probe_joint_fit(d.x1, d.x2, d.f1_n, d.f2_n, dt, d.sign) if dt > 0 else None
            joint.append(jf)
    joint_c, joint_m = _joint_credible(joint)
    short = [d for d in dirs if d.f2_n < PROBE_MIN_LEVEL_RATIO * d.f1_n]
    if not masses and short:
        raise SanityError(f"sanity: breakaway {short[0].breakaway_n:.3g} N leaves too little force under the cap "
                          f"{short[0].f2_n:.3g} N for two acceleration levels (need {PROBE_MIN_LEVEL_RATIO:g}x apart); "
                          "raise --max-force, safety.max_force_n or controller.max_force_n")
    driven: list[dict[str, Any] | None] = []
    if not masses and dirs:
        # the levels were too short for two accelerations: the fit over every driven cycle (levels and brake)
        driven = [probe_driven_fit(d.x_drive, d.u_drive, d.breakaway_n, d.dt_s, d.sign) for d in dirs]
        if all(_driven_credible(f) for f in driven):
            masses = [f["mass_kg"] for f in driven if f is not None]
    if not masses:
        if v_stop_m_s is None:
            raise SanityError("sanity: the accelerations under two force levels could not be measured (too little "
                              "travel or force); raise --max-stroke or --max-force")
        raise SanityError("sanity: the accelerations under two force levels could not be measured (too little "
                          f"travel, force or speed: the levels end at {v_stop_m_s / 3:.3g} and {v_stop_m_s:.3g} m/s, "
                          "0.24 and 0.72 of the velocity cap); raise --max-stroke, --max-force or --max-velocity")
    quad = list(masses)
    m = float(np.median(masses))
    m_std = (max(masses) - min(masses)) / 2 + 0.05 * abs(m)
    mass_from = "quadratic"
    if driven:
        quad = []
        mass_from = "driven"
        m_std = max(math.sqrt(sum(f["mass_std_kg"] ** 2 for f in driven if f is not None)) / len(masses),
                    (max(masses) - min(masses)) / 2) + 0.05 * abs(m)
        notes.append("the probe's two levels gave no mass from their accelerations (too few cycles, or the "
                     "second no faster than the first; cycles per level "
                     + ", ".join(f"{len(d.x1)} + {len(d.x2)}" for d in dirs)
                     + f" cycles): mass {m:.4g} ± {m_std:.2g} kg from a mass + viscous fit over every driven cycle "
                     "(levels and brake), viscous "
                     + ", ".join(f"{f['viscous_n_s_m']:.3g}" for f in driven if f is not None) + " N s/m")
    if joint_m and len(joint_m) == len(masses):
        # every direction's joint fit is credible and finds a viscous force that biases the quadratic mass
        mj = [v for v, _ in joint_m]
        mass_from, masses = "joint", mj
        m, m_std = _joint_mass(joint_m)
        notes.append(f"viscous force in the probe: mass {m:.4g} ± {m_std:.2g} kg from a mass + viscous fit "
                     f"(the two-acceleration estimate, {float(np.median(quad)):.4g} kg, ignores it)")
    if not (m > 0 and math.isfinite(m)):
        raise SanityError(f"sanity: moving mass estimate {m:.3g} kg is not positive: check io.drive.force_per_unit_n "
                          "and io.drive.resolution_m")
    if expected_mass_kg is not None:
        r = m / expected_mass_kg
        if not 0.2 <= r <= 5.0:
            raise SanityError(f"sanity: force/position scale off by {r:.3g}x: the probe moves like {m:.4g} kg where "
                              f"the configuration expects {expected_mass_kg:.4g} kg; check io.drive.force_per_unit_n "
                              "and the sensor's resolution_m")
        notes.append(f"scale plausible: probe mass {m:.4g} kg vs {expected_mass_kg:.4g} kg configured ({r:.2f}x)")
    jm = js = math.nan
    if joint_c and len(joint_c) == len(quad):
        jm, js = _joint_mass(joint_c)
    return SanityResult(m, masses, brk, notes, mass_std_kg=m_std, mass_from=mass_from, quadratic_mass_kg=quad,
                        joint=joint, joint_mass_kg=jm, joint_mass_std_kg=js, driven=driven)


#: the FRF's mass is refused when it differs from the probe's by more than this many combined standard errors
FRF_MASS_SIGMAS = 3.0
#: the probe's standard error counts at least this fraction of its mass there (its own is statistical only: a
#: spring, cogging or Stribeck drop over the probe's travel biases it by a few %)
PROBE_MASS_MIN_REL_STD = 0.05


def probe_reference_mass(s: SanityResult) -> tuple[float, float, bool]:
    """The probe's mass [kg], its standard error [kg] (at least ``PROBE_MASS_MIN_REL_STD`` of it) and whether it is
    the joint fit's: the joint fit's where every direction's is credible (:attr:`SanityResult.joint_mass_kg`),
    whatever its viscous share (the two-acceleration estimate is biased by ``c·Δv/(F2 − F1)``, up to the 10 %
    share under which the probe keeps it), else the probe's own."""
    if math.isfinite(s.joint_mass_kg) and s.joint_mass_kg > 0:
        return s.joint_mass_kg, max(s.joint_mass_std_kg, PROBE_MASS_MIN_REL_STD * s.joint_mass_kg), True
    return s.mass_kg, max(s.mass_std_kg, PROBE_MASS_MIN_REL_STD * s.mass_kg), False


#: the FRF mass's standard error counts at least this fraction of it where it is averaged with the probe's
#: (:func:`combined_mass`): its own is statistical only, and the fit's model (a linear pre-sliding spring, the
#: fitted band) leaves a few % (fresh plants k120-k125, generated 70-75 of tests/commission: -3.5 … +2.4 %,
#: k125 +1.3 % for a stated 0.28 %)
FRF_MASS_MIN_REL_STD = 0.03


def combined_mass(frf_mass_kg: float, frf_std_kg: float, probe_mass_kg: float, probe_std_kg: float
                  ) -> tuple[float, float]:
    """The inverse-variance mean [kg] of the FRF's mass and the probe's, and its standard error [kg]:
    ``m = (w_F·m_F + w_p·m_p)/(w_F + w_p)``, ``σ = (w_F + w_p)^(−1/2)``, ``w = 1/σ²`` with the FRF's ``σ_F`` at least
    :data:`FRF_MASS_MIN_REL_STD` of ``m_F``. For two measurements that passed :func:`frf_mass_consistent`: a
    poorly measured FRF (generated plant 71 of tests/commission/plant_gen.py, 1.27 kg standing on its
    pre-sliding spring: 1.159 ± 0.082 kg from five lines at 280-450 Hz, 0.15 rms log error) no longer
    outweighs a probe that measured 1.266 kg."""
    sf = max(frf_std_kg, FRF_MASS_MIN_REL_STD * abs(frf_mass_kg))
    wf, wp = 1.0 / sf ** 2, 1.0 / probe_std_kg ** 2
    return (wf * frf_mass_kg + wp * probe_mass_kg) / (wf + wp), 1.0 / math.sqrt(wf + wp)


#: the joint fits' viscous coefficients of the probe's directions agree when within this many combined standard
#: errors (:func:`probe_viscous_agrees`)
PROBE_VISCOUS_AGREE_SIGMAS = 2.0


def probe_viscous_agrees(s: SanityResult) -> bool:
    """Whether the probe's joint fits measured one viscous force: every direction's fit credible
    (:attr:`SanityResult.joint_mass_kg` finite), at least two, ``c > 0`` in each, and their ``c`` within
    :data:`PROBE_VISCOUS_AGREE_SIGMAS` combined standard errors of each other. Two measurements of one ``c``: a
    friction that is not linear in the speed over the probe's range (a Stribeck drop, stick-slip at the
    start), and differently so in the two directions, makes them disagree (fresh plant k110 of
    tests/commission/plant_kinds.py, 0.93 kg, 3.6 N s/m, vs 1.9 mm/s and a 0.21 N offset: 6.7 ± 0.7 and
    35 ± 6 N s/m; k106: −15 and +14). Where they agree, the two-acceleration mass's bias ``c·Δv/(F2 − F1)`` is measured, even
    under the :data:`PROBE_VISCOUS_SHARE` that the probe itself keeps (k105, 0.700 kg, 9.92 N s/m: 9.83 ± 0.27 and
    10.32 ± 0.29 N s/m, joint mass 0.703 kg, two-acceleration 0.772)."""
    js = s.joint
    if len(js) < 2 or not (math.isfinite(s.joint_mass_kg) and s.joint_mass_kg > 0):
        return False
    cs: list[tuple[float, float]] = []
    for j in js:
        if j is None or not (j["viscous_n_s_m"] > 0 and math.isfinite(j["viscous_std_n_s_m"])):
            return False
        cs.append((j["viscous_n_s_m"], j["viscous_std_n_s_m"]))
    return all(abs(c1 - c2) <= PROBE_VISCOUS_AGREE_SIGMAS * math.hypot(s1, s2)
               for i, (c1, s1) in enumerate(cs) for c2, s2 in cs[i + 1:])


def probe_replacement_mass(s: SanityResult) -> tuple[float, float, bool]:
    """The mass [kg] and standard error [kg] that replace an FRF mass that is not credible, and whether it is
    the joint fit's where the probe itself kept its two-acceleration mass: the joint mass + viscous fit's when
    its directions agree on the viscous force (:func:`probe_viscous_agrees`; its standard error, at least
    ``PROBE_MASS_MIN_REL_STD``), else the probe's own mass with half its directions' spread + 5 % (or the joint
    fit's error where the probe took it)."""
    if s.mass_from != "joint" and probe_viscous_agrees(s):
        m, sd, _ = probe_reference_mass(s)
        return m, sd, True
    return s.mass_kg, max(s.mass_std_kg, 0.05 * s.mass_kg), False


def frf_mass_consistent(frf_mass_kg: float, frf_std_kg: float, probe_mass_kg: float, probe_std_kg: float) -> bool:
    """Whether the FRF's mass agrees with the probe's within ``FRF_MASS_SIGMAS`` combined standard errors:
    ``|m_FRF − m_probe| ≤ z·√(σ_FRF² + σ_probe²)``. Two independent measurements of one mass: a larger gap means
    one of them measured something else, and the FRF around a standing position is the one that can (a stage
    held by its pre-sliding spring, a poorly fitted band: fresh plant k111 of tests/commission/plant_kinds.py
    read 2.26 ± 0.24 kg for 3.37, the probe's joint fit 3.367; plant_gen.py 3 read 0.601 ± 0.013 kg for 0.686,
    the probe 0.72)."""
    return abs(frf_mass_kg - probe_mass_kg) <= FRF_MASS_SIGMAS * math.hypot(frf_std_kg, probe_std_kg)


# ================================================================================================ FRF
#: FRF amplitude limits (:func:`frf_amplitude`): a sliding stage's predicted peak position error within this
#: many following-error limits, counted as sliding only with a peak force of at least FRF_SLIDE_MIN_X_BREAKAWAY
#: breakaways; or a peak force within FRF_STICK_X_BREAKAWAY of the breakaway (the stage stands)
FRF_SLIDE_ERROR_X_FE = 0.6
FRF_SLIDE_MIN_X_BREAKAWAY = 2.0
FRF_STICK_X_BREAKAWAY = 0.5
#: the FRF's mass is kept when within this ratio range of the probe's and its std under FRF_MASS_MAX_REL_STD of
#: it; otherwise (a stage that stood on its stiff pre-sliding spring: 3e-8 kg fitted for a 0.80 kg stage
#: excited under its breakaway) the probe's mass is used
FRF_MASS_PLAUSIBLE = (0.5, 2.0)
FRF_MASS_MAX_REL_STD = 0.25
#: ... and a refusal when the allowed amplitude moves the stage less than this many sensor quanta
FRF_MIN_QUANTA = 20.0


@dataclass(frozen=True)
class FrfAmplitude:
    """The FRF multisine's amplitude per line [N] and how it was chosen (all SI)."""

    amplitude_n: float
    nominal_n: float
    peak_force_n: float
    predicted_peak_error_m: float
    limit: str

    def as_dict(self) -> dict[str, Any]:
        return {"amplitude_per_line_n": self.amplitude_n, "nominal_per_line_n": self.nominal_n,
                "peak_force_n": self.peak_force_n, "predicted_sliding_peak_error_m": self.predicted_peak_error_m,
                "amplitude_limit": self.limit}


def frf_amplitude(wave: FloatArray, bins: npt.NDArray[np.int64], nominal_n: float, period_s: float,
                  mass_kg: float, K: ComplexArray, delay_s: float, breakaway_n: float, following_error_m: float,
                  quantum_m: float) -> FrfAmplitude:
    """Amplitude per line of the FRF multisine ``wave`` (one period, unit amplitude per line, lines ``bins``).

    The stage stands at a fixed reference; the multisine is a force disturbance. A frictionless rigid mass
    under the closed loop ``K`` (the tuning it runs with) would follow
    ``e(t) = Σ_k A·|S_k|·cos(ω_k t + φ_k + ∠S_k)``, ``S = P/(1 + P·K)``, ``P(jω) = e^{−jωτ}/(−m·ω²)``, whose
    peak over a period per unit ``A`` is ``ê``; ``û`` is the wave's peak force per unit ``A``. Friction
    takes up to the breakaway ``F_b`` of the force, so a stage that clearly slides (``A·û ≥
    FRF_SLIDE_MIN_X_BREAKAWAY·F_b``) is predicted at ``ê·(A − F_b/û)``; between ``FRF_STICK_X_BREAKAWAY·F_b``
    and that it stick-slips, and no linear figure bounds it (a 1.26 kg stage with 1.66 N breakaway under a
    2.0 N peak: 12 µm predicted so, 51 µm measured, fault). Below, it stands on its stiff pre-sliding
    spring. Hence::

        A_slide = F_b/û + FRF_SLIDE_ERROR_X_FE·e_FE/ê     if A_slide·û ≥ FRF_SLIDE_MIN_X_BREAKAWAY·F_b, else 0
        A_stick = FRF_STICK_X_BREAKAWAY·F_b/û
        A = min(A_nominal, max(A_slide, A_stick))

    (``F_b = 0``: the frictionless prediction, ``ê·A ≤ 0.6·e_FE``; it is within 15 % of a time-domain
    simulation of the loop.) A 0.80 kg stage with 0.78 N breakaway got 0.2× the nominal amplitude (its
    nominal peak 133 µm frictionless, 81 µm with friction, against a 50 µm band); config/sim.yaml (2 kg,
    0.97 N) keeps the nominal one.

    Raises
    ------
    StageError
        One line when the allowed amplitude moves the stage less than ``FRF_MIN_QUANTA`` sensor quanta.
    """
    n = wave.shape[0]
    f = bins.astype(np.float64) / (n * period_s)
    w = 2 * np.pi * f
    P = np.exp(-1j * w * delay_s) / (-mass_kg * w ** 2)
    S = P / (1 + P * K)
    spec = np.zeros(n // 2 + 1, np.complex128)
    spec[bins] = np.fft.rfft(wave)[bins] * S
    e_unit = float(np.abs(np.fft.irfft(spec, n)).max())
    u_unit = float(np.abs(wave).max())
    fb = max(breakaway_n, 0.0)
    a_slide = fb / u_unit + FRF_SLIDE_ERROR_X_FE * following_error_m / e_unit
    if a_slide * u_unit < FRF_SLIDE_MIN_X_BREAKAWAY * fb:
        a_slide = 0.0
    a_stick = FRF_STICK_X_BREAKAWAY * fb / u_unit
    a = min(nominal_n, max(a_slide, a_stick))
    limit = "nominal" if a == nominal_n else ("sliding error" if a_slide >= a_stick else "breakaway")
    e_pred = e_unit * max(a - fb / u_unit, 0.0) if a * u_unit >= FRF_SLIDE_MIN_X_BREAKAWAY * fb else 0.0
    if a * e_unit < FRF_MIN_QUANTA * quantum_m:
        raise StageError(f"frf: the largest safe multisine ({a:.3g} N per line, peak {a * u_unit:.3g} N against "
                         f"{fb:.3g} N breakaway and following_error_m {following_error_m * 1e6:.3g} um) moves the "
                         f"stage under {FRF_MIN_QUANTA:g} sensor quanta ({quantum_m:.3g} m); raise "
                         "safety.following_error_m")
    return FrfAmplitude(a, nominal_n, a * u_unit, e_pred, limit)


#: nonlinear distortion (:func:`frf_distortion`): the level at the FRF_DISTORTION_NEIGHBOURS non-excited bins
#: nearest a line, relative to the line's; above FRF_DISTORTION_MAX the line carries no linear information
#: (:meth:`Frf.linear_lines`, :meth:`Frf.margin_lines`; all lines count when fewer than FRF_MARGIN_MIN_LINES
#: would remain)
FRF_DISTORTION_NEIGHBOURS = 4
FRF_DISTORTION_MAX = 0.5
FRF_MARGIN_MIN_LINES = 6


@dataclass
class Frf:
    """Measured plant FRF at the excited lines: ``f_hz``, ``p`` [m/N], ``p_std`` (per-line std of ``p``),
    ``distortion`` (per-line relative level of what the non-excited bins around it hold; None: not measured),
    ``delay_s`` (the I/O delay with the zero-order hold's half period the passivity test of
    :meth:`margin_lines` takes out; set once the plant fit has measured it, NaN until then: no line is left out,
    since with no delay taken out every line of a delayed mass leads)."""

    f_hz: FloatArray
    p: ComplexArray
    p_std: FloatArray
    periods: int
    distortion: FloatArray | None = None
    delay_s: float = math.nan

    def _at_least(self, keep: npt.NDArray[np.bool_]) -> npt.NDArray[np.bool_]:
        return keep if int(keep.sum()) >= FRF_MARGIN_MIN_LINES else np.ones(self.f_hz.shape[0], bool)

    def linear_lines(self) -> npt.NDArray[np.bool_]:
        """The lines whose distortion is at most FRF_DISTORTION_MAX."""
        if self.distortion is None:
            return np.ones(self.f_hz.shape[0], bool)
        return self._at_least(np.asarray(self.distortion <= FRF_DISTORTION_MAX, bool))

    def margin_lines(self) -> npt.NDArray[np.bool_]:
        """The lines the margins are read on: all but those dominated by distortion (``δ > FRF_DISTORTION_MAX``)
        *and* impossible for a passive stage. Force in, position out at the same carriage: the mobility
        ``jω·P`` of a passive system has a non-negative real part (it takes power in), so
        ``Im(P·e^{jωτ}) ≤ 0`` once the delay ``τ`` is taken out; friction is passive too. A line above that
        is wrong in the direction that fakes −180° crossings (its phase unwraps a full turn). Either test
        alone is not enough: a real mode of a non-collocated sensor has clean lines, and dropping every
        distorted line leaves a stage measured under its breakaway without the lines its crossover is on."""
        if self.distortion is None or not math.isfinite(self.delay_s):
            return np.ones(self.f_hz.shape[0], bool)
        lead = (self.p * np.exp(1j * 2 * np.pi * self.f_hz * self.delay_s)).imag > 0.0
        return self._at_least(~(np.asarray(self.distortion > FRF_DISTORTION_MAX, bool) & lead))


def estimate_frf(x: FloatArray, u: FloatArray, n_period: int, bins: npt.NDArray[np.int64], period_s: float) -> Frf:
    """Periodic-averaging FRF (module docstring). ``x``, ``u`` start at the excitation's first sample."""
    p_count = x.shape[0] // n_period - 1
    if p_count < 2:
        raise StageError(f"frf: {x.shape[0]} samples hold fewer than 3 excitation periods of {n_period}")
    xs = x[n_period: n_period * (p_count + 1)].reshape(p_count, n_period)
    us = u[n_period: n_period * (p_count + 1)].reshape(p_count, n_period)
    xs = xs - xs.mean(axis=1, keepdims=True)
    us = us - us.mean(axis=1, keepdims=True)
    Xa = np.fft.rfft(xs, axis=1)
    Ua = np.fft.rfft(us, axis=1)
    X, U = Xa[:, bins], Ua[:, bins]
    p = X.mean(axis=0) / U.mean(axis=0)
    per = X / U
    p_std = np.abs(per - p).std(axis=0, ddof=1) / math.sqrt(p_count) if p_count > 1 else np.abs(p)
    f = bins.astype(float) / (n_period * period_s)
    return Frf(f, p.astype(np.complex128), np.asarray(p_std, float), p_count,
               frf_distortion(Xa.mean(axis=0), Ua.mean(axis=0), bins))


def frf_distortion(X: ComplexArray, U: ComplexArray, bins: npt.NDArray[np.int64]) -> FloatArray:
    """Per excited line ``k``: ``δ_k = √((x̃_k/|X_k|)² + (ũ_k/|U_k|)²)``, with ``x̃_k``, ``ũ_k`` the RMS of the
    period-averaged spectra ``X``, ``U`` (all bins, 0 … N/2) over the ``FRF_DISTORTION_NEIGHBOURS``
    non-excited bins nearest ``k`` ("detection lines"). A linear loop puts only noise there; friction's
    distortion of a periodic excitation is periodic too, so averaging does not remove it nor does the
    per-period spread (``p_std``) show it, but it lands on the non-excited bins around the lines as much as on
    the lines. ``δ`` is then the relative error of ``P = X/U`` it causes (a 0.60 kg stage standing on a
    2.1e6 N/m pre-sliding spring under half its breakaway: δ 0.3–3.6 at 2–17 Hz, one line at 11 Hz with
    phase +45°, which no passive stage has; 0.07–0.2 at 50–340 Hz)."""
    n = X.shape[0]
    mask = np.ones(n, bool)
    mask[0] = False
    mask[bins] = False
    free = np.nonzero(mask)[0]
    if free.size == 0:
        return np.zeros(bins.shape[0])
    out = np.empty(bins.shape[0])
    for i, b in enumerate(bins.tolist()):
        near = free[np.argsort(np.abs(free - b), kind="stable")[:FRF_DISTORTION_NEIGHBOURS]]
        fx = math.sqrt(float(np.mean(np.abs(X[near]) ** 2)))
        fu = math.sqrt(float(np.mean(np.abs(U[near]) ** 2)))
        out[i] = math.hypot(fx / max(abs(X[b]), 1e-300), fu / max(abs(U[b]), 1e-300))
    return out


def plant_response(f_hz: FloatArray, m: float, c: float, k: float, tau: float, period_s: float) -> ComplexArray:
    """``ZOH{1/(m s² + c s + k)}(e^{jωT})·e^{−jωτ}`` at ``f_hz``."""
    num, den, _ = signal.cont2discrete(([1.0], [m, c, k]), period_s, method="zoh")
    w = 2 * np.pi * f_hz * period_s
    _, h = signal.freqz(np.ravel(num), den, worN=w)
    return np.asarray(h * np.exp(-1j * 2 * np.pi * f_hz * tau), np.complex128)


@dataclass
class PlantFit:
    mass_kg: float
    mass_std_kg: float
    damping_n_s_m: float
    stiffness_n_m: float
    stiffness_std_n_m: float
    delay_s: float
    delay_std_s: float
    rms_log_error: float
    resonances_hz: list[float]
    f_lo_hz: float
    #: "frf", "probe" when the FRF's mass was not credible (:data:`FRF_MASS_PLAUSIBLE`) or disagreed with the
    #: probe's, "frf+probe" when averaged with the probe's (:func:`combined_mass`)
    mass_from: str = "frf"

    @property
    def presliding_resonance_hz(self) -> float:
        return math.sqrt(max(self.stiffness_n_m, 0.0) / self.mass_kg) / (2 * math.pi)

    def as_dict(self) -> dict[str, Any]:
        return {"mass_kg": self.mass_kg, "mass_std_kg": self.mass_std_kg, "damping_n_s_m": self.damping_n_s_m,
                "presliding_stiffness_n_m": self.stiffness_n_m, "presliding_stiffness_std_n_m": self.stiffness_std_n_m,
                "presliding_resonance_hz": self.presliding_resonance_hz, "delay_s": self.delay_s,
                "delay_std_s": self.delay_std_s, "rms_log_error": self.rms_log_error,
                "unmodelled_resonances_hz": self.resonances_hz, "fit_band_hz": [self.f_lo_hz, None],
                "mass_from": self.mass_from}


def _fit_band(frf: Frf, sel: npt.NDArray[np.bool_], period_s: float, mass_guess_kg: float
              ) -> tuple[FloatArray, FloatArray, float, int]:
    """Least-squares ``m, c, k, τ`` on the lines ``sel``; returns (θ, std(θ), rms log error, lines)."""
    fo, po = frf.f_hz[sel], frf.p[sel]
    wo = 1.0 / np.clip(frf.p_std[sel] / np.maximum(np.abs(po), 1e-300), 1e-3, 1.0)

    def model(th: FloatArray) -> ComplexArray:
        return plant_response(fo, math.exp(th[0]), th[1], th[2], th[3], period_s)

    def logres(th: FloatArray) -> ComplexArray:
        with np.errstate(divide="ignore", invalid="ignore"):  # a trial θ whose model is 0 or inf: an inf residual
            r = np.log(po / model(th))
        return np.asarray(r.real + 1j * np.angle(np.exp(1j * r.imag)), np.complex128)

    def resid(th: FloatArray) -> FloatArray:
        r = logres(th)
        return np.concatenate([r.real * wo, r.imag * wo])

    best = None
    for k0 in (0.0, mass_guess_kg * (2 * math.pi * float(np.median(fo)) / 3) ** 2):
        th0 = np.array([math.log(mass_guess_kg), 0.0, k0, period_s])
        scale = np.array([1.0, max(mass_guess_kg * 10.0, 1e-3), max(mass_guess_kg * 1e4, 1.0), period_s])
        sol = least_squares(resid, th0, bounds=([-30, 0.0, 0.0, 0.0], [30, np.inf, np.inf, 0.1]), x_scale=scale)
        if best is None or sol.cost < best.cost:
            best = sol
    assert best is not None
    n = best.fun.shape[0]
    s2 = 2 * best.cost / max(n - 4, 1)
    sd = np.sqrt(np.clip(np.diag(np.linalg.pinv(best.jac.T @ best.jac) * s2), 0, None))
    rms = float(np.sqrt(np.mean(np.abs(logres(best.x)) ** 2)))
    return best.x, sd, rms, int(sel.sum())


def fit_plant(frf: Frf, period_s: float, mass_guess_kg: float) -> PlantFit:
    """Fit ``m, c, k, τ`` to the measured FRF (module docstring), in two passes: over every well-measured line,
    which locates the pre-sliding resonance ``f0``, then over the lines above ``max(FIT_ABOVE_F0·f0,
    MASS_BAND_X_PERIOD/T)`` (at most from ``0.3/T``; repeated while the band moves up), where the rigid-body mass dominates and the hysteretic pre-sliding (a spring only to
    first order) no longer biases it."""
    f, p = frf.f_hz, frf.p
    ok = frf.p_std / np.maximum(np.abs(p), 1e-300) < 0.3
    if ok.sum() < 6:
        raise StageError(f"frf: only {int(ok.sum())} lines measured with < 30 % uncertainty; raise the excitation "
                         "(--max-force) or check the sensor")
    th, sd, rms, _ = _fit_band(frf, ok, period_s, mass_guess_kg)
    f_lo = float(f[ok].min())
    band = ok
    for _ in range(4):  # the band moves up with the resonance each refit finds (a hysteretic spring is stiffer
        f0 = math.sqrt(max(th[2], 0.0) / math.exp(th[0])) / (2 * math.pi)  # at the smaller high-f amplitudes)
        lo = min(max(FIT_ABOVE_F0 * f0, f_lo, MASS_BAND_X_PERIOD / period_s), 0.3 / period_s)
        nb = ok & (f >= lo)
        if lo <= f_lo or nb.sum() < 6:
            break
        f_lo, band = lo, nb
        th, sd, rms, _ = _fit_band(frf, band, period_s, math.exp(th[0]))
    m = math.exp(th[0])
    full = plant_response(f, m, th[1], th[2], th[3], period_s)
    ratio = np.abs(p / full)
    lin = frf.linear_lines()
    res = [float(fi) for fi, r, good, li in zip(f, ratio, band, lin) if good and li and r > RESONANCE_RATIO]
    return PlantFit(m, m * float(sd[0]), float(th[1]), float(th[2]), float(sd[2]), float(th[3]), float(sd[3]), rms,
                    res, f_lo)


# ================================================================================================ friction
@dataclass
class CvSegment:
    v_m_s: float
    f_n: float
    f_std_n: float
    n: int
    stuck_fraction: float = 0.0  # share of the pass's samples in which the stage stood (stick-slip)
    #: the pass's speed over short windows [m/s] (:func:`cv_segments`), for the ripple correction of
    #: :func:`cv_friction`; None when not measured
    v_window: FloatArray | None = field(default=None, repr=False, compare=False)
    #: the pass stick-slipped (its short-window speed fell to ``STUCK_SPEED_FRACTION`` of its mean) and was read
    #: from its sliding phases only: ``v_m_s``, ``f_n`` and ``v_window`` are theirs (:func:`_sliding_phases`),
    #: this their share of the pass's samples; 1.0 for a pass read whole
    sliding_fraction: float = 1.0
    #: the pass's mean speed over its whole window [m/s] when it was read from its sliding phases, else 0
    v_pass_m_s: float = 0.0


#: a pass in which the stage covers less than STUCK_SPEED_FRACTION of the reference's travel over
#: STUCK_WINDOW samples is standing there; a pass that stands in more than STUCK_PASS_FRACTION of its samples
#: is stick-slip, not sliding (see :func:`cv_segments`)
STUCK_WINDOW = 5
STUCK_SPEED_FRACTION = 0.25
STUCK_PASS_FRACTION = 0.1
#: a pass's speed ripple is read over at least RIPPLE_WINDOW samples, and over at least RIPPLE_MIN_QUANTA sensor
#: quanta of travel (its quantisation noise then ≲ 2 % of the speed) (:func:`cv_segments`, :func:`cv_friction`)
RIPPLE_WINDOW = 5
RIPPLE_MIN_QUANTA = 20.0
#: the ripple correction's fixed-point iterations (:func:`cv_friction`)
RIPPLE_ITERATIONS = 3
#: a pass's mean is corrected for its ripple (:func:`cv_friction`) only when the standard deviation of its
#: short-window speed exceeds this fraction of its mean speed: the cogging ripples a settled pass by 5-15 %, a
#: ringing one by 25-55 %; below it the correction is a fraction of a mN and the fit is left as it was. A pass
#: whose short-window speed falls to STUCK_SPEED_FRACTION of its mean nearly stands at times (generated plant
#: 34's −0.16 mm/s pass: 0…3.6× its mean speed): corrected over the whole pass, the curve there runs through the
#: static break-away and the correction is of the order of Fs − Fc (its cosine 1.6 → 8.1× exact); such a pass
#: is read from its sliding phases instead (:func:`_sliding_phases`), where the correction holds
RIPPLE_MIN_FRACTION = 0.2
#: the odd Stribeck curve's parameters (Fc, Fs, vs, δ, Fv): :func:`cv_friction` fits it to at least as many pairs
STRIBECK_PARAMETERS = 5
#: the + and − passes of one designed speed are paired when their measured speeds differ by at most this
#: fraction (:func:`odd_points`)
CV_PAIR_TOLERANCE = 0.2
#: offset (:func:`offset_evidence`): two-sided confidence of the t-test on the pairs' even parts, fewest
#: pairs, the largest ratio between the slow passes' even part and the constant-velocity passes' (either
#: way; the factor 2 the cogging's two directions must agree within), and the largest force change along
#: the slow passes' travel from their slope over the offset's size
OFFSET_CONFIDENCE = 0.99
OFFSET_MIN_PAIRS = 3
OFFSET_AGREEMENT = 2.0
OFFSET_SLOPE_SHARE = 1.0


def cv_segments(t: FloatArray, x: FloatArray, u: FloatArray, v_ref: FloatArray, a_ref: FloatArray,
                mass_kg: float, min_samples: int = 50, speeds: FloatArray | None = None,
                dropped: list[CvSegment] | None = None, delay_s: float = 0.0,
                position_force_n: FloatArray | None = None,
                cogging: tuple[float, float] | None = None, quantum_m: float = 0.0) -> list[CvSegment]:
    """Steady constant-velocity segments (``a_ref = 0``, ``v_ref ≠ 0``), each trimmed by 20 % at both ends;
    mean force ``ū − m·ā`` with its standard error (from the sample spread, decorrelated over 20 samples).
    With ``speeds`` [m/s] only segments whose ``|v_ref|`` is one of them (relative 1e-6): the passes, not
    the repositioning moves between them. Those run one way only, so an offset and the cogging over their
    range do not cancel, and they are short: on a 0.69 kg stage with 35 N s/m the 8 mm/s repositioning
    cruise (36 samples) read 54 mN off the true curve, every pass within 1 mN, and the fit's Coulomb came
    out 10 % low and its viscous 9 % high. With ``speeds``, a speed is kept only when both directions are
    (the cogging and offset over the pass's range then enter both means alike and cancel in the odd part
    ``Fc·sgn(v) + Fv·v`` the fit reads).

    With ``speeds``, a pass also needs ``min_samples`` after the trims (not before): the loop's transient
    after the reference's acceleration ends must be well behind. The fastest pass of an 8.9 kg stage (50
    samples at 16 mm/s) never settled: its speed went 2.6 % over and 1.7 % under, its force mean read 32 mN
    (2 %) high in both directions, and the fit's viscous came out 14 % high. A speed criterion cannot tell
    it: the cogging ripples the speed of settled passes by 5-7 %. A fixed settling time (five crossover
    periods over 2π, 53 ms) cannot either: it also dropped the 16 mm/s passes of light stages, which had
    settled within 4 mN, and without them the Stribeck tail and the viscous term traded (viscous −45 % on a
    0.60 kg stage with vs 2.9 mm/s).

    A pass in which the stage stick-slips is not a point of the sliding curve and is dropped (appended to
    ``dropped`` when given): its mean force averages the stuck phases, where the friction is whatever the
    controller pushes below break-away, with slips at several times the pass's speed. The test: over
    ``STUCK_WINDOW`` samples the stage covers less than ``STUCK_SPEED_FRACTION`` of the reference's travel
    in more than ``STUCK_PASS_FRACTION`` of the pass (a sliding pass, cogging included, never does: its speed
    ripples by 5-7 %). Generated plant 36 (0.97 kg, Fs 0.78 N, vs 0.49 mm/s, cogging 0.09 N): its 0.16 and
    0.40 mm/s passes stood in 69 % and 46 % of their samples and read 0.68 N where the sliding curve is 0.76
    and 0.70 N; the curve fitted through them (δ = 4 at its bound, vs 0.83 mm/s) made the cosine 700× the
    exact model's.

    ``delay_s``: the force's delay from command to stage [s] (I/O delay plus half a period of zero-order hold):
    the mean force is read from ``u(t − τ)``, the force acting while the stage is at ``x(t)``. Read at ``u(t)``,
    a position force ``P(x)`` enters a pass as ``P(x + v·τ)``: its odd part ``τ·v·P'`` is a viscous force in
    disguise. A 445 N/m spring with 1.5 ms put 10 mN into the 16 mm/s pair's odd part (``k·v·τ``), and a 0.29 N,
    0.51 mm cogging over 1.6 periods of the 16 mm/s pass 21 mN (tests/commission/plant_kinds.py k111,
    plant_gen.py 34: viscous +48 %, Stribeck vs −10 %); aligned, both within 2 mN.

    ``position_force_n``: the position force at ``x`` [N] (the slow passes' cogging and spring), taken off
    before the means: the + and − windows of a short fast pass do not cover the same range (52 samples at
    16 mm/s: −402…+421 µm and +404…−406 µm), and a 0.29 N cogging's means there differed by 9 mN of odd part
    (generated plant 34: viscous +3.7 %).

    ``cogging``: its ``(wavelength_m, phase_rad)`` (``A·sin(2πx/λ + φ)``) when one is taken off. Each pass's
    window is then narrowed to the longest one centred on an extremum of the cogging
    (:func:`_cogging_symmetric_window`): the force's delay enters a pass's mean as ``dτ·(u_end − u_start)/T_window``, and the controller's
    force follows the cogging, so a window shorter than a period whose ends sit at different cogging levels
    reads ``dτ·v·(P(x_end) − P(x_start))/L``, a viscous force. Fresh plant k106 (0.42 N, 1.35 mm cogging over
    ~1 mm windows, FRF delay 1.35 ± 0.23 ms for 1 ms): viscous +16 %, and −4…+20 % for τ of 1–2 ms; with
    windows ending at equal cogging levels +5.5 % (+5…+8 %). A phase error of the fitted cogging cancels there
    too (its residual is odd about the extremum).

    With ``speeds``, each pass keeps its speed over ``w`` samples, ``(x[k+w] − x[k])/(w·dt)``
    (``CvSegment.v_window``) when their standard deviation exceeds ``RIPPLE_MIN_FRACTION`` of its mean speed
    (the pass rings) and it never falls to ``STUCK_SPEED_FRACTION`` of it, ``w`` at least ``RIPPLE_WINDOW`` and
    long enough to cover ``RIPPLE_MIN_QUANTA`` sensor quanta ``quantum_m`` [m] at the pass's speed, for
    :func:`cv_friction`'s ripple correction. A pass whose speed over ``w`` samples does fall to
    ``STUCK_SPEED_FRACTION`` of its mean, but that stood in no more than ``STUCK_PASS_FRACTION`` of its
    samples (above), is read from its sliding phases instead (:func:`_sliding_phases`: ``v_m_s``, ``f_n``
    and ``v_window`` are theirs, ``sliding_fraction`` < 1)."""
    out: list[CvSegment] = []
    if delay_s > 0.0 and len(u) > 1:
        uu = np.asarray(u, np.float64)
        ii = np.arange(uu.shape[0], dtype=np.float64)
        # u(t − τ); the first τ hold the first value
        u = np.interp(ii - delay_s / float(np.median(np.diff(np.asarray(t, np.float64)))), ii, uu)
    if position_force_n is not None:
        u = np.asarray(u, np.float64) - position_force_n
    steady = (np.abs(a_ref) < 1e-12) & (np.abs(v_ref) > 0)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], steady.astype(np.int8), [0]])))
    dt = float(np.median(np.diff(t)))
    for i0, i1 in zip(edges[::2], edges[1::2]):
        n = i1 - i0
        if n < min_samples:
            continue
        if speeds is not None and not np.any(np.abs(abs(float(v_ref[i0])) / speeds - 1.0) < 1e-6):
            continue
        j0, j1 = i0 + n // 5, i1 - n // 5
        if speeds is not None and j1 - j0 < min_samples:  # too short to have settled
            continue
        if cogging is not None:
            j0, j1 = _cogging_symmetric_window(x, j0, j1, *cogging)
        vel = (x[j1 - 1] - x[j0]) / (t[j1 - 1] - t[j0])
        acc = np.gradient(np.gradient(x[j0:j1], dt), dt)
        f = u[j0:j1] - mass_kg * acc
        se = float(np.std(f) / math.sqrt(max((j1 - j0) / 20.0, 1.0)))
        w = STUCK_WINDOW
        ahead = np.sign(v_ref[j0]) * (x[j0 + w:j1] - x[j0:j1 - w]) if j1 - j0 > w else np.zeros(1)
        stuck = float(np.mean(ahead < STUCK_SPEED_FRACTION * abs(float(v_ref[j0])) * w * dt))
        seg = CvSegment(float(vel), float(np.mean(f)), se, int(j1 - j0), stuck)
        if speeds is not None and abs(vel) > 0.0:
            ww = max(RIPPLE_WINDOW, math.ceil(RIPPLE_MIN_QUANTA * max(quantum_m, 0.0) / (abs(vel) * dt)))
            if j1 - j0 >= 4 * ww:
                vw = (x[j0 + ww:j1] - x[j0:j1 - ww]) / (ww * dt)
                rel = vw / float(vel)
                if float(np.min(rel)) <= STUCK_SPEED_FRACTION:
                    if stuck <= STUCK_PASS_FRACTION:  # (a pass that stood longer is dropped below)
                        seg = _sliding_phases(seg, f, vw, rel, ww, min_samples)
                elif float(np.std(rel)) > RIPPLE_MIN_FRACTION:
                    seg.v_window = vw
        if stuck > STUCK_PASS_FRACTION:
            if dropped is not None:
                dropped.append(seg)
            continue
        out.append(seg)
    if speeds is not None:  # both directions of each speed, or neither
        def key(sg: CvSegment) -> int:
            return int(np.argmin(np.abs(np.log(abs(sg.v_m_s) / speeds))))
        ways = {(key(sg), sg.v_m_s > 0) for sg in out}
        out = [sg for sg in out if (key(sg), sg.v_m_s <= 0) in ways]
    return out


def _sliding_phases(seg: CvSegment, f: FloatArray, vw: FloatArray, rel: FloatArray, ww: int,
                    min_samples: int) -> CvSegment:
    """A pass that stick-slips, read from its sliding phases (:func:`cv_segments`). Its short-window speed
    ``vw`` [m/s] (windows of ``ww`` samples) falls to ``STUCK_SPEED_FRACTION`` of its mean ``v̄`` at times: the
    stage stands, the friction there is whatever the loop pushes below break-away, and a slip follows at up to
    several times ``v̄``. The pass's mean force is then neither the curve at ``v̄`` nor the ripple correction's
    ``mean F(v(t))`` (a standing window reads ``F̂(0)``). Only the samples whose centred window runs faster than
    ``STUCK_SPEED_FRACTION·v̄`` count: the friction ``f = u(t − τ) − m·a`` [N] averaged over them, at their mean
    window speed, with those window speeds as ``v_window`` for :func:`cv_friction`'s correction (``mean F̂(v_w)
    − F̂(v̄_slide)``), which then always applies. Each sliding phase starts and ends near the threshold speed,
    so ``m·a`` averages out over it and an error of the mass does not enter. A plain stage with a 22 Hz loop
    (``tests/commission/test_stick_slip_passes.py``) stood in 6-8 % of its 1 mm/s passes (``v_s`` 1.06 mm/s):
    their whole means read 16 mN above the curve and the fitted ``v_s`` came out +11 %, the viscous +14 %;
    read from their sliding phases, within 2 %. ``seg`` unchanged (read whole) when fewer than ``min_samples``
    slide."""
    h = ww // 2
    slide = np.zeros(f.shape[0], bool)
    slide[h:h + rel.shape[0]] = rel > STUCK_SPEED_FRACTION
    ok = rel > STUCK_SPEED_FRACTION
    if int(slide.sum()) < min_samples or int(ok.sum()) < 4:
        return seg
    fs = f[slide]
    n = int(slide.sum())
    return CvSegment(float(np.mean(vw[ok])), float(np.mean(fs)), float(np.std(fs) / math.sqrt(max(n / 20.0, 1.0))),
                     n, seg.stuck_fraction, np.asarray(vw[ok], np.float64), n / f.shape[0], seg.v_m_s)


#: a pass's window centred on a cogging extremum is used when it keeps at least this many samples; a fraction
#: of the window instead (20 %) kept one direction of a pair and narrowed the other, and their odd part mixed
#: the two (generated plant 36: viscous −3.9 % against −0.9 %)
COGGING_WINDOW_MIN_SAMPLES = 8


def _cogging_symmetric_window(x: FloatArray, j0: int, j1: int, wavelength_m: float, phase_rad: float
                              ) -> tuple[int, int]:
    """The longest sub-window of ``x[j0:j1]`` (one pass, monotonic) centred on an extremum of
    ``sin(2πx/λ + φ)`` (``2πx/λ + φ = π/2 + kπ``), whose two ends sit at the same cogging level; ``(j0, j1)``
    unchanged when none keeps :data:`COGGING_WINDOW_MIN_SAMPLES` (:func:`cv_segments`)."""
    if not (wavelength_m > 0.0 and math.isfinite(wavelength_m) and math.isfinite(phase_rad)) or j1 - j0 < 8:
        return j0, j1
    xs = x[j0:j1]
    lo, hi = float(np.min(xs)), float(np.max(xs))
    w = 2.0 * math.pi / wavelength_m
    k_lo = math.floor((w * lo + phase_rad - 0.5 * math.pi) / math.pi)
    k_hi = math.ceil((w * hi + phase_rad - 0.5 * math.pi) / math.pi)
    best: tuple[float, float] | None = None  # (centre, half-length) [m]
    for k in range(k_lo, k_hi + 1):
        e = (0.5 * math.pi + k * math.pi - phase_rad) / w
        h = min(e - lo, hi - e)
        if h > 0.0 and (best is None or h > best[1]):
            best = (e, h)
    if best is None:
        return j0, j1
    sel = np.flatnonzero((xs >= best[0] - best[1]) & (xs <= best[0] + best[1]))
    if sel.size < COGGING_WINDOW_MIN_SAMPLES:
        return j0, j1
    return j0 + int(sel[0]), j0 + int(sel[-1]) + 1


@dataclass
class CvFriction:
    coulomb_n: float
    coulomb_std_n: float
    viscous_n_s_m: float
    viscous_std_n_s_m: float
    offset_n: float
    offset_std_n: float
    segments: list[CvSegment]
    used: int
    stribeck: dict[str, float] | None = None
    #: the (velocity [m/s], force [N]) points the curve was fitted to: the pairs' odd parts mirrored
    points: tuple[FloatArray, FloatArray] | None = None
    #: the position force taken off the passes (the slow passes' slope [N/m] and cogging), None before
    position_force: dict[str, Any] | None = None
    #: the points' standard errors [N] the curve was weighted with (:func:`stribeck_point_errors`), None when
    #: the plain fit stood
    points_sigma: FloatArray | None = None
    #: the points' standard errors [N] about the curve (the weights when weighted), for tests on it
    points_error: FloatArray | None = None
    #: what the Stribeck shape leaves open of Fc and Fv (:func:`_stribeck_shape`), None where not profiled
    shape: dict[str, Any] | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"coulomb_n": self.coulomb_n, "coulomb_std_n": self.coulomb_std_n,
                "viscous_n_s_m": self.viscous_n_s_m, "viscous_std_n_s_m": self.viscous_std_n_s_m,
                "offset_n": self.offset_n, "offset_std_n": self.offset_std_n, "segments_used": self.used,
                "stribeck_curve": self.stribeck, "stribeck_shape": self.shape, "position_force": self.position_force,
                "segments": [{"v_m_s": s.v_m_s, "f_n": s.f_n, "f_std_n": s.f_std_n, "samples": s.n,
                              **({"stick_slip": True, "sliding_fraction": s.sliding_fraction,
                                  "pass_v_m_s": s.v_pass_m_s} if s.sliding_fraction < 1.0 else {})}
                             for s in self.segments]}

    def stick_slip_read(self) -> list[CvSegment]:
        """The passes that stick-slipped and were read from their sliding phases (:func:`_sliding_phases`)."""
        return [s for s in self.segments if s.sliding_fraction < 1.0]


def odd_points(segs: list[CvSegment], tol: float = CV_PAIR_TOLERANCE,
               errors: list[float] | None = None,
               pairs: list[tuple[CvSegment, CvSegment]] | None = None) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The passes paired by speed: for each + segment the − segment of the nearest speed (relative difference
    at most ``tol``), each used once. Returns the mean speeds ``(|v₊| + |v₋|)/2`` [m/s], the odd parts
    ``(F₊ − F₋)/2`` and the even parts ``(F₊ + F₋)/2`` [N] (:func:`cv_friction`). ``errors``, when given,
    gets each pair's standard error of its odd part, ``√(σ₊² + σ₋²)/2`` [N] (the segments' ``f_std_n``);
    ``pairs``, when given, each pair's two segments ``(+, −)`` in the same order."""
    pos = sorted((s for s in segs if s.v_m_s > 0), key=lambda s: s.v_m_s)
    neg = [s for s in segs if s.v_m_s < 0]
    vk: list[float] = []
    fo: list[float] = []
    fe: list[float] = []
    for p in pos:
        if not neg:
            break
        q = min(neg, key=lambda s: abs(-s.v_m_s / p.v_m_s - 1))
        if abs(-q.v_m_s / p.v_m_s - 1) <= tol:
            neg.remove(q)
            vk.append(0.5 * (p.v_m_s - q.v_m_s))
            fo.append(0.5 * (p.f_n - q.f_n))
            fe.append(0.5 * (p.f_n + q.f_n))
            if errors is not None:
                errors.append(0.5 * math.hypot(p.f_std_n, q.f_std_n))
            if pairs is not None:
                pairs.append((p, q))
    return np.array(vk), np.array(fo), np.array(fe)


def stribeck_curve_at(curve: dict[str, float], v: FloatArray) -> FloatArray:
    """A fitted curve's force [N] at speeds ``v`` [m/s]: ``sgn(v)(Fc + (Fs − Fc)·exp(−|v/vs|^δ)) + Fv·v + F0``
    (``offset_n`` F0 when the curve has one)."""
    e = np.exp(-np.abs(v / curve["vs_m_s"]) ** curve["delta"])
    return np.asarray(np.sign(v) * (curve["fc_n"] + (curve["fs_n"] - curve["fc_n"]) * e)
                      + curve["viscous_n_s_m"] * v + float(curve.get("offset_n", 0.0)), dtype=np.float64)


def stribeck_point_errors(curve: dict[str, float], v: FloatArray, f: FloatArray, se: FloatArray) -> FloatArray:
    """Each point's standard error for the weighted Stribeck fit [N]: ``√(se_i² + s²)``, ``se_i`` its
    mean's sampling error (``f_std_n`` of the pair's segments) and ``s`` the scatter the sampling errors do
    not explain, robustly from the unweighted ``curve``'s residuals (``1.4826·median|r|``, at least 10⁻⁶ of the
    largest force): a position force's residue or the delay's differs from pass to pass alike. A pass whose
    force wandered (a start that stuck, a disturbance) has a large ``se_i`` and counts little; where all
    sampling errors are small the fit stays the unweighted one."""
    r = f - stribeck_curve_at(curve, v)
    s = max(1.4826 * float(np.median(np.abs(r))), 1e-6 * float(np.max(np.abs(f))), 1e-12)
    return np.sqrt(np.asarray(se, np.float64) ** 2 + s * s)


#: family-wise false-alarm rate of the Stribeck outlier test (:func:`stribeck_outlier_limit`)
STRIBECK_OUTLIER_ALPHA = 0.01
#: a pair set aside keeps this many times the largest kept error (:func:`_stribeck_without_outliers`)
STRIBECK_SET_ASIDE = 1e4


def stribeck_outlier_z(curve: dict[str, float], v: FloatArray, f: FloatArray, sigma: FloatArray) -> float:
    """The largest normalised residual ``max |f_i − F(v_i)|/σ_i`` of a fitted curve (:func:`stribeck_point_errors`)."""
    return float(np.max(np.abs(f - stribeck_curve_at(curve, v)) / sigma))


def stribeck_outlier_limit(pairs: int) -> float:
    """The two-sided normal quantile ``z`` with ``P(max_i |Z_i| > z) = STRIBECK_OUTLIER_ALPHA`` over ``pairs``
    independent points (Šidák): 3.0 for 6 pairs. Below it the unweighted curve is consistent with the points'
    errors and stays; above it one pair lies where no error explains it (:func:`cv_friction`)."""
    from scipy.stats import norm

    p = 1.0 - (1.0 - STRIBECK_OUTLIER_ALPHA) ** (1.0 / max(int(pairs), 1))
    return float(norm.ppf(1.0 - 0.5 * p))


def _stribeck_without_outliers(v: FloatArray, f: FloatArray, se: FloatArray, sigma: FloatArray
                               ) -> tuple[dict[str, float], FloatArray, npt.NDArray[np.bool_]]:
    """The weighted Stribeck curve (``sigma``: :func:`stribeck_point_errors` of the plain curve), then, while
    a pair lies beyond :func:`stribeck_outlier_limit` of the weighted curve and more than
    ``STRIBECK_PARAMETERS`` pairs are left, the farthest pair set aside (its points' errors made
    ``STRIBECK_SET_ASIDE`` times the largest) and the curve refitted, the errors from its residuals. ``v, f,
    se``: the mirrored pairs (``+`` half first). A pass's mean moved by a disturbance over part of its window
    lies several of its own standard errors off (a step of ``A`` over half of ``n`` samples: ``A/2`` against
    ``A/(2√(n/20))``); weighting alone still bends the curve toward it. Returns the curve, the errors
    used and which pairs were kept."""
    from stagectl.ident.identify import fit_stribeck_curve

    n = v.size // 2
    curve = fit_stribeck_curve(v, f, sigma_n=sigma)
    kept = np.ones(n, bool)
    for _ in range(n):
        k2 = np.concatenate([kept, kept])
        sg = np.full(v.size, np.inf)
        sg[k2] = stribeck_point_errors(curve, v[k2], f[k2], se[k2])
        z = (np.abs(f - stribeck_curve_at(curve, v)) / sg)[:n]
        j = int(np.argmax(z))
        if z[j] <= stribeck_outlier_limit(int(kept.sum())) or int(kept.sum()) <= STRIBECK_PARAMETERS:
            break
        kept[j] = False
        k2 = np.concatenate([kept, kept])
        sigma = np.where(k2, sg, STRIBECK_SET_ASIDE * float(np.max(sg[k2])))
        curve = fit_stribeck_curve(v, f, sigma_n=sigma)
    curve["set_aside_pairs"] = float(n - int(kept.sum()))
    return curve, sigma, kept


#: the Stribeck shape exponents δ the passes' profile tries (:func:`_stribeck_shape`), the one held where the
#: passes do not tell (the Gaussian curve, the most common shape and the shipped models'), and the rise of the
#: points' χ² that still counts as allowed (χ²₁ at 95 %: the profile-likelihood interval of δ)
STRIBECK_DELTA_PROFILE = (0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0)
STRIBECK_DELTA_DEFAULT = 2.0
STRIBECK_SHAPE_CHI2 = 3.84
#: the curve holding δ is weighted by the points' errors (as the profile is) where the largest exceeds this
#: many times their median, else fitted as the free curve was (:func:`_stribeck_shape`)
STRIBECK_UNEVEN_ERRORS = 10.0
#: ... and replaces the free curve only where that moves its Fc or Fv by more than this fraction: below it the
#: shape costs the identification little (the ranges still enter the standard errors) and the fit stays the
#: one it was (a 0.3 N cogging's passes, ±10 mN: Fv −14 % free, −15 % held)
STRIBECK_HOLD_MIN_CHANGE = 0.05


def _shape_std(value: float, rng: list[float]) -> float:
    """A standard error [unit of ``value``] from the 95 % range ``rng`` the Stribeck shape allows
    (:func:`_stribeck_shape`): the larger distance from ``value`` to its ends over 1.96."""
    return max(abs(value - float(rng[0])), abs(float(rng[1]) - value)) / 1.96


def _stribeck_shape(v: FloatArray, f: FloatArray, curve: dict[str, float], err: FloatArray
                    ) -> tuple[dict[str, float], dict[str, Any]]:
    """The Stribeck curve's shape exponent δ where the passes do not fix it, and what it leaves open of Fc
    and Fv (:func:`_cv_friction_once`). ``v, f``: the pairs' odd parts mirrored; ``err``: their standard
    errors (:func:`stribeck_point_errors`); ``curve``: the free curve fitted to them.

    The curve has five parameters (Fc, Fs, vs, δ, Fv). Where only one or two pairs lie beyond the dip
    (``|v| ≳ 2.5·vs``), its tail and the viscous term trade: a shallower, wider tail with a lower Fc and a
    steeper Fv passes through the same points. Generated plant 72 (11 kg, Fc 0.304 N, Fs 0.325 N, vs 2.7 mm/s,
    δ 2, Fv 30.3 N s/m; its 16 mm/s pair too short to read, five pairs left at 0.16-6.4 mm/s): the free curve
    went through all five within 10⁻⁸ N with δ 1.47, vs 3.9 mm/s, Fc −14 %, Fv +18 % and reported ±0.01 %;
    plant 75 (1.1 kg, vs 2.0 mm/s, one pair beyond the dip read over 15 samples of a cogging-centred window,
    ±4 mN): Fv +17 %. So the curve is fitted with δ held at each of ``STRIBECK_DELTA_PROFILE`` (weighted by
    ``err``); the shapes whose χ² over the pairs lies within ``STRIBECK_SHAPE_CHI2`` of the best are the ones
    the passes allow. Where ``STRIBECK_DELTA_DEFAULT`` is among them and holding it moves Fc or Fv by more
    than ``STRIBECK_HOLD_MIN_CHANGE``, the curve holding it is returned (plants 72 and 75: χ² +0.01 and +0.5;
    Fc +0.6 % and 0.0 %, Fv −1.0 % and +2.0 %), else ``curve``.
    The Fc and Fv of the allowed shapes are returned as their ranges (``coulomb_range_n``,
    ``viscous_range_n_s_m``: the standard errors include them, and the report says when they exceed
    ``SHAPE_WARN_FRACTION``), with ``delta_range`` and ``delta_held``."""
    from stagectl.ident.identify import fit_stribeck_curve

    n = v.size // 2

    def chi2(c: dict[str, float]) -> float:  # (the points are odd parts mirrored: no offset)
        r = (f - stribeck_curve_at(dict(c, offset_n=0.0), v)) / err
        return float(np.sum(r[:n] ** 2))

    fits: list[dict[str, float]] = [fit_stribeck_curve(v, f, sigma_n=err)]
    for d in STRIBECK_DELTA_PROFILE:
        try:
            fits.append(fit_stribeck_curve(v, f, delta=d, sigma_n=err))
        except (StageError, ValueError):
            continue
    c2 = [chi2(c) for c in fits]
    best = min(c2 + [chi2(curve)])
    ok = [c for c, x in zip(fits, c2) if x <= best + STRIBECK_SHAPE_CHI2]
    held = [c for c, x in zip(fits[1:], c2[1:]) if c.get("stribeck_identified")
            and abs(float(c["delta"]) - STRIBECK_DELTA_DEFAULT) < 1e-6 and x <= best + STRIBECK_SHAPE_CHI2]
    chosen = curve
    if held and abs(float(curve["delta"]) - STRIBECK_DELTA_DEFAULT) > 1e-6:
        # fitted as the free curve was (weighted only where it was, or where one pair's error stands far
        # above the others': a fast pair read over few samples, plant 75)
        weigh = bool(curve.get("weighted")) or float(np.max(err[:n])) > STRIBECK_UNEVEN_ERRORS * float(np.median(err[:n]))
        h = held[0] if weigh else fit_stribeck_curve(v, f, delta=STRIBECK_DELTA_DEFAULT)
        moved = max(abs(float(h["fc_n"]) / max(float(curve["fc_n"]), 1e-12) - 1.0),
                    abs(float(h["viscous_n_s_m"]) / max(float(curve["viscous_n_s_m"]), 1e-12) - 1.0))
        if h.get("stribeck_identified") and moved > STRIBECK_HOLD_MIN_CHANGE:
            chosen = dict(h, **{k: curve[k] for k in ("set_aside_pairs",) if k in curve})
    ok.append(chosen)
    if chi2(curve) <= best + STRIBECK_SHAPE_CHI2:  # the free curve as it was fitted, where the points allow it
        ok.append(curve)
    ds = [float(c["delta"]) for c in ok if c.get("stribeck_identified")]
    shape: dict[str, Any] = {
        "coulomb_range_n": [min(float(c["fc_n"]) for c in ok), max(float(c["fc_n"]) for c in ok)],
        "viscous_range_n_s_m": [min(float(c["viscous_n_s_m"]) for c in ok),
                                max(float(c["viscous_n_s_m"]) for c in ok)],
        "delta_range": [min(ds), max(ds)] if ds else [],
        "chi2_rise_held": (chi2(chosen) - best) if chosen is not curve else 0.0,
        "delta_held": chosen is not curve,
        "free_delta": float(curve["delta"]), "free_coulomb_n": float(curve["fc_n"]),
        "free_viscous_n_s_m": float(curve["viscous_n_s_m"])}
    return chosen, shape


#: the report notes a Coulomb level or viscous coefficient whose range over the Stribeck shapes the passes
#: allow (:func:`_stribeck_shape`) reaches this fraction of it either way
SHAPE_WARN_FRACTION = 0.1


def shape_line(cv: CvFriction) -> str | None:
    """A line for the report when the passes do not separate the Coulomb level or the viscous coefficient
    from the Stribeck curve's shape (:func:`_stribeck_shape`), else None."""
    sh = cv.shape
    if sh is None:
        return None
    parts = []
    for name, val, key, unit in (("Coulomb", cv.coulomb_n, "coulomb_range_n", "N"),
                                 ("viscous", cv.viscous_n_s_m, "viscous_range_n_s_m", "N s/m")):
        lo, hi = sh[key]
        if val > 0.0 and max(val - lo, hi - val) >= SHAPE_WARN_FRACTION * val:
            parts.append(f"{name} {val:.4g} {unit} (shapes allowed: {lo:.4g}-{hi:.4g})")
    if not parts:
        return None
    dr = sh.get("delta_range") or []
    held = f"δ held at {STRIBECK_DELTA_DEFAULT:g}; " if sh.get("delta_held") else ""
    span = "" if not dr else (f"δ {dr[0]:.2g}-{dr[1]:.2g}" if dr[1] > 1.05 * dr[0] else f"δ ≈ {dr[0]:.2g}")
    return ("friction_cv: the passes do not separate the Stribeck tail from the viscous term ("
            + held + (f"curves with {span} fit them within χ² + {STRIBECK_SHAPE_CHI2:g}" if span else "")
            + "): " + "; ".join(parts) + "; the standard errors include this range. Faster or longer passes "
            "beyond the dip would tell them apart")


def cv_friction(segs: list[CvSegment]) -> CvFriction:
    """Friction from the segment means (:func:`_cv_friction_once`), corrected for the passes' speed ripple.
    A pass's mean force is the curve averaged over the speeds the stage ran at, ``mean F(v(t))``, not the curve
    at the mean speed ``F(v̄)``; they differ by ``≈ ½F''(v̄)·var(v)`` where the speed ripples on a curved part of
    the curve. Where the Stribeck slope ``dF/dv`` is about as negative as the loop's damping is positive the
    loop rings along the pass: fresh plant k106 (Fs 2.04 N, Fc 1.70 N, vs 1.06 mm/s, δ 2, a 35 Hz PID with
    276 N s/m) rang ±47 % at 1 mm/s, those passes read 17-19 mN above the curve in both directions, and the
    curve fitted through them had vs +9 % and the viscous +5.5 % (the cosine tracked 2.8× the exact model's).
    With each pass's speeds over short windows (``CvSegment.v_window``), each mean is corrected by
    ``mean F̂(v_w) − F̂(v̄)`` of the fitted curve ``F̂`` and the curve refitted, ``RIPPLE_ITERATIONS`` times (k106:
    vs +1 %, viscous −2 %). Only ringing passes carry ``v_window`` (:data:`RIPPLE_MIN_FRACTION`), and passes
    that stick-slip, read from their sliding phases (:func:`_sliding_phases`: their mean force and speed, their
    window speeds, standing ones left out); without any the fit is the plain one. The returned segments are the
    corrected ones."""
    cv = _cv_friction_once(segs)
    if not any(s.v_window is not None for s in segs):
        return cv
    for _ in range(RIPPLE_ITERATIONS):
        c = cv.stribeck
        if c is None:
            break
        c0 = dict(c, offset_n=0.0)
        fixed: list[CvSegment] = []
        for s in segs:
            corr = 0.0
            if s.v_window is not None and s.v_window.size:
                vv = np.asarray(s.v_window, np.float64)
                corr = float(np.mean(stribeck_curve_at(c0, vv))
                             - stribeck_curve_at(c0, np.array([s.v_m_s]))[0])
                if not math.isfinite(corr):
                    corr = 0.0
            fixed.append(CvSegment(s.v_m_s, s.f_n - corr, s.f_std_n, s.n, s.stuck_fraction, s.v_window,
                                   s.sliding_fraction, s.v_pass_m_s))
        cv = _cv_friction_once(fixed)
    return cv


def _cv_friction_once(segs: list[CvSegment]) -> CvFriction:
    """Friction from the segment means (module docstring). The + and − passes of a speed are paired
    (:func:`odd_points`) and the fit reads their odd part only: a position force over a pass's range
    (cogging, offset, spring) enters both means alike, so the odd part cancels it. Each pair has the
    designed speed, but the two measured means differ by up to a few % (generated stage k102 of
    ``tests/commission/plant_kinds.py``: 0.1591 vs 0.1599 mm/s, 15.94 vs 15.54 mm/s), and a curve fitted to
    the segments themselves could read a cogging's even part as odd: a 0.19 N, 0.68 mm cogging over the
    0.32 mm slowest passes put 0.16 N into their even part, and the curve took it with Fs = 6·10²⁷⁸ N at vs =
    25 µm/s (steep enough to tell 0.1591 from 0.1599 mm/s); the viscous came out −1.9 N s/m for a true 5.6
    and the commissioned stage faulted under its own feed-forward. The Stribeck curve
    (:func:`stagectl.ident.identify.fit_stribeck_curve`) is fitted where the data allow it to the odd points
    mirrored (``±v``, ``±F_odd``), then, with its excess removed, ``F_odd = Fc + Fv·|v|``; the offset is the
    mean even part. Fewer than two pairs (segments not from designed passes): every segment, with
    ``F = Fc·sgn(v) + Fv·v + F0``."""
    from stagectl.ident.identify import fit_stribeck_curve

    if len(segs) < 4:
        raise StageError(f"friction: {len(segs)} constant-velocity segments; need at least 4 (both directions)")
    pair_se: list[float] = []
    pair_segs: list[tuple[CvSegment, CvSegment]] = []
    vk, fo, fe = odd_points(segs, errors=pair_se, pairs=pair_segs)
    paired = vk.size >= 2
    sigma: FloatArray | None = None
    errors: FloatArray | None = None
    use = np.ones(vk.size, bool)  # the pairs the curve kept (_stribeck_without_outliers)
    if paired:
        v, f = np.concatenate([vk, -vk]), np.concatenate([fo, -fo])
    else:
        v, f = np.array([s.v_m_s for s in segs]), np.array([s.f_n for s in segs])
    stri: dict[str, float] | None = None
    try:
        stri = fit_stribeck_curve(v, f)
        if paired:
            sg = stribeck_point_errors(stri, v, f, np.concatenate([pair_se, pair_se]))
            errors = sg
            if stribeck_outlier_z(stri, v, f, sg) > stribeck_outlier_limit(vk.size):
                stri, sigma, use = _stribeck_without_outliers(v, f, np.concatenate([pair_se, pair_se]), sg)
                errors = sigma
    except (StageError, ValueError):
        stri = None
    vmax = float(np.max(np.abs(v)))
    shape: dict[str, Any] | None = None
    if (paired and stri is not None and errors is not None and stri.get("stribeck_identified")
            and not stri.get("fs_fixed") and stri["vs_m_s"] <= vmax and vk.size >= STRIBECK_PARAMETERS):
        stri, shape = _stribeck_shape(v, f, stri, errors)
    if stri is not None and v.size >= 3 and (stri["vs_m_s"] > vmax or (paired and vk.size < STRIBECK_PARAMETERS)):
        # a drop beyond the fastest pass is no Stribeck curve the passes measured, only a way to bend a nearly
        # straight line, and fewer pairs than the curve's parameters fit it exactly whatever the scatter: with
        # the slowest pairs left out as stick-slip, fresh plant k111's four pairs (1-16 mm/s, within 0.2 mN of
        # Fc + Fv·v once the spring was off) gave Fc 0.075 N, Fs 1.63 N, vs 92 mm/s, δ 4 for a true Fc 1.63 N;
        # four pairs on a line with 0.3 mN of scatter a vs of 12 mm/s and the viscous +4 %. The curve is then
        # flat (Fs = Fc), the line's; fit._refit_stribeck still refits it with Fs held at the pre-sliding level
        # where the slow passes stick-slipped. The pairs the curve set aside (_stribeck_without_outliers) stay out
        # of the line, as they do of the line below: the flat curve's Fc and Fv are the returned ones
        k2 = np.concatenate([use, use]) if paired else np.ones(v.size, bool)
        vl, fl = v[k2], f[k2]
        A_l = np.column_stack([np.sign(vl), vl, np.ones_like(vl)])
        th_l, *_ = np.linalg.lstsq(A_l, fl, rcond=None)
        r_l = fl - A_l @ th_l
        stri = {"fc_n": float(th_l[0]), "fs_n": float(th_l[0]), "vs_m_s": float(np.min(np.abs(vl))),
                "delta": 2.0, "viscous_n_s_m": float(th_l[1]), "offset_n": float(th_l[2]),
                "rms_n": float(np.sqrt(np.mean(r_l ** 2))), "segments": float(vl.size), "stribeck_identified": False,
                "v_min_m_s": float(np.min(np.abs(vl))), "fs_fixed": False, "beyond_fastest_vs_m_s": stri["vs_m_s"],
                **({"set_aside_pairs": stri["set_aside_pairs"]} if "set_aside_pairs" in stri else {})}

    def excess(vv: FloatArray) -> FloatArray:
        if stri is None:
            return np.zeros_like(vv)
        return np.asarray(np.sign(vv) * (stri["fs_n"] - stri["fc_n"])
                          * np.exp(-np.abs(vv / stri["vs_m_s"]) ** stri["delta"]), dtype=np.float64)

    if paired:
        # the pairs the curve set aside (_stribeck_without_outliers) are left out here too, from the line, the
        # offset and the standard errors alike: a disturbance over part of one pass moves that pass's mean, so
        # the pair's even part by half as much as its odd part (a 60 mN push on one slowest pass of six pairs
        # moved the offset by 5 mN), and its residual would count in every standard error
        # weighted by the points' errors where the curve's shape was chosen on them (_stribeck_shape): a short
        # fast pair read over few samples (plant 75: ±4 mN against ≤ 0.3 mN) then counts as little as in the curve
        wl = (1.0 / errors[:vk.size] if shape is not None and errors is not None and stri is not None
              and stri.get("weighted") else np.ones_like(vk))
        th, *_ = np.linalg.lstsq((wl[:, None] * np.column_stack([np.ones_like(vk), vk]))[use],
                                 (wl * (fo - excess(vk)))[use], rcond=None)
        off = float(np.mean(fe[use]))
        # standard errors as for every segment's own fit: the residual of each segment's mean against the odd
        # curve plus the offset (a position force's even part scatters them and counts), over the segments
        # less the curve's and the regression's parameters (a curve through 6 pairs leaves almost nothing)
        dropped = {id(sg) for k, pq in enumerate(pair_segs) if not use[k] for sg in pq}
        kept_segs = [sg for sg in segs if id(sg) not in dropped]
        va = np.array([sg.v_m_s for sg in kept_segs])
        fa = np.array([sg.f_n for sg in kept_segs])
        A = np.column_stack([np.sign(va), va, np.ones_like(va)])
        r = fa - excess(va) - A @ np.array([th[0], th[1], off])
        s2 = float(r @ r) / max(va.size - 3 - (4 if stri else 0), 1)
        sd = np.sqrt(np.clip(np.diag(np.linalg.pinv(A.T @ A) * s2), 0, None))
        if shape is not None:  # the shape's share: the curves the passes allow (_stribeck_shape)
            sd[0] = math.hypot(sd[0], _shape_std(float(th[0]), shape["coulomb_range_n"]))
            sd[1] = math.hypot(sd[1], _shape_std(float(th[1]), shape["viscous_range_n_s_m"]))
        if stri is not None:
            stri["offset_n"] = off
            if shape is not None and shape["delta_held"]:
                stri["delta_held"] = 1.0  # (fit._refit_stribeck keeps it)
        return CvFriction(float(th[0]), float(sd[0]), float(th[1]), float(sd[1]), off, float(sd[2]), segs,
                          int(2 * use.sum()), stri, (v, f), points_sigma=sigma, points_error=errors, shape=shape)
    A = np.column_stack([np.sign(v), v, np.ones_like(v)])
    th, *_ = np.linalg.lstsq(A, f - excess(v), rcond=None)
    r = f - excess(v) - A @ th
    s2 = float(r @ r) / max(v.size - 3 - (4 if stri else 0), 1)
    sd = np.sqrt(np.clip(np.diag(np.linalg.pinv(A.T @ A) * s2), 0, None))
    return CvFriction(float(th[0]), float(sd[0]), float(th[1]), float(sd[1]), float(th[2]), float(sd[2]), segs,
                      int(v.size), stri, (v, f))


def offset_evidence(segs: list[CvSegment], slow_even_n: float | None, slope_n_m: float,
                    span_m: float) -> dict[str, Any]:
    """Is there a constant force (an offset: gravity on an inclined axis, a cable's pull)? From the
    constant-velocity passes, confirmed by the slow passes over the stroke.

    The passes of each speed are paired (:func:`odd_points`); with a position force already taken off
    (:func:`cv_segments`' ``position_force_n``), the even part ``e_i = (F₊ + F₋)/2`` of pair ``i`` is what
    the stage needs whatever the direction. An offset ``F_0`` makes it

    * **significant**: ``t = ē/(s_e/√n) ≥ t_{(1+OFFSET_CONFIDENCE)/2, n−1}`` (Student's t over the ``n`` pairs'
      scatter ``s_e``: a position force left in the windows, which differ by speed, scatters them; the segments'
      own sample errors are far smaller and would count that residue as signal);
    * **speed-independent**: a constant fits the even parts better than a force proportional to the friction
      level, ``e_i = r·o_i`` with ``o_i = (F₊ − F₋)/2`` (a Coulomb/viscous asymmetry ``F·(1 + r·sgn F)``,
      whose even part grows with the friction as an offset's does not; docs/discovery.md §1). The pairs'
      friction levels differ by the viscous force and the Stribeck drop; where they hardly differ, both fit
      alike and the simpler effect, the offset, is named (docs/discovery.md §2). The joint fit
      ``e_i = F_0 + r·o_i`` gives the asymmetry ratio the passes allow, ``r̂ ± t_{(1+OFFSET_CONFIDENCE)/2, n−2}·σ_r``
      (``asymmetry_ratio``, ``asymmetry_std``, ``joint_t_needed``), against which a discovered asymmetry is
      checked (:func:`stagectl.commission.fit.fit_models`);
    * **position-independent**: the slow passes over the stroke (another experiment, other positions) measure
      the same even part, ``slow_even_n`` (same sign, within a factor ``OFFSET_AGREEMENT``), and their slope
      changes the force along their travel by at most ``OFFSET_SLOPE_SHARE``·|F_0| (a spring
      ``k·(x − x0)`` also has an even part at the passes' centre, but it changes along the stroke).

    ``F_0 = ē``. ``decided``: the passes settle the question, present (all three hold) or absent (not
    significant: the passes measure the even part to a fraction of a mN); an even part that follows the
    friction level, is not confirmed along the stroke or changes along it (or no slow passes, ``slow_even_n``
    None) is left to ``discover``'s asymmetry/spring/offset. Returns the decision (``present``), ``force_n``,
    its standard error, ``t`` and the quantile needed (``ratio`` = t over it, confidence ``high`` at twice the
    quantile), the even and odd parts, both one-parameter fits' residual sums of squares, the joint fit's
    constant and ratio with their t, and the reason when absent."""
    from scipy import stats

    _, fo, fe = odd_points(segs)
    n = int(fe.size)
    out: dict[str, Any] = {"present": False, "decided": False, "confidence": "none", "ratio": 0.0, "pairs": n,
                           "even_n": fe.tolist(), "odd_n": fo.tolist(), "slow_even_n": slow_even_n,
                           "slope_n_m": slope_n_m, "span_m": span_m}
    if n < OFFSET_MIN_PAIRS:
        return {**out, "reason": f"{n} speed pairs of passes, need {OFFSET_MIN_PAIRS}"}
    f0 = float(np.mean(fe))
    se = float(np.std(fe, ddof=1)) / math.sqrt(n)
    t = abs(f0) / max(se, 1e-300)
    t_need = float(stats.t.ppf(0.5 * (1.0 + OFFSET_CONFIDENCE), n - 1))
    # the constant and the asymmetry ratio jointly, with their standard errors from the residual
    A = np.column_stack([np.ones(n), fo])
    th, *_ = np.linalg.lstsq(A, fe, rcond=None)
    res = fe - A @ th
    s2 = float(res @ res) / (n - 2) if n > 2 else math.inf
    sd = np.sqrt(np.clip(np.diag(np.linalg.pinv(A.T @ A)) * s2, 0.0, None))
    t_j = [abs(float(th[i])) / max(float(sd[i]), 1e-300) for i in (0, 1)]
    t_need_j = float(stats.t.ppf(0.5 * (1.0 + OFFSET_CONFIDENCE), max(n - 2, 1)))
    r_prop = float(fo @ fe / max(float(fo @ fo), 1e-300))
    rss_c = float(np.sum((fe - f0) ** 2))
    rss_p = float(np.sum((fe - r_prop * fo) ** 2))
    out.update(force_n=f0, std_n=se, t=t, t_needed=t_need, ratio=t / t_need, rss_constant_n2=rss_c,
               rss_proportional_n2=rss_p, proportional_ratio=r_prop, joint_force_n=float(th[0]), joint_t=t_j[0],
               asymmetry_ratio=float(th[1]), asymmetry_std=float(sd[1]), asymmetry_t=t_j[1],
               joint_t_needed=t_need_j)
    if t < t_need:
        return {**out, "decided": True,
                "reason": f"even part {f0:+.3g} N not significant (t = {t:.3g} < {t_need:.3g})"}
    if rss_p <= rss_c:
        return {**out, "reason": f"the even part follows the friction level (an asymmetry r = {r_prop:+.3g}) at "
                                 "least as well as a constant"}
    if slow_even_n is None:
        return {**out, "reason": "no slow passes to confirm it along the stroke"}
    lo, hi = sorted((abs(slow_even_n), abs(f0)))
    agree = slow_even_n * f0 > 0 and hi <= OFFSET_AGREEMENT * lo
    if not agree:
        return {**out, "reason": f"the slow passes' even part {slow_even_n:+.3g} N does not confirm {f0:+.3g} N"}
    if abs(slope_n_m) * span_m > OFFSET_SLOPE_SHARE * abs(f0):
        return {**out, "reason": f"position-dependent: the slow passes' slope {slope_n_m:.3g} N/m changes the force "
                                 f"by {abs(slope_n_m) * span_m:.3g} N along {1e3 * span_m:.3g} mm (a spring)"}
    return {**out, "present": True, "decided": True, "confidence": "high" if t >= 2.0 * t_need else "moderate"}


def asymmetry_miss(ev: dict[str, Any], ratio: float) -> float:
    """How many standard errors of the passes' joint asymmetry ratio (:func:`offset_evidence`) a discovered
    asymmetry ``ratio`` lies from it; 0 where the passes name no offset. Beyond ``joint_t_needed`` the passes
    refute that asymmetry: its even part ``ratio·o_i`` would follow the friction level, and theirs does not."""
    if not ev.get("present"):
        return 0.0
    return abs(ratio - float(ev["asymmetry_ratio"])) / max(float(ev["asymmetry_std"]), 1e-300)


# ================================================================================================ margins
@dataclass
class Margins:
    phase_margin_deg: float
    gain_margin_db: float
    crossover_hz: float
    phase_crossover_hz: float

    def as_dict(self) -> dict[str, float]:
        return {"phase_margin_deg": self.phase_margin_deg, "gain_margin_db": self.gain_margin_db,
                "crossover_hz": self.crossover_hz, "phase_crossover_hz": self.phase_crossover_hz}


def margins_from_response(f: FloatArray, L: ComplexArray) -> Margins:
    """Phase margin at the last |L| = 1 crossing, gain margin at the worst −180° crossing above it
    (linear interpolation between lines; ∞ when no crossing is inside the measured band)."""
    mag = np.abs(L)
    ph = np.unwrap(np.angle(L))
    pm, wc = math.inf, math.nan
    above = mag >= 1.0
    idx = np.nonzero(above[:-1] & ~above[1:])[0]
    if idx.size:
        i = int(idx[-1])
        t = -math.log(mag[i]) / (math.log(mag[i + 1]) - math.log(mag[i]))
        wc = float(f[i] + t * (f[i + 1] - f[i]))
        p = ph[i] + t * (ph[i + 1] - ph[i])
        pm = (math.degrees(p) + 180.0 + 180.0) % 360.0 - 180.0
    gm, wp = math.inf, math.nan
    phd = np.degrees(ph)
    k = np.floor((phd + 180.0) / 360.0)
    for i in np.nonzero(np.diff(k) != 0)[0].tolist():
        if not math.isnan(wc) and f[i + 1] < wc:
            continue
        t = ((k[i + 1] * 360.0 - 180.0) - phd[i]) / (phd[i + 1] - phd[i]) if phd[i + 1] != phd[i] else 0.0
        t = min(max(t, 0.0), 1.0)
        mg = math.exp(math.log(mag[i]) + t * (math.log(mag[i + 1]) - math.log(mag[i])))
        g = -20 * math.log10(max(mg, 1e-300))
        if g < gm:
            gm, wp = g, float(f[i] + t * (f[i + 1] - f[i]))
    return Margins(pm, gm, wc, wp)


def controller_response(f_hz: FloatArray, period_s: float, pid: Any, dob_kind: str, dob_bandwidth_hz: float,
                        dob_mass_kg: float, command_delay_samples: int) -> ComplexArray:
    """Frequency response of the equivalent controller ``K = (C + H_y)/(1 − H_u)`` (or ``C`` without an
    observer) at ``f_hz`` (``stagectl.control.design`` transfer functions)."""
    from stagectl.control import design

    z = np.exp(1j * 2 * np.pi * f_hz * period_s)
    C = design.pid_tf(pid, period_s)
    c = np.array([complex(C(zi)) for zi in z])
    if dob_kind == "none":
        return c.astype(np.complex128)
    Hu, Hy = design.qfilter_tfs(dob_mass_kg, dob_bandwidth_hz, period_s, command_delay_samples)
    hu = np.array([complex(Hu(zi)) for zi in z])
    hy = np.array([complex(Hy(zi)) for zi in z])
    return np.asarray((c + hy) / (1 - hu), np.complex128)


def rigid_margins(period_s: float, mass_kg: float, delay_s: float, pid: Any, dob_bandwidth_hz: float,
                  n_lines: int = 400) -> Margins:
    """Margins of ``L = P·K`` for a rigid ``mass_kg`` behind ``delay_s`` of I/O delay and the zero-order hold's
    half period (``P = −e^{−jω(τ + T/2)}/(m ω²)``, the model :meth:`Frf.margin_lines` tests the measured lines
    against), ``K`` the PID with a Q-filter observer for the same mass (:func:`controller_response`), on
    ``n_lines`` log-spaced lines from 0.5 Hz to 0.49/T."""
    f = np.geomspace(0.5, 0.49 / period_s, n_lines)
    K = controller_response(f, period_s, pid, "qfilter", dob_bandwidth_hz, mass_kg, 1)
    w = 2 * np.pi * f
    P = -np.exp(-1j * w * (delay_s + 0.5 * period_s)) / (mass_kg * w * w)
    return margins_from_response(f, np.asarray(P * K, np.complex128))


def measured_margins(frf: Frf, K: ComplexArray) -> Margins:
    """Margins of ``L = P_meas·K`` on the measured lines but those :meth:`Frf.margin_lines` leaves out
    (``K`` at every line of ``frf``)."""
    keep = frf.margin_lines()
    return margins_from_response(frf.f_hz[keep], (frf.p * K)[keep])
