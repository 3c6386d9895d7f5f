"""Compiled inner loops for identification (numba, cached on disk)."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from numba import njit

from stagectl.jit import kernel

FloatArray = npt.NDArray[np.float64]


@njit(cache=True)
def maxwell_unit_states(x: FloatArray, deltas: FloatArray) -> FloatArray:  # pragma: no cover - compiled
    """Normalised Maxwell-slip element deflections ``z_i/Δ_i`` ∈ [−1, 1] along ``x`` (relaxed start).

    Element i: ``z_i ← clip(z_i + Δx, −Δ_i, Δ_i)`` (exact elasto-slip update), so the element force is
    ``W_i·z_i/Δ_i`` with saturation force ``W_i`` [N] and break displacement ``Δ_i`` [m].
    """
    n = x.shape[0]
    m = deltas.shape[0]
    out = np.zeros((n, m))
    z = np.zeros(m)
    for k in range(1, n):
        dx = x[k] - x[k - 1]
        for i in range(m):
            zi = z[i] + dx
            d = deltas[i]
            if zi > d:
                zi = d
            elif zi < -d:
                zi = -d
            z[i] = zi
            out[k, i] = zi / d
    return out


@njit(cache=True)
def first_order_lag(e_ss: FloatArray, dt: float, tau: float, e0: float) -> FloatArray:  # pragma: no cover
    """``τ·de/dt = e_ss − e`` integrated exactly with ``e_ss`` frozen over each interval, ``e[0] = e0``.

    Same update as the ``stribeck`` model's frictional lag: ``e ← e_ss + (e − e_ss)·exp(−dt/τ)``.
    """
    n = e_ss.shape[0]
    out = np.empty(n)
    a = np.exp(-dt / tau) if tau > 0.0 else 0.0
    e = e0
    out[0] = e
    for k in range(1, n):
        e = e_ss[k] + (e - e_ss[k]) * a
        out[k] = e
    return out


@kernel
def sin_cos_rows(a: FloatArray, lam: float) -> FloatArray:  # pragma: no cover - compiled
    """``[sin(φ), cos(φ)]`` (shape (2, n)) of ``φ = a/λ``, each φ the same double numpy's ``a / lam`` gives.

    The same libm ``sin``/``cos`` numpy calls for float64 (bit for bit where numpy's float64 sine is libm's,
    tests/ident/test_speed_equivalence.py), but LLVM pairs the two calls on one argument into one ``sincos``:
    0.6 ms instead of 1.0 ms for 25 000 samples, and the discovery's periodic searches build a few hundred of
    these pairs."""
    n = a.shape[0]
    out = np.empty((2, n))
    for i in range(n):
        ph = a[i] / lam
        out[0, i] = math.sin(ph)
        out[1, i] = math.cos(ph)
    return out
