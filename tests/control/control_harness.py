"""Small closed-loop harness for the control tests: StagePlant (stagectl.sim) + StageController.

Simulated time only. The plant is the seed stage (config/models/kamenar2016_gms.yaml: Table 1 GMS, 2 kg),
1 nm quantisation. ``io_delay_s`` puts a pure actuation delay into the plant (one cycle of I/O delay).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from stagectl.control.controller import ControllerConfig, StageController
from stagectl.control.trajectory import Scenario, TrajectoryGenerator
from stagectl.friction import StageModel, load_model_file
from stagectl.schema import load

REPO = Path(__file__).resolve().parents[2]
SEED_MODEL = REPO / "config" / "models" / "kamenar2016_gms.yaml"


def seed_model() -> StageModel:
    return load_model_file(SEED_MODEL)


def mismatched(model: StageModel, factor: float = 0.8) -> StageModel:
    """The §6.3 "20 % off" model: k × 0.8, Fs 0.8, Fc 0.72, Vs 1.2 mm/s, σ2 8 (for the seed GMS)."""
    f = model.friction
    p = f.params
    fr = f.replace(k_n_m=[k * factor for k in p.k_n_m], fs_n=p.fs_n * 0.8 / 0.9, fc_n=p.fc_n * 0.9,
                   vs_m_s=p.vs_m_s * 1.2, viscous_n_s_m=p.viscous_n_s_m * 0.8)
    return StageModel(friction=fr, effects=model.effects, mass_kg=model.mass_kg)


def make_plant(model: StageModel, io_delay_s: float = 0.0, resolution_m: float = 1e-9, noise_std_m: float = 0.0):
    from stagectl.sim.plant import PlantConfig, StagePlant

    data: dict[str, Any] = {"mass_kg": model.mass_kg, "friction": model.friction,
                            "sensor": {"resolution_m": resolution_m, "noise_std_m": noise_std_m}}
    eff = model.effects.spec()
    if io_delay_s > 0.0:
        eff["delay"] = {"delay_s": io_delay_s}
    data["effects"] = eff
    return StagePlant(load(PlantConfig, data, "plant"))


class KarnoppStage:
    """A plain oracle plant for lock-step control tests, written from the physics, not from stagectl.sim: a mass
    on Karnopp stick/slip friction at the seed stage's levels (static F_S, kinetic F_C + viscous SIGMA2·v, stuck
    while |v| < V_STICK and |u| ≤ F_S), semi-implicit Euler in ``sub`` sub-steps per period, the force applied one
    period late (one cycle of I/O delay). ``step(u)`` advances one period under the previous command, latches
    ``u`` and returns the position [m]."""

    F_C, F_S, SIGMA2, MASS = 0.8, 0.9, 10.0, 2.0  # [N], [N], [N·s/m], [kg]
    V_STICK = 1e-7  # Karnopp band [m/s]

    def __init__(self, period_s: float, sub: int) -> None:
        self.x = self.v = self.u_applied = 0.0
        self.sub = sub
        self.h = period_s / sub

    def step(self, u_n: float) -> float:
        x, v, u, h = self.x, self.v, self.u_applied, self.h
        for _ in range(self.sub):
            if abs(v) < self.V_STICK and abs(u) <= self.F_S:
                v = 0.0
                continue
            f = ((self.F_C * math.copysign(1.0, v) + self.SIGMA2 * v) if abs(v) >= self.V_STICK
                 else math.copysign(self.F_S, u))
            v += (u - f) / self.MASS * h
            x += v * h
        self.x, self.v, self.u_applied = x, v, u_n
        return x


def controller_cfg(**sections: Any) -> ControllerConfig:
    data: dict[str, Any] = {"mass_kg": 2.0}
    data.update(sections)
    return load(ControllerConfig, data, "controller")


def run_closed_loop(ctl: StageController, plant, scenario: Scenario, period_s: float,
                    duration_s: float | None = None) -> dict[str, np.ndarray]:
    """Read -> step -> write at ``period_s``; returns arrays t, x (true), x_ref, e, u."""
    gen = TrajectoryGenerator(0.0)
    gen.load(scenario)
    n = int(round((duration_s if duration_s is not None else gen.remaining_s()) / period_s))
    plant.reset(0.0)
    ctl.reset(plant.measure())
    out = {k: np.empty(n) for k in ("t", "x", "x_ref", "e", "u")}
    ref = gen.sample()
    for k in range(n):
        cmd = ctl.step(period_s, plant.measure(), ref)
        plant.step(cmd.force_n, period_s)
        ref = gen.step(period_s)
        out["t"][k] = plant.t_s
        out["x"][k] = plant.x_m
        out["x_ref"][k] = ref.x_m
        out["u"][k] = cmd.force_n
    out["e"] = out["x_ref"] - out["x"]
    return out


def rms_after(res: dict[str, np.ndarray], t0: float) -> float:
    m = res["t"] > t0
    return float(math.sqrt(np.mean(res["e"][m] ** 2)))
