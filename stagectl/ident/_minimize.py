"""The two small derivative-free minimisers the discovery shape searches use, without importing
``scipy.optimize`` (with ``scipy.linalg`` under it, about 0.35 s of ``stagectl discover``'s 0.6 s of imports).

* :func:`bounded_scalar` is Brent's bounded minimisation (golden section with parabolic steps; R. P. Brent,
  *Algorithms for Minimization without Derivatives*, 1973, ch. 5; the ``fminbound`` of Forsythe, Malcolm and
  Moler), step for step the algorithm of ``scipy.optimize.minimize_scalar(method="bounded")``;
* :func:`nelder_mead` is the standard (non-adaptive) Nelder-Mead simplex with reflection 1, expansion 2,
  contraction 1/2 and shrink 1/2, from a given initial simplex, as ``scipy.optimize.minimize(method=
  "Nelder-Mead")`` runs it.

Both are checked against scipy on random problems to rounding (tests/ident/test_minimize.py): the discovery
results do not change.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

_SQRT_EPS = math.sqrt(2.2e-16)
_GOLDEN = 0.5 * (3.0 - math.sqrt(5.0))


def bounded_scalar(fun: Callable[[float], float], lo: float, hi: float, xatol: float = 1e-5,
                   maxiter: int = 500) -> tuple[float, float]:
    """Minimise ``fun`` on ``[lo, hi]`` (Brent); returns (x, fun(x)) of the best point, at most ``maxiter``
    evaluations, stopping when the bracket is within ``xatol`` (absolute) plus √ε relative."""
    if not lo <= hi:
        raise ValueError(f"bounds [{lo}, {hi}] are empty")
    a, b = lo, hi
    fulc = a + _GOLDEN * (b - a)
    nfc, xf = fulc, fulc
    rat = e = 0.0
    x = xf
    fx = fun(x)
    num = 1
    ffulc = fnfc = fx
    xm = 0.5 * (a + b)
    tol1 = _SQRT_EPS * abs(xf) + xatol / 3.0
    tol2 = 2.0 * tol1
    while abs(xf - xm) > (tol2 - 0.5 * (b - a)):
        golden = True
        if abs(e) > tol1:  # try a parabola through the three best points
            golden = False
            r = (xf - nfc) * (fx - ffulc)
            q = (xf - fulc) * (fx - fnfc)
            p = (xf - fulc) * q - (xf - nfc) * r
            q = 2.0 * (q - r)
            if q > 0.0:
                p = -p
            q = abs(q)
            r = e
            e = rat
            if abs(p) < abs(0.5 * q * r) and p > q * (a - xf) and p < q * (b - xf):
                rat = (p + 0.0) / q
                x = xf + rat
                if (x - a) < tol2 or (b - x) < tol2:
                    rat = tol1 * _sign1(xm - xf)
            else:
                golden = True
        if golden:
            e = (a - xf) if xf >= xm else (b - xf)
            rat = _GOLDEN * e
        x = xf + _sign1(rat) * max(abs(rat), tol1)
        fu = fun(x)
        num += 1
        if fu <= fx:
            if x >= xf:
                a = xf
            else:
                b = xf
            fulc, ffulc = nfc, fnfc
            nfc, fnfc = xf, fx
            xf, fx = x, fu
        else:
            if x < xf:
                a = x
            else:
                b = x
            if fu <= fnfc or nfc == xf:
                fulc, ffulc = nfc, fnfc
                nfc, fnfc = x, fu
            elif fu <= ffulc or fulc == xf or fulc == nfc:
                fulc, ffulc = x, fu
        xm = 0.5 * (a + b)
        tol1 = _SQRT_EPS * abs(xf) + xatol / 3.0
        tol2 = 2.0 * tol1
        if num >= maxiter:
            break
    return xf, fx


def _sign1(v: float) -> float:
    """sgn(v), with sgn(0) = 1 (the step direction of the bounded search)."""
    return -1.0 if v < 0.0 else 1.0


def nelder_mead(fun: Callable[[FloatArray], float], simplex: FloatArray, maxfev: int, xatol: float = 1e-4,
                fatol: float = 1e-4) -> FloatArray:
    """Minimise ``fun`` from the initial ``simplex`` (N+1 points of dimension N) by Nelder-Mead with at most
    ``maxfev`` evaluations; stops when the simplex is within ``xatol`` and its values within ``fatol``.
    Returns the best point."""
    sim = np.array(simplex, dtype=np.float64)
    n = sim.shape[1]
    calls = 0

    class _Done(Exception):
        pass

    def f(x: FloatArray) -> float:
        nonlocal calls
        if calls >= maxfev:
            raise _Done
        calls += 1
        return float(fun(np.copy(x)))

    fsim = np.full(n + 1, np.inf)
    try:
        for k in range(n + 1):
            fsim[k] = f(sim[k])
    except _Done:
        pass
    ind = np.argsort(fsim)
    sim, fsim = np.take(sim, ind, 0), np.take(fsim, ind, 0)
    while calls < maxfev:
        try:
            if (np.max(np.ravel(np.abs(sim[1:] - sim[0]))) <= xatol
                    and np.max(np.abs(fsim[0] - fsim[1:])) <= fatol):
                break
            xbar = np.add.reduce(sim[:-1], 0) / n
            xr = 2.0 * xbar - sim[-1]
            fxr = f(xr)
            shrink = False
            if fxr < fsim[0]:
                xe = 3.0 * xbar - 2.0 * sim[-1]
                fxe = f(xe)
                if fxe < fxr:
                    sim[-1], fsim[-1] = xe, fxe
                else:
                    sim[-1], fsim[-1] = xr, fxr
            elif fxr < fsim[-2]:
                sim[-1], fsim[-1] = xr, fxr
            elif fxr < fsim[-1]:
                xc = 1.5 * xbar - 0.5 * sim[-1]
                fxc = f(xc)
                if fxc <= fxr:
                    sim[-1], fsim[-1] = xc, fxc
                else:
                    shrink = True
            else:
                xcc = 0.5 * xbar + 0.5 * sim[-1]
                fxcc = f(xcc)
                if fxcc < fsim[-1]:
                    sim[-1], fsim[-1] = xcc, fxcc
                else:
                    shrink = True
            if shrink:
                for j in range(1, n + 1):
                    sim[j] = sim[0] + 0.5 * (sim[j] - sim[0])
                    fsim[j] = f(sim[j])
        except _Done:
            pass
        ind = np.argsort(fsim)
        sim, fsim = np.take(sim, ind, 0), np.take(fsim, ind, 0)
    return np.asarray(sim[0], dtype=np.float64)
