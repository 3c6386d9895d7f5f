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

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from stagectl.ident import effects as fx
from stagectl.ident.columns import given_force
from stagectl.ident.hypothesis import Column, FitResult, Hyp
from stagectl.ident.signals import ArrayCache, Signals

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

__all__ = ["FitResult", "Hyp", "LinearFitter", "design", "filtered_design", "fit_linear", "friction_columns",
           "friction_force", "residual", "solve"]


# ---------------------------------------------------------------------------------------------- columns
def friction_columns(sig: Signals, h: Hyp) -> list[Column]:
    """Raw (unfiltered) friction columns before scaling effects: Coulomb, the effects' friction columns,
    viscous (or only the scale of a given friction model)."""
    if h.given_spec is not None:
        spec = h.given_spec
        return [Column("given", given_force(sig, spec), "given:" + repr(sorted(spec.items())), nonneg=True)]
    cols = [Column("fc", sig.direction, "fc", nonneg=True)]
    for spec_ in fx.REGISTRY.active(h):
        if spec_.friction_columns is not None:
            cols += spec_.friction_columns(sig, h)
    cols.append(Column("fv", sig.v, "fv", nonneg=True))
    return cols


def friction_force(sig: Signals, h: Hyp, theta: dict[str, float] | None = None) -> FloatArray:
    """Friction force before scaling effects [N] (raw, unfiltered)."""
    return _force_of(sig, friction_columns(sig, h), h.theta if theta is None else theta)


def _force_of(sig: Signals, fcols: list[Column], th: dict[str, float]) -> FloatArray:
    out = np.zeros(sig.n)
    for c in fcols:
        out += th.get(c.name, 0.0) * c.values
    return out


def _target_delay(h: Hyp) -> float:
    return sum((s.target_delay(h) for s in fx.REGISTRY.active(h) if s.target_delay is not None), 0.0)


def design(sig: Signals, h: Hyp, f_prev: FloatArray | None = None, scaled: bool = True
           ) -> tuple[list[Column], FloatArray]:
    """Raw columns and raw target ``ū_τ − m_fixed·a`` (all unfiltered) for hypothesis ``h``.

    ``f_prev``: the friction estimate the scaling and friction-following columns use (default: the friction
    force of ``h``'s coefficients, or sgn(v) before the first fit). ``scaled=False`` leaves the friction
    scaling out (:func:`filtered_design` applies it after filtering).
    """
    cols, target, _ = _design(sig, h, f_prev, scaled)
    return cols, target


def _design(sig: Signals, h: Hyp, f_prev: FloatArray | None, scaled: bool
            ) -> tuple[list[Column], FloatArray, int]:
    """:func:`design`, and how many of the columns are friction columns (they come first)."""
    active = fx.REGISTRY.active(h)
    needs_f = any(s.scaling is not None or s.iterative for s in active)  # else no column reads the estimate
    fcols = friction_columns(sig, h)
    if f_prev is None:
        f_prev = _force_of(sig, fcols, h.theta) if h.theta and needs_f else sig.direction
    mult: FloatArray | None = None
    if scaled:
        for s in active:
            if s.scaling is not None:
                m1 = 1.0 + s.scaling(h) * np.sign(f_prev)
                mult = m1 if mult is None else mult * m1
    n_friction = len(fcols)
    cols = list(fcols)
    if mult is not None:
        cols = [Column(c.name, c.values * mult, c.cache_key, c.nonneg) for c in cols]
    f_est = f_prev if mult is None else f_prev * mult
    for s in active:
        if s.columns is not None:
            cols += s.columns(sig, h, f_est)
    names = [c.name for c in cols]
    if len(set(names)) != len(names):  # theta is keyed by column name: two would collapse (a registry bug,
        # so not a ValueError, which discovery treats as a candidate that cannot be fitted)
        dup = sorted({n for n in names if names.count(n) > 1})
        raise RuntimeError(f"design: column name(s) {', '.join(dup)} produced twice by the effects "
                         f"{', '.join(s.name for s in active)}; each column must belong to one effect")
    target = sig.ubar(_target_delay(h))
    if h.fixed_mass_kg is None:
        cols.append(Column("m", sig.acc_raw, "m", nonneg=True))
    else:
        target = target - h.fixed_mass_kg * sig.acc_raw
    return cols, target, n_friction


def _filtered_design(
    sig: Signals, h: Hyp, f_prev: FloatArray | None = None
) -> tuple[list[Column], _Stack, FloatArray]:
    """Raw columns, filtered design matrix (all samples) and filtered target.

    Columns that do not depend on the previous fit are filtered once and cached. The friction scaling is
    linear in its ratio, ``c·(1 + r·s) = c + r·(c·s)`` with ``s = sgn(F_prev)``, so both parts are cached
    (keyed by the sign pattern) and combined; the rest is filtered in one batched call.
    """
    scaling = [s for s in fx.REGISTRY.active(h) if s.scaling is not None]
    r = 0.0
    sgn_f: FloatArray | None = None
    if scaling:
        r = scaling[0].scaling(h)  # type: ignore[misc]  # not None: filtered above
        # the estimate design() would compute itself (a scaling effect reads it), computed once
        f_prev = f_prev if f_prev is not None else (friction_force(sig, h) if h.theta else sig.direction)
        sgn_f = np.sign(f_prev)
    cols, target, n_friction = _design(sig, h, f_prev, scaled=False)
    raw = [c.values for c in cols]
    if sgn_f is not None:
        # friction-following columns carry the scaling of the friction estimate
        raw = [v * (1.0 + r * sgn_f) if c.follows_friction else v for c, v in zip(cols, raw)]
    out: list[FloatArray | None] = [None] * len(cols)
    keys: list[str | None] = [None] * len(cols)
    todo: list[int] = []
    skey = None if sgn_f is None else "sgn:" + str(hash(sgn_f.astype(np.int8).tobytes()))
    # every filtered column this design needs that the cache does not hold, filtered in one batched call
    got: dict[str, FloatArray] = {}
    need: dict[str, FloatArray] = {}

    def want(key: str, raw_of: Callable[[], FloatArray]) -> None:
        if key in got or key in need:
            return
        hit = sig.cache.get("F:" + key)
        if hit is None:
            need[key] = raw_of()
        else:
            got[key] = cast(FloatArray, hit)

    scaled_key: dict[int, str] = {}
    for j, c in enumerate(cols):
        if c.cache_key is None:
            todo.append(j)
            continue
        want(c.cache_key, lambda j=j: raw[j])  # type: ignore[misc]
        if sgn_f is not None and skey is not None and j < n_friction:
            scaled_key[j] = c.cache_key + "|" + skey
            want(scaled_key[j], lambda j=j: raw[j] * sgn_f)  # type: ignore[misc]
    ykey = f"target:{_target_delay(h):.6e}:{h.fixed_mass_kg}"
    want(ykey, lambda: target)
    filt = sig.filt_rows([*need.values(), *(raw[j] for j in todo)])
    for key, f in zip(need, filt):
        sig.cache["F:" + key] = f
        got[key] = f
    for i, j in enumerate(todo):
        out[j] = filt[len(need) + i]
    for j, c in enumerate(cols):
        if c.cache_key is None:
            continue
        base = got[c.cache_key]
        keys[j] = c.cache_key
        if j in scaled_key:
            base = base + r * got[scaled_key[j]]
            keys[j] = f"{c.cache_key}|{skey}|{r!r}"
        out[j] = base
    y = got[ykey]
    return cols, _Stack(cast(list[FloatArray], out), keys, ykey), y


class _Stack:
    """The filtered design matrix, stacked only when someone needs the matrix (the fit reads the columns)."""

    def __init__(self, cols: list[FloatArray], keys: list[str | None], ykey: str) -> None:
        self.cols = cols
        self.keys = keys  # cache key of each filtered column (None: depends on the fit)
        self.ykey = ykey
        self._m: FloatArray | None = None

    def matrix(self) -> FloatArray:
        if self._m is None:
            self._m = np.column_stack(self.cols)
        return self._m


def filtered_design(
    sig: Signals, h: Hyp, f_prev: FloatArray | None = None
) -> tuple[list[Column], FloatArray, FloatArray]:
    """Raw columns, filtered design matrix (all samples) and filtered target (see :func:`_filtered_design`)."""
    cols, st, y = _filtered_design(sig, h, f_prev)
    return cols, st.matrix(), y


class _GramStore:
    """Products of fit-independent filtered columns over one row set, kept in a matrix indexed by the columns'
    cache keys (NaN: not computed yet), so that a fit reads its whole cached block in one indexing step."""

    #: keys beyond which the store starts afresh (2048² products: 32 MB; EMPS discovery uses 1850 keys)
    MAX_KEYS = 2048

    def __init__(self) -> None:
        self.index: dict[str, int] = {}
        self.m = np.full((64, 64), np.nan)

    def ids(self, keys: Sequence[str]) -> list[int]:
        if len(self.index) + len(keys) > self.MAX_KEYS:
            self.__init__()  # type: ignore[misc]
        out = []
        for k in keys:
            i = self.index.get(k)
            if i is None:
                i = len(self.index)
                self.index[k] = i
                if i >= self.m.shape[0]:
                    cap = 2 * self.m.shape[0]
                    m = np.full((cap, cap), np.nan)
                    m[: self.m.shape[0], : self.m.shape[0]] = self.m
                    self.m = m
            out.append(i)
        return out


def _gram(sig: Signals, rows: BoolArray, a: list[FloatArray], y: FloatArray, keys: Sequence[str | None],
          ykey: str, rk: str | None = None) -> tuple[FloatArray, FloatArray, float]:
    """``AᵀA``, ``Aᵀy`` and ``yᵀy`` over ``rows``, with every product of two cached (fit-independent) columns
    cached on ``sig`` (:class:`_GramStore`): a search that changes one column computes one row of the Gram
    matrix, not all of it, and reads the rest in one step."""
    if rk is None:  # the rows' key (fit_linear passes the one it made)
        rk = "rows:" + str(hash(rows.tobytes()))
    stores = cast(dict[str, _GramStore], sig.cache.setdefault("_gram", {}))
    gs = stores.get(rk)
    if gs is None:
        gs = stores[rk] = _GramStore()
    rowcols = cast(dict[str, FloatArray], sig.cache.setdefault("_rowcols", ArrayCache()))
    # the rows as indices: ``v.take(idx)`` is ``v[rows]`` (the same values, contiguous) at a third of the cost
    idx_of = cast(dict[str, npt.NDArray[np.intp]], sig.cache.setdefault("_rowidx", {}))
    idx = idx_of.get(rk)
    if idx is None:
        idx = idx_of[rk] = np.flatnonzero(rows)
    p = len(a)
    allk = [*keys, ykey]
    allv = [*a, y]
    vecs: dict[int, FloatArray] = {}

    def vec(j: int) -> FloatArray:
        """Column ``j`` (``p``: the target) on ``rows``."""
        v = vecs.get(j)
        if v is None:
            k = allk[j]
            if k is None:
                v = allv[j].take(idx)
            else:
                v = rowcols.get(rk + "|" + k)
                if v is None:
                    v = allv[j].take(idx)
                    rowcols[rk + "|" + k] = v
            vecs[j] = v
        return v

    full = np.empty((p + 1, p + 1))
    kj = [j for j in range(p + 1) if allk[j] is not None]
    ids = gs.ids([cast(str, allk[j]) for j in kj])
    ia = np.asarray(ids)
    sub = gs.m[ia[:, None], ia]
    missing = np.isnan(sub)
    if missing.any():
        mu, mw = np.nonzero(missing)  # row-major, as np.nonzero(np.triu(missing)) after keeping u <= w
        upper = mu <= mw
        for u, w in zip(mu[upper].tolist(), mw[upper].tolist()):
            val = float(vec(kj[u]) @ vec(kj[w]))
            sub[u, w] = sub[w, u] = val
            gs.m[ids[u], ids[w]] = gs.m[ids[w], ids[u]] = val
    ka = np.asarray(kj)
    full[ka[:, None], ka] = sub
    for j in range(p + 1):
        if allk[j] is None:  # a fit-dependent column: every product afresh
            for i in range(p + 1):
                if allk[i] is not None or i <= j:
                    full[i, j] = full[j, i] = float(vec(min(i, j)) @ vec(max(i, j)))
    return full[:p, :p].copy(), full[:p, p].copy(), float(full[p, p])


# ---------------------------------------------------------------------------------------------- small solves
# The fits solve thousands of p x p systems (p <= ~30): numpy.linalg's argument checks cost 3-4 times the LAPACK
# call itself. These call the same gufuncs under the same floating-point error handling (same results, bit for
# bit; a singular or indefinite matrix raises LinAlgError as numpy.linalg does).
def _raise_singular(err: str, flag: int) -> None:
    raise np.linalg.LinAlgError("Singular matrix")


def _raise_nonposdef(err: str, flag: int) -> None:
    raise np.linalg.LinAlgError("Matrix is not positive definite")


def _fast_lsolve(a: FloatArray, b: FloatArray) -> FloatArray:
    with np.errstate(call=_raise_singular, invalid="call", over="ignore", divide="ignore", under="ignore"):
        return cast(FloatArray, _UL.solve1(a, b, signature="dd->d"))


def _fast_cholesky(a: FloatArray) -> FloatArray:
    with np.errstate(call=_raise_nonposdef, invalid="call", over="ignore", divide="ignore", under="ignore"):
        return cast(FloatArray, _UL.cholesky_lo(a, signature="d->d"))


def _public_lsolve(a: FloatArray, b: FloatArray) -> FloatArray:
    return cast(FloatArray, np.linalg.solve(a, b))


def _public_cholesky(a: FloatArray) -> FloatArray:
    return cast(FloatArray, np.linalg.cholesky(a))


def _pick_solvers() -> tuple[Callable[[FloatArray, FloatArray], FloatArray], Callable[[FloatArray], FloatArray]]:
    """numpy's private gufuncs when they exist and agree bit for bit with numpy.linalg on a probe (numpy may
    rename or change them in any release), else numpy.linalg itself: same results, only slower."""
    try:
        a = np.array([[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]])
        b = np.array([1.0, -2.0, 0.5])
        if (np.array_equal(_fast_lsolve(a, b), np.linalg.solve(a, b))
                and np.array_equal(_fast_cholesky(a), np.linalg.cholesky(a))):
            return _fast_lsolve, _fast_cholesky
    except Exception:  # noqa: BLE001 - any failure of a private API means: use the public one
        pass
    return _public_lsolve, _public_cholesky


_UL: Any
try:
    from numpy.linalg import _umath_linalg as _UL  # private: guarded by _pick_solvers
except ImportError:  # pragma: no cover - a numpy without it
    _UL = None
_lsolve, _cholesky = _pick_solvers()


def nonneg_lstsq(r: FloatArray, c: FloatArray, nonneg: npt.NDArray[np.bool_],
                 start: npt.NDArray[np.bool_] | None = None) -> FloatArray:
    """``argmin ‖c − R·θ‖²`` subject to ``θ_j >= 0`` where ``nonneg[j]`` (the others free), for a small square
    upper-triangular ``R`` (p <= ~30): the Lawson-Hanson active-set method on the normal equations
    ``G = RᵀR``, ``b = Rᵀc``, with the free variables always in the passive set. Checked against
    ``scipy.optimize.lsq_linear(method="bvls")`` in tests/ident/test_regress_solver.py.

    ``start``: a guess of the passive set (e.g. ``θ > 0`` of a neighbouring problem in a shape search). If the
    unbounded solution on it is feasible, the iterations start there instead of from the free variables
    alone: a valid Lawson-Hanson state, so they end at the same optimum, whose passive set is unique for a
    positive definite ``G`` and whose solution is computed from that set alone (the same result, in a few
    solves instead of one per element that carries force)."""
    g = r.T @ r
    b = r.T @ c
    p = b.shape[0]
    passive = ~nonneg.copy()

    def sub(mask: npt.NDArray[np.bool_]) -> FloatArray:
        z = np.zeros(p)
        if mask.any():
            idx = np.flatnonzero(mask)
            z[idx] = _lsolve(g[idx[:, None], idx], b[idx])
        return z

    tol = 1e-12 * max(float(np.max(np.abs(b))), 1e-300)  # gradient components below it count as zero
    x: FloatArray | None = None
    if start is not None and start.shape == passive.shape:
        p0 = passive | (start & nonneg)
        if (p0 != passive).any():
            z0 = sub(p0)
            if not (p0 & nonneg & (z0 <= 0.0)).any():
                passive, x = p0, z0
    if x is None:
        x = sub(passive)
    for _ in range(3 * p + 10):
        w = b - g @ x
        cand = nonneg & ~passive & (w > tol)
        if not cand.any():
            break
        j = int(np.argmax(np.where(cand, w, -np.inf)))
        passive[j] = True
        for _inner in range(3 * p + 10):
            z = sub(passive)
            viol = passive & nonneg & (z <= 0.0)
            if not viol.any():
                x = z
                break
            iv = np.flatnonzero(viol)
            alpha = float(np.min(x[iv] / (x[iv] - z[iv])))
            x = x + alpha * (z - x)
            drop = passive & nonneg & (x <= tol)
            passive &= ~drop
            x[drop] = 0.0
        else:  # pragma: no cover - cycling: a guard, never seen
            raise np.linalg.LinAlgError("nonneg_lstsq: active-set iterations did not converge")
    return x


def solve_gram(nonneg: Sequence[bool], g0: FloatArray, b0: FloatArray, yy: float, n: int,
               start: npt.NDArray[np.bool_] | None = None) -> tuple[FloatArray, float]:
    """:func:`solve` from the normal equations ``G = AᵀA``, ``b = Aᵀy``, ``yᵀy`` of ``n`` rows (``start``: a
    guess of the passive set for :func:`nonneg_lstsq`)."""
    scale = np.sqrt(np.maximum(np.diag(g0), 0.0) / max(n, 1))
    scale[scale == 0] = 1.0
    g = g0 / np.outer(scale, scale)
    b = b0 / scale
    p = g.shape[0]
    g[np.diag_indices(p)] += 1e-12 * max(float(np.trace(g)), 1e-300)
    try:
        r = _cholesky(g).T
    except np.linalg.LinAlgError:
        g[np.diag_indices(p)] += 1e-8 * float(np.trace(g))
        r = _cholesky(g).T
    c = _lsolve(r.T, b)
    base = max(yy - float(c @ c), 0.0)
    lo = np.array([0.0 if nn else -np.inf for nn in nonneg])
    hi = np.full(p, np.inf)
    sol = _lsolve(r, c)
    th = sol / scale
    if not (np.all(th >= lo - 1e-12) and np.all(th <= hi + 1e-12)):
        sol = nonneg_lstsq(r, np.asarray(c, dtype=np.float64), np.isfinite(lo), start)
        th = sol / scale
    e = c - r @ sol
    return np.asarray(th, dtype=np.float64), base + float(e @ e)


def solve(nonneg: Sequence[bool], a: FloatArray, y: FloatArray) -> tuple[FloatArray, float]:
    """Bounded linear least squares with column scaling (``nonneg[j]``: θ_j >= 0). Returns (θ, residual sum
    of squares).

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
        r = _cholesky(g).T
    except np.linalg.LinAlgError:
        g[np.diag_indices(p)] += 1e-8 * float(np.trace(g))
        r = _cholesky(g).T
    c = _lsolve(r.T, b)
    yy = float(y @ y)
    base = max(yy - float(c @ c), 0.0)
    lo = np.array([0.0 if nn else -np.inf for nn in nonneg])
    hi = np.full(p, np.inf)
    sol = _lsolve(r, c)
    th = sol / scale
    if not (np.all(th >= lo - 1e-12) and np.all(th <= hi + 1e-12)):
        sol = nonneg_lstsq(r, np.asarray(c, dtype=np.float64), np.isfinite(lo))
        th = sol / scale
    e = c - r @ sol
    return np.asarray(th, dtype=np.float64), base + float(e @ e)


def fit_linear(sig: Signals, h: Hyp, rows: BoolArray) -> FitResult:
    """Fit the linear parameters of ``h`` (shapes fixed) on ``rows``; two passes when a column depends on the
    previous fit (friction scaling, friction-following columns)."""
    # the searches ask for the same fit again (the centre of each refinement grid, the winner refitted, the
    # clean-up steps): the result depends on the hypothesis and the rows only, so it is kept on the signals
    rk = "rows:" + str(hash(rows.tobytes()))
    key = (rk, h.effects, repr(sorted(h.shapes.items())),
           repr(sorted(h.theta.items())), h.fixed_mass_kg, h.x_center_m, repr(h.given_spec))
    memo = cast(dict[object, FitResult], sig.cache.setdefault("_fits", {}))
    hit = memo.get(key)
    if hit is not None:
        return FitResult(hit.hyp.copy(), hit.rss, hit.n)
    passes = 2 if any(s.iterative for s in fx.REGISTRY.active(h)) else 1
    hh = h.copy()
    rss = np.inf
    # the passive set of the last bounded fit with the same columns starts the next one (a shape search
    # refits the same columns many times)
    warm = cast(dict[object, npt.NDArray[np.bool_]], sig.cache.setdefault("_passive", {}))
    counts = cast(dict[str, int], sig.cache.setdefault("_rowcount", {}))
    n = counts.get(rk)
    if n is None:
        n = counts[rk] = int(rows.sum())
    for _ in range(passes):
        cols, st, y = _filtered_design(sig, hh)
        g, b, yy = _gram(sig, rows, st.cols, y, st.keys, st.ykey, rk)
        nonneg = [c.nonneg for c in cols]
        wkey = (rk, tuple(c.name for c in cols))
        th, rss = solve_gram(nonneg, g, b, yy, n, warm.get(wkey))
        warm[wkey] = ~np.asarray(nonneg, dtype=bool) | (th > 0.0)
        hh.theta = dict(zip((c.name for c in cols), (float(v) for v in th)))
    memo[key] = FitResult(hh.copy(), float(rss), n)
    return FitResult(hh, float(rss), n)


def residual(sig: Signals, h: Hyp) -> FloatArray:
    """Filtered force residual ``L[moving·(ū_τ − m·a − F_model)]`` of a fitted hypothesis [N] (all samples)."""
    cols, st, y = _filtered_design(sig, h)
    out = y.copy()
    for c, v in zip(cols, st.cols):
        th = h.theta.get(c.name, 0.0)
        if th != 0.0:
            out -= th * v
    return out


@dataclass(frozen=True)
class LinearFitter:
    """:class:`~stagectl.ident.hypothesis.Fitter` on signals ``sig`` and rows ``rows``."""

    sig: Signals
    rows: BoolArray

    def fit(self, h: Hyp) -> FitResult:
        return fit_linear(self.sig, h, self.rows)

    def residual(self, h: Hyp) -> FloatArray:
        return residual(self.sig, h)

    def friction_force(self, h: Hyp) -> FloatArray:
        return friction_force(self.sig, h)
