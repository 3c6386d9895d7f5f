"""Raw regression columns built from a recording, cached on the :class:`~stagectl.ident.signals.Signals`.

Building blocks for the effects' design-matrix columns (see :mod:`stagectl.ident.effects`): Maxwell-slip
element states and rates, the Stribeck shape (optionally lagged), sine/cosine of position, the force of a
given friction model. Every builder caches its result in ``sig.cache`` under a key made of its parameters.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from stagectl.friction import build
from stagectl.ident._kernels import first_order_lag, maxwell_unit_states
from stagectl.ident.signals import Signals

FloatArray = npt.NDArray[np.float64]


def cached(sig: Signals, key: str, fn: Callable[[], FloatArray]) -> FloatArray:
    """``sig.cache[key]``, computed by ``fn()`` on the first call."""
    hit = sig.cache.get(key)
    if hit is None:
        hit = fn()
        sig.cache[key] = hit
    return cast(FloatArray, hit)


def gated_position(sig: Signals) -> FloatArray:
    """Position that drives the pre-sliding elements: the **raw** measured position.

    The zero-phase filtered position anticipates a reversal by a few samples (elements driven by it would flip
    before the stage does), and gating out slow samples would lose the sub-threshold creep that stiff
    pre-sliding elements respond to. The raw position has neither problem; its noise only toggles elements
    far smaller than any resolvable break displacement (the grid starts at 4 noise levels).
    """
    return cached(sig, "xgated", lambda: np.ascontiguousarray(sig.x, dtype=np.float64))


def element(sig: Signals, delta: float) -> FloatArray:
    """Normalised state z/Δ of one Maxwell-slip element along the gated position (depends on Δ only)."""
    return cached(sig, f"maxwell:{delta:.6e}", lambda: maxwell_unit_states(
        gated_position(sig), np.array([delta], dtype=np.float64))[:, 0].copy())


def min_damped_delta(sig: Signals) -> float:
    """Smallest break displacement [m] that gets a micro-damping column: 20 noise levels, 5 counts."""
    return max(20.0 * sig.noise_m, 5.0 * sig.quantum_m, 1e-8)


def element_rate(sig: Signals, delta: float) -> FloatArray:
    """Element deflection rate dz/dt [m/s] (micro-damping column: force σ1_i·dz_i/dt)."""
    return cached(sig, f"rate:{delta:.6e}", lambda: np.asarray(
        np.gradient(element(sig, delta) * delta, sig.dt_s), dtype=np.float64))


def given_force(sig: Signals, spec: Mapping[str, Any]) -> FloatArray:
    """Force of a given friction model (any tag) along the direction-gated position [N]."""
    return cached(sig, "given:" + repr(sorted(spec.items())), lambda: np.asarray(
        build(spec).force_along(gated_position(sig), sig.t), dtype=np.float64))


def stribeck_shape(sig: Signals, vs: float, delta: float, lag_s: float) -> FloatArray:
    """``sgn(v)·e`` with ``e = exp(−|v/vs|^δ)``, lagged by ``lag_s`` [s] when positive (frictional lag)."""
    def make() -> FloatArray:
        ess = np.exp(-np.abs(sig.v / vs) ** delta)
        e = ess if lag_s <= 0.0 else first_order_lag(np.ascontiguousarray(ess), sig.dt_s, lag_s, 1.0)
        return np.asarray(sig.direction * e, dtype=np.float64)

    return cached(sig, f"strib:{vs:.6e}:{delta:g}:{lag_s:.6e}", make)


def position_sin_cos(sig: Signals, lam: float) -> tuple[FloatArray, FloatArray]:
    """``sin(2πx/λ)`` and ``cos(2πx/λ)`` of the filtered position for wavelength ``lam`` [m]."""
    def make() -> FloatArray:
        ph = 2.0 * np.pi * sig.xf / lam
        both = np.empty((2, ph.shape[0]))
        np.sin(ph, out=both[0])
        np.cos(ph, out=both[1])
        return both

    both = cached(sig, f"sincos2:{lam:.9e}", make)
    return both[0], both[1]
