"""Shared helpers of the friction tests: the per-sample paths of a model, and a minimal fused mass loop."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numba import njit, types

from stagectl.friction._numba import STEP_FN


def scalar_and_kernel_paths(model, x, t):
    """Forces along ``x(t)`` by ``model.step`` and by the raw kernel ``step``, both from the relaxed state,
    with the ``force_along`` sampling convention (F[0] = force(relaxed, first-difference velocity))."""
    kern = model.kernel()
    s_model, s_kern = model.initial_state(), model.initial_state()
    v0 = (x[1] - x[0]) / (t[1] - t[0])
    f_model, f_kern = [model.force(s_model, v0)], [kern.force(kern.p, s_kern, v0)]
    for k in range(1, len(x)):
        dx, dt = x[k] - x[k - 1], t[k] - t[k - 1]
        f_model.append(model.step(s_model, dx, dx / dt, dt))
        f_kern.append(kern.step(kern.p, s_kern, dx, dx / dt, dt))
    return np.array(f_model), np.array(f_kern)


@njit(types.void(STEP_FN, types.float64[::1], types.float64[::1], types.float64, types.float64,
                 types.float64, types.float64, types.int64, types.float64[::1]), cache=True)
def _mass_loop(step, p, state, dt, m, u0, ua, n, xs):  # pragma: no cover - compiled
    """m·a = u − F, u = u0 + ua·sin(2πt), symplectic Euler with the friction kernel fused in (as a plant)."""
    x = 0.0
    v = 0.0
    f = 0.0
    for k in range(n):
        u = u0 + ua * math.sin(2.0 * math.pi * k * dt)
        v += dt * (u - f) / m
        dx = v * dt
        x += dx
        f = step(p, state, dx, v, dt)
        xs[k] = x


def mass_loop(model, dt: float, mass_kg: float, u0_n: float, ua_n: float, n: int, state=None) -> np.ndarray:
    """Positions [m] of a mass driven by u = u0 + ua·sin(2πt) against ``model`` from rest; the friction
    state starts relaxed, or is ``state`` (advanced in place)."""
    kern = model.kernel()
    xs = np.empty(n)
    _mass_loop(kern.step, kern.p, model.initial_state() if state is None else state, dt, mass_kg, u0_n, ua_n,
               n, xs)
    return xs


@pytest.fixture(scope="session")
def paths():
    return scalar_and_kernel_paths


@pytest.fixture(scope="session")
def driven_mass():
    return mass_loop
