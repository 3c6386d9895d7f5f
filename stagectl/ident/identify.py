"""Friction identification from a recording: GMS / Maxwell-slip, Stribeck (Coulomb + viscous), LuGre, Dahl,
Hsieh (module by module).

Measured friction force (inverse dynamics, zero-order hold, see :mod:`stagectl.ident.signals`)::

    F_meas[k] = L[ū][k] − m·L[a][k],      ū[k] = (u[k−1] + u[k])/2,  a = second difference of x / dt²

with ``m`` from the recording (regression of ``ū`` on ``a``, sgn(v), v over moving samples) when the data
excite it, otherwise 0 (quasi-static data).

**GMS / Maxwell-slip (Kamenar–Zelenika / Lampaert–Al-Bender piecewise-linear method, docs/friction-models.md §2.3).**
Virgin-curve points come from the first loading from rest (``F_v(d) = |F|``, ``d = |x − x0|``) and from every
branch after a reversal by the Masing rule (``F_v(d/2) = |F − F_r|/2``). The virgin curve of N elements is
``F_v(d) = Σ W_i·min(d/Δ_i, 1)``: piecewise linear with breakpoints Δ_i, segment slopes
``K_j = Σ_{i≥j} k_i`` and element stiffnesses ``k_i = W_i/Δ_i``. Given the breakpoints the W_i enter linearly
(non-negative least squares keeps the curve concave, k_i > 0); the breakpoints start from a dense-grid NNLS
(clustered to N) and are refined by coordinate descent on log Δ_i. N is chosen by BIC
(``n·ln(RSS/n) + 2N·ln n``, N = 1..8) unless given. The elements are then refined by least squares over all
hysteresis loops of the recording (the same linear-in-W regression along the measured trajectory that
``discover`` uses). GMS: ``α_i = W_i/ΣW``, ``Fs = ΣW`` (+ Stribeck excess if sliding data show one).

**Stribeck** from constant-velocity segments: mean force per segment vs speed, fitted with
``F(v) = sgn(v)(Fc + (Fs − Fc)·exp(−|v/vs|^δ)) + σ2·v`` (scipy least squares).

**LuGre**: Stribeck curve as above, ``σ0`` = initial slope of the virgin curve, ``σ1`` for a bristle damping
ratio of 1 with the identified mass (or fitted by 1-D search when loops are present). **Dahl**: σ0 and Fc
from the virgin curve ``F = Fc(1 − exp(−σ0·d/Fc))``. **Hsieh**: spring module from the unloading branches
(elastic: ``|F − F_r| = k1s·δ + (k2s/β)(1 − e^{−βδ})``), plastic module from the virgin loading
(``x_p = x − x_s(F)``, equilibrium ``x_p = |F|^a/ψ`` → log-linear fit), sliding model from the Stribeck fit.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy import signal
from scipy.optimize import least_squares, minimize_scalar, nnls

from stagectl.errors import ConfigError, DataError, short
from stagectl.friction import build
from stagectl.ident import effects as fx
from stagectl.ident import regress as rg
from stagectl.ident._kernels import maxwell_unit_states
from stagectl.ident.hypothesis import Hyp
from stagectl.ident.modelio import hyp_to_spec
from stagectl.ident.recording import Recording
from stagectl.ident.signals import Signals, prepare
from stagectl.ident.verdict import _leaves, assess

FloatArray = npt.NDArray[np.float64]

MODELS = ("gms", "maxwell_slip", "stribeck", "lugre", "dahl", "hsieh")


# ================================================================================================ data
@dataclass
class Measured:
    """Signals plus the measured friction force."""

    sig: Signals
    force: FloatArray
    mass_kg: float | None
    notes: list[str] = field(default_factory=list)


def measure(rec: Recording, mass_kg: float | None = None, cutoff_hz: float | None = None) -> Measured:
    """Inverse-dynamics friction force of a recording (mass estimated unless given)."""
    sig = prepare(rec, cutoff_hz=cutoff_hz, min_rows=50, require_motion=False) if len(rec) >= 50 else None
    if sig is None:
        raise DataError(f"{rec.source}: {len(rec)} rows; identification needs at least 50")
    notes: list[str] = list(sig.notes)  # what the preparation did (irregular sampling resampled, ...)
    ub = signal.sosfiltfilt(sig.sos, sig.ubar())
    acc = signal.sosfiltfilt(sig.sos, sig.acc_raw)
    m = mass_kg
    if m is None:
        rows = sig.evaluate
        if rows.sum() > 100 and np.std(acc[rows]) > 0:
            h = Hyp()
            fit = rg.fit_linear(sig, h, rows)
            m_fit = fit.hyp.theta.get("m", 0.0)
            # mass is identifiable only if the acceleration carries force well above the noise
            if m_fit > 0 and m_fit * np.std(acc[rows]) > 0.05 * np.std(ub[rows]):
                m = float(m_fit)
                notes.append(f"mass {m:.6g} kg from the inverse-dynamics regression")
        if m is None:
            notes.append("mass not identifiable from these data (quasi-static); m·a neglected")
    force = ub - (m or 0.0) * acc
    return Measured(sig, np.asarray(force, dtype=np.float64), m, notes)


# ================================================================================================ virgin curve
def virgin_points(meas: Measured, rule: str = "masing", max_points: int = 2000) -> tuple[FloatArray, FloatArray]:
    """Virgin-curve samples (d [m], F_v [N]) from the first loading (from rest) and the reversal branches.

    ``rule``: ``"masing"`` (Maxwell-slip/GMS: ``F_v(δ/2) = |F − F_r|/2``), ``"same"`` (Hsieh: branches have the
    virgin shape, ``F_v(δ) = |F − F_r|``) or ``"first"`` (first loading only: Dahl, LuGre).
    """
    x = meas.sig.xf
    f = meas.force
    n = x.shape[0]
    eps = max(3 * meas.sig.noise_m, 2 * meas.sig.quantum_m, 1e-12)
    # direction changes with hysteresis eps on position
    turns = [0]
    ext = x[0]
    direction = 0.0
    for k in range(1, n):
        if direction >= 0 and x[k] > ext:
            ext = x[k]
            kext = k
            if direction == 0 and x[k] - x[0] > eps:
                direction = 1.0
        elif direction <= 0 and x[k] < ext:
            ext = x[k]
            kext = k
            if direction == 0 and x[0] - x[k] > eps:
                direction = -1.0
        if direction > 0 and x[k] < ext - eps:
            turns.append(kext)
            direction = -1.0
            ext = x[k]
        elif direction < 0 and x[k] > ext + eps:
            turns.append(kext)
            direction = 1.0
            ext = x[k]
    turns.append(n - 1)
    ds_: list[FloatArray] = []
    fs_: list[FloatArray] = []
    for j in range(len(turns) - 1):
        a, b = turns[j], turns[j + 1]
        if b - a < 3:
            continue
        seg = slice(a, b + 1)
        if j == 0:
            d = np.abs(x[seg] - x[a])
            fv = np.abs(f[seg])  # first loading from the relaxed state
        elif rule == "first":
            break
        elif rule == "same":
            d = np.abs(x[seg] - x[a])
            fv = np.abs(f[seg] - f[a])
        else:
            d = 0.5 * np.abs(x[seg] - x[a])
            fv = 0.5 * np.abs(f[seg] - f[a])
        ds_.append(d)
        fs_.append(fv)
    if not ds_:
        raise DataError(f"{meas.sig.source}: no loading branch found for a virgin curve")
    d = np.concatenate(ds_)
    fv = np.concatenate(fs_)
    order = np.argsort(d)
    d, fv = d[order], fv[order]
    if d.size > max_points:
        idx = np.unique(np.geomspace(1, d.size, max_points).astype(int) - 1)
        d, fv = d[idx], fv[idx]
    return d, fv


def _nnls_virgin(d: FloatArray, f: FloatArray, deltas: FloatArray) -> tuple[FloatArray, float]:
    a = np.minimum(d[:, None] / deltas[None, :], 1.0)
    w, rn = nnls(a, f, maxiter=50 * a.shape[1])
    return w, float(rn * rn)


def fit_virgin(d: FloatArray, f: FloatArray, n_elements: int) -> tuple[FloatArray, FloatArray, float]:
    """Piecewise-linear virgin-curve fit with ``n_elements`` breakpoints. Returns (Δ, W, RSS)."""
    pos = d[d > 0]
    if pos.size < 2 * n_elements + 2:
        raise DataError(f"virgin curve: {pos.size} points, too few for {n_elements} elements")
    lo, hi = float(pos.min()), float(pos.max())
    grid = np.geomspace(max(lo, hi * 1e-5), hi, 200)
    w, _ = _nnls_virgin(d, f, grid)
    nz = np.flatnonzero(w > 1e-12 * max(w.sum(), 1e-300))
    # cluster adjacent grid points into groups, then merge/split to n_elements
    groups: list[list[int]] = []
    for i in nz:
        if groups and i - groups[-1][-1] <= 1:
            groups[-1].append(int(i))
        else:
            groups.append([int(i)])
    cents = [float(np.exp(np.average(np.log(grid[g]), weights=w[g]))) for g in groups]
    weights = [float(w[g].sum()) for g in groups]
    while len(cents) > n_elements:
        j = int(np.argmin(weights))
        k = j - 1 if j > 0 and (j == len(cents) - 1 or abs(math.log(cents[j - 1] / cents[j])) <
                                abs(math.log(cents[j + 1] / cents[j]))) else j + 1
        wsum = weights[j] + weights[k]
        cents[k] = math.exp((weights[j] * math.log(cents[j]) + weights[k] * math.log(cents[k])) / wsum)
        weights[k] = wsum
        del cents[j], weights[j]

    def rss_of(ds_: FloatArray) -> float:
        return _nnls_virgin(d, f, ds_)[1]

    def descend(deltas: FloatArray, sweeps: int = 6) -> tuple[FloatArray, float]:
        deltas = np.sort(deltas)
        best = rss_of(deltas)
        for _sweep in range(sweeps):
            prev = best
            for j in range(deltas.size):
                lo_j = deltas[j - 1] if j > 0 else deltas[j] / 4
                hi_j = deltas[j + 1] if j + 1 < deltas.size else min(deltas[j] * 4, hi * 2)
                if hi_j <= lo_j:
                    continue

                def cost(s: float, j: int = j) -> float:
                    trial = deltas.copy()
                    trial[j] = math.exp(s)
                    return rss_of(trial)

                res = minimize_scalar(cost, bounds=(math.log(lo_j), math.log(hi_j)), method="bounded",
                                      options={"xatol": 1e-7, "maxiter": 60})
                if res.fun < best:
                    deltas[j] = math.exp(float(res.x))
                    best = float(res.fun)
            if best >= prev * (1 - 1e-9) or best <= 1e-30:
                break
        return deltas, best

    deltas, best = descend(np.array(sorted(cents)) if cents else np.array([math.sqrt(lo * hi)]))
    # too few clusters (close breakpoints share a grid cell): split the cluster whose split helps most
    while deltas.size < n_elements:
        trials = []
        for j in range(deltas.size):
            c = deltas[j]
            trial = np.concatenate([deltas[:j], [c / 1.01, c * 1.01], deltas[j + 1:]])
            trials.append(descend(trial, sweeps=3))
        deltas, best = min(trials, key=lambda tr: tr[1])
    deltas, best = descend(deltas)
    w, rss = _nnls_virgin(d, f, deltas)
    keep = w > 0
    return deltas[keep], w[keep], rss


def choose_elements(d: FloatArray, f: FloatArray, n_max: int = 8) -> tuple[int, list[dict[str, float]]]:
    """Number of elements by BIC = n·ln(RSS/n) + 2N·ln(n)."""
    n = d.size
    table: list[dict[str, float]] = []
    best_n, best_bic = 1, math.inf
    for k in range(1, n_max + 1):
        try:
            dl, w, rss = fit_virgin(d, f, k)
        except DataError:
            break
        bic = n * math.log(max(rss, 1e-300) / n) + 2 * dl.size * math.log(n)
        table.append({"elements": float(k), "rss_n2": rss, "bic": bic})
        if bic < best_bic - 1e-9:
            best_n, best_bic = k, bic
        elif k >= best_n + 2:
            break  # BIC rose twice in a row: more elements will not pay
    return best_n, table


_VIRGIN_CACHE: dict[tuple[int, int, int | None], tuple[int, Any, FloatArray, FloatArray, float]] = {}


# ================================================================================================ stribeck
def constant_velocity_points(meas: Measured, min_len: int = 20, min_rev_dist_m: float = 0.0
                             ) -> tuple[FloatArray, FloatArray]:
    """(v [m/s], mean F [N]) of constant-velocity segments (speed within 3 %, at least ``min_len`` samples,
    moving, and more than ``min_rev_dist_m`` past the last reversal, i.e. beyond pre-sliding)."""
    sig = meas.sig
    v = sig.v
    vmax = float(np.percentile(np.abs(v[sig.evaluate]), 99)) if sig.evaluate.any() else 0.0
    tol_v = 0.03
    ok = sig.evaluate & (sig.x_rev_dist > min_rev_dist_m)
    out_v: list[float] = []
    out_f: list[float] = []
    k = 0
    n = v.size
    while k < n:
        if not ok[k]:
            k += 1
            continue
        j = k
        while j + 1 < n and ok[j + 1] and abs(v[j + 1] - v[k]) <= tol_v * abs(v[k]) + 1e-3 * vmax:
            j += 1
        if j - k + 1 >= min_len:
            mid = slice(k + (j - k) // 5, j + 1 - (j - k) // 5)
            out_v.append(float(np.mean(v[mid])))
            out_f.append(float(np.mean(meas.force[mid])))
        k = j + 1
    return np.array(out_v), np.array(out_f)


def _wmean(w2: FloatArray, r: FloatArray, weighted: bool) -> float:
    """The weighted mean ``Σ w2_i·r_i`` (``Σ w2 = 1``), or the plain mean when unweighted."""
    return float(w2 @ r) if weighted else float(np.mean(r))


#: grid of the Stribeck fit: (log-spaced vs values, δ values)
_STRIBECK_GRID = (121, 15)
#: how many of the grid's local minima the Stribeck fit refines
_STRIBECK_REFINE = 6


def fit_stribeck_curve(v: FloatArray, f: FloatArray, fs_n: float | None = None,
                       delta: float | None = None, vs_min_m_s: float | None = None,
                       sigma_n: FloatArray | None = None) -> dict[str, float]:
    """Least-squares fit of F(v) = sgn(v)(Fc + (Fs − Fc)·exp(−|v/vs|^δ)) + σ2·v [+ a constant offset].

    The model is linear in (Fc, Fs − Fc, σ2, offset) once (vs, δ) are fixed, and the cost over (vs, δ) has
    several shallow local minima (a local solver started from a few vs lands in one of them depending on
    0.01 % changes of the data). So the fit is global on a grid: for each vs (``_STRIBECK_GRID`` log-spaced
    values in [v_min/20, 20·v_max], 9 % apart for a 100:1 speed range) and δ in [0.5, 4], the linear
    parameters are the non-negative least squares solution (Fc, Fs − Fc, σ2 ≥ 0; the free offset projected
    out); the grid's best local minima (``_STRIBECK_REFINE``) are then refined by a bounded local least
    squares over all six parameters, and the lowest cost of all wins.

    ``fs_n``: the static level measured elsewhere (the pre-sliding elements' ``Σ k_i·Δ_i``, at rest). Then
    ``F = sgn(v)(Fc(1 − e) + Fs·e) + σ2·v + offset`` with ``e = exp(−|v/vs|^δ)`` is linear in (Fc, σ2, offset)
    for fixed (vs, δ), and the same grid and refinement run with Fs held. Constant-velocity means alone do
    not fix Fs when the curve has dropped by the slowest speed: on a generated plant (vs 0.30 mm/s, slowest
    pass 0.16 mm/s) Fs came out 2.30 N (vs 32 µm/s, δ 0.5) for a true 1.73 N, with a lower residual than the
    true curve's. Returned: ``v_min_m_s`` (the slowest speed) and ``fs_fixed``.

    ``delta``: the shape exponent δ held (the grid and the refinement keep it): where the means see only the
    curve's tail (its dip lies below the slowest sliding speed), the tail fits any δ with a matching vs.
    ``vs_min_m_s``: a lower bound of vs [m/s] known from elsewhere (the grid starts there when it is above
    ``v_min/20``).

    ``sigma_n``: each point's standard error [N]; the fit then minimises ``Σ ((F(v_i) − f_i)/σ_i)²`` (weighted
    least squares, the offset a weighted mean) and chooses between the Stribeck and the plain curve on that
    cost. Unweighted, one disturbed point pulls the shape: generated plant 34's slowest − pass read 24 mN
    below its + pass (its mean's standard error 12 mN, the others' 0.03-0.3 mN), and the curve took δ = 2.94
    for a true 2, 11 mN too high at the triangle's 1.57 mm/s (tracking 2.4× the exact model's). ``rms_n``
    stays the plain RMS of the residuals; ``weighted`` tells which fit ran.
    """
    if v.size < 3:
        raise DataError(f"Stribeck fit: {v.size} constant-velocity segments found, need at least 3")
    s = np.sign(v)
    av = np.abs(v)
    vmin, vmax = float(av.min()), float(av.max())
    weighted = sigma_n is not None
    if sigma_n is not None:
        sg = np.asarray(sigma_n, np.float64)
        if sg.shape != v.shape or not np.all(np.isfinite(sg) & (sg > 0.0)):
            raise DataError("Stribeck fit: the points' standard errors must be positive and one per point")
        w = 1.0 / sg
    else:
        w = np.ones_like(v)
    w2 = w * w / float(np.sum(w * w))  # weighted-mean weights (the offset projected out)

    fixed = fs_n is not None
    fs_fix = float(fs_n) if fs_n is not None else 0.0

    def model(p: FloatArray) -> FloatArray:
        fc, ds, lvs, dl, fv, off = p
        if fixed:  # ds is ignored: Fs − Fc follows Fc
            ds = fs_fix - fc
        return np.asarray(s * (fc + ds * np.exp(-((av / math.exp(lvs)) ** dl))) + fv * v + off, dtype=np.float64)

    lo_lvs, hi_lvs = math.log(vmin / 20 + 1e-12), math.log(vmax * 20 + 1e-12)
    if vs_min_m_s is not None:
        lo_lvs = min(max(lo_lvs, math.log(vs_min_m_s)), hi_lvs - 1e-9)
    lvs_grid = np.linspace(lo_lvs, hi_lvs, _STRIBECK_GRID[0])
    dl_grid = np.linspace(0.5, 4.0, _STRIBECK_GRID[1]) if delta is None else np.array([float(delta)])
    cost = np.full((lvs_grid.size, dl_grid.size), np.inf)
    lin_p = np.zeros((lvs_grid.size, dl_grid.size, 4))
    for i, lvs in enumerate(lvs_grid.tolist()):
        for j, dl in enumerate(dl_grid.tolist()):
            e = np.exp(-((av / math.exp(lvs)) ** dl))
            # columns Fc, Fs − Fc, σ2 (all ≥ 0); the free offset is projected out (columns and data centred);
            # with Fs fixed: columns Fc·(1 − e), σ2 on f − sgn(v)·Fs·e
            a = np.column_stack([s * (1.0 - e), v]) if fixed else np.column_stack([s, s * e, v])
            y = f - s * fs_fix * e if fixed else f
            try:
                if weighted:
                    th, rnorm = nnls(w[:, None] * (a - w2 @ a), w * (y - w2 @ y))
                else:  # (the plain means: bit-for-bit the unweighted fit)
                    th, rnorm = nnls(a - a.mean(axis=0), y - y.mean())
            except RuntimeError:  # nnls iteration limit (degenerate columns): skip this grid point
                continue
            if not (np.all(np.isfinite(th)) and math.isfinite(rnorm)):
                continue
            cost[i, j] = 0.5 * float(rnorm) ** 2
            if fixed:
                lin_p[i, j] = (th[0], fs_fix - th[0], th[1], float(_wmean(w2, y - a @ th, weighted)))
            else:
                lin_p[i, j] = (th[0], th[1], th[2], float(_wmean(w2, f - a @ th, weighted)))
    if not np.isfinite(cost).any():
        raise DataError("Stribeck fit: no grid point could be fitted")
    # refine the grid's local minima (the best few) by a bounded local least squares over all six parameters
    padded = np.pad(cost, 1, constant_values=np.inf)
    neigh = np.min([padded[1 + di:padded.shape[0] - 1 + di, 1 + dj:padded.shape[1] - 1 + dj]
                    for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj], axis=0)
    minima = np.argwhere(np.isfinite(cost) & (cost <= neigh))
    minima = minima[np.argsort(cost[minima[:, 0], minima[:, 1]])][:_STRIBECK_REFINE]
    dl_lo, dl_hi = (0.5, 4.0) if delta is None else (float(delta) * (1 - 1e-9), float(delta) * (1 + 1e-9))
    bounds = ([0, 0, lo_lvs, dl_lo, 0, -np.inf], [np.inf, np.inf, hi_lvs, dl_hi, np.inf, np.inf])
    x_best: FloatArray | None = None
    c_best = math.inf
    for i, j in minima.tolist():
        fc0, ds0, fv0, off0 = lin_p[i, j].tolist()
        p0 = np.clip(np.array([fc0, ds0, lvs_grid[i], dl_grid[j], fv0, off0]), bounds[0], bounds[1])
        # (from a degenerate grid minimum, e.g. vs far below the slowest speed, the solver may overflow on
        # its way: such a result is not finite and simply loses)
        with np.errstate(over="ignore", invalid="ignore"):
            refined = least_squares(lambda q: w * (model(q) - f), p0, bounds=bounds).x
            for p in (p0, refined):
                c = 0.5 * float(np.sum((w * (model(p) - f)) ** 2))
                if math.isfinite(c) and c < c_best:
                    c_best, x_best = c, np.asarray(p, dtype=np.float64)
    assert x_best is not None
    fc, ds, lvs, dl, fv, off = x_best
    rms = float(np.sqrt(np.mean((model(x_best) - f) ** 2)))
    wrms = float(np.sqrt(np.mean((w * (model(x_best) - f)) ** 2)))
    # plain Coulomb + viscous + offset: preferred unless the Stribeck terms reduce the (weighted) RMS by 20 %
    # and the segments cover at least 3 distinct speeds (otherwise vs and Fs are not identifiable)
    a = np.column_stack([s, v, np.ones_like(v)])
    lin, *_ = np.linalg.lstsq(w[:, None] * a, w * f, rcond=None) if weighted else np.linalg.lstsq(a, f, rcond=None)
    if lin[0] < 0.0 or lin[1] < 0.0:
        # Fc, σ2 ≥ 0 as in the grid (non-negative least squares, the free offset projected out). Clamping the
        # free solution's negative slope to 0 kept its intercept: passes at 38-42 mm/s only, whose means a
        # cogging scattered into a falling slope, gave Fc 7.1 N, σ2 0 for a 2.8 N friction level there
        a2 = a[:, :2]
        th, _ = nnls(w[:, None] * (a2 - w2 @ a2), w * (f - w2 @ f))
        lin = np.array([th[0], th[1], _wmean(w2, f - a2 @ th, weighted)])
    rms_lin = float(np.sqrt(np.mean((a @ lin - f) ** 2)))
    wrms_lin = float(np.sqrt(np.mean((w * (a @ lin - f)) ** 2)))
    levels = np.unique(np.round(np.log(av) / 0.1))
    if not fixed and (levels.size < 3 or wrms > 0.8 * wrms_lin):
        return {"fc_n": float(max(lin[0], 0.0)), "fs_n": float(max(lin[0], 0.0)), "vs_m_s": 1e-3, "delta": 2.0,
                "viscous_n_s_m": float(max(lin[1], 0.0)), "offset_n": float(lin[2]), "rms_n": rms_lin,
                "segments": float(v.size), "stribeck_identified": False, "v_min_m_s": vmin, "fs_fixed": False,
                "weighted": weighted}
    return {"fc_n": float(fc), "fs_n": fs_fix if fixed else float(fc + ds), "vs_m_s": float(math.exp(lvs)),
            "delta": float(dl), "viscous_n_s_m": float(fv), "offset_n": float(off), "rms_n": rms,
            "segments": float(v.size), "stribeck_identified": True, "v_min_m_s": vmin, "fs_fixed": fixed,
            "weighted": weighted}


# ================================================================================================ driver
@dataclass
class Identified:
    spec: dict[str, Any]
    mass_kg: float | None
    quality: dict[str, Any]
    meas: Measured
    virgin: tuple[FloatArray, FloatArray] | None = None
    effects: dict[str, Any] = field(default_factory=dict)


def _fit_quality(meas: Measured, spec: dict[str, Any], rows: npt.NDArray[np.bool_],
                 effects: dict[str, Any] | None = None) -> dict[str, float]:

    model = build(spec)
    fm = model.force_along(meas.sig.xf, meas.sig.t)
    if effects and "offset" in effects:
        fm = fm + effects["offset"]["force_n"]
    fm = signal.sosfiltfilt(meas.sig.sos, fm)
    e = (meas.force - fm)[rows]
    ref = meas.force[rows]
    rms = float(np.sqrt(np.mean(e * e)))
    return {"force_rms_error_n": rms, "force_rms_n": float(np.sqrt(np.mean(ref * ref))),
            "relative_error": rms / max(float(np.sqrt(np.mean(ref * ref))), 1e-300),
            "samples": int(rows.sum())}


class _Runs:
    """identify's work counted in model runs along the recording (``force_along`` over every sample: where its
    time goes on a long recording), told to ``progress(done, total, what)``. ``total`` is an upper bound: the
    joint refinement's evaluation budget until it ends, then what it used; the verdict's runs (one per
    parameter, plus one) once the model is known. Before the first run ``done`` is 0 (no rate yet)."""

    def __init__(self, progress: Callable[[float, float, str], None] | None) -> None:
        self.progress = progress
        self.done = 0
        self.total = 1
        self.what = ""

    def tell(self, what: str | None = None, total: int | None = None) -> None:
        if what is not None:
            self.what = what
        if total is not None:
            self.total = total
        if self.progress is not None:
            self.progress(float(self.done), float(max(self.total, self.done, 1)), self.what)

    def ran(self) -> None:
        self.done += 1
        self.tell()


def _refine_budget(model: str, max_nfev: int = 60) -> int:
    """Most model runs :func:`refine_by_simulation` makes: the start, then per accepted step of least squares
    (``max_nfev`` steps at most) one run and a forward-difference Jacobian of one run per parameter."""
    keys = REFINE_KEYS.get(model)
    return 0 if keys is None else 1 + max_nfev * (1 + len(keys))


def identify(rec: Recording, model: str, n_elements: int | None = None, mass_kg: float | None = None,
             cutoff_hz: float | None = None,
             progress: Callable[[float, float, str], None] | None = None) -> Identified:
    """Identify friction model ``model`` (one of :data:`MODELS`) from a recording.

    ``progress(done, total, what)`` is told how far the fit is, in model runs along the recording (``total``
    an upper bound that shrinks as the fits end early, ``done == total`` at the end; see :class:`_Runs`).

    Raises
    ------
    DataError
        The recording does not contain what the model needs (no loading branch, no constant-velocity
        segments, ...); the message says what is missing.
    """
    if model not in MODELS:
        raise DataError(f"--model: unknown model {short(model)} (known: {', '.join(MODELS)})")
    runs = _Runs(progress)
    runs.tell(f"measuring the friction force (inverse dynamics, {len(rec)} rows)")
    meas = measure(rec, mass_kg, cutoff_hz)
    quality: dict[str, Any] = {"notes": list(meas.notes)}
    runs.tell("virgin curve and constant-velocity segments")
    virgin = None
    min_rev = 0.0
    if model in ("gms", "maxwell_slip", "dahl", "lugre", "hsieh"):
        rule = {"gms": "masing", "maxwell_slip": "masing", "hsieh": "same"}.get(model, "first")
        try:
            virgin = virgin_points(meas, rule)
            d, f = virgin
            d99 = float(d[np.argmax(f >= 0.99 * f.max())])
            # sliding starts beyond the pre-sliding range (Masing: branch displacement is 2·d)
            min_rev = (2.0 if rule == "masing" else 1.0) * 2.0 * d99
        except DataError:
            if model != "lugre":
                raise
    stri: dict[str, float] | None = None
    vpts, fpts = constant_velocity_points(meas, min_rev_dist_m=min_rev)
    if vpts.size >= 3 and np.ptp(np.abs(vpts)) > 0:
        try:
            stri = fit_stribeck_curve(vpts, fpts)
            quality["stribeck_fit"] = stri
        except DataError:
            stri = None
    all_rows = np.ones(meas.sig.n, bool)
    all_rows[: 4 * meas.sig.guard] = False
    all_rows[-4 * meas.sig.guard:] = False

    if model == "stribeck":
        if stri is None:
            raise DataError(f"{rec.source}: no constant-velocity segments at 3 or more speeds; the Stribeck curve "
                            "needs steady motion at several speeds")
        spec = {"model": "stribeck", "fc_n": stri["fc_n"], "fs_n": stri["fs_n"], "vs_m_s": stri["vs_m_s"],
                "delta": stri["delta"], "viscous_n_s_m": stri["viscous_n_s_m"]}
        effects = {}
        if abs(stri["offset_n"]) > 0.02 * max(stri["fc_n"], 1e-12):
            effects["offset"] = {"force_n": stri["offset_n"]}
            quality["notes"].append(f"constant force {stri['offset_n']:.4g} N found with the friction curve; "
                                    "written as effects.offset")
        runs.tell("fit quality", total=2 + len(_leaves(spec)))
        quality["fit"] = _fit_quality(meas, spec, meas.sig.evaluate, effects)
        runs.ran()
        runs.tell(f"verdict: sensitivity to {len(_leaves(spec))} parameters")
        quality["verdict"] = assess(meas.sig, meas.force, spec, meas.sig.evaluate, model=model,
                                    mass_estimated=meas.mass_kg if mass_kg is None else None,
                                    offset_n=effects.get("offset", {}).get("force_n", 0.0), on_run=runs.ran)
        return Identified(spec, meas.mass_kg, quality, meas, virgin, effects)

    assert virgin is not None or model == "lugre"
    best: tuple[float, dict[str, Any], dict[str, Any], Measured] | None = None
    # the sliding terms from constant-velocity segments are kept only if they improve the fit of the whole
    # record (pre-sliding-only data can show spurious "constant-velocity" segments)
    passes = (True, False) if stri is not None else (False,)
    for i, use_stri in enumerate(passes):
        q: dict[str, Any] = {}
        left = len(passes) - i  # this pass and the ones after it
        runs.tell(f"fit {i + 1} of {len(passes)}: {model} "
                  + ("with" if use_stri else "without") + " the sliding curve of the constant-velocity segments")
        spec = _build_spec(model, meas, virgin, stri if use_stri else None, n_elements, q)
        # the bound: what this pass and the later ones may still run, and the verdict (one run per parameter)
        # (refined parameters that start at zero are not counted by _leaves yet: counted here)
        runs.total = (runs.done + left * (_refine_budget(model) + 1) + 1 + len(_leaves(spec))
                      + len(REFINE_KEYS.get(model, ())))
        if model in REFINE_KEYS:
            runs.tell(f"fit {i + 1} of {len(passes)}: joint least squares by simulation on "
                      f"{len(REFINE_KEYS[model])} parameters")
            before = runs.done
            spec, note = refine_by_simulation(meas, spec, REFINE_KEYS[model], all_rows, on_run=runs.ran)
            runs.total -= _refine_budget(model) - (runs.done - before)  # the budget it did not use
            q["joint_refinement"] = note
        m_q = meas
        if "mass_kg_from_loops" in q and mass_kg is None:
            m_q = measure(rec, q["mass_kg_from_loops"], cutoff_hz)
            m_q.notes = [f"mass {q['mass_kg_from_loops']:.6g} kg from the regression over all hysteresis loops"]
        runs.tell(f"fit {i + 1} of {len(passes)}: fit quality")
        fq = _fit_quality(m_q, spec, all_rows)
        runs.ran()
        if best is None or fq["force_rms_error_n"] < best[0]:
            best = (fq["force_rms_error_n"], spec, {**q, "fit": fq, "sliding_terms_from_segments": use_stri}, m_q)
    assert best is not None
    spec = best[1]
    if best[3] is not meas:
        meas = best[3]
        quality["notes"] = list(meas.notes)
    notes = quality["notes"] + best[2].pop("notes", [])
    quality.update(best[2])
    quality["notes"] = notes
    runs.tell(f"verdict: sensitivity to {len(_leaves(spec))} parameters", total=runs.done + 1 + len(_leaves(spec)))
    quality["verdict"] = assess(meas.sig, meas.force, spec, all_rows, model=model,
                                mass_estimated=meas.mass_kg if mass_kg is None else None, on_run=runs.ran)
    return Identified(spec, meas.mass_kg, quality, meas, virgin)


def _build_spec(model: str, meas: Measured, virgin: tuple[FloatArray, FloatArray] | None,
                stri: dict[str, float] | None, n_elements: int | None, quality: dict[str, Any]) -> dict[str, Any]:
    quality.setdefault("notes", [])
    if model in ("gms", "maxwell_slip"):
        d, f = virgin  # type: ignore[misc]
        key = (id(d), id(f), n_elements)
        if key not in _VIRGIN_CACHE:  # the virgin fit does not depend on the sliding terms: compute once
            _VIRGIN_CACHE.clear()
            if n_elements is None:
                n_el, table = choose_elements(d, f)
            else:
                n_el, table = int(n_elements), None
            _VIRGIN_CACHE[key] = (n_el, table, *fit_virgin(d, f, n_el))
        n_el, table, deltas, w, rss = _VIRGIN_CACHE[key]
        if table is not None:
            quality["element_selection"] = {"criterion": "BIC", "table": table, "chosen": n_el}
        quality["virgin_fit"] = {"rms_n": math.sqrt(rss / d.size), "points": int(d.size),
                                 "breakpoints_m": [float(x) for x in deltas]}
        reg = _refine_by_regression(meas, deltas, stri)
        if reg is not None:
            spec, mass, note = reg
            quality["loop_refinement"] = note
            quality["mass_kg_from_loops"] = mass
            if model == "maxwell_slip":
                w_el = np.array(spec["alpha"]) * spec["fc_n"]
                spec = {"model": "maxwell_slip", "k_n_m": spec["k_n_m"], "w_n": [float(x) for x in w_el],
                        "viscous_n_s_m": spec["viscous_n_s_m"]}
            return spec
        deltas, w, loop_note = _refine_on_loops(meas, deltas, w)
        if loop_note:
            quality["loop_refinement"] = loop_note
        k = w / deltas
        fsum = float(w.sum())
        if model == "maxwell_slip":
            spec = {"model": "maxwell_slip", "k_n_m": [float(x) for x in k], "w_n": [float(x) for x in w],
                    "viscous_n_s_m": float(stri["viscous_n_s_m"]) if stri else 0.0}
        else:
            fc = fsum
            fs = fsum
            vs, dl = 1e-3, 2.0
            if stri is not None and stri["fs_n"] > stri["fc_n"] * 1.01:
                fc = fsum * stri["fc_n"] / stri["fs_n"]
                vs, dl = stri["vs_m_s"], stri["delta"]
            spec = {"model": "gms", "k_n_m": [float(x) for x in k], "alpha": [float(x) for x in w / fsum],
                    "fc_n": fc, "fs_n": fs, "vs_m_s": vs, "delta": dl, "c_n_s": 1e4,
                    "viscous_n_s_m": float(stri["viscous_n_s_m"]) if stri else 0.0}
    elif model == "dahl":
        d, f = virgin  # type: ignore[misc]

        def res_dahl(p: FloatArray) -> FloatArray:
            return np.asarray(p[1] * (1 - np.exp(-p[0] * d / p[1])) - f, dtype=np.float64)

        k0 = _initial_slope(d, f)
        r = least_squares(res_dahl, [k0, float(f.max())], bounds=([1e-6, 1e-9], [np.inf, np.inf]))
        spec = {"model": "dahl", "sigma0_n_m": float(r.x[0]), "fc_n": float(r.x[1]),
                "viscous_n_s_m": float(stri["viscous_n_s_m"]) if stri else 0.0}
    elif model == "lugre":
        if stri is None and virgin is None:
            raise DataError(f"{meas.sig.source}: LuGre needs constant-velocity segments or a loading branch")
        fc = stri["fc_n"] if stri else float(virgin[1].max())  # type: ignore[index]
        fs = stri["fs_n"] if stri else fc
        sigma0 = _initial_slope(*virgin) if virgin is not None else 1e5
        m = meas.mass_kg or 1.0
        spec = {"model": "lugre", "sigma0_n_m": sigma0, "sigma1_n_s_m": 2.0 * math.sqrt(sigma0 * m),
                "fc_n": max(fc, 1e-9), "fs_n": max(fs, fc, 1e-9), "vs_m_s": stri["vs_m_s"] if stri else 1e-3,
                "delta": stri["delta"] if stri else 2.0,
                "viscous_n_s_m": stri["viscous_n_s_m"] if stri else 0.0}
        quality["notes"].append("sigma1 set for a bristle damping ratio of 1 with the identified mass")
    else:  # hsieh
        spec = _identify_hsieh(meas, virgin, stri)  # type: ignore[arg-type]
    return spec



#: parameters refined jointly by simulation (log scale) after the module-by-module / curve estimates
REFINE_KEYS = {
    "hsieh": ("k1s_n_m", "k2s_n_m", "beta_1_m", "cv_n_s_m", "rho_1_s", "psi", "a"),
    "lugre": ("sigma0_n_m", "sigma1_n_s_m", "fc_n", "fs_n"),
}


def refine_by_simulation(meas: Measured, spec: dict[str, Any], keys: tuple[str, ...],
                         rows: npt.NDArray[np.bool_], max_nfev: int = 60,
                         on_run: Callable[[], None] | None = None) -> tuple[dict[str, Any], str]:
    """Least squares on log-parameters ``keys`` of the filtered model force along the measured trajectory
    (every 4th sample of ``rows``). Zero-valued parameters start at a small positive value. ``on_run()`` is
    called after every model run (at most ``1 + max_nfev·(1 + len(keys))``, see :func:`_refine_budget`)."""

    sig = meas.sig
    idx = np.flatnonzero(rows)[::4]
    target = meas.force[idx]
    base = dict(spec)
    p0 = []
    for k in keys:
        v = float(base[k])
        if v <= 0:
            v = {"cv_n_s_m": 10.0, "rho_1_s": 10.0}.get(k, 1e-3)
        p0.append(math.log(v))

    def force(p: FloatArray) -> FloatArray:
        trial = dict(base)
        for k, lv in zip(keys, p):
            trial[k] = float(math.exp(min(lv, 600.0)))  # an optimiser step may overshoot: no OverflowError
        if "fs_n" in trial and "fc_n" in trial and trial["fs_n"] < trial["fc_n"]:
            trial["fs_n"] = trial["fc_n"]
        fm = build(trial).force_along(sig.xf, sig.t)
        return np.asarray(signal.sosfiltfilt(sig.sos, fm)[idx], dtype=np.float64)

    def resid(p: FloatArray) -> FloatArray:
        try:
            r = force(p) - target
        except (ConfigError, ValueError, FloatingPointError):
            return np.full(idx.size, 1e3)
        finally:
            if on_run is not None:
                on_run()
        return np.where(np.isfinite(r), r, 1e3)

    r0 = resid(np.array(p0))
    res = least_squares(resid, np.array(p0), max_nfev=max_nfev, x_scale=1.0, diff_step=1e-3)
    out = dict(base)
    if res.cost * 2 < float(r0 @ r0):
        for k, lv in zip(keys, res.x):
            out[k] = float(math.exp(lv))
        if "fs_n" in out and "fc_n" in out and out["fs_n"] < out["fc_n"]:
            out["fs_n"] = out["fc_n"]
    rms0 = math.sqrt(float(r0 @ r0) / idx.size)
    rms1 = math.sqrt(2 * float(res.cost) / idx.size)
    return out, f"joint least squares on {', '.join(keys)}: RMS {rms0:.4g} N -> {min(rms0, rms1):.4g} N"


def _initial_slope(d: FloatArray, f: FloatArray) -> float:
    pos = d > 0
    dd, ff = d[pos], f[pos]
    k = max(3, dd.size // 50)
    return float(max(np.polyfit(dd[:k], ff[:k], 1)[0], 1e-3))


def _refine_by_regression(meas: Measured, deltas: FloatArray, stri: dict[str, float] | None
                          ) -> tuple[dict[str, Any], float, str] | None:
    """Closed-loop data (enough moving samples): least squares over all hysteresis loops with the
    inverse-dynamics regression of ``discover`` (mass, Coulomb, Maxwell-slip elements with micro-damping,
    viscous, Stribeck excess if identified), starting from the virgin-curve breakpoints; the breakpoints are
    refined by coordinate descent on log Δ_i. Returns (GMS spec, mass, note) or None for quasi-static data."""
    sig = meas.sig
    rows = sig.evaluate
    if rows.sum() < 500:
        return None
    h = fx.PRESLIDING.reshaped(Hyp(effects=(fx.PRESLIDING.name,)), deltas_m=tuple(float(d) for d in deltas))
    if stri is not None and stri.get("stribeck_identified"):
        h = fx.STRIBECK.reshaped(h.adding(fx.STRIBECK.name), vs_m_s=stri["vs_m_s"], delta=stri["delta"])
    first = rg.fit_linear(sig, h, rows)
    best = first
    ds_ = list(fx.PRESLIDING.shape(h).deltas_m)
    for _sweep in range(2):
        for j in range(len(ds_)):
            def cost(lv: float, j: int = j) -> float:
                trial = list(ds_)
                trial[j] = math.exp(lv)
                return rg.fit_linear(sig, fx.PRESLIDING.reshaped(h, deltas_m=tuple(trial)), rows).rss

            dj = ds_[j]
            res = minimize_scalar(cost, bounds=(math.log(dj / 2.5), math.log(dj * 2.5)), method="bounded",
                                  options={"maxiter": 10})
            if res.fun < best.rss:
                ds_[j] = math.exp(float(res.x))
                best = rg.fit_linear(sig, fx.PRESLIDING.reshaped(h, deltas_m=tuple(ds_)), rows)
    spec = hyp_to_spec(best.hyp)["friction"]
    if spec.get("model") != "gms":
        return None
    mass = float(best.hyp.theta.get("m", 0.0))
    n = int(rows.sum())
    note = (f"inverse-dynamics least squares over {n} moving samples (all loops): RMS "
            f"{math.sqrt(first.rss / n):.4g} N -> {math.sqrt(best.rss / n):.4g} N, mass {mass:.6g} kg")
    return spec, mass, note


def _refine_on_loops(meas: Measured, deltas: FloatArray, w: FloatArray) -> tuple[FloatArray, FloatArray, str]:
    """Least-squares refinement of the elements on the whole force trajectory (all hysteresis loops)."""
    sig = meas.sig
    x = sig.xf
    rows = np.zeros(sig.n, bool)
    rows[4 * sig.guard: -4 * sig.guard: max(1, sig.n // 5000)] = True
    # loops present? need at least two reversals
    if np.count_nonzero(np.diff(np.sign(np.diff(sig.xf))) != 0) < 2:
        return deltas, w, ""
    v = sig.v

    def design(ds_: FloatArray) -> FloatArray:
        z = maxwell_unit_states(np.ascontiguousarray(x), np.asarray(ds_, float))
        return np.column_stack([z, v])

    def rss_of(ds_: FloatArray) -> tuple[float, FloatArray]:
        a = design(ds_)[rows]
        coef, rn = nnls(a, meas.force[rows])
        return float(rn * rn), coef

    best, coef = rss_of(deltas)
    start = best
    for _sweep in range(2):
        for j in range(deltas.size):
            dj = deltas[j]

            def cost(s: float, j: int = j) -> float:
                trial = deltas.copy()
                trial[j] = math.exp(s)
                return rss_of(trial)[0]

            res = minimize_scalar(cost, bounds=(math.log(dj / 2), math.log(dj * 2)), method="bounded",
                                  options={"maxiter": 20})
            if res.fun < best:
                deltas = deltas.copy()
                deltas[j] = math.exp(float(res.x))
                best = float(res.fun)
    best, coef = rss_of(deltas)
    w_new = coef[: deltas.size]
    keep = w_new > 0
    note = (f"refined on {int(rows.sum())} samples of hysteresis loops: RMS {math.sqrt(start / rows.sum()):.4g} N "
            f"-> {math.sqrt(best / rows.sum()):.4g} N")
    if not keep.any():
        return deltas, w, note
    return deltas[keep], w_new[keep], note


def _identify_hsieh(meas: Measured, virgin: tuple[FloatArray, FloatArray],
                    stri: dict[str, float] | None) -> dict[str, Any]:
    """Hsieh & Pan module by module (see module docstring)."""
    d, f = virgin
    # spring module from the branches (virgin shape): |F − F_r| = k1s·δ + (k2s/β)(1 − e^{−βδ})
    dd, ff = d, f

    def res_spring(p: FloatArray) -> FloatArray:
        k1, k2, lb = p
        b = math.exp(lb)
        return np.asarray(k1 * dd + (k2 / b) * (1 - np.exp(-b * dd)) - ff, dtype=np.float64)

    k0 = _initial_slope(dd, ff)
    r = least_squares(res_spring, [0.05 * k0, 0.95 * k0, math.log(k0 / max(ff.max(), 1e-12))],
                      bounds=([0, 0, -50], [np.inf, np.inf, 50]))
    k1, k2, lb = (float(v) for v in r.x)
    beta = math.exp(lb)
    # plastic module from the virgin loading: x_p = x − x_s(F); equilibrium x_p = |F|^a/ψ
    fmax = float(f.max())
    fgrid = np.linspace(0.2 * fmax, 0.95 * fmax, 12)
    xs = np.array([_invert_spring(fi, k1, k2, beta) for fi in fgrid])
    xtot = np.interp(fgrid, f, d)  # first loading: d is the displacement of the virgin branch
    xp = xtot - xs
    ok = xp > 0
    if ok.sum() >= 3:
        a_exp, c = np.polyfit(np.log(fgrid[ok]), np.log(xp[ok]), 1)
        psi = float(math.exp(-c))
        a_exp = float(np.clip(a_exp, 0.1, 20.0))
        rho = 500.0
    else:
        a_exp, psi, rho = 1.0, 1e12, 0.0
    fc = stri["fc_n"] if stri else fmax
    fs = stri["fs_n"] if stri else fmax
    return {"model": "hsieh", "k1s_n_m": max(k1, 1e-6), "k2s_n_m": k2, "beta_1_m": beta,
            "cv_n_s_m": 0.0, "rho_1_s": rho, "psi": psi, "a": a_exp, "fc_n": max(fc, 1e-9),
            "fs_n": max(fs, fc, 1e-9), "vs_m_s": stri["vs_m_s"] if stri else 1e-3,
            "delta": stri["delta"] if stri else 2.0, "viscous_n_s_m": stri["viscous_n_s_m"] if stri else 0.0}


def _invert_spring(fv: float, k1: float, k2: float, beta: float) -> float:
    lo, hi = 0.0, 1.0
    def g(s: float) -> float:
        return k1 * s + (k2 / beta) * (1 - math.exp(-beta * s)) - fv
    while g(hi) < 0 and hi < 1e3:
        hi *= 2
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if g(mid) < 0:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)
