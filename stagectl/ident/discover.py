"""The discovery workflow: find where model and measurement disagree, name the missing effect, add it,
show the validation gap shrink, iterate (issue 6).

Gap metric (``GAP_METRIC``): **filtered inverse-dynamics force residual, RMS [N], on validation data**::

    r = L[moving · (ū_τ − m·a − F_model(x, v) − F_other(x))]        (see stagectl.ident.signals)

evaluated on moving samples away from stick phases. It is a closed-loop-safe metric: it needs no
integration of the plant (an open-loop replay of a double integrator drifts) and is insensitive to the
controller. Validation data is the ``--validate`` recording, or contiguous held-out blocks of the same file
(block ``k`` of ``HOLDOUT_BLOCKS`` equal blocks, with a guard of filter length removed at each boundary).

Decision rule (docs/discovery.md §4): each round every catalogue effect not in the model is added in turn,
refitted on estimation data and scored on validation data. An effect is *acceptable* if

1. the validation gap shrinks by at least ``MIN_REL_GAIN`` (relative), a margin above what noise-only
   recordings with a complete model reach (the null tests in ``tests/ident`` measure it),
2. the force it explains, ``sqrt(gap_before² − gap_after²)``, is at least ``MIN_EXPLAINED_FRACTION`` of
   the RMS non-inertial force ``ū − m̂·a`` and ``MIN_EXPLAINED_NOISE`` times the sensor-noise floor of the metric, and
3. the mean per-sample reduction of the squared residual is positive at the 97.5 % level of a circular
   block bootstrap (block length from the autocorrelation of the per-sample gain, >= 0.1 s).

Among acceptable effects the one with the largest gain is named, except that a richer effect that contains
a simpler acceptable one (spring ⊃ offset, asymmetry ⊃ offset, frictional_lag ⊃ stribeck) is named only if it
beats the simpler one by the same tests. Rejected candidates (fit on estimation data but fail on
validation data) are reported with their figures. Rounds repeat until nothing more is accepted.

Two refinements of the greedy search:

* **pairs**: when no single effect validates, pairs of the best-fitting candidates are tried (interacting
  effects, e.g. an offset and a cogging whose position coverage differs between estimation and validation
  blocks, each biasing the other's fit alone); a pair must pass the same test;
* **pruning**: at the end, an accepted effect that later, richer effects made redundant (an offset accepted
  before the asymmetry or spring that contains it) is removed when the model without it is not
  significantly worse; it is then listed under ``rejected`` with the reason.

Stick phases (docs/discovery.md §5) are excluded explicitly (see :mod:`stagectl.ident.signals`); a frictional lag
shorter than two samples is treated as no lag; ripple/cogging phases are fitted on estimation data only, so a
phase-locked ripple that does not transfer fails validation and is rejected (§6).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from stagectl.errors import DataError
from stagectl.ident import regress as rg
from stagectl.ident.recording import Recording
from stagectl.ident.regress import CATALOGUE, NESTED, FitResult, Hyp
from stagectl.ident.signals import Signals, prepare

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

GAP_METRIC = (
    "force_residual_rms_n: RMS [N] of the zero-phase low-pass filtered inverse-dynamics force residual "
    "L[ū_τ − m·a − F_friction(x,v) − F_other(x)] on validation data, moving samples outside stick phases "
    "(ZOH-consistent: the second difference of x is paired with the hat-kernel average of the held, possibly "
    "delayed force; (u[k−1]+u[k])/2 without delay)"
)
#: minimum relative reduction of the validation gap for an effect to be accepted
MIN_REL_GAIN = 0.20
#: minimum force an effect must explain on validation data, sqrt(gap_before² − gap_after²): the larger of
#: MIN_EXPLAINED_FRACTION of the RMS non-inertial force ū − m̂·a (physically negligible below) and MIN_EXPLAINED_NOISE
#: times the sensor-noise floor of the metric (m·σ_x·gain; at a few times that floor, sampling and
#: discretisation residue, not physics, is what a flexible effect fits)
MIN_EXPLAINED_FRACTION = 0.002
MIN_EXPLAINED_NOISE = 1.5
#: bootstrap confidence for the "gap reduced" test
BOOT_QUANTILE = 0.025
BOOT_SAMPLES = 400
HOLDOUT_BLOCKS = 6
HOLDOUT_VALIDATION = (1, 4)


# ================================================================================================ data
@dataclass
class Dataset:
    """Estimation and validation signals with their evaluation rows."""

    est: Signals
    est_rows: BoolArray
    val: Signals
    val_rows: BoolArray
    split: str


def make_dataset(
    rec: Recording, validate: Recording | None = None, cutoff_hz: float | None = None
) -> Dataset:
    """Prepare estimation/validation data (held-out contiguous blocks when ``validate`` is None)."""
    est = prepare(rec, cutoff_hz=cutoff_hz)
    if validate is not None:
        val = prepare(validate, cutoff_hz=est.cutoff_hz)
        return Dataset(est, est.evaluate.copy(), val, val.evaluate.copy(), f"validation file {validate.source}")
    n = est.n
    edges = np.linspace(0, n, HOLDOUT_BLOCKS + 1).astype(int)
    vmask = np.zeros(n, bool)
    for b in HOLDOUT_VALIDATION:
        vmask[edges[b] : edges[b + 1]] = True
    # guard: a few filter lengths at every block boundary, so that estimation and validation residuals are
    # not correlated through the filter
    g = 4 * est.guard
    boundary = np.zeros(n, bool)
    for e in edges[1:-1]:
        boundary[max(e - g, 0) : e + g] = True
    val_rows = est.evaluate & vmask & ~boundary
    est_rows = est.evaluate & ~vmask & ~boundary
    if val_rows.sum() < 50 or est_rows.sum() < 50:
        raise DataError(f"{rec.source}: not enough moving samples to hold out validation blocks")
    blocks = ", ".join(f"{rec.t[edges[b]]:.3g}-{rec.t[edges[b + 1] - 1]:.3g} s" for b in HOLDOUT_VALIDATION)
    return Dataset(est, est_rows, est, val_rows, f"held-out contiguous blocks of {rec.source}: {blocks}")


# ================================================================================================ fitting
def fit_start(ds: Dataset, start: Hyp | None = None) -> FitResult:
    """Start model: the given hypothesis refitted, or mass + Coulomb + viscous."""
    h = start.copy() if start is not None else Hyp()
    if start is None:
        x = ds.est.xf[ds.est_rows]
        h.x_center_m = float(0.5 * (x.min() + x.max()))
    return rg.fit_linear(ds.est, h, ds.est_rows)


def _fit_with(ds: Dataset, h: Hyp, **nl: Any) -> FitResult:
    hh = h.copy()
    hh.nl.update(nl)
    return rg.fit_linear(ds.est, hh, ds.est_rows)


def fit_candidate(ds: Dataset, cur: FitResult, name: str) -> FitResult:
    """Add effect ``name`` to the current model and fit it (nonlinear parameters searched) on estimation data."""
    sig, rows = ds.est, ds.est_rows
    h = cur.hyp.with_effect(name)
    if name in ("offset", "spring", "presliding"):
        if name != "presliding":
            return rg.fit_linear(sig, h, rows)
        h.nl["deltas_m"] = rg.presliding_grid(sig)
        first = rg.fit_linear(sig, h, rows)
        active = [i for i in range(len(h.nl["deltas_m"])) if first.hyp.theta.get(f"w{i}", 0.0) > 0]
        if not active:
            return first
        # keep the elements that carry force and refine their break displacements (coordinate descent on
        # log Δ_i: the virgin curve is piecewise linear with breakpoints Δ_i, §2.3)
        deltas = [h.nl["deltas_m"][i] for i in active]
        for _sweep in range(2):
            for j in range(len(deltas)):
                def cost(d: float, j: int = j) -> float:
                    trial = list(deltas)
                    trial[j] = d
                    return _fit_with(ds, h, deltas_m=tuple(trial)).rss
                dj = deltas[j]
                best, _ = rg._best_scalar(cost, [dj / 1.8, dj, dj * 1.8], dj / 2.5, dj * 2.5, maxiter=8)
                deltas[j] = best
        h.nl["deltas_m"] = tuple(sorted(deltas))
        return rg.fit_linear(sig, h, rows)
    if name == "stribeck" or (name == "frictional_lag" and not cur.hyp.has("stribeck")):
        h_s = cur.hyp.with_effect("stribeck")
        vmin, vmax = rg.speed_range(sig)
        grid = list(np.geomspace(vmin, 0.5 * vmax, 10))
        best: tuple[float, float, float] | None = None
        for delta in (1.0, 2.0):
            vs, f = rg._best_scalar(lambda v, d=delta: _fit_with(ds, h_s, vs_m_s=v, delta=d).rss, grid, vmin, vmax)
            if best is None or f < best[2]:
                best = (vs, delta, f)
        assert best is not None
        vs, delta, _ = best
        dl, _ = rg._best_scalar(lambda d: _fit_with(ds, h_s, vs_m_s=vs, delta=d).rss, [0.7, 1.0, 1.5, 2.0, 3.0],
                                0.5, 4.0, log=False, maxiter=8)
        # joint refinement of (log vs, δ): the two trade off, separate line searches stop short
        from scipy.optimize import minimize

        res = minimize(lambda p: _fit_with(ds, h_s, vs_m_s=math.exp(p[0]), delta=float(np.clip(p[1], 0.5, 4.0))).rss,
                       np.array([math.log(vs), dl]), method="Nelder-Mead",
                       options={"maxfev": 40, "xatol": 1e-3, "fatol": 1e-12, "initial_simplex": np.array(
                           [[math.log(vs), dl], [math.log(vs) + 0.2, dl], [math.log(vs), dl + 0.2]])})
        vs, dl = math.exp(float(res.x[0])), float(np.clip(res.x[1], 0.5, 4.0))
        if name == "stribeck":
            return _fit_with(ds, h_s, vs_m_s=vs, delta=dl)
        h.nl.update(vs_m_s=vs, delta=dl)
    if name == "frictional_lag":
        dt = sig.dt_s
        # a lag shorter than one sample cannot be told from the sampling itself: search from dt up
        grid = list(np.geomspace(dt, 0.5, 10))
        lag, _ = rg._best_scalar(lambda s: _fit_with(ds, h, lag_s=s).rss, grid, dt, 1.0)
        if lag < 2.0 * dt:
            # the optimum sits at the search bound: no lag longer than a sample is supported by the data
            if cur.hyp.has("stribeck"):
                return cur
            h_s = cur.hyp.with_effect("stribeck")
            h_s.nl.update(vs_m_s=h.nl["vs_m_s"], delta=h.nl["delta"])
            return rg.fit_linear(sig, h_s, rows)
        # re-tune vs with the lag in place
        vs0 = h.nl["vs_m_s"]
        vs, _ = rg._best_scalar(lambda v: _fit_with(ds, h, lag_s=lag, vs_m_s=v).rss,
                                [vs0 / 2, vs0, vs0 * 2], vs0 / 4, vs0 * 4, maxiter=8)
        return _fit_with(ds, h, lag_s=lag, vs_m_s=vs)
    if name == "delay":
        dt = sig.dt_s
        grid = [k * dt for k in range(0, 21)]
        tau, _ = rg._best_scalar(lambda s: _fit_with(ds, h, delay_s=s).rss, grid, 0.0, 20 * dt, log=False)
        return _fit_with(ds, h, delay_s=tau)
    if name == "asymmetry":
        r, _ = rg._best_scalar(lambda r: _fit_with(ds, h, r=r).rss, list(np.linspace(-0.8, 0.8, 9)), -0.95, 0.95,
                               log=False, maxiter=14)
        return _fit_with(ds, h, r=r)
    if name in ("position_ripple", "cogging"):
        resid = rg.residual(sig, cur.hyp)
        key = "ripple_lambda_m" if name == "position_ripple" else "cogging_lambda_m"
        weight = None
        if name == "position_ripple":
            weight = sig.filt(rg.friction_force(sig, cur.hyp))
        cands = rg.position_periodogram(sig, rows, resid, weight)
        span = float(np.ptp(sig.xf[rows]))
        best_fit: FitResult | None = None
        for lam0 in cands:
            rel = 1.5 * lam0 / span
            lo, hi = lam0 * (1 - rel), lam0 * (1 + rel)
            lam, _ = rg._best_scalar(lambda s: _fit_with(ds, h, **{key: s}).rss, [lo, lam0, hi], lo, hi, maxiter=10)
            fr = _fit_with(ds, h, **{key: lam})
            if best_fit is None or fr.rss < best_fit.rss:
                best_fit = fr
        if best_fit is None:
            h.nl[key] = span
            return rg.fit_linear(sig, h, rows)
        return best_fit
    raise ValueError(f"unknown effect {name!r}")


# ================================================================================================ statistics
def gap(sig: Signals, rows: BoolArray, h: Hyp) -> tuple[float, FloatArray]:
    """Validation gap (RMS [N]) and the residual on ``rows``."""
    r = rg.residual(sig, h)[rows]
    return float(np.sqrt(np.mean(r * r))), r


def block_length(d: FloatArray, dt_s: float) -> int:
    """Block length for the bootstrap: 2× the lag where the autocorrelation of ``d`` falls below 0.1
    (at least 0.1 s, at most a tenth of the data)."""
    n = d.shape[0]
    x = d - d.mean()
    nf = 1 << int(math.ceil(math.log2(2 * n)))
    f = np.fft.rfft(x, nf)
    ac = np.fft.irfft(f * np.conj(f), nf)[:n]
    ac = ac / ac[0] if ac[0] > 0 else ac
    below = np.flatnonzero(ac < 0.1)
    lag = int(below[0]) if below.size else n // 10
    return int(min(max(2 * lag, int(0.1 / dt_s), 10), max(n // 10, 10)))


def bootstrap_lower(d: FloatArray, block: int, seed: int = 0) -> float:
    """Lower ``BOOT_QUANTILE`` quantile of the mean of ``d`` under a circular block bootstrap."""
    n = d.shape[0]
    rng = np.random.default_rng(seed)
    nb = int(math.ceil(n / block))
    cs = np.concatenate([[0.0], np.cumsum(np.concatenate([d, d[:block]]))])
    starts = rng.integers(0, n, size=(BOOT_SAMPLES, nb))
    sums = (cs[starts + block] - cs[starts]).sum(axis=1)
    means = sums / (nb * block)
    return float(np.quantile(means, BOOT_QUANTILE))


@dataclass
class Comparison:
    gap_before: float
    gap_after: float
    rel_gain: float
    boot_lower: float
    block: int
    explained_n: float
    min_explained_n: float

    @property
    def significant(self) -> bool:
        return (self.rel_gain >= MIN_REL_GAIN and self.boot_lower > 0.0
                and self.explained_n >= self.min_explained_n)


def compare(r_before: FloatArray, r_after: FloatArray, dt_s: float, min_explained_n: float = 0.0) -> Comparison:
    """Validation comparison of two residuals (same samples); ``min_explained_n``: explained-force floor [N]."""
    d = r_before**2 - r_after**2
    blk = block_length(d, dt_s)
    gb = float(np.sqrt(np.mean(r_before**2)))
    ga = float(np.sqrt(np.mean(r_after**2)))
    expl = math.sqrt(max(gb * gb - ga * ga, 0.0))
    return Comparison(gb, ga, (gb - ga) / gb if gb > 0 else 0.0, bootstrap_lower(d, blk), blk, expl,
                      min_explained_n)


# ================================================================================================ localisation
def regimes(sig: Signals, rows: BoolArray) -> dict[str, BoolArray]:
    """Masks (within ``rows``) of the regimes used to localise the residual."""
    v = sig.v
    a = sig.acc_f
    sp = np.abs(v)
    vmax = float(np.percentile(sp[rows], 99)) if rows.any() else 1.0
    amax = float(np.percentile(np.abs(a[rows]), 95)) if rows.any() else 1.0
    span = float(np.ptp(sig.xf))
    d_pre = float(np.clip(0.002 * span, 5e-6, 1e-4))
    near = sig.x_rev_dist < d_pre
    low = (sp < 0.1 * vmax) & ~near
    const = (np.abs(a) < 0.1 * amax) & (sp >= 0.1 * vmax) & ~near
    accel = (np.abs(a) >= 0.3 * amax) & ~near
    out = {
        f"near_reversal (< {d_pre * 1e6:.3g} µm after a reversal)": near,
        f"low_speed (|v| < {0.1 * vmax:.3g} m/s)": low,
        "constant_speed": const,
        f"accelerating (|a| > {0.3 * amax:.3g} m/s²)": accel,
        "positive_direction": v > 0,
        "negative_direction": v < 0,
    }
    return {k: m & rows for k, m in out.items()}


def localise(sig: Signals, rows: BoolArray, resid_all: FloatArray, n_windows: int = 12) -> list[dict[str, Any]]:
    """Where the residual lives: per regime, per position band and per time window (on ``rows``)."""
    out: list[dict[str, Any]] = []
    r = resid_all
    tot = float(np.sum(r[rows] ** 2)) or 1.0
    nrows = int(rows.sum()) or 1
    for name, m in regimes(sig, rows).items():
        k = int(m.sum())
        if k == 0:
            continue
        rr = r[m]
        out.append({
            "kind": "regime", "regime": name, "samples": k, "share_of_samples": k / nrows,
            "rms_n": float(np.sqrt(np.mean(rr * rr))), "mean_n": float(np.mean(rr)),
            "share_of_squared_residual": float(np.sum(rr * rr)) / tot,
        })
    x = sig.xf
    lo, hi = float(x[rows].min()), float(x[rows].max())
    edges = np.linspace(lo, hi, 9)
    for i in range(8):
        m = rows & (x >= edges[i]) & (x <= edges[i + 1])
        k = int(m.sum())
        if k == 0:
            continue
        rr = r[m]
        out.append({
            "kind": "position", "regime": f"x in [{edges[i]:.6g}, {edges[i + 1]:.6g}] m", "samples": k,
            "share_of_samples": k / nrows, "rms_n": float(np.sqrt(np.mean(rr * rr))),
            "mean_n": float(np.mean(rr)), "share_of_squared_residual": float(np.sum(rr * rr)) / tot,
        })
    t = sig.t
    idx = np.flatnonzero(rows)
    wins = np.array_split(idx, n_windows)
    for w in wins:
        if w.size == 0:
            continue
        rr = r[w]
        out.append({
            "kind": "time", "regime": f"t in [{t[w[0]]:.3f}, {t[w[-1]]:.3f}] s", "samples": int(w.size),
            "share_of_samples": w.size / nrows, "rms_n": float(np.sqrt(np.mean(rr * rr))),
            "mean_n": float(np.mean(rr)), "share_of_squared_residual": float(np.sum(rr * rr)) / tot,
        })
    return out


# ================================================================================================ evidence
def describe_params(h: Hyp, name: str) -> dict[str, float]:
    """Physical parameters of effect ``name`` in a fitted hypothesis (SI units)."""
    th, nl = h.theta, h.nl
    fc = _coulomb(h)
    if name == "offset":
        return {"force_n": th.get("f0", 0.0)}
    if name == "spring":
        k = th.get("ks", 0.0)
        return {"stiffness_n_m": k, "x0_m": h.x_center_m - (th.get("f0", 0.0) / k if k and not h.has("offset") else 0.0)}
    if name == "asymmetry":
        return {"ratio": float(nl.get("r", 0.0))}
    if name == "position_ripple":
        rs, rc = th.get("rs", 0.0), th.get("rc", 0.0)
        return {"amplitude": math.hypot(rs, rc), "wavelength_m": float(nl["ripple_lambda_m"]),
                "phase_rad": math.atan2(rc, rs)}
    if name == "cogging":
        cs, cc = th.get("cs", 0.0), th.get("cc", 0.0)
        return {"amplitude_n": math.hypot(cs, cc), "wavelength_m": float(nl["cogging_lambda_m"]),
                "phase_rad": math.atan2(cc, cs)}
    if name == "delay":
        return {"delay_s": float(nl.get("delay_s", 0.0))}
    if name == "stribeck":
        return {"fs_n": fc + th.get("ds", 0.0), "fc_n": fc, "vs_m_s": float(nl["vs_m_s"]),
                "delta": float(nl.get("delta", 2.0))}
    if name == "frictional_lag":
        return {"lag_s": float(nl.get("lag_s", 0.0))}
    if name == "presliding":
        d = np.asarray(nl["deltas_m"], float)
        w = np.array([th.get(f"w{i}", 0.0) for i in range(d.size)])
        keep = w > 1e-9 * max(w.sum(), 1e-300)
        return {"elements": int(keep.sum()), "total_slip_force_n": float(w.sum()) + th.get("fc", 0.0),
                "coulomb_part_n": th.get("fc", 0.0),
                "initial_stiffness_n_m": float(np.sum(w[keep] / d[keep])),
                "largest_break_displacement_m": float(d[keep].max()) if keep.any() else 0.0}
    return {}


def _coulomb(h: Hyp) -> float:
    w = sum(v for k, v in h.theta.items() if k.startswith("w") and k[1:].isdigit())
    return float(h.theta.get("fc", 0.0) + w)


def evidence(name: str, sig: Signals, rows: BoolArray, r_before: FloatArray, after: Hyp, cmp: Comparison) -> str:
    """One paragraph: what in the residual points to ``name`` and what the fit found."""
    r = r_before
    v = sig.v
    x = sig.xf
    pos = rows & (v > 0)
    neg = rows & (v < 0)
    mp = float(np.mean(r[pos])) if pos.any() else 0.0
    mn = float(np.mean(r[neg])) if neg.any() else 0.0
    p = describe_params(after, name)
    gain = f"validation gap {cmp.gap_before:.4g} N -> {cmp.gap_after:.4g} N ({100 * cmp.rel_gain:.0f} % smaller, " \
           f"block-bootstrap lower bound of the per-sample MSE gain {cmp.boot_lower:.3g} N² > 0)"
    regs = regimes(sig, rows)

    def reg_rms(prefix: str) -> float:
        for k, m in regs.items():
            if k.startswith(prefix) and m.any():
                return float(np.sqrt(np.mean(r[m] ** 2)))
        return float("nan")

    if name == "offset":
        txt = (f"the residual has the same sign in both directions of motion (mean {mp:+.4g} N for v > 0, "
               f"{mn:+.4g} N for v < 0): a constant force; fitted F_0 = {p['force_n']:.4g} N")
    elif name == "spring":
        rr, xx = r[rows], x[rows]
        c = float(np.corrcoef(rr, xx)[0, 1]) if rr.size > 2 else 0.0
        slope = float(np.polyfit(xx, rr, 1)[0]) if rr.size > 2 else 0.0
        txt = (f"the residual grows linearly with position (slope {slope:.4g} N/m, correlation {c:+.2f}) in both "
               f"directions; fitted k_s = {p['stiffness_n_m']:.4g} N/m, x0 = {p['x0_m']:.6g} m")
    elif name == "asymmetry":
        txt = (f"the residual depends on the direction of motion (mean {mp:+.4g} N for v > 0, {mn:+.4g} N for v < 0) "
               f"and scales with the friction level (viscous part too), which a constant offset cannot explain; "
               f"fitted r = {p['ratio']:+.4g} (F+ = (1+r)·F, F- = (1-r)·F)")
    elif name in ("position_ripple", "cogging"):
        kind = ("multiplies the friction force (changes sign with the direction of motion)" if name ==
                "position_ripple" else "is the same in both directions (conservative force)")
        amp = f"a = {p['amplitude']:.4g}" if name == "position_ripple" else f"A = {p['amplitude_n']:.4g} N"
        txt = (f"the residual is periodic in position with wavelength {p['wavelength_m']:.6g} m and {kind}; "
               f"fitted {amp}, phase {p['phase_rad']:.3g} rad; it transfers to the validation data")
    elif name == "delay":
        du = np.gradient(sig.u)
        rr = r[rows]
        c = float(np.corrcoef(rr, du[rows])[0, 1]) if rr.size > 2 else 0.0
        txt = (f"the residual is correlated with the rate of change of the commanded force (correlation {c:+.2f}): "
               f"the force acts later than commanded; fitted τ = {1e3 * p['delay_s']:.3g} ms")
    elif name == "stribeck":
        txt = (f"the residual is largest at low speed (RMS {reg_rms('low_speed'):.4g} N vs "
               f"{reg_rms('constant_speed'):.4g} N at constant speed) and has the sign of the velocity: friction "
               f"falls with speed; fitted Fs = {p['fs_n']:.4g} N, Fc = {p['fc_n']:.4g} N, vs = {p['vs_m_s']:.3g} m/s, "
               f"δ = {p['delta']:.2g}")
    elif name == "frictional_lag":
        acc = rows & (np.sign(sig.acc_f) == np.sign(v))
        dec = rows & (np.sign(sig.acc_f) != np.sign(v))
        ma = float(np.sqrt(np.mean(r[acc] ** 2))) if acc.any() else 0.0
        md = float(np.sqrt(np.mean(r[dec] ** 2))) if dec.any() else 0.0
        txt = (f"the low-speed friction differs between accelerating and decelerating motion (residual RMS "
               f"{ma:.4g} N vs {md:.4g} N): the Stribeck part lags the velocity; fitted lag {1e3 * p['lag_s']:.3g} ms")
    elif name == "presliding":
        txt = (f"the residual is concentrated right after velocity reversals (RMS {reg_rms('near_reversal'):.4g} N vs "
               f"{reg_rms('constant_speed'):.4g} N at constant speed): the force builds up elastically over "
               f"displacement instead of jumping with sgn(v); fitted {p['elements']} Maxwell-slip elements, "
               f"initial stiffness {p['initial_stiffness_n_m']:.4g} N/m, largest break displacement "
               f"{1e6 * p['largest_break_displacement_m']:.3g} µm")
    else:
        txt = name
    return f"{txt}; {gain}"


# ================================================================================================ workflow
def _refresh(ds: Dataset, fr: FitResult) -> FitResult:
    """Re-search the cheap nonlinear parameters that trade off with effects added later (asymmetry ratio,
    delay) around their current values; keep the result only if the estimation fit improves."""
    h = fr.hyp
    best = fr
    if h.has("asymmetry"):
        r0 = float(h.nl.get("r", 0.0))
        r, f = rg._best_scalar(lambda r: _fit_with(ds, best.hyp, r=r).rss, [r0 - 0.05, r0, r0 + 0.05], -0.95, 0.95,
                               log=False, maxiter=10)
        if f < best.rss:
            best = _fit_with(ds, best.hyp, r=r)
    if h.has("delay"):
        dt = ds.est.dt_s
        t0 = float(h.nl.get("delay_s", 0.0))
        tau, f = rg._best_scalar(lambda s: _fit_with(ds, best.hyp, delay_s=s).rss,
                                 [max(t0 - 0.5 * dt, 0.0), t0, t0 + 0.5 * dt], 0.0, 20 * dt, log=False, maxiter=10)
        if f < best.rss:
            best = _fit_with(ds, best.hyp, delay_s=tau)
    return best


def _upgrade_nested(ds: Dataset, cur: FitResult, effects: list[dict[str, Any]], rejected: list[dict[str, Any]],
                    min_explained: float) -> FitResult:
    """A simpler effect named while a richer one could not yet be told apart (e.g. offset vs asymmetry before
    the Stribeck curve was in the model) is replaced by the richer one if, with everything else found since,
    the richer one is now significantly better on validation data."""
    richer_of = {s: [r for r, ss in NESTED.items() if s in ss] for s in ("offset", "stribeck")}
    for item in list(effects):
        simple = item["name"]
        for rich in richer_of.get(simple, []):
            if cur.hyp.has(rich):
                continue
            h = cur.hyp.copy()
            h.effects = tuple(e for e in h.effects if e != simple)
            h.theta = {}
            try:
                base = rg.fit_linear(ds.est, h, ds.est_rows)
                fr = fit_candidate(ds, base, rich)
            except (ValueError, np.linalg.LinAlgError):
                continue
            _, r_cur = gap(ds.val, ds.val_rows, cur.hyp)
            _, r_new = gap(ds.val, ds.val_rows, fr.hyp)
            c = compare(r_cur, r_new, ds.est.dt_s, min_explained)
            if c.significant:
                idx = effects.index(item)
                effects[idx] = {
                    "name": rich, "parameters": describe_params(fr.hyp, rich), "gap_before": item["gap_before"],
                    "gap_after": c.gap_after, "replaces": simple,
                    "evidence": evidence(rich, ds.val, ds.val_rows, r_cur, fr.hyp, c)
                    + f" (replaces {simple}, named earlier when the two could not yet be told apart)",
                }
                rejected.append({**item, "reason": f"replaced by the richer {rich}, significantly better on "
                                 f"validation data once the other effects were in the model "
                                 f"({c.gap_before:.4g} N -> {c.gap_after:.4g} N)"})
                cur = fr
                break
    return cur


def _prune(ds: Dataset, cur: FitResult, effects: list[dict[str, Any]], rejected: list[dict[str, Any]],
           min_explained: float) -> FitResult:
    """Backward check: an accepted effect that a later, richer one made redundant (e.g. an offset accepted
    before the asymmetry or spring that contains it) is removed if the model without it is not significantly
    worse on validation data."""
    changed = True
    while changed and len(effects) > 1:
        changed = False
        _, r_full = gap(ds.val, ds.val_rows, cur.hyp)
        for item in list(effects[:-1]):
            name = item["name"]
            h = cur.hyp.copy()
            if name == "stribeck" and h.has("frictional_lag"):
                continue
            h.effects = tuple(e for e in h.effects if e != name)
            h.theta = {}
            try:
                fr = rg.fit_linear(ds.est, h, ds.est_rows)
                if h.has("asymmetry"):
                    # the asymmetry ratio trades off with a constant force: search it again
                    r, _ = rg._best_scalar(lambda r: _fit_with(ds, h, r=r).rss, [h.nl["r"] - 0.1, h.nl["r"],
                                           h.nl["r"] + 0.1], -0.95, 0.95, log=False, maxiter=12)
                    fr = _fit_with(ds, h, r=r)
            except (ValueError, np.linalg.LinAlgError):
                continue
            _, r_without = gap(ds.val, ds.val_rows, fr.hyp)
            c = compare(r_without, r_full, ds.est.dt_s, min_explained)
            if not c.significant:
                effects.remove(item)
                rejected.append({**item, "reason": f"made redundant by the effects found after it: removing it "
                                 f"changes the validation gap only from {c.gap_after:.4g} N to {c.gap_before:.4g} N"})
                cur = fr
                changed = True
                break
    return cur


PAIR_CANDIDATES = 4


def _try_pairs(
    ds: Dataset, cur: FitResult, cands: dict[str, tuple[FitResult, Comparison, FloatArray]], r_cur: FloatArray,
    force_rms: float,
) -> tuple[tuple[str, str], FitResult, Comparison] | None:
    """Interacting effects: when no single effect validates, try pairs of the candidates that fit the
    estimation data best (e.g. an offset plus a cogging whose position coverage differs between estimation
    and validation blocks, where each alone absorbs part of the other). The pair must pass the same test."""
    est = sorted(cands, key=lambda k: cands[k][0].rss)
    top = [k for k in est if 1.0 - math.sqrt(cands[k][0].rss / max(cur.rss, 1e-300)) >= 0.5 * MIN_REL_GAIN]
    top = top[:PAIR_CANDIDATES]
    best: tuple[tuple[str, str], FitResult, Comparison] | None = None
    for i, a in enumerate(top):
        for b in top[i + 1:]:
            if b in NESTED.get(a, ()) or a in NESTED.get(b, ()):
                continue
            try:
                fr = fit_candidate(ds, cands[a][0], b)
            except (ValueError, np.linalg.LinAlgError):
                continue
            _, r_new = gap(ds.val, ds.val_rows, fr.hyp)
            cmp = compare(r_cur, r_new, ds.est.dt_s, force_rms)
            if cmp.significant and (best is None or cmp.gap_after < best[2].gap_after):
                best = ((a, b), fr, cmp)
    if best is None:
        return None
    # nested effects: a pair with the simpler member is preferred unless the richer pair is significantly better
    (a, b), fr, cmp = best
    for rich, other in ((a, b), (b, a)):
        for simpler in NESTED.get(rich, ()):
            if cur.hyp.has(simpler) or simpler == other:
                continue
            try:
                base = cands[other][0] if other in cands else fit_candidate(ds, cur, other)
                fr2 = fit_candidate(ds, base, simpler)
            except (ValueError, np.linalg.LinAlgError, KeyError):
                continue
            _, r2 = gap(ds.val, ds.val_rows, fr2.hyp)
            c2 = compare(r_cur, r2, ds.est.dt_s, force_rms)
            if not c2.significant:
                continue
            _, r_rich = gap(ds.val, ds.val_rows, fr.hyp)
            if not compare(r2, r_rich, ds.est.dt_s, force_rms).significant:
                return (other, simpler), fr2, c2
    return best


@dataclass
class Round:
    candidates: list[dict[str, Any]]
    chosen: str | None


@dataclass
class DiscoveryResult:
    start: FitResult
    final: FitResult
    gap_before: float
    gap_after: float
    effects: list[dict[str, Any]]
    rejected: list[dict[str, Any]]
    rounds: list[Round]
    disagreement_before: list[dict[str, Any]]
    disagreement_after: list[dict[str, Any]]
    split: str
    elapsed_s: float
    history: list[Hyp] = field(default_factory=list)
    dataset: Dataset | None = None
    noise_floor_n: float = 0.0
    min_explained_n: float = 0.0


def discover(
    rec: Recording,
    validate: Recording | None = None,
    start: Hyp | None = None,
    catalogue: tuple[str, ...] = CATALOGUE,
    max_rounds: int = 6,
    cutoff_hz: float | None = None,
) -> DiscoveryResult:
    """Run the workflow (see module docstring). ``start`` is the starting hypothesis (None: m + Coulomb + viscous)."""
    t0 = time.perf_counter()
    ds = make_dataset(rec, validate, cutoff_hz)
    cur = fit_start(ds, start)
    start_fit = cur
    g0, r0 = gap(ds.val, ds.val_rows, cur.hyp)
    dis_before = localise(ds.val, ds.val_rows, rg.residual(ds.val, cur.hyp))
    m_hat = float(cur.hyp.theta.get("m", cur.hyp.fixed_mass_kg or 0.0))
    # the non-inertial force ū − m̂·a (friction and other forces): the physical scale an effect is judged
    # against. The commanded force itself scales with how hard the motion accelerates (a fast point-to-point
    # recording of a heavy stage has an RMS force hundreds of times its friction), not with the physics sought.
    uf = (ds.val.filt(ds.val.ubar()) - m_hat * ds.val.acc_f)[ds.val_rows]
    noise_floor = ds.val.noise_floor_n(m_hat)
    force_rms = max(MIN_EXPLAINED_FRACTION * float(np.sqrt(np.mean(uf * uf))), MIN_EXPLAINED_NOISE * noise_floor)
    effects: list[dict[str, Any]] = []
    rejected: list[dict[str, Any]] = []
    rounds: list[Round] = []
    history = [cur.hyp]
    for _ in range(max_rounds):
        g_cur, r_cur = gap(ds.val, ds.val_rows, cur.hyp)
        cands: dict[str, tuple[FitResult, Comparison, FloatArray]] = {}
        info: list[dict[str, Any]] = []
        for name in catalogue:
            if cur.hyp.has(name):
                continue
            try:
                fr = fit_candidate(ds, cur, name)
            except (ValueError, np.linalg.LinAlgError) as exc:  # a candidate that cannot be fitted here
                info.append({"name": name, "error": str(exc)})
                continue
            _, r_new = gap(ds.val, ds.val_rows, fr.hyp)
            cmp = compare(r_cur, r_new, ds.est.dt_s, force_rms)
            est_gain = 1.0 - math.sqrt(fr.rss / max(cur.rss, 1e-300))
            cands[name] = (fr, cmp, r_new)
            info.append({
                "name": name, "parameters": describe_params(fr.hyp, name), "estimation_rel_gain": est_gain,
                "gap_before": cmp.gap_before, "gap_after": cmp.gap_after, "rel_gain": cmp.rel_gain,
                "bootstrap_lower_n2": cmp.boot_lower, "block_samples": cmp.block, "explained_n": cmp.explained_n,
                "min_explained_n": cmp.min_explained_n, "acceptable": cmp.significant,
            })
        ok = {k: v for k, v in cands.items() if v[1].significant}
        chosen: str | None = None
        if ok:
            order = sorted(ok, key=lambda k: ok[k][1].gap_after)
            chosen = order[0]
            for simpler in NESTED.get(chosen, ()):
                if simpler in ok and not cur.hyp.has(simpler):
                    c2 = compare(ok[simpler][2], ok[chosen][2], ds.est.dt_s, force_rms)
                    if not c2.significant:
                        note = (f"{chosen} did not beat the nested, simpler {simpler} significantly on validation data "
                                f"({100 * c2.rel_gain:.1f} % further gain)")
                        for item in info:
                            if item["name"] == chosen:
                                item["note"] = note
                        chosen = simpler
                        break
        rounds.append(Round(info, chosen))
        if chosen is None:
            pair = _try_pairs(ds, cur, cands, r_cur, force_rms)
            if pair is not None:
                (a, b), fr, cmp = pair
                rounds[-1].chosen = f"{a}+{b}"
                r_before = rg.residual(ds.val, cur.hyp)
                for name in (a, b):
                    effects.append({
                        "name": name, "parameters": describe_params(fr.hyp, name), "gap_before": cmp.gap_before,
                        "gap_after": cmp.gap_after, "accepted_jointly_with": b if name == a else a,
                        "evidence": evidence(name, ds.val, ds.val_rows, r_before, fr.hyp, cmp)
                        + f" (neither {a} nor {b} validated alone: each biases the other's fit; accepted as a pair)",
                    })
                cur = _refresh(ds, fr)
                history.append(cur.hyp)
                continue
            for item in info:
                if "error" in item:
                    continue
                if item["estimation_rel_gain"] >= MIN_REL_GAIN:
                    rejected.append({**item, "reason": "fits the estimation data "
                                     f"({100 * item['estimation_rel_gain']:.0f} % smaller residual) but the validation "
                                     f"gap shrinks only {100 * item['rel_gain']:.1f} % "
                                     f"(needs >= {100 * MIN_REL_GAIN:.0f} %, a positive bootstrap bound and at "
                                     f"least {item['min_explained_n']:.3g} N explained; got "
                                     f"{item['explained_n']:.3g} N)"})
            break
        fr, cmp, _ = cands[chosen]
        effects.append({
            "name": chosen, "parameters": describe_params(fr.hyp, chosen), "gap_before": cmp.gap_before,
            "gap_after": cmp.gap_after, "evidence": evidence(chosen, ds.val, ds.val_rows,
                                                              rg.residual(ds.val, cur.hyp), fr.hyp, cmp),
        })
        cur = _refresh(ds, fr)
        history.append(cur.hyp)
    cur = _prune(ds, cur, effects, rejected, force_rms)
    cur = _upgrade_nested(ds, cur, effects, rejected, force_rms)
    g1, _ = gap(ds.val, ds.val_rows, cur.hyp)
    dis_after = localise(ds.val, ds.val_rows, rg.residual(ds.val, cur.hyp))
    res = DiscoveryResult(
        start=start_fit, final=cur, gap_before=g0, gap_after=g1,
        effects=effects, rejected=rejected, rounds=rounds, disagreement_before=dis_before,
        disagreement_after=dis_after, split=ds.split, elapsed_s=time.perf_counter() - t0, history=history,
        dataset=ds, noise_floor_n=noise_floor, min_explained_n=force_rms,
    )
    return res
