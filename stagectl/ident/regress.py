"""Inverse-dynamics regression of a rigid-body + friction + effects model (separable least squares).

The model of a recording (symbols → names, SI units)::

    ū_τ = m·a + P(x, F)·F_fric + F_other(x)                                   [N]
    F_fric = fc·sgn(v) [+ Σ_i W_i·z_i/Δ_i]        Coulomb [+ Maxwell-slip elements: presliding]
           + (fs − fc)·sgn(v)·e,  e = exp(−|v/vs|^δ)   Stribeck (e lagged by lag_s: frictional lag)
           + fv·v                                    viscous
    P = (1 + a·sin(2πx/λ_r + φ_r)) · (1 + r·sgn(F_fric))    position_ripple, asymmetry
    F_other = A·sin(2πx/λ_c + φ_c) + F_0 + k_s·(x − x0)      cogging, offset, spring
    ū_τ: commanded force delayed by τ = delay_s, ZOH-averaged (see :mod:`stagectl.ident.signals`)

Given the nonlinear parameters (vs, δ, lag_s, τ, r, λ_r, λ_c, Δ_i) every other parameter enters linearly,
so each fit is a bounded linear least-squares problem on the filtered columns ``L[moving·column]``; the
nonlinear parameters are found by grid + bounded scalar search (ripple/cogging wavelengths from a position
periodogram of the residual). The ripple amplitude multiplies the current friction estimate, so that fit
is iterated (two passes).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.optimize import lsq_linear, minimize_scalar

from stagectl.ident._kernels import first_order_lag, maxwell_unit_states
from stagectl.ident.signals import Signals

FloatArray = npt.NDArray[np.float64]

#: the discovery catalogue (issue 6); ``coulomb``, ``viscous`` and ``inertia`` are always in the model
CATALOGUE = (
    "stribeck",
    "presliding",
    "frictional_lag",
    "asymmetry",
    "position_ripple",
    "cogging",
    "offset",
    "spring",
    "delay",
)
#: nested effects: richer -> simpler effects it contains (docs/discovery.md §1-2)
NESTED = {"spring": ("offset",), "asymmetry": ("offset",), "frictional_lag": ("stribeck",)}
#: effects whose presence implies another one in the model
IMPLIES = {"frictional_lag": ("stribeck",)}

FRICTION_COLS_PREFIX = ("fc", "w", "ds", "fv")


@dataclass
class Hyp:
    """A model hypothesis: which effects, their nonlinear parameters, the fitted linear parameters.

    ``theta`` maps column names to coefficients: ``m`` [kg], ``fc`` [N], ``fv`` [N·s/m], ``ds`` = fs − fc [N],
    ``w0..`` Maxwell-slip saturation forces W_i [N], ``f0`` [N], ``ks`` [N/m], ``cs``/``cc`` cogging sine and
    cosine amplitudes [N], ``rs``/``rc`` ripple sine/cosine relative amplitudes [–].
    """

    effects: tuple[str, ...] = ()
    nl: dict[str, Any] = field(default_factory=dict)
    theta: dict[str, float] = field(default_factory=dict)
    fixed_mass_kg: float | None = None
    x_center_m: float = 0.0

    def with_effect(self, name: str) -> Hyp:
        eff = list(self.effects)
        for dep in (*IMPLIES.get(name, ()), name):
            if dep not in eff:
                eff.append(dep)
        return replace(self, effects=tuple(eff), nl=dict(self.nl), theta=dict(self.theta))

    def has(self, name: str) -> bool:
        return name in self.effects

    def copy(self) -> Hyp:
        return replace(self, effects=tuple(self.effects), nl=dict(self.nl), theta=dict(self.theta))


# ---------------------------------------------------------------------------------------------- columns
def _cached(sig: Signals, key: str, fn: Any) -> FloatArray:
    hit = sig.cache.get(key)
    if hit is None:
        hit = fn()
        sig.cache[key] = hit
    return hit  # type: ignore[no-any-return]


def _sgn_v(sig: Signals) -> FloatArray:
    return sig.direction


def _element(sig: Signals, delta: float) -> FloatArray:
    """Normalised state z/Δ of one Maxwell-slip element along the gated position (depends on Δ only)."""
    return _cached(sig, f"maxwell:{delta:.6e}", lambda: maxwell_unit_states(
        _gated_position(sig), np.array([delta], dtype=np.float64))[:, 0].copy())


def _elements(sig: Signals, deltas: Sequence[float]) -> FloatArray:
    return np.column_stack([_element(sig, d) for d in deltas])


def min_damped_delta(sig: Signals) -> float:
    """Smallest break displacement [m] that gets a micro-damping column: 20 noise levels, 5 counts."""
    return max(20.0 * sig.noise_m, 5.0 * sig.quantum_m, 1e-8)


def _element_rate(sig: Signals, delta: float) -> FloatArray:
    """Element deflection rate dz/dt [m/s] (micro-damping column: force σ1_i·dz_i/dt)."""
    return _cached(sig, f"rate:{delta:.6e}", lambda: np.asarray(
        np.gradient(_element(sig, delta) * delta, sig.dt_s), dtype=np.float64))


def _given(sig: Signals, spec: dict[str, Any]) -> FloatArray:
    """Force of a given friction model (any tag) along the direction-gated position [N]."""
    def make() -> FloatArray:
        from stagectl.friction import build

        return np.asarray(build(spec).force_along(_gated_position(sig), sig.t), dtype=np.float64)

    return _cached(sig, "given:" + repr(sorted(spec.items())), make)


def _gated_position(sig: Signals) -> FloatArray:
    """Position that drives the pre-sliding elements: the **raw** measured position.

    The zero-phase filtered position anticipates a reversal by a few samples (elements driven by it would flip
    before the stage does), and gating out slow samples would lose the sub-threshold creep that stiff
    pre-sliding elements respond to. The raw position has neither problem; its noise only toggles elements
    far smaller than any resolvable break displacement (the grid starts at 4 noise levels).
    """
    def make() -> FloatArray:
        return np.ascontiguousarray(sig.x, dtype=np.float64)

    return _cached(sig, "xgated", make)


def _stribeck_col(sig: Signals, vs: float, delta: float, lag_s: float) -> FloatArray:
    def make() -> FloatArray:
        ess = np.exp(-np.abs(sig.v / vs) ** delta)
        e = ess if lag_s <= 0.0 else first_order_lag(np.ascontiguousarray(ess), sig.dt_s, lag_s, 1.0)
        return np.asarray(_sgn_v(sig) * e, dtype=np.float64)

    return _cached(sig, f"strib:{vs:.6e}:{delta:g}:{lag_s:.6e}", make)


def friction_columns(sig: Signals, h: Hyp) -> list[tuple[str, FloatArray]]:
    """Raw (unfiltered) friction columns before multiplicative effects."""
    cols: list[tuple[str, FloatArray]] = []
    if "given_spec" in h.nl:
        return [("given", _given(sig, h.nl["given_spec"]))]
    cols.append(("fc", _sgn_v(sig)))
    if h.has("presliding"):
        for i, d in enumerate(h.nl["deltas_m"]):
            cols.append((f"w{i}", _element(sig, d)))
        if h.nl.get("damped", True):
            # micro-damping only on elements that stay elastic over more than a sample at typical reversal
            # speeds; on the stiffest ones dz/dt is a one-sample spike that would fit transients, not physics
            d_min = min_damped_delta(sig)
            for i, d in enumerate(h.nl["deltas_m"]):
                if d >= d_min:
                    cols.append((f"s{i}", _element_rate(sig, d)))
    if h.has("stribeck"):
        lag = float(h.nl.get("lag_s", 0.0)) if h.has("frictional_lag") else 0.0
        cols.append(("ds", _stribeck_col(sig, h.nl["vs_m_s"], h.nl.get("delta", 2.0), lag)))
    cols.append(("fv", sig.v))
    return cols


def friction_force(sig: Signals, h: Hyp, theta: dict[str, float] | None = None) -> FloatArray:
    """Friction force before multiplicative effects [N] (raw, unfiltered)."""
    th = h.theta if theta is None else theta
    out = np.zeros(sig.n)
    for name, col in friction_columns(sig, h):
        out += th.get(name, 0.0) * col
    return out


def _ripple_phase(sig: Signals, lam: float) -> tuple[FloatArray, FloatArray]:
    def make() -> tuple[FloatArray, FloatArray]:
        ph = 2.0 * np.pi * sig.xf / lam
        return np.sin(ph), np.cos(ph)

    return _cached(sig, f"sincos:{lam:.9e}", make)  # type: ignore[return-value]


def _bounds(name: str) -> tuple[float, float]:
    if name in ("m", "fc", "fv", "ds", "given") or (name[0] in "ws" and name[1:].isdigit()):
        return 0.0, np.inf
    return -np.inf, np.inf


def design(
    sig: Signals, h: Hyp, f_prev: FloatArray | None = None
) -> tuple[list[str], list[FloatArray], FloatArray]:
    """Raw columns and raw target for hypothesis ``h``.

    Returns names, raw columns and the raw target ``ū_τ − m_fixed·a`` (all unfiltered).
    """
    names: list[str] = []
    cols: list[FloatArray] = []
    fcols = friction_columns(sig, h)
    if f_prev is None:
        f_prev = friction_force(sig, h) if h.theta else _sgn_v(sig)
    mult = np.ones(sig.n)
    if h.has("asymmetry"):
        mult = mult * (1.0 + h.nl.get("r", 0.0) * np.sign(f_prev))
    for name, c in fcols:
        names.append(name)
        cols.append(c * mult)
    if h.has("position_ripple"):
        s, co = _ripple_phase(sig, h.nl["ripple_lambda_m"])
        fp = f_prev * mult
        names += ["rs", "rc"]
        cols += [fp * s, fp * co]
    if h.has("offset") or h.has("spring"):
        names.append("f0")
        cols.append(np.ones(sig.n))
    if h.has("spring"):
        names.append("ks")
        cols.append(sig.xf - h.x_center_m)
    if h.has("cogging"):
        s, co = _ripple_phase(sig, h.nl["cogging_lambda_m"])
        names += ["cs", "cc"]
        cols += [s, co]
    target = sig.ubar(float(h.nl.get("delay_s", 0.0)) if h.has("delay") else 0.0)
    if h.fixed_mass_kg is None:
        names.append("m")
        cols.append(sig.acc_raw)
    else:
        target = target - h.fixed_mass_kg * sig.acc_raw
    return names, cols, target


def _filtered(sig: Signals, key: str, raw: FloatArray) -> FloatArray:
    return _cached(sig, "F:" + key, lambda: sig.filt(raw))


def _col_key(name: str, h: Hyp) -> str | None:
    """Cache key for a column that does not depend on the previous fit (None: do not cache)."""
    if name in ("rs", "rc"):
        return None
    nl = h.nl
    if name == "fc":
        return "fc"
    if name == "fv":
        return "fv"
    if name == "m":
        return "m"
    if name == "f0":
        return "f0"
    if name == "ks":
        return f"ks:{h.x_center_m:.9e}"
    if name == "ds":
        lag = nl.get("lag_s", 0.0) if h.has("frictional_lag") else 0.0
        return f"ds:{nl['vs_m_s']:.6e}:{nl.get('delta', 2.0):g}:{lag:.6e}"
    if name[0] in "ws" and name[1:].isdigit():
        return f"{name[0]}:{nl['deltas_m'][int(name[1:])]:.6e}"
    if name == "given":
        return "given:" + repr(sorted(nl["given_spec"].items()))
    if name in ("cs", "cc"):
        return f"{name}:{nl['cogging_lambda_m']:.9e}"
    return None


@dataclass
class FitResult:
    hyp: Hyp
    rss: float
    n: int

    @property
    def rms(self) -> float:
        return math.sqrt(self.rss / max(self.n, 1))


def filtered_design(
    sig: Signals, h: Hyp, f_prev: FloatArray | None = None
) -> tuple[list[str], FloatArray, FloatArray]:
    """Filtered design matrix (all samples) and filtered target.

    Columns that do not depend on the previous fit are filtered once and cached. The asymmetry
    multiplier is linear in r, ``c·(1 + r·s) = c + r·(c·s)`` with ``s = sgn(F_prev)``, so both parts are
    cached (keyed by the sign pattern) and combined; the rest is filtered in one batched call.
    """
    hb = h
    r = 0.0
    sgn_f: FloatArray | None = None
    if h.has("asymmetry"):
        r = float(h.nl.get("r", 0.0))
        fp = f_prev if f_prev is not None else (friction_force(sig, h) if h.theta else _sgn_v(sig))
        sgn_f = np.sign(fp)
        hb = h.copy()
        hb.effects = tuple(e for e in h.effects if e != "asymmetry")
    names, cols, target = design(sig, hb, f_prev)
    if h.has("position_ripple") and sgn_f is not None:
        # ripple columns carry the asymmetry multiplier of the friction estimate
        for j, name in enumerate(names):
            if name in ("rs", "rc"):
                cols[j] = cols[j] * (1.0 + r * sgn_f)
    out: list[FloatArray | None] = [None] * len(names)
    todo: list[int] = []
    skey = None
    if sgn_f is not None:
        skey = "sgn:" + str(hash(sgn_f.astype(np.int8).tobytes()))
    for j, name in enumerate(names):
        key = _col_key(name, hb)
        if key is None:
            todo.append(j)
            continue
        base = _filtered(sig, key, cols[j])
        if sgn_f is not None and _is_friction_col(name):
            assert skey is not None
            part = _filtered(sig, key + "|" + skey, cols[j] * sgn_f)
            base = base + r * part
        out[j] = base
    if todo:
        raw = np.column_stack([cols[j] for j in todo])
        filt = sig.filt_many(raw)
        for i, j in enumerate(todo):
            out[j] = filt[:, i]
    tkey = f"target:{h.nl.get('delay_s', 0.0) if h.has('delay') else 0.0:.6e}:{h.fixed_mass_kg}"
    y = _filtered(sig, tkey, target)
    return names, np.column_stack(out), y


def _is_friction_col(name: str) -> bool:
    return name in ("fc", "fv", "ds", "given") or (name[0] in "ws" and name[1:].isdigit())


def solve(names: list[str], a: FloatArray, y: FloatArray) -> tuple[FloatArray, float]:
    """Bounded linear least squares with column scaling. Returns (θ, residual sum of squares).

    Solved through the normal equations of the scaled columns (p ≤ ~30, so the Gram matrix is cheap and
    well conditioned after scaling): with ``G = AᵀA = RᵀR`` and ``c = R⁻ᵀAᵀy``,
    ``‖y − Aθ‖² = ‖y‖² − ‖c‖² + ‖c − Rθ‖²``, so the bounded solver only sees a p×p system.
    """
    scale = np.sqrt(np.mean(a * a, axis=0))
    scale[scale == 0] = 1.0
    an = a / scale
    g = an.T @ an
    b = an.T @ y
    p = g.shape[0]
    g[np.diag_indices(p)] += 1e-12 * max(float(np.trace(g)), 1e-300)
    try:
        r = np.linalg.cholesky(g).T
    except np.linalg.LinAlgError:
        g[np.diag_indices(p)] += 1e-8 * float(np.trace(g))
        r = np.linalg.cholesky(g).T
    c = np.linalg.solve(r.T, b)
    yy = float(y @ y)
    base = max(yy - float(c @ c), 0.0)
    lo = np.array([_bounds(n)[0] for n in names])
    hi = np.array([_bounds(n)[1] for n in names])
    sol = np.linalg.solve(r, c)
    th = sol / scale
    if not (np.all(th >= lo - 1e-12) and np.all(th <= hi + 1e-12)):
        res = lsq_linear(r, c, bounds=(lo * scale, hi * scale), method="bvls")
        sol = res.x
        th = sol / scale
    e = c - r @ sol
    return np.asarray(th, dtype=np.float64), base + float(e @ e)


def fit_linear(sig: Signals, h: Hyp, rows: npt.NDArray[np.bool_]) -> FitResult:
    """Fit the linear parameters of ``h`` (nonlinear ones fixed) on ``rows``; iterate for multiplicative terms."""
    passes = 2 if (h.has("position_ripple") or h.has("asymmetry")) else 1
    hh = h.copy()
    f_prev = None
    if not hh.theta:
        f_prev = None
    rss = np.inf
    for _ in range(passes):
        names, a, y = filtered_design(sig, hh, f_prev)
        th, rss = solve(names, a[rows], y[rows])
        new_theta = dict(zip(names, (float(v) for v in th)))
        if hh.has("position_ripple"):
            base = friction_force(sig, hh, new_theta)
            # fold the ripple amplitude into the next pass's friction estimate
            f_prev = base
        hh.theta = new_theta
    return FitResult(hh, rss, int(rows.sum()))


def residual(sig: Signals, h: Hyp) -> FloatArray:
    """Filtered force residual ``L[moving·(ū_τ − m·a − F_model)]`` of a fitted hypothesis [N] (all samples)."""
    f_prev = friction_force(sig, h) if h.theta else None
    names, a, y = filtered_design(sig, h, f_prev)
    th = np.array([h.theta.get(n, 0.0) for n in names])
    return np.asarray(y - a @ th, dtype=np.float64)


def model_force(sig: Signals, h: Hyp) -> FloatArray:
    """Filtered model force ``L[moving·(m·a + F_model)]`` [N] for plots."""
    f_prev = friction_force(sig, h) if h.theta else None
    names, a, _ = filtered_design(sig, h, f_prev)
    th = np.array([h.theta.get(n, 0.0) for n in names])
    return np.asarray(a @ th, dtype=np.float64)


# ---------------------------------------------------------------------------------------------- searches
def _best_scalar(
    fun: Any, grid: Iterable[float], lo: float, hi: float, log: bool = True, maxiter: int = 12
) -> tuple[float, float]:
    """Grid search then bounded Brent refinement around the best grid point. Returns (x, f(x))."""
    pts = list(grid)
    vals = [fun(p) for p in pts]
    i = int(np.argmin(vals))
    best_x, best_f = pts[i], vals[i]
    a = pts[max(i - 1, 0)]
    b = pts[min(i + 1, len(pts) - 1)]
    a, b = max(min(a, b), lo), min(max(a, b), hi)
    if b > a:
        if log and a > 0:
            res = minimize_scalar(
                lambda s: fun(math.exp(s)), bounds=(math.log(a), math.log(b)), method="bounded",
                options={"maxiter": maxiter, "xatol": 1e-3},
            )
            xr = math.exp(float(res.x))
        else:
            res = minimize_scalar(fun, bounds=(a, b), method="bounded", options={"maxiter": maxiter})
            xr = float(res.x)
        fr = float(res.fun)
        if fr < best_f:
            best_x, best_f = xr, fr
    return best_x, best_f


def speed_range(sig: Signals) -> tuple[float, float]:
    sp = np.abs(sig.v[sig.evaluate])
    vmax = float(np.percentile(sp, 99)) if sp.size else 1.0
    vmin = max(2.0 * sig.v_stick, 2e-3 * vmax)
    return vmin, vmax


def presliding_grid(sig: Signals, n: int = 14) -> list[float]:
    """Break displacements Δ_i [m] for presliding elements: log-spaced, from a few noise levels up to
    about the displacement of a few samples at high speed (beyond that the element is Coulomb)."""
    span = float(np.ptp(sig.xf))
    lo = max(4.0 * sig.noise_m, 2.0 * sig.quantum_m, 1e-8)
    hi = min(0.05 * span, 5e-4)
    hi = max(hi, 20 * lo)
    return [float(v) for v in np.geomspace(lo, hi, n)]


def position_periodogram(
    sig: Signals, rows: npt.NDArray[np.bool_], resid: FloatArray, weight: FloatArray | None = None, top: int = 4
) -> list[float]:
    """Candidate wavelengths [m] of a periodic dependence of ``resid`` (or ``resid/weight``) on position.

    The residual is averaged in position bins (weighted least squares per bin when ``weight`` is given,
    e.g. the friction force for a multiplicative ripple), then Fourier transformed over position; the
    strongest peaks with at least 2 periods in the travelled span and 4 bins per period are returned.
    """
    x = sig.xf[rows]
    r = resid[rows]
    w = np.ones_like(r) if weight is None else weight[rows]
    lo, hi = float(x.min()), float(x.max())
    span = hi - lo
    if span <= 0:
        return []
    nb = 4096
    idx = np.clip(((x - lo) / span * nb).astype(int), 0, nb - 1)
    num = np.bincount(idx, weights=r * w, minlength=nb)
    den = np.bincount(idx, weights=w * w, minlength=nb)
    have = den > 0
    prof = np.zeros(nb)
    prof[have] = num[have] / den[have]
    prof[have] -= prof[have].mean()
    spec = np.abs(np.fft.rfft(prof * have, n=4 * nb)) ** 2
    freqs = np.fft.rfftfreq(4 * nb, d=span / nb)  # cycles per metre
    ok = (freqs >= 2.0 / span) & (freqs <= nb / (4.0 * span))
    spec = np.where(ok, spec, 0.0)
    out: list[float] = []
    s = spec.copy()
    for _ in range(top):
        k = int(np.argmax(s))
        if s[k] <= 0:
            break
        out.append(float(1.0 / freqs[k]))
        s[max(k - 6, 0) : k + 7] = 0.0
    return out
