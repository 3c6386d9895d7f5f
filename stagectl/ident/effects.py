"""The discovery catalogue: one :class:`~stagectl.ident.hypothesis.EffectSpec` per effect, in :data:`REGISTRY`.

Each entry below holds everything about one effect: its shape (nonlinear parameters, a frozen dataclass),
its design-matrix columns, its typed fitted parameters (for the effects that have a twin in the model file's
``effects:`` section these are the :mod:`stagectl.friction.effects` dataclasses themselves), the search of its shape, the
evidence text the report prints, and the mapping to and from the model file. The regression
(:mod:`stagectl.ident.regress`), the workflow (:mod:`stagectl.ident.discover`) and the model-file conversion
(:mod:`stagectl.ident.modelio`) iterate over :data:`REGISTRY` and name no effect.

Adding an effect: write its shape and parameter dataclasses, its column builder, search and evidence
functions, and one ``EffectSpec(...)`` in the ``REGISTRY`` tuple (its position is its place in the search and
the report); if it belongs in model files, add its twin to :mod:`stagectl.friction.effects` (dataclass,
``Effects`` field, scalar/array/compiled terms) and set ``twin``/``to_twin``/``from_twin``.

Column names (keys of ``Hyp.theta``) used here: ``ds`` = fs − fc [N] (Stribeck excess), ``w<i>``/``s<i>``
Maxwell-slip saturation force W_i [N] / micro-damping [N·s/m], ``rs``/``rc`` ripple sine/cosine relative
amplitudes [–], ``f0`` [N], ``ks`` [N/m], ``cs``/``cc`` cogging sine/cosine amplitudes [N].
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from stagectl.friction.effects import Asymmetry, Cogging, Delay, Offset, PositionRipple, Spring, ViscousAsymmetry
from stagectl.ident._kernels import backlash_load
from stagectl.ident._minimize import nelder_mead
from stagectl.ident.columns import (
    cached,
    element,
    element_rate,
    min_damped_delta,
    position_sin_cos,
    stribeck_shape,
)
from stagectl.ident.hypothesis import Column, EffectSpec, FitResult, Fitter, HiddenStage, Hyp, NoShape, Registry
from stagectl.ident.localise import ResidualView
from stagectl.ident.search import best_scalar, position_periodogram, presliding_grid, speed_range
from stagectl.ident.signals import Signals

FloatArray = npt.NDArray[np.float64]


# ============================================================================================ shapes and params
@dataclass(frozen=True)
class StribeckShape:
    vs_m_s: float = 1e-3  # Stribeck velocity [m/s]
    delta: float = 2.0  # Stribeck exponent [–]


@dataclass(frozen=True)
class StribeckParams:
    fs_n: float  # static (break-away) force [N]
    fc_n: float  # Coulomb force [N]
    vs_m_s: float
    delta: float


@dataclass(frozen=True)
class LagShape:
    lag_s: float = 0.0  # time constant of the frictional lag [s]


@dataclass(frozen=True)
class LagParams:
    lag_s: float


@dataclass(frozen=True)
class PreslidingShape:
    deltas_m: tuple[float, ...] = ()  # break displacements Δ_i of the Maxwell-slip elements [m]
    damped: bool = True  # micro-damping columns on elements that stay elastic long enough
    #: elements (indices into deltas_m) without a micro-damping column: their damping fitted beyond its
    #: physical bound (:func:`_damping_excess`) and was left out (:func:`_fit_presliding`)
    undamped: tuple[int, ...] = ()


@dataclass(frozen=True)
class PreslidingParams:
    elements: int
    total_slip_force_n: float
    coulomb_part_n: float
    initial_stiffness_n_m: float
    largest_break_displacement_m: float
    #: elements whose micro-damping exceeds its physical bound: (Δ_i [m], σ1_i [N·s/m], bound [N·s/m])
    damping_excess: tuple[tuple[float, float, float], ...] = ()


@dataclass(frozen=True)
class AsymmetryShape:
    ratio: float = 0.0  # r: F+ = (1+r)F, F- = (1-r)F


@dataclass(frozen=True)
class WavelengthShape:
    wavelength_m: float = 1.0  # period in position [m]


@dataclass(frozen=True)
class DelayShape:
    delay_s: float = 0.0  # actuation delay [s]


# ============================================================================================ friction shape
def coulomb_level(h: Hyp) -> float:
    """Sliding friction level [N]: Coulomb column plus every Maxwell-slip saturation force."""
    w = sum(v for k, v in h.theta.items() if k.startswith("w") and k[1:].isdigit())
    return float(h.theta.get("fc", 0.0) + w)


def _stribeck_lag(h: Hyp) -> float:
    return LAG.shape(h).lag_s if h.has(LAG.name) else 0.0


def _stribeck_columns(sig: Signals, h: Hyp) -> list[Column]:
    s = STRIBECK.shape(h)
    lag = _stribeck_lag(h)
    # either sign: Fs > Fc is the Stribeck dip, Fs < Fc a friction that rises with speed from a lower
    # break-away level (rolling contacts); the physical bound is Fs >= 0 (_stribeck_bounds)
    return [Column("ds", stribeck_shape(sig, s.vs_m_s, s.delta, lag), f"ds:{s.vs_m_s:.6e}:{s.delta:g}:{lag:.6e}")]


def _stribeck_params(h: Hyp) -> StribeckParams:
    fc = coulomb_level(h)
    s = STRIBECK.shape(h)
    return StribeckParams(fc + h.theta.get("ds", 0.0), fc, float(s.vs_m_s), float(s.delta))


def _stribeck_evidence(ev: ResidualView, p: StribeckParams) -> str:
    how = ("has the sign of the velocity: friction falls with speed (Stribeck dip)" if p.fs_n >= p.fc_n else
           "has the opposite sign of the velocity: friction rises with speed from a lower break-away level "
           "(no Stribeck dip, as on rolling contacts)")
    return (f"the residual is largest at low speed (RMS {ev.regime_text('low_speed')} vs "
            f"{ev.regime_text('constant_speed')} at constant speed) and {how}; fitted Fs = {p.fs_n:.4g} N, "
            f"Fc = {p.fc_n:.4g} N, vs = {p.vs_m_s:.3g} m/s, δ = {p.delta:.2g}")


def _search_stribeck_shape(fitter: Fitter, h_s: Hyp) -> tuple[float, float]:
    """(vs, δ) of the Stribeck curve in ``h_s``: grid + Brent per δ ∈ {1, 2}, line search in δ, then a joint
    Nelder-Mead refinement of (log vs, δ) (the two trade off, separate line searches stop short).

    Memoised on the signals per (rows, hypothesis): the ``stribeck`` and ``frictional_lag`` candidates of a
    round both start from the same Stribeck search on the same model."""
    key = ("stribeck_shape", hash(fitter.rows.tobytes()), h_s.effects,
           repr(sorted((k, repr(v)) for k, v in h_s.shapes.items())), repr(sorted(h_s.theta.items())),
           h_s.fixed_mass_kg, h_s.x_center_m, repr(h_s.given_spec))
    memo = cast(dict[object, tuple[float, float]], fitter.sig.cache.setdefault("_memo", {}))
    got = memo.get(key)
    if got is None:
        got = _search_stribeck_shape_now(fitter, h_s)
        memo[key] = got
    return got


def _search_stribeck_shape_now(fitter: Fitter, h_s: Hyp) -> tuple[float, float]:
    def rss(vs: float, delta: float) -> float:
        return STRIBECK.fit_with(fitter, h_s, vs_m_s=vs, delta=delta).rss

    vmin, vmax = speed_range(fitter.sig)
    grid = list(np.geomspace(vmin, 0.5 * vmax, 10))
    best: tuple[float, float, float] | None = None
    for delta in (1.0, 2.0):
        vs, f = best_scalar(lambda v, d=delta: rss(v, d), grid, vmin, vmax)  # type: ignore[misc]
        if best is None or f < best[2]:
            best = (vs, delta, f)
    assert best is not None
    vs, delta, _ = best
    dl, _ = best_scalar(lambda d: rss(vs, d), [0.7, 1.0, 1.5, 2.0, 3.0], 0.5, 4.0, log=False, maxiter=8)
    lv = math.log(vs)
    x = nelder_mead(lambda p: rss(math.exp(p[0]), float(np.clip(p[1], 0.5, 4.0))),
                    np.array([[lv, dl], [lv + 0.2, dl], [lv, dl + 0.2]]), maxfev=40, xatol=1e-3, fatol=1e-12)
    return math.exp(float(x[0])), float(np.clip(x[1], 0.5, 4.0))


def _search_stribeck(fitter: Fitter, cur: FitResult, h: Hyp) -> FitResult:
    vs, dl = _search_stribeck_shape(fitter, h)
    return STRIBECK.fit_with(fitter, h, vs_m_s=vs, delta=dl)


def _search_lag(fitter: Fitter, cur: FitResult, h: Hyp) -> FitResult:
    """Lag time constant from ``dt`` up (a lag shorter than a sample cannot be told from the sampling); a
    lag below two samples means no lag is supported: the Stribeck model alone (or ``cur``) is returned."""
    if not cur.hyp.has(STRIBECK.name):
        vs, dl = _search_stribeck_shape(fitter, cur.hyp.adding(STRIBECK.name))
        h = STRIBECK.reshaped(h, vs_m_s=vs, delta=dl)
    dt = fitter.sig.dt_s
    lag, _ = best_scalar(lambda s: LAG.fit_with(fitter, h, lag_s=s).rss, list(np.geomspace(dt, 0.5, 10)), dt, 1.0)
    if lag < 2.0 * dt:
        if cur.hyp.has(STRIBECK.name):
            return cur
        s = STRIBECK.shape(h)
        return STRIBECK.fit_with(fitter, cur.hyp.adding(STRIBECK.name), vs_m_s=s.vs_m_s, delta=s.delta)
    # re-tune vs with the lag in place
    h = LAG.reshaped(h, lag_s=lag)
    vs0 = STRIBECK.shape(h).vs_m_s
    vs, _ = best_scalar(lambda v: STRIBECK.fit_with(fitter, h, vs_m_s=v).rss, [vs0 / 2, vs0, vs0 * 2], vs0 / 4,
                        vs0 * 4, maxiter=8)
    return STRIBECK.fit_with(fitter, h, vs_m_s=vs)


def _lag_evidence(ev: ResidualView, p: LagParams) -> str:
    sig, rows, r, v = ev.sig, ev.rows, ev.r, ev.sig.v
    acc = rows & (np.sign(sig.acc_f) == np.sign(v))
    dec = rows & (np.sign(sig.acc_f) != np.sign(v))
    ma = float(np.sqrt(np.mean(r[acc] ** 2))) if acc.any() else 0.0
    md = float(np.sqrt(np.mean(r[dec] ** 2))) if dec.any() else 0.0
    return (f"the low-speed friction differs between accelerating and decelerating motion (residual RMS "
            f"{ma:.4g} N vs {md:.4g} N): the Stribeck part lags the velocity; fitted lag {1e3 * p.lag_s:.3g} ms")


def _presliding_columns(sig: Signals, h: Hyp) -> list[Column]:
    sh = PRESLIDING.shape(h)
    cols = [Column(f"w{i}", element(sig, d), f"w:{d:.6e}", nonneg=True) for i, d in enumerate(sh.deltas_m)]
    if sh.damped:
        # micro-damping only on elements that stay elastic over more than a sample at typical reversal
        # speeds; on the stiffest ones dz/dt is a one-sample spike that would fit transients, not physics
        d_min = min_damped_delta(sig)
        cols += [Column(f"s{i}", element_rate(sig, d), f"s:{d:.6e}", nonneg=True)
                 for i, d in enumerate(sh.deltas_m) if d >= d_min and i not in sh.undamped]
    return cols


#: micro-damping bound: σ1_i <= DAMPING_MAX_ZETA · 2·sqrt(k_i·m), element i critically damped on the mass
DAMPING_MAX_ZETA = 1.0


def _damping_excess(h: Hyp) -> tuple[tuple[int, float, float, float], ...]:
    """Elements whose fitted micro-damping exceeds its physical bound: ``(i, Δ_i, σ1_i, bound)``.

    A Maxwell-slip element of stiffness ``k_i = W_i/Δ_i`` [N/m] with micro-damping ``σ1_i`` [N·s/m] on the
    moving mass ``m`` is a spring-damper of damping ratio ``ζ_i = σ1_i / (2·sqrt(k_i·m))``; bound ``ζ_i <=
    DAMPING_MAX_ZETA``. A damper on an element that carries no force (``W_i = 0``) has bound 0: the model file
    keeps no such element (:mod:`stagectl.ident.modelio`), so the fit would describe a force the file drops.

    Measured (docs/discovery.md §8): on commissioning recordings of GMS stages (true ζ 0.1) the unbounded fit
    put σ1 = 3.9·10⁸ N·s/m on a 0.2 µm element whose deflection rate the estimation recording barely excites
    (RMS 5·10⁻¹² m/s; 85× the bound, or 1.1·10⁵ N·s/m on an element with W = 0): pre-sliding then failed
    validation (289 N against 0.22 N) and a backlash took its place."""
    th = h.theta
    m = float(th.get("m", h.fixed_mass_kg or 0.0))
    out = []
    for i, d in enumerate(PRESLIDING.shape(h).deltas_m):
        s = th.get(f"s{i}", 0.0)
        if s <= 0.0:
            continue
        k = max(th.get(f"w{i}", 0.0), 0.0) / d
        bound = DAMPING_MAX_ZETA * 2.0 * math.sqrt(k * max(m, 0.0))
        if s > bound * (1.0 + 1e-9):
            out.append((i, float(d), float(s), float(bound)))
    return tuple(out)


def bound_damping(fitter: Fitter, fr: FitResult) -> FitResult:
    """``fr`` with every pre-sliding micro-damping within its physical bound (:func:`_damping_excess`): the
    damping column of the element farthest beyond its bound is left out and the fit repeated, until none is
    (``fr`` itself when none is; the other shapes are kept). Discovery applies it after every candidate's fit,
    so that an effect added later refits the damping within the bound instead of failing on it."""
    res = fr
    while True:
        ex = _damping_excess(res.hyp)
        if not ex:
            return res
        worst = max(ex, key=lambda e: e[2] / max(e[3], 1e-300))[0]
        res = fitter.fit(PRESLIDING.reshaped(res.hyp, undamped=(*PRESLIDING.shape(res.hyp).undamped, worst)))


def _fit_presliding(fitter: Fitter, h: Hyp) -> FitResult:
    """The pre-sliding fit, every damping column offered, then bounded (:func:`bound_damping`)."""
    return bound_damping(fitter, fitter.fit(PRESLIDING.reshaped(h, undamped=())))


def _presliding_params(h: Hyp) -> PreslidingParams:
    th = h.theta
    d = np.asarray(PRESLIDING.shape(h).deltas_m, float)
    w = np.array([th.get(f"w{i}", 0.0) for i in range(d.size)])
    keep = w > 1e-9 * max(w.sum(), 1e-300)
    return PreslidingParams(int(keep.sum()), float(w.sum()) + th.get("fc", 0.0), th.get("fc", 0.0),
                            float(np.sum(w[keep] / d[keep])), float(d[keep].max()) if keep.any() else 0.0,
                            tuple((e[1], e[2], e[3]) for e in _damping_excess(h)))


def _search_presliding(fitter: Fitter, cur: FitResult, h: Hyp) -> FitResult:
    """Elements on a log grid; keep those that carry force and refine their break displacements (coordinate
    descent on log Δ_i: the virgin curve is piecewise linear with breakpoints Δ_i, docs/friction-models.md §2.3)."""
    h = PRESLIDING.reshaped(h, deltas_m=tuple(presliding_grid(fitter.sig)))
    first = _fit_presliding(fitter, h)
    grid = PRESLIDING.shape(h).deltas_m
    deltas = [grid[i] for i in range(len(grid)) if first.hyp.theta.get(f"w{i}", 0.0) > 0]
    if not deltas:
        return first
    for _sweep in range(2):
        for j in range(len(deltas)):
            def cost(d: float, j: int = j) -> float:
                trial = list(deltas)
                trial[j] = d
                return _fit_presliding(fitter, PRESLIDING.reshaped(h, deltas_m=tuple(trial))).rss
            dj = deltas[j]
            deltas[j], _ = best_scalar(cost, [dj / 1.8, dj, dj * 1.8], dj / 2.5, dj * 2.5, maxiter=8)
    return _fit_presliding(fitter, PRESLIDING.reshaped(h, deltas_m=tuple(sorted(deltas))))


def _presliding_evidence(ev: ResidualView, p: PreslidingParams) -> str:
    return (f"the residual is concentrated right after velocity reversals (RMS {ev.regime_text('near_reversal')} "
            f"vs {ev.regime_text('constant_speed')} at constant speed): the force builds up elastically over "
            f"displacement instead of jumping with sgn(v); fitted {p.elements} Maxwell-slip elements, "
            f"initial stiffness {p.initial_stiffness_n_m:.4g} N/m, largest break displacement "
            f"{1e6 * p.largest_break_displacement_m:.3g} µm")


@dataclass(frozen=True)
class SlipElement:
    break_displacement_m: float  # Δ_i [m]
    slip_force_n: float  # W_i [N], clipped at 0
    damping_n_s_m: float  # σ1_i [N·s/m], clipped at 0


@dataclass(frozen=True)
class FrictionFit:
    """The friction part of a fitted hypothesis, typed (what :mod:`stagectl.ident.modelio` turns into the
    model file's ``friction:`` section)."""

    coulomb_n: float
    viscous_n_s_m: float  # clipped at 0
    stribeck_excess_n: float  # fs − fc [N]; 0 without the Stribeck effect
    vs_m_s: float
    delta: float
    lag_s: float  # 0 without the frictional lag
    elements: tuple[SlipElement, ...] | None  # None without pre-sliding
    given_scale: float  # scale of ``Hyp.given_spec``


def friction_fit(h: Hyp) -> FrictionFit:
    th = h.theta
    s = STRIBECK.shape(h)
    elements = None
    if h.has(PRESLIDING.name):
        elements = tuple(SlipElement(float(d), max(th.get(f"w{i}", 0.0), 0.0), max(th.get(f"s{i}", 0.0), 0.0))
                         for i, d in enumerate(PRESLIDING.shape(h).deltas_m))
    return FrictionFit(float(th.get("fc", 0.0)), max(float(th.get("fv", 0.0)), 0.0),
                       float(th.get("ds", 0.0)) if h.has(STRIBECK.name) else 0.0, float(s.vs_m_s), float(s.delta),
                       float(_stribeck_lag(h)), elements, float(th.get("given", 1.0)))


# ============================================================================================ asymmetry
def _asymmetry_evidence(ev: ResidualView, p: Asymmetry) -> str:
    return (f"the residual depends on the direction of motion (mean {ev.mean_positive_n:+.4g} N for v > 0, "
            f"{ev.mean_negative_n:+.4g} N for v < 0) and scales with the friction level (viscous part too), which a "
            f"constant offset cannot explain; fitted r = {p.ratio:+.4g} (F+ = (1+r)·F, F- = (1-r)·F)")


def _search_asymmetry(fitter: Fitter, cur: FitResult, h: Hyp) -> FitResult:
    r, _ = best_scalar(lambda r: ASYMMETRY.fit_with(fitter, h, ratio=r).rss, list(np.linspace(-0.8, 0.8, 9)), -0.95,
                       0.95, log=False, maxiter=14)
    return ASYMMETRY.fit_with(fitter, h, ratio=r)


def _retune_asymmetry(fitter: Fitter, h: Hyp, step: float, maxiter: int) -> tuple[float, float]:
    r0 = ASYMMETRY.shape(h).ratio
    return best_scalar(lambda r: ASYMMETRY.fit_with(fitter, h, ratio=r).rss, [r0 - step, r0, r0 + step], -0.95, 0.95,
                       log=False, maxiter=maxiter)


def _refresh_asymmetry(fitter: Fitter, fr: FitResult) -> FitResult:
    r, f = _retune_asymmetry(fitter, fr.hyp, 0.05, 10)
    return ASYMMETRY.fit_with(fitter, fr.hyp, ratio=r) if f < fr.rss else fr


def _asymmetry_after_removal(fitter: Fitter, h: Hyp) -> FitResult:
    # the asymmetry ratio trades off with a constant force: search it again
    r, _ = _retune_asymmetry(fitter, h, 0.1, 12)
    return ASYMMETRY.fit_with(fitter, h, ratio=r)


# ============================================================================================ viscous asymmetry
@dataclass(frozen=True)
class ViscousAsymmetryParams:
    """Viscous coefficients per direction [N·s/m]: ``Fv± = fv ± d_v`` (the Coulomb level is symmetric)."""

    difference_n_s_m: float  # d_v = (Fv+ − Fv−)/2
    fv_plus_n_s_m: float
    fv_minus_n_s_m: float


def _vasym_columns(sig: Signals, h: Hyp) -> list[Column]:
    return [Column("dv", cached(sig, "absv", lambda: np.abs(sig.v)), "dv")]


def _vasym_params(h: Hyp) -> ViscousAsymmetryParams:
    fv, dv = h.theta.get("fv", 0.0), h.theta.get("dv", 0.0)
    return ViscousAsymmetryParams(dv, fv + dv, fv - dv)


def _vasym_evidence(ev: ResidualView, p: ViscousAsymmetryParams) -> str:
    sig, rows, r = ev.sig, ev.rows, ev.r
    slopes = []
    for sgn in (1.0, -1.0):
        m = rows & (np.sign(sig.v) == sgn)
        vv = np.abs(sig.v[m])
        slopes.append(float(np.polyfit(vv, r[m], 1)[0]) if m.sum() > 2 and np.ptp(vv) > 0 else 0.0)
    return (f"the residual grows with speed differently in the two directions (slope {slopes[0]:+.4g} N·s/m for "
            f"v > 0, {slopes[1]:+.4g} N·s/m for v < 0 against |v|): the viscous coefficient depends on the "
            f"direction; fitted Fv+ = {p.fv_plus_n_s_m:.4g} N·s/m, Fv− = {p.fv_minus_n_s_m:.4g} N·s/m "
            f"(d_v = {p.difference_n_s_m:+.4g} N·s/m; Coulomb level unchanged)")


def _hide_vasym(st: HiddenStage) -> None:
    """|d_v| 0.25-0.5 of the stage's viscous coefficient (Fv+/Fv− from 1.67 to 3)."""
    fv = float(st.friction.get("viscous_n_s_m", 0.0))
    st.effects["viscous_asymmetry"] = {"difference_n_s_m": st.sign * float(st.rng.uniform(0.25, 0.5)) * fv}


# ============================================================================================ periodic effects
def _search_periodic(spec: EffectSpec[WavelengthShape, Any], fitter: Fitter, cur: FitResult, h: Hyp,
                     weight: FloatArray | None) -> FitResult:
    """Wavelength candidates from a position periodogram of the current residual, each refined by Brent."""
    sig, rows = fitter.sig, fitter.rows
    cands = position_periodogram(sig, rows, fitter.residual(cur.hyp), weight)
    span = float(np.ptp(sig.xf[rows]))
    best_fit: FitResult | None = None
    for lam0 in cands:
        rel = 1.5 * lam0 / span
        lo, hi = lam0 * (1 - rel), lam0 * (1 + rel)
        lam, _ = best_scalar(lambda s: spec.fit_with(fitter, h, wavelength_m=s).rss, [lo, lam0, hi], lo, hi,
                             maxiter=10)
        fr = spec.fit_with(fitter, h, wavelength_m=lam)
        if best_fit is None or fr.rss < best_fit.rss:
            best_fit = fr
    return best_fit if best_fit is not None else spec.fit_with(fitter, h, wavelength_m=span)


def _periodic_evidence(kind: str, amp: str, p: PositionRipple | Cogging) -> str:
    return (f"the residual is periodic in position with wavelength {p.wavelength_m:.6g} m and {kind}; "
            f"fitted {amp}, phase {p.phase_rad:.3g} rad; it transfers to the validation data")


def _ripple_columns(sig: Signals, h: Hyp, f_est: FloatArray) -> list[Column]:
    s, c = position_sin_cos(sig, RIPPLE.shape(h).wavelength_m)
    return [Column("rs", f_est * s, None, follows_friction=True), Column("rc", f_est * c, None, follows_friction=True)]


def _ripple_params(h: Hyp) -> PositionRipple:
    rs, rc = h.theta.get("rs", 0.0), h.theta.get("rc", 0.0)
    return PositionRipple(amplitude=math.hypot(rs, rc), wavelength_m=float(RIPPLE.shape(h).wavelength_m),
                          phase_rad=math.atan2(rc, rs))


#: longest ripple wavelength searched, in travelled spans [–]: a friction level that varies smoothly along the
#: stroke (one hump, or a gradient) is a ripple of wavelength 0.5-3 spans (docs/discovery.md §13)
LONG_RIPPLE_SPANS = (0.5, 3.0)


def _search_ripple(fitter: Fitter, cur: FitResult, h: Hyp) -> FitResult:
    """The periodogram's wavelengths (at least 2 periods in the span), and one search over long wavelengths
    (``LONG_RIPPLE_SPANS``): a friction level that varies smoothly along the stroke has no periodogram peak
    (the periodogram excludes fewer than 2 periods, where every smooth trend would peak) but is the same
    multiplicative form 1 + a·sin(2πx/λ + φ) within the travelled span."""
    weight = fitter.sig.filt(fitter.friction_force(cur.hyp))  # the ripple multiplies the friction force
    best = _search_periodic(RIPPLE, fitter, cur, h, weight)
    span = float(np.ptp(fitter.sig.xf[fitter.rows]))
    if span <= 0.0:
        return best
    lo, hi = LONG_RIPPLE_SPANS[0] * span, LONG_RIPPLE_SPANS[1] * span
    lam, f = best_scalar(lambda s: RIPPLE.fit_with(fitter, h, wavelength_m=s).rss, list(np.geomspace(lo, hi, 4)),
                         lo, hi, maxiter=6)
    if f < best.rss:
        fr = RIPPLE.fit_with(fitter, h, wavelength_m=lam)
        if not _ripple_bounds(_ripple_params(fr.hyp)):
            return fr
    return best


def _cogging_columns(sig: Signals, h: Hyp, f_est: FloatArray) -> list[Column]:
    lam = COGGING.shape(h).wavelength_m
    s, c = position_sin_cos(sig, lam)
    return [Column("cs", s, f"cs:{lam:.9e}"), Column("cc", c, f"cc:{lam:.9e}")]


def _cogging_params(h: Hyp) -> Cogging:
    cs, cc = h.theta.get("cs", 0.0), h.theta.get("cc", 0.0)
    return Cogging(amplitude_n=math.hypot(cs, cc), wavelength_m=float(COGGING.shape(h).wavelength_m),
                   phase_rad=math.atan2(cc, cs))


#: a cogging must recur: at least this share of the half-period position windows of the validation data
#: carry between ``RECUR_SCALES`` times the fitted amplitude (docs/discovery.md §13)
RECUR_MIN_SHARE = 0.5
RECUR_SCALES = (0.5, 2.0)


def _cogging_recurs(sig: Signals, rows: npt.NDArray[np.bool_], h: Hyp, _floor_n: float, rr: FloatArray
                    ) -> list[str]:
    """What a periodic (cogging) fit lacks to be periodic: the force must recur period after period.

    The travelled span of the validation rows is cut into windows half a wavelength λ long (equal shares of
    a sinusoid's power). In each window holding at least 50 samples over half its length or more, the local
    scale of the fitted force g = L[cs·sin(2πx/λ) + cc·cos(2πx/λ)] [N] is s_k = Σ(r + g)·g / Σg² [–], with
    r = ``rr`` the residual on ``rows`` with the cogging in the model (s_k = 1 where the fit is right). A
    cogging has s_k ≈ 1 everywhere (``RECUR_SCALES`` 0.5-2 accepted); a single local force (a hump or dip
    over 1-1.5 periods, a dent in a guide, a cable at one place) has s_k of several in one or two windows
    and ≈ 0 elsewhere, and the sinusoid fitted to it spreads a force over the whole stroke that is not
    there. With fewer than 4 windows (under 2 periods travelled) the test cannot judge and passes."""
    lam = float(COGGING.shape(h).wavelength_m)
    x = sig.xf[rows]
    if x.size == 0 or lam <= 0.0:
        return []
    cs, cc = h.theta.get("cs", 0.0), h.theta.get("cc", 0.0)
    s, c = position_sin_cos(sig, lam)
    gr = sig.filt(cs * s + cc * c)[rows]
    lo = float(x.min())
    w = 0.5 * lam
    k = np.floor((x - lo) / w).astype(np.int64)
    scales: list[tuple[float, float]] = []
    for j in np.unique(k):
        m = k == j
        gg = float(np.dot(gr[m], gr[m]))
        if m.sum() < 50 or float(np.ptp(x[m])) < 0.5 * w or gg <= 0.0:
            continue
        scales.append((lo + j * w, float(np.dot(rr[m] + gr[m], gr[m])) / gg))
    if len(scales) < 4:
        return []
    good = [w0 for w0, sk in scales if RECUR_SCALES[0] <= sk <= RECUR_SCALES[1]]
    if len(good) >= RECUR_MIN_SHARE * len(scales):
        return []
    big = max(scales, key=lambda t: t[1])
    return [(f"the force does not recur period after period: only {len(good)} of {len(scales)} half-period "
             f"windows (λ = {1e3 * lam:.4g} mm) carry {RECUR_SCALES[0]:g}-{RECUR_SCALES[1]:g}× the fitted "
             f"amplitude, the largest {big[1]:.2g}× it at x in [{big[0]:.6g}, {big[0] + w:.6g}] m: a local force "
             "over about one period (a bump, a dent, a cable), not a periodic cogging")]


# ============================================================================================ offset, spring
def _offset_columns(sig: Signals, h: Hyp, f_est: FloatArray) -> list[Column]:
    return [Column("f0", np.ones(sig.n), "f0")]


def _offset_evidence(ev: ResidualView, p: Offset) -> str:
    if ev.both_directions:
        txt = (f"the residual has the same sign in both directions of motion (mean {ev.mean_positive_n:+.4g} N for "
               f"v > 0, {ev.mean_negative_n:+.4g} N for v < 0): a constant force")
    else:
        txt = (f"the residual has a constant part (mean {ev.mean_positive_n + ev.mean_negative_n:+.4g} N); the motion "
               "is almost all in one direction, so a constant force and a change of the friction level cannot be "
               "told apart here (move in both directions to separate them)")
    return (f"{txt}; fitted F_0 = {p.force_n:.4g} N. While sliding this is the same force as a Coulomb asymmetry "
            f"Fc+ − Fc− = {2 * p.force_n:+.4g} N (docs/discovery.md §1): sliding data cannot separate the two; "
            "the break-away force in each direction, or holding at rest, can")


def _spring_columns(sig: Signals, h: Hyp, f_est: FloatArray) -> list[Column]:
    cols = [] if h.has(OFFSET.name) else _offset_columns(sig, h, f_est)  # the spring's constant part
    return [*cols, Column("ks", sig.xf - h.x_center_m, f"ks:{h.x_center_m:.9e}")]


def _spring_params(h: Hyp) -> Spring:
    k = h.theta.get("ks", 0.0)
    f0 = h.theta.get("f0", 0.0) / k if k and not h.has(OFFSET.name) else 0.0
    return Spring(stiffness_n_m=k, x0_m=h.x_center_m - f0)


def _spring_evidence(ev: ResidualView, p: Spring) -> str:
    rr, xx = ev.r[ev.rows], ev.sig.xf[ev.rows]
    c = float(np.corrcoef(rr, xx)[0, 1]) if rr.size > 2 else 0.0
    slope = float(np.polyfit(xx, rr, 1)[0]) if rr.size > 2 else 0.0
    return (f"the residual grows linearly with position (slope {slope:.4g} N/m, correlation {c:+.2f}) in both "
            f"directions; fitted k_s = {p.stiffness_n_m:.4g} N/m, x0 = {p.x0_m:.6g} m")


def _fit_as_is(fitter: Fitter, cur: FitResult, h: Hyp) -> FitResult:
    return fitter.fit(h)


# ============================================================================================ delay
def _delay_evidence(ev: ResidualView, p: Delay) -> str:
    du = np.gradient(ev.sig.u)
    rr = ev.r[ev.rows]
    c = float(np.corrcoef(rr, du[ev.rows])[0, 1]) if rr.size > 2 else 0.0
    return (f"the residual is correlated with the rate of change of the commanded force (correlation {c:+.2f}): "
            f"the force acts later than commanded; fitted τ = {1e3 * p.delay_s:.3g} ms")


def _search_delay(fitter: Fitter, cur: FitResult, h: Hyp) -> FitResult:
    dt = fitter.sig.dt_s
    tau, _ = best_scalar(lambda s: DELAY.fit_with(fitter, h, delay_s=s).rss, [k * dt for k in range(21)], 0.0,
                         20 * dt, log=False)
    return DELAY.fit_with(fitter, h, delay_s=tau)


def _refresh_delay(fitter: Fitter, fr: FitResult) -> FitResult:
    dt = fitter.sig.dt_s
    t0 = DELAY.shape(fr.hyp).delay_s
    tau, f = best_scalar(lambda s: DELAY.fit_with(fitter, fr.hyp, delay_s=s).rss,
                         [max(t0 - 0.5 * dt, 0.0), t0, t0 + 0.5 * dt], 0.0, 20 * dt, log=False, maxiter=10)
    return DELAY.fit_with(fitter, fr.hyp, delay_s=tau) if f < fr.rss else fr


# ============================================================================================ hidden (synthetic)
# Each draws over plausible ranges relative to the stage's Coulomb level Fc (after the common random sign).
def _hide_stribeck(st: HiddenStage) -> None:
    """Fs/Fc 1.3-2, vs 0.5-3 mm/s, δ 1-2 (unless the stage already has a Stribeck curve)."""
    fr, rng = st.friction, st.rng
    if float(fr["fs_n"]) <= st.coulomb_n:
        fr["fs_n"] = st.coulomb_n * float(rng.uniform(1.3, 2.0))
        fr["vs_m_s"] = float(rng.uniform(0.5e-3, 3e-3))
        fr["delta"] = float(rng.uniform(1.0, 2.0))


def _hide_lag(st: HiddenStage) -> None:
    """A Stribeck curve (see :func:`_hide_stribeck`) with a frictional lag of 10-50 ms."""
    _hide_stribeck(st)
    st.friction["lag_s"] = float(st.rng.uniform(10e-3, 50e-3))


def _hide_presliding(st: HiddenStage) -> None:
    """GMS with 4 elements, break displacements 0.5-30 µm."""
    fr, rng, n = st.friction, st.rng, 4
    deltas = np.sort(np.exp(rng.uniform(np.log(0.5e-6), np.log(30e-6), n)))
    alpha = rng.dirichlet(np.ones(n))
    fs = float(fr["fs_n"])
    k = alpha * fs / deltas
    st.friction = {"model": "gms", "k_n_m": [float(v) for v in k], "alpha": [float(a) for a in alpha],
                   "fc_n": st.coulomb_n, "fs_n": fs, "vs_m_s": float(fr.get("vs_m_s", 1e-3)),
                   "delta": float(fr.get("delta", 2.0)), "c_n_s": 1e4, "viscous_n_s_m": float(fr["viscous_n_s_m"]),
                   "sigma1_n_s_m": float(0.1 * 2 * math.sqrt(float(np.sum(k)) * st.mass_kg))}


def _hide_asymmetry(st: HiddenStage) -> None:
    """|r| 0.15-0.35."""
    st.effects["asymmetry"] = {"ratio": st.sign * float(st.rng.uniform(0.15, 0.35))}


def _hide_ripple(st: HiddenStage) -> None:
    """a 0.15-0.35, λ 0.5-2 mm, any phase."""
    rng = st.rng
    st.effects["position_ripple"] = {"amplitude": float(rng.uniform(0.15, 0.35)),
                                     "wavelength_m": float(rng.uniform(0.5e-3, 2e-3)),
                                     "phase_rad": float(rng.uniform(0, 2 * np.pi))}


def _hide_cogging(st: HiddenStage) -> None:
    """A 0.2-0.5 Fc, λ 0.5-3 mm, any phase."""
    rng = st.rng
    st.effects["cogging"] = {"amplitude_n": float(rng.uniform(0.2, 0.5)) * st.coulomb_n,
                             "wavelength_m": float(rng.uniform(0.5e-3, 3e-3)),
                             "phase_rad": float(rng.uniform(0, 2 * np.pi))}


def _hide_offset(st: HiddenStage) -> None:
    """|F_0| 0.2-0.6 Fc."""
    st.effects["offset"] = {"force_n": st.sign * float(st.rng.uniform(0.2, 0.6)) * st.coulomb_n}


def _hide_spring(st: HiddenStage) -> None:
    """k·span/2 0.3-0.8 Fc, rest position within ±20 % of the span."""
    k = float(st.rng.uniform(0.3, 0.8)) * st.coulomb_n / (st.span_m / 2)
    st.effects["spring"] = {"stiffness_n_m": k, "x0_m": float(st.rng.uniform(-0.2, 0.2)) * st.span_m}


def _hide_delay(st: HiddenStage) -> None:
    """0.5-2 ms."""
    st.effects["delay"] = {"delay_s": float(st.rng.uniform(0.5e-3, 2e-3))}


# ============================================================================================ backlash
@dataclass(frozen=True)
class BacklashShape:
    gap_m: float = 1e-5  # total play b between motor and load [m]
    # the load's own friction per unit load mass, a_l = −(dec_c·sgn v_l + dec_v·v_l): dec_c [m/s²], dec_v [1/s];
    # inf: the load stops at once when it leaves the motor (the play opens only at reversals)
    dec_c_m_s2: float = math.inf
    dec_v_1_s: float = 0.0


@dataclass(frozen=True)
class BacklashParams:
    """Backlash seen from a motor-side sensor: for the first ``gap_m`` after each reversal the motor moves
    alone; ``coulomb_lost_n`` [N] of friction and ``mass_lost_kg`` [kg] of mass are then not carried."""

    gap_m: float
    coulomb_lost_n: float
    viscous_lost_n_s_m: float
    mass_lost_kg: float
    coulomb_n: float  # the full Coulomb level, for the bounds
    mass_kg: float
    impact_mass_kg: float = 0.0  # effective mass of the engagement impact (coefficient of (v_m − v_l)/dt)
    viscous_n_s_m: float = math.inf  # the full viscous coefficient, for the bounds (inf: not known)


def _play_open(sig: Signals, gap: float) -> FloatArray:
    """1 while the play is open (the motor has moved less than ``gap`` since it last pushed the load the
    other way), else 0: the play operator of half-width b/2 on the raw motor position, i.e. a Maxwell-slip
    element of break displacement b/2 that is not saturated."""
    return cached(sig, f"play:{gap:.6e}", lambda: np.asarray(
        np.abs(element(sig, 0.5 * gap)) < 1.0 - 1e-9, dtype=np.float64))


def _load_state(sig: Signals, s: BacklashShape) -> FloatArray:
    """(play open, engagement velocity step / dt) of the load simulated from the motor trajectory
    (:func:`stagectl.ident._kernels.backlash_load`), or the reversal-only play operator when ``dec_c`` is inf."""
    def make() -> FloatArray:
        if math.isinf(s.dec_c_m_s2):
            g = _play_open(sig, s.gap_m)
            eng = np.zeros(sig.n)
            eng[1:] = (g[:-1] > 0.5) & (g[1:] < 0.5)  # the play closes: the load is engaged (an impact)
            return np.vstack([g, eng * sig.v / sig.dt_s])
        return np.asarray(backlash_load(np.ascontiguousarray(sig.xf), np.ascontiguousarray(sig.v),
                                        np.ascontiguousarray(sig.acc_f), float(s.gap_m), float(s.dec_c_m_s2),
                                        float(s.dec_v_1_s), float(sig.dt_s)), dtype=np.float64)

    return cached(sig, "load:" + _shape_key(s), make)


def _shape_key(s: BacklashShape) -> str:
    return f"{s.gap_m:.6e}:{s.dec_c_m_s2:.6e}:{s.dec_v_1_s:.6e}"


def _backlash_columns(sig: Signals, h: Hyp, f_est: FloatArray) -> list[Column]:
    """While the play is open (g = 1) the motor carries neither the load's friction nor its mass: columns
    g·sgn(v), g·v, g·a with coefficients −(lost Coulomb, viscous, mass). When it closes, the load is engaged
    at once, an inelastic impact: the motor's measured acceleration has a one-sample spike of the momentum
    handed to the load, column ``δ_engage·(v_m − v_l)/dt`` (coefficient: the effective impact mass [kg];
    without it the spike leaks into the mass column and pushes the lost mass beyond the total).

    g comes from the load simulated along the measured motor trajectory (:func:`_load_state`): the play opens
    at reversals and also while the motor decelerates harder than the load's own friction decelerates the
    load (|a| > (Fc + Fv·|v|)/m_load), when the load runs ahead through the play."""
    s = BACKLASH.shape(h)
    st = _load_state(sig, s)
    g = st[0]
    k = _shape_key(s)
    if not math.isinf(s.dec_c_m_s2):  # one coefficient, the load mass: the lost friction is m_l·(dec_c, dec_v)
        return [Column("bl", g * (sig.acc_raw + s.dec_c_m_s2 * sig.direction + s.dec_v_1_s * sig.v), f"bl:{k}"),
                Column("bi", st[1], f"bi:{k}")]
    return [Column("bc", g * sig.direction, f"bc:{k}"), Column("bv", g * sig.v, f"bv:{k}"),
            Column("bm", g * sig.acc_raw, f"bm:{k}"), Column("bi", st[1], f"bi:{k}")]


def _backlash_params(h: Hyp) -> BacklashParams:
    th = h.theta
    m = th.get("m", h.fixed_mass_kg or 0.0)
    s = BACKLASH.shape(h)
    if "bl" in th:
        ml = -th["bl"]
        return BacklashParams(float(s.gap_m), ml * s.dec_c_m_s2, ml * s.dec_v_1_s, ml, coulomb_level(h), float(m),
                              float(th.get("bi", 0.0)), float(th.get("fv", math.inf)))
    return BacklashParams(float(s.gap_m), -th.get("bc", 0.0), -th.get("bv", 0.0), -th.get("bm", 0.0),
                          coulomb_level(h), float(m), float(th.get("bi", 0.0)), float(th.get("fv", math.inf)))


def _search_backlash(fitter: Fitter, cur: FitResult, h: Hyp) -> FitResult:
    """Two forms, the better physical fit wins.

    1. Reversal-only (the shape's default ``dec_c = inf``): the play operator on the motor position; free
       lost Coulomb, viscous and mass coefficients; b by a 1-D search (12-point grid + Brent).
    2. The load simulated along the measured motor trajectory (:func:`_load_state`) with all the friction on
       the load: ``dec_c = Fc/m_l``, ``dec_v = Fv/m_l`` from the current fit's Fc, Fv and a load mass m_l
       that starts at 0.8·m and is iterated from the fitted lost mass (one coefficient, column ``bl``, so the
       lost friction is m_l·(dec_c, dec_v) by construction). The RSS over b has several minima (a small play
       that only moves the engagement impacts fits them too, with an unphysical lost mass), so the grid is
       fine (ratio 1.4) and a fit outside the physical bounds (:func:`_backlash_bounds`) ranks behind every
       fit inside them.
    """
    sig = fitter.sig
    span = float(np.ptp(sig.xf))
    lo = max(4.0 * sig.noise_m, 2.0 * sig.quantum_m, 1e-7)
    hi = max(min(0.02 * span, 2e-3), 20 * lo)

    def score(r: FitResult) -> float:
        return r.rss + (2.0 * cur.rss if _backlash_bounds(_backlash_params(r.hyp)) else 0.0)

    b, _ = best_scalar(lambda g: BACKLASH.fit_with(fitter, h, gap_m=g).rss, list(np.geomspace(lo, hi, 12)), lo, hi,
                       maxiter=10)
    best = BACKLASH.fit_with(fitter, h, gap_m=b)
    th = cur.hyp.theta
    m = float(th.get("m", cur.hyp.fixed_mass_kg or 0.0))
    fc = coulomb_level(cur.hyp)
    if m <= 0.0 or fc <= 0.0:
        return best
    fv = max(float(th.get("fv", 0.0)), 0.0)
    ml = 0.8 * m
    lo = min(max(lo, 1e-6), 0.1 * hi)  # a play below 1 µm: the reversal-only form covers it, the overrun is nil
    ngrid = max(math.ceil(math.log(hi / lo) / math.log(1.4)), 8)
    for it in range(3):
        dc, dv = fc / ml, fv / ml

        def phys(g: float, dc: float = dc, dv: float = dv) -> float:
            return score(BACKLASH.fit_with(fitter, h, gap_m=g, dec_c_m_s2=dc, dec_v_1_s=dv))
        grid = list(np.geomspace(lo, hi, ngrid)) if it == 0 else [b / 1.2, b, b * 1.2]
        b, _ = best_scalar(phys, grid, lo, hi, maxiter=6 if it == 0 else 4)
        res = BACKLASH.fit_with(fitter, h, gap_m=b, dec_c_m_s2=dc, dec_v_1_s=dv)
        if score(res) < score(best):
            best = res
        p = _backlash_params(res.hyp)
        if _backlash_bounds(p) or abs(p.mass_lost_kg - ml) < 0.02 * m:
            break
        ml = p.mass_lost_kg
    return best


def _backlash_evidence(ev: ResidualView, p: BacklashParams) -> str:
    return (f"the residual is concentrated right after velocity reversals (RMS {ev.regime_text('near_reversal')} "
            f"vs {ev.regime_text('constant_speed')} at constant speed) and behaves like lost motion: for the "
            f"first {1e6 * p.gap_m:.3g} µm after a reversal the motor moves without the load ({p.coulomb_lost_n:.3g} N "
            f"of friction and {p.mass_lost_kg:.3g} kg of mass not carried), then the load engages at once (an impact; a step "
            "in displacement, where pre-sliding builds up gradually). Written to model.yaml as its backlash: "
            "section (a plant structure: stagectl.sim.backlash.plant_from_model simulates it; the feed-forward "
            "does not compensate the play)")


def backlash_split(p: BacklashParams) -> tuple[bool, float]:
    """How a backlash fit maps onto a motor + load plant: (friction on the load, mass of the side without
    friction [kg]). The friction is on the load when more than half the Coulomb level is lost inside the play;
    the side without it is the mass carried inside the play (friction on the motor) or lost in it (on the
    load). A valid plant needs that mass strictly between 0 and the total mass."""
    on_load = p.coulomb_lost_n >= 0.5 * abs(p.coulomb_n)
    return on_load, (p.mass_kg - p.mass_lost_kg if on_load else p.mass_lost_kg)


def _backlash_bounds(p: BacklashParams) -> list[str]:
    out = []
    on_load, other = backlash_split(p)
    if not p.mass_kg > 0:
        # no mass to split between motor and load (a recording that shows none, e.g. a force in phase with the
        # speed): the model writer could not represent the play, so it is not accepted
        out.append(f"fitted mass m = {p.mass_kg:.3g} kg leaves no motor/load split")
    elif not 0.0 < other < p.mass_kg:
        # the bound of the model file's motor + load plant: a fit it cannot represent is not accepted (before,
        # such a fit was accepted and then refused by the model writer, failing the whole run)
        out.append(f"mass lost in the play {p.mass_lost_kg:.3g} kg of m = {p.mass_kg:.3g} kg leaves no motor/load "
                   f"split (the {'motor' if on_load else 'load'}-side mass would be {other:.3g} kg, outside (0, m))")
    if not (-0.1 * abs(p.coulomb_n) <= p.coulomb_lost_n <= 1.1 * abs(p.coulomb_n)):
        out.append(f"friction lost in the play {p.coulomb_lost_n:.3g} N outside [0, Fc = {p.coulomb_n:.3g} N]")
    if p.mass_kg > 0 and not (-0.1 * p.mass_kg <= p.mass_lost_kg <= p.mass_kg):
        out.append(f"mass lost in the play {p.mass_lost_kg:.3g} kg outside [0, m = {p.mass_kg:.3g} kg]")
    if p.viscous_lost_n_s_m > 1.1 * max(p.viscous_n_s_m, 0.0) + 1e-9:
        out.append(f"viscous friction lost in the play {p.viscous_lost_n_s_m:.3g} N·s/m above all the viscous "
                   f"friction Fv = {p.viscous_n_s_m:.3g} N·s/m")
    if p.mass_kg > 0 and p.impact_mass_kg > 3.0 * max(p.mass_lost_kg, 0.0) + 0.02 * p.mass_kg:
        # an engagement hands the load at most its own momentum: about m_l·Δv, with m_l the mass lost in the
        # play (the column's Δv is taken at the engagement sample, partly after the impact, hence the margin
        # of 3). A larger impact coefficient is the impact column fitting something else (a null recording
        # with a hole once gave a 2 µm "backlash" with an impact mass 19x the mass lost)
        out.append(f"impact mass {p.impact_mass_kg:.3g} kg above the mass lost in the play {p.mass_lost_kg:.3g} kg "
                   "(an engagement cannot hand over more than the load's momentum)")
    return out


def _backlash_resolved(sig: Signals, rows: npt.NDArray[np.bool_], h: Hyp, floor_n: float,
                       _r: FloatArray) -> list[str]:
    """What shows lost motion, by the motor/load split the model file would write (:func:`backlash_split`).

    * Friction on the load (at least half the Coulomb level lost inside the play): the lost friction itself,
      a force of the order of the whole friction level, is the evidence; the acceptance rule judges its gain.
    * Friction on the motor: the load the file describes carries no friction, so the only thing the play
      takes away is the load's inertia. Its force ``L[m_lost·g·a]`` (g = 1 while the play is open) must
      reach ``floor_n`` in RMS over the validation samples within 2·b after a reversal. Below it, what the
      fit explains is a small change of the friction force right after reversals, which the model file
      would not even keep, and which any friction model that is slightly off there gives (a rate-dependent
      pre-sliding fitted by a rate-independent one, a controller whose force bends near reversals).

    Measured (docs/discovery.md §10): a GMS stage without play, whose commissioning experiments ran with the
    observer anti-wind-up on, gave a 24 µm "play" losing 0.05 N of 0.82 N and 0.35 g of 1.95 kg: lost
    inertia 4e-6 N RMS against a floor of 1.7e-3 N."""
    p = _backlash_params(h)
    on_load, _ = backlash_split(p)
    if on_load:
        return []
    s = BACKLASH.shape(h)
    g = _load_state(sig, s)[0]
    near = rows & (sig.x_rev_dist < 2.0 * s.gap_m)
    if not near.any():
        return [f"less than half the friction is lost in the play ({p.coulomb_lost_n:.3g} N of {p.coulomb_n:.3g} N) "
                f"and no validation sample lies within 2·b = {2e6 * s.gap_m:.3g} µm of a reversal to show the "
                "load's lost inertia"]
    f = sig.filt(p.mass_lost_kg * g * sig.acc_raw)[near]
    rms = float(np.sqrt(np.mean(f * f)))
    if rms >= floor_n:
        return []
    return [f"less than half the friction is lost in the play ({p.coulomb_lost_n:.3g} N of {p.coulomb_n:.3g} N: the "
            f"friction stays on the motor side), and the load's inertia lost while it is open (m_lost = "
            f"{p.mass_lost_kg:.3g} kg, {100 * p.mass_lost_kg / max(p.mass_kg, 1e-300):.2g} % of m) is {rms:.3g} N "
            f"RMS near reversals, below the {floor_n:.3g} N the acceptance rule credits: the data show a small "
            "friction change right after reversals, not lost motion"]


def _hide_backlash(st: HiddenStage) -> None:
    """Motor + load with a play of 5-30 µm; the motor side is 10-25 % of the load mass; friction on the load,
    sensor on the motor (a ball-screw axis with a rotary encoder)."""
    rng = st.rng
    st.backlash = {"gap_m": float(rng.uniform(5e-6, 30e-6)),
                   "other_mass_kg": float(rng.uniform(0.1, 0.25)) * st.mass_kg,
                   "contact_stiffness_n_m": 1e7, "coupling_step_s": 2e-5}


# ============================================================================================ bounds, keys
def _stribeck_bounds(p: StribeckParams) -> list[str]:
    out = []
    if p.fs_n < 0.0:
        out.append(f"Fs = {p.fs_n:.3g} N below 0 (a friction at rest that pushes)")
    if p.delta <= 0.5 + 1e-6 or p.delta >= 4.0 - 1e-6:
        out.append(f"δ = {p.delta:.3g} at the search bound [0.5, 4]")
    return out


def _presliding_bounds(p: PreslidingParams) -> list[str]:
    out = [] if p.elements > 0 else ["every slip force W_i at its lower bound 0 (no elastic element carries force)"]
    out += [f"micro-damping σ1 = {s:.3g} N·s/m on the Δ = {1e6 * d:.3g} µm element above its bound {b:.3g} N·s/m "
            f"(critically damped on the mass; 0 for an element without slip force)" for d, s, b in p.damping_excess]
    return out


def _lag_bounds(p: LagParams) -> list[str]:
    return [f"lag {p.lag_s:.3g} s at the search bound 1 s"] if p.lag_s >= 0.999 else []


def _asym_bounds(p: Asymmetry) -> list[str]:
    return [f"r = {p.ratio:+.3g} at the bound |r| < 0.95 (friction in one direction would vanish)"] \
        if abs(p.ratio) >= 0.949 else []


def _vasym_bounds(p: ViscousAsymmetryParams) -> list[str]:
    return [f"{name} = {v:.4g} N·s/m < 0 (viscous friction would push the stage)"
            for name, v in (("Fv+", p.fv_plus_n_s_m), ("Fv−", p.fv_minus_n_s_m)) if v < 0]


def _ripple_bounds(p: PositionRipple) -> list[str]:
    return [f"amplitude a = {p.amplitude:.3g} >= 1 (friction would reverse sign; bound a < 1)"] \
        if p.amplitude >= 1.0 else []


# ============================================================================================ the registry
BACKLASH: EffectSpec[BacklashShape, BacklashParams] = EffectSpec(
    "backlash", BacklashShape, _backlash_params, _backlash_evidence, _search_backlash, column_rank=80,
    columns=_backlash_columns, hide=_hide_backlash, regime="near_reversal", bounds=_backlash_bounds,
    resolved=_backlash_resolved,
    key=lambda p: f"play = {1e6 * p.gap_m:.3g} µm",
    separate_by="slow small reversals with a load-side sensor, or compare motor and load positions (lost motion "
                "is a step; pre-sliding a gradual build-up)")
STRIBECK: EffectSpec[StribeckShape, StribeckParams] = EffectSpec(
    "stribeck", StribeckShape, _stribeck_params, _stribeck_evidence, _search_stribeck, column_rank=20,
    friction_columns=_stribeck_columns, hide=_hide_stribeck, regime="low_speed", bounds=_stribeck_bounds,
    key=lambda p: f"Fs/Fc = {p.fs_n / max(p.fc_n, 1e-300):.3g}, vs = {p.vs_m_s:.3g} m/s",
    separate_by="slow constant-speed moves (below the Stribeck velocity) in both directions")
PRESLIDING: EffectSpec[PreslidingShape, PreslidingParams] = EffectSpec(
    "presliding", PreslidingShape, _presliding_params, _presliding_evidence, _search_presliding, column_rank=10,
    friction_columns=_presliding_columns, hide=_hide_presliding, regime="near_reversal",
    bounds=_presliding_bounds,
    key=lambda p: f"{p.elements} elements, largest Δ = {1e6 * p.largest_break_displacement_m:.3g} µm",
    separate_by="small back-and-forth moves of a few break displacements (pre-sliding hysteresis loops)")
LAG: EffectSpec[LagShape, LagParams] = EffectSpec(
    "frictional_lag", LagShape, lambda h: LagParams(float(LAG.shape(h).lag_s)), _lag_evidence, _search_lag,
    column_rank=21, implies=("stribeck",), contains=("stribeck",), hide=_hide_lag, regime="low_speed",
    bounds=_lag_bounds, key=lambda p: f"lag = {1e3 * p.lag_s:.3g} ms",
    separate_by="accelerate and decelerate through low speed at different rates")
ASYMMETRY: EffectSpec[AsymmetryShape, Asymmetry] = EffectSpec(
    "asymmetry", AsymmetryShape, lambda h: Asymmetry(ratio=float(ASYMMETRY.shape(h).ratio)), _asymmetry_evidence,
    _search_asymmetry, column_rank=25, scaling=lambda h: float(ASYMMETRY.shape(h).ratio), iterative=True,
    contains=("offset",), twin="asymmetry",
    to_twin=lambda p: Asymmetry(ratio=float(p.ratio)),
    from_twin=lambda h, e: ASYMMETRY.reshaped(h.adding("asymmetry"), ratio=e.ratio),
    refresh=_refresh_asymmetry, after_removal=_asymmetry_after_removal, hide=_hide_asymmetry,
    bounds=_asym_bounds, key=lambda p: f"r = {p.ratio:+.3g}",
    separate_by="constant-speed moves in both directions at several speeds (a common ratio on Coulomb and "
                "viscous parts vs a viscous-only difference)")
VISCOUS_ASYMMETRY: EffectSpec[NoShape, ViscousAsymmetryParams] = EffectSpec(
    "viscous_asymmetry", NoShape, _vasym_params, _vasym_evidence, _fit_as_is, column_rank=26,
    friction_columns=_vasym_columns, twin="viscous_asymmetry", tried_with=("offset",),
    to_twin=lambda p: ViscousAsymmetry(difference_n_s_m=float(p.difference_n_s_m)),
    from_twin=lambda h, e: h.adding("viscous_asymmetry"), hide=_hide_vasym, bounds=_vasym_bounds,
    key=lambda p: f"Fv+ = {p.fv_plus_n_s_m:.4g}, Fv− = {p.fv_minus_n_s_m:.4g} N·s/m",
    separate_by="constant-speed moves in both directions at several speeds")
RIPPLE: EffectSpec[WavelengthShape, PositionRipple] = EffectSpec(
    "position_ripple", WavelengthShape, _ripple_params,
    lambda ev, p: _periodic_evidence("multiplies the friction force (changes sign with the direction of motion)",
                                     f"a = {p.amplitude:.4g}", p),
    _search_ripple, column_rank=30, columns=_ripple_columns, iterative=True, twin="position_ripple",
    to_twin=lambda p: p,
    from_twin=lambda h, e: RIPPLE.reshaped(h.adding("position_ripple"), wavelength_m=e.wavelength_m),
    hide=_hide_ripple, bounds=_ripple_bounds,
    key=lambda p: f"λ = {1e3 * p.wavelength_m:.4g} mm, a = {p.amplitude:.3g}",
    separate_by="move over the same positions in both directions (a ripple of friction changes sign with "
                "the direction, cogging does not)")
COGGING: EffectSpec[WavelengthShape, Cogging] = EffectSpec(
    "cogging", WavelengthShape, _cogging_params,
    lambda ev, p: _periodic_evidence("is the same in both directions (conservative force)",
                                     f"A = {p.amplitude_n:.4g} N", p),
    lambda fitter, cur, h: _search_periodic(COGGING, fitter, cur, h, None), column_rank=60, columns=_cogging_columns,
    twin="cogging", to_twin=lambda p: p, resolved=_cogging_recurs,
    from_twin=lambda h, e: COGGING.reshaped(h.adding("cogging"), wavelength_m=e.wavelength_m), hide=_hide_cogging,
    key=lambda p: f"λ = {1e3 * p.wavelength_m:.4g} mm, A = {p.amplitude_n:.3g} N",
    separate_by="move over the same positions in both directions (cogging is the same both ways)")
OFFSET: EffectSpec[NoShape, Offset] = EffectSpec(
    "offset", NoShape, lambda h: Offset(force_n=h.theta.get("f0", 0.0)), _offset_evidence, _fit_as_is,
    column_rank=40, columns=_offset_columns, twin="offset", to_twin=lambda p: p,
    from_twin=lambda h, e: h.adding("offset"), hide=_hide_offset, key=lambda p: f"F_0 = {p.force_n:+.4g} N",
    separate_by="hold the stage at rest with the loop open or measure the break-away force in both directions "
                "(a constant force acts at rest, an asymmetric Coulomb level does not)")
SPRING: EffectSpec[NoShape, Spring] = EffectSpec(
    "spring", NoShape, _spring_params, _spring_evidence, _fit_as_is, column_rank=50, columns=_spring_columns,
    contains=("offset",), twin="spring", to_twin=lambda p: p,
    from_twin=lambda h, e: dataclasses.replace(h.adding("spring"), x_center_m=e.x0_m), hide=_hide_spring,
    key=lambda p: f"k_s = {p.stiffness_n_m:.4g} N/m",
    separate_by="hold the stage at several positions across the travel")
DELAY: EffectSpec[DelayShape, Delay] = EffectSpec(
    "delay", DelayShape, lambda h: Delay(delay_s=float(DELAY.shape(h).delay_s)), _delay_evidence, _search_delay,
    column_rank=70, target_delay=lambda h: float(DELAY.shape(h).delay_s), twin="delay", to_twin=lambda p: p,
    from_twin=lambda h, e: DELAY.reshaped(h.adding("delay"), delay_s=e.delay_s), refresh=_refresh_delay,
    hide=_hide_delay, key=lambda p: f"τ = {1e3 * p.delay_s:.3g} ms",
    separate_by="a sine sweep of the reference up to the loop bandwidth")

#: the discovery catalogue (issue 6), in search and report order; ``coulomb``, ``viscous`` and ``inertia`` are
#: always in the model. ``contains``: richer -> simpler nested effects (docs/discovery.md §1-2).
REGISTRY = Registry((STRIBECK, PRESLIDING, LAG, ASYMMETRY, RIPPLE, COGGING, OFFSET, SPRING, DELAY, VISCOUS_ASYMMETRY,
                     BACKLASH))
