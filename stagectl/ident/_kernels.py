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


@kernel
def backlash_load(xm: FloatArray, vm: FloatArray, am: FloatArray, gap: float, dec_c: float, dec_v: float,
                  dt: float) -> FloatArray:  # pragma: no cover - compiled
    """Load side of a motor + load pair with play ``gap`` [m], driven by the measured motor trajectory.

    ``xm, vm, am``: motor position [m], velocity [m/s], acceleration [m/s²]. The load (friction per unit load
    mass ``dec_c·sgn(v) + dec_v·v`` [m/s²]) sits at ``δ = x_l − x_m ∈ [−b/2, b/2]``. In contact at
    ``δ = −b/2`` (motor pushing +) it follows the motor while the contact force per load mass
    ``a_m + dec_c·sgn(v_m) + dec_v·v_m`` stays ≥ 0 (≤ 0 at ``+b/2``); when it would pull, the load leaves
    the face and coasts under its own friction (semi-implicit step, stopping at v = 0) until ``δ`` reaches
    a face again, where it is engaged inelastically. This opens the play at reversals *and* whenever the
    motor decelerates harder than the load's friction decelerates the load.

    Returns ``out[0]``: 1 while the play is open; ``out[1]``: at each engagement ``(v_m − v_l)/dt`` [m/s²]
    (the velocity step the motor hands the load), else 0.
    """
    n = xm.shape[0]
    out = np.zeros((2, n))
    h = 0.5 * gap
    xl = xm[0]
    vl = 0.0
    c = 0
    for k in range(1, n):
        if c != 0:
            s = 1.0 if vm[k] > 0.0 else (-1.0 if vm[k] < 0.0 else 0.0)
            req = am[k] + dec_c * s + dec_v * vm[k]
            if c * req >= 0.0:
                xl = xm[k] - c * h
                vl = vm[k]
                continue
            xl = xm[k - 1] - c * h
            vl = vm[k - 1]
            c = 0
        if vl != 0.0:
            s = 1.0 if vl > 0.0 else -1.0
            vn = (vl - dt * dec_c * s) / (1.0 + dt * dec_v)
            if vn * vl <= 0.0:
                vn = 0.0
            xl += 0.5 * (vl + vn) * dt
            vl = vn
        d = xl - xm[k]
        if d <= -h or d >= h:
            c = 1 if d <= -h else -1
            out[1, k] = (vm[k] - vl) / dt
            xl = xm[k] - c * h
            vl = vm[k]
        else:
            out[0, k] = 1.0
    return out
