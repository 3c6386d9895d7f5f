"""Compiled inner loops for identification (numba kernels declared with :func:`stagectl.jit.kernel`: compiled
on first use, cached in its cache directory)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from stagectl.jit import kernel

FloatArray = npt.NDArray[np.float64]


@kernel
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


@kernel
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
