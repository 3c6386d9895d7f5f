"""Search helpers for the nonlinear parameters of the discovery effects (grids, bounded scalar search,
speed range, pre-sliding grid, position periodogram)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

import numpy as np
import numpy.typing as npt

from stagectl.ident._minimize import bounded_scalar
from stagectl.ident.signals import Signals

FloatArray = npt.NDArray[np.float64]


def best_scalar(
    fun: Callable[[float], float], grid: Iterable[float], lo: float, hi: float, log: bool = True, maxiter: int = 12
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
            xs, fr = bounded_scalar(lambda s: fun(math.exp(s)), math.log(a), math.log(b), xatol=1e-3,
                                    maxiter=maxiter)
            xr = math.exp(xs)
        else:
            xr, fr = bounded_scalar(fun, a, b, maxiter=maxiter)
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
