"""Closed-loop recordings from the simulated plant, with hidden effects (tests and demos).

A PID position loop with mass feed-forward (``u = m̂·a_ref + kp·e + ki·∫e + kd·ė``, bandwidth
``bandwidth_hz``, derivative on the measured position) runs at ``1/dt_s`` (1 kHz default) against
:class:`stagectl.sim.plant.StagePlant`; the recording follows docs/recordings.md (``u[k]`` is computed from
``x[k]`` and held over ``[t[k], t[k+1])``).

The reference (:func:`reference`) is built to excite every catalogue effect: jerk-limited back-and-forth
strokes at log-spread speeds (constant-speed segments for Coulomb/viscous/Stribeck, reversals for
pre-sliding, position coverage for ripple/cogging/spring), a sine sweep (acceleration, delay) and a
micrometre oscillation (pre-sliding). Random draws (speed order, stroke lengths) come from ``seed``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from stagectl.ident import effects as fx
from stagectl.ident.hypothesis import HiddenStage
from stagectl.ident.recording import Recording
from stagectl.schema import load
from stagectl.sim.backlash import BacklashConfig, BacklashPlant
from stagectl.sim.plant import PlantConfig, StagePlant

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Motion:
    """Reference motion design (SI units)."""

    duration_s: float = 14.0
    v_min_m_s: float = 0.4e-3
    v_max_m_s: float = 20e-3
    a_max_m_s2: float = 0.5
    cruise_s: float = 0.35
    dwell_s: float = 0.04
    micro_amplitude_m: float = 8e-6
    micro_hz: float = 3.0
    sweep_amplitude_m: float = 0.5e-3


def _stroke(v: float, a: float, cruise_s: float, dt: float) -> FloatArray:
    """Velocity profile of one stroke: raised-cosine acceleration to v, cruise, deceleration."""
    ta = max(1.5 * v / a, 0.02)
    na = max(int(round(ta / dt)), 2)
    ramp = v * 0.5 * (1 - np.cos(np.pi * np.arange(na) / na))
    cruise = np.full(max(int(round(cruise_s / dt)), 1), v)
    return np.concatenate([ramp, cruise, ramp[::-1], [0.0]])


def reference(motion: Motion, dt_s: float, seed: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Reference position, velocity and acceleration (arrays of ``duration_s/dt_s`` samples)."""
    rng = np.random.default_rng(seed)
    n = int(round(motion.duration_s / dt_s))
    speeds = list(np.geomspace(motion.v_min_m_s, motion.v_max_m_s, 7))
    vel: list[FloatArray] = []
    direction = 1.0
    pos = 0.0
    total = 0

    def push(seg: FloatArray) -> None:
        nonlocal total, pos
        vel.append(seg)
        total += seg.size
        pos += float(np.sum(seg)) * dt_s

    dwell = np.zeros(max(int(round(motion.dwell_s / dt_s)), 1))
    t_micro = 1.2
    t_sweep = 1.5
    budget = n - int((t_micro + t_sweep) / dt_s)
    while total < budget:
        order = rng.permutation(len(speeds))
        for i in order:
            v = speeds[i]
            cruise = motion.cruise_s * rng.uniform(0.6, 1.4)
            # keep the stage near the middle: head back if far out
            if pos > 4 * motion.v_max_m_s * motion.cruise_s:
                direction = -1.0
            elif pos < -4 * motion.v_max_m_s * motion.cruise_s:
                direction = 1.0
            push(direction * _stroke(v, motion.a_max_m_s2, cruise, dt_s))
            push(dwell)
            direction = -direction
            if total >= budget:
                break
    v_ref = np.concatenate(vel)[:budget]
    x_ref = pos_from_vel(v_ref, dt_s)
    # micro oscillation (pre-sliding) and a sine sweep (accelerations), both smooth-windowed
    tm = np.arange(int(t_micro / dt_s)) * dt_s
    win = np.sin(np.pi * tm / tm[-1]) ** 2
    xm = x_ref[-1] + motion.micro_amplitude_m * win * np.sin(2 * np.pi * motion.micro_hz * tm)
    ts = np.arange(int(t_sweep / dt_s)) * dt_s
    f = 1.0 + 3.0 * ts / ts[-1]
    phase = 2 * np.pi * np.cumsum(f) * dt_s
    ws = np.sin(np.pi * ts / ts[-1]) ** 2
    xs = xm[-1] + motion.sweep_amplitude_m * ws * np.sin(phase)
    x = np.concatenate([x_ref, xm, xs])
    x = np.concatenate([x, np.full(max(n - x.size, 0), x[-1])])[:n]
    v = np.gradient(x, dt_s)
    a = np.gradient(v, dt_s)
    return x, v, a


def pos_from_vel(v: FloatArray, dt: float) -> FloatArray:
    return np.concatenate([[0.0], np.cumsum(v[:-1]) * dt])


def closed_loop(
    plant_cfg: Mapping[str, Any],
    motion: Motion | None = None,
    dt_s: float = 1e-3,
    seed: int = 0,
    bandwidth_hz: float = 20.0,
    mass_estimate_kg: float | None = None,
    source: str = "synth",
    x_ref: FloatArray | None = None,
    backlash: Mapping[str, Any] | None = None,
) -> Recording:
    """Simulate a closed-loop recording.

    Parameters
    ----------
    plant_cfg : mapping
        A ``plant:`` mapping for :meth:`stagectl.sim.plant.PlantConfig.from_mapping` (mass_kg, friction,
        effects, sensor, ...); its ``seed`` is replaced by ``seed``.
    backlash : mapping, optional
        A :class:`stagectl.sim.backlash.BacklashConfig` mapping: the stage becomes motor + load with that play
        (``plant_cfg`` is then the friction side; the mass estimate defaults to the sum of both masses).
    motion : Motion
        Reference design.
    bandwidth_hz : float
        PID bandwidth [Hz]: kp = m̂ω², kd = 1.4·m̂ω, ki = kp·ω/8.
    x_ref : array, optional
        A reference position [m] per sample to use instead of :func:`reference` (``motion`` is then ignored).

    Returns
    -------
    Recording
        Columns t, x (measured), u (commanded), x_ref, and the true friction as extra column ``f_true``.
    """

    plant_map = dict(plant_cfg)
    if backlash is None and "backlash" in plant_map:  # a stage drawn by hide(..., "backlash", ...)
        backlash = plant_map.pop("backlash")
    plant_map.pop("backlash", None)
    cfg = PlantConfig.from_mapping({**plant_map, "seed": int(seed)})
    plant: StagePlant | BacklashPlant = StagePlant(cfg)
    m_total = cfg.mass_kg
    if backlash is not None:
        bl = load(BacklashConfig, dict(backlash), "backlash")
        plant = BacklashPlant(cfg, bl)
        m_total += bl.other_mass_kg
    m_hat = float(mass_estimate_kg if mass_estimate_kg is not None else m_total)
    if x_ref is None:
        x_ref, v_ref, a_ref = reference(motion or Motion(), dt_s, seed)
    else:
        x_ref = np.asarray(x_ref, dtype=np.float64)
        v_ref = np.gradient(x_ref, dt_s)
        a_ref = np.gradient(v_ref, dt_s)
    w = 2 * math.pi * bandwidth_hz
    kp, kd, ki = m_hat * w * w, 1.4 * m_hat * w, m_hat * w**3 / 8.0
    n = x_ref.size
    xs = np.empty(n)
    us = np.empty(n)
    fr = np.empty(n)
    integ = 0.0
    x_prev = plant.measure()
    vf = 0.0
    alpha = math.exp(-dt_s * 2 * math.pi * 5 * bandwidth_hz)
    for k in range(n):
        xm = plant.measure()
        e = x_ref[k] - xm
        vm = (xm - x_prev) / dt_s
        vf = alpha * vf + (1 - alpha) * vm
        x_prev = xm
        integ += e * dt_s
        u = m_hat * a_ref[k] + kp * e + ki * integ + kd * (v_ref[k] - vf)
        xs[k] = xm
        us[k] = u
        fr[k] = plant.friction_n
        plant.step(u, dt_s)
    t = np.arange(n, dtype=np.float64) * dt_s
    return Recording(t=t, x=xs, u=us, x_ref=x_ref, source=source, extra={"f_true": fr})


# --------------------------------------------------------------------------------------------- hidden effects
def draw_stage(rng: np.random.Generator) -> dict[str, Any]:
    """Random plausible stage: mass 1-5 kg, Coulomb 0.5-3 N, viscous 5-30 N·s/m; 1 nm encoder, 2 nm noise."""
    m = float(rng.uniform(1.0, 5.0))
    fc = float(rng.uniform(0.5, 3.0))
    fv = float(rng.uniform(5.0, 30.0))
    return {
        "mass_kg": m,
        "friction": {"model": "stribeck", "fc_n": fc, "fs_n": fc, "viscous_n_s_m": fv,
                     "stick_velocity_m_s": 1e-6},
        "sensor": {"resolution_m": 1e-9, "noise_std_m": 2e-9},
    }


def hide(stage: dict[str, Any], effect: str, rng: np.random.Generator, span_m: float = 0.02) -> dict[str, Any]:
    """Add ``effect`` with parameters drawn at random over plausible ranges to a stage mapping (a copy).

    A random sign is drawn first, then the effect's ``hide`` hook in :data:`stagectl.ident.effects.REGISTRY`
    draws its parameters (the ranges are in each hook's docstring; relative to the stage's Coulomb level Fc).
    """
    spec = fx.REGISTRY.get(effect)
    if spec.hide is None:
        raise ValueError(f"effect {effect!r} cannot be hidden in a simulated stage")
    st = {k: (dict(v) if isinstance(v, dict) else v) for k, v in stage.items()}
    fr = dict(st["friction"])
    sign = float(rng.choice([-1.0, 1.0]))
    hs = HiddenStage(fr, dict(st.get("effects") or {}), float(fr["fc_n"]), sign,
                     float(stage.get("mass_kg", math.nan)), span_m, rng)
    spec.hide(hs)
    if hs.backlash is not None:
        st["backlash"] = hs.backlash
    st["friction"] = hs.friction
    if hs.effects:
        st["effects"] = hs.effects
    return st
