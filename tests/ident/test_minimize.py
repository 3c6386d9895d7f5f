"""The discovery's own minimisers (stagectl.ident._minimize) against scipy.optimize, which they replace to keep
scipy.optimize out of `stagectl discover`'s imports: the same points on random problems, to rounding."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import minimize, minimize_scalar

from stagectl.ident._minimize import bounded_scalar, nelder_mead


def _wiggly(rng: np.random.Generator):  # a smooth function with several local minima and a flat stretch
    c = rng.normal(size=4)
    w = rng.uniform(0.5, 6.0, size=4)
    p = rng.uniform(0, 2 * math.pi, size=4)
    return lambda x: float(np.sum(c * np.sin(w * x + p)) + 0.05 * (x - c[0]) ** 2 + (0.3 if x > 2.0 else 0.0))


@pytest.mark.parametrize("seed", range(40))
def test_bounded_scalar_matches_scipy(seed: int) -> None:
    rng = np.random.default_rng(seed)
    f = _wiggly(rng)
    lo = float(rng.uniform(-3, 1))
    hi = lo + float(rng.uniform(1e-3, 5))
    xatol = float(rng.choice([1e-5, 1e-3]))
    maxiter = int(rng.choice([8, 12, 500]))
    ref = minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"maxiter": maxiter, "xatol": xatol})
    x, fx = bounded_scalar(f, lo, hi, xatol=xatol, maxiter=maxiter)
    assert x == pytest.approx(float(ref.x), rel=1e-12, abs=1e-15)
    assert fx == pytest.approx(float(ref.fun), rel=1e-12, abs=1e-15)
    assert lo <= x <= hi


@pytest.mark.parametrize("seed", range(30))
def test_nelder_mead_matches_scipy(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    a = rng.normal(size=(2, 2))
    q = a @ a.T + 0.1 * np.eye(2)
    x0 = rng.normal(size=2)

    def f(p: np.ndarray) -> float:
        d = p - x0
        return float(d @ q @ d + 0.3 * math.sin(3 * p[0]) * math.cos(2 * p[1]))

    start = rng.normal(size=2)
    simplex = np.array([start, start + [0.2, 0], start + [0, 0.2]])
    maxfev = int(rng.choice([5, 40, 400]))
    ref = minimize(f, start, method="Nelder-Mead",
                   options={"maxfev": maxfev, "xatol": 1e-3, "fatol": 1e-12, "initial_simplex": simplex})
    got = nelder_mead(f, simplex, maxfev=maxfev, xatol=1e-3, fatol=1e-12)
    np.testing.assert_allclose(got, ref.x, rtol=1e-12, atol=1e-15)


def test_bounded_scalar_refuses_empty_bounds() -> None:
    with pytest.raises(ValueError, match="empty"):
        bounded_scalar(lambda x: x * x, 1.0, 0.0)
