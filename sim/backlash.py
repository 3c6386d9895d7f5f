"""Backlash: a motor and a load separated by a deadband (ball-screw nut play, gear lash), for simulation.

Two rigid bodies, motor (mass ``m_m``, driven by the commanded force ``u``) and load (mass ``m_l``), touch
through a dead-zone contact of total play ``gap_m`` = b (SI units)::

    d = x_m − x_l                                   (relative position; free while |d| < b/2)
    F_c = k_c·(d − b/2) + c_c·(v_m − v_l)   if d > b/2 (and F_c > 0)
        = k_c·(d + b/2) + c_c·(v_m − v_l)   if d < −b/2 (and F_c < 0),   0 otherwise
    m_m·a_m = u − F_c − [F_friction if friction_side = motor]
    m_l·a_l = F_c − [F_friction if friction_side = load]

The side carrying the friction (and every effect of ``plant.effects``) is a full
:class:`stagectl.sim.plant.StagePlant` with mass ``plant.mass_kg``; the other side is a friction-free body of
mass ``other_mass_kg``. The two are coupled explicitly every ``coupling_step_s`` (the contact force is held
over it; stable for ``h·√(k_c/m) < 2`` on the lighter body, checked with margin). The sensor reads the motor
or the load (``sensor_side``) with the noise, quantisation and delay of ``plant.sensor``.

With the sensor on the motor (a rotary encoder on a ball-screw motor, as on EMPS), every reversal shows as
*lost motion*: the motor travels b with no friction and only its own inertia before the load follows; this is
the evidence `stagectl discover` looks for (docs/discovery.md §10).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from stagectl.schema import load, param
from stagectl.sim.plant import PlantConfig, StagePlant


@dataclass(frozen=True)
class BacklashConfig:
    """Deadband between motor and load (YAML block ``backlash:`` beside ``plant:`` in test generators)."""

    gap_m: float = param(unit="m", desc="total play b between motor and load", ge=0.0, le=0.01)
    other_mass_kg: float = param(unit="kg", desc="mass of the side without friction", gt=0.0)
    friction_side: str = param("load", unit="", desc="side carrying the friction and effects: load or motor",
                               choices=("load", "motor"))
    sensor_side: str = param("motor", unit="", desc="side the position sensor reads: motor or load",
                             choices=("motor", "load"))
    contact_stiffness_n_m: float = param(2e6, unit="N/m", desc="contact stiffness k_c once the play is closed",
                                         gt=0.0)
    contact_damping_fraction: float = param(0.7, unit="", desc="contact damping as a fraction of critical", ge=0.0)
    coupling_step_s: float = param(2e-5, unit="s", desc="explicit coupling step h", gt=0.0, le=1e-3)


class BacklashPlant:
    """Motor + load with backlash (see module docstring); the interface of :class:`StagePlant` that the
    closed-loop generators use: ``step(u, dt)``, ``measure()``, ``friction_n``, ``x_m``, ``v_m_s``."""

    def __init__(self, cfg: PlantConfig, bl: BacklashConfig) -> None:
        self.cfg, self.bl = cfg, bl
        self.side = StagePlant(cfg)  # the friction side
        self._m_other = float(bl.other_mass_kg)
        m_red = 1.0 / (1.0 / cfg.mass_kg + 1.0 / self._m_other)
        self._k = float(bl.contact_stiffness_n_m)
        self._c = 2.0 * float(bl.contact_damping_fraction) * math.sqrt(self._k * m_red)
        if bl.coupling_step_s * math.sqrt(self._k / m_red) > 0.5:
            raise ValueError(f"backlash.coupling_step_s: must be <= {0.5 / math.sqrt(self._k / m_red):.3g} s for "
                             f"contact stiffness {self._k:.4g} N/m (h·√(k_c/m) <= 0.5)")
        self._x_o = float(cfg.x0_m)
        self._v_o = 0.0
        self._fc = 0.0
        self._rng = np.random.default_rng(cfg.seed)
        nd = int(cfg.sensor.delay_steps)
        self._ring = [self._counts(self._x_o)] * (nd + 1)

    @classmethod
    def from_mapping(cls, plant: Any, backlash: Any) -> BacklashPlant:
        return cls(PlantConfig.from_mapping(plant), load(BacklashConfig, backlash, "backlash"))

    # ------------------------------------------------------------------ state
    def _motor_load(self) -> tuple[float, float, float, float]:
        xs, vs = self.side.x_m, self.side.v_m_s
        if self.bl.friction_side == "load":
            return self._x_o, self._v_o, xs, vs
        return xs, vs, self._x_o, self._v_o

    @property
    def x_motor_m(self) -> float:
        return self._motor_load()[0]

    @property
    def x_load_m(self) -> float:
        return self._motor_load()[2]

    @property
    def x_m(self) -> float:
        """Position of the sensed side [m] (without sensor noise)."""
        return self.x_motor_m if self.bl.sensor_side == "motor" else self.x_load_m

    @property
    def v_m_s(self) -> float:
        xm, vm, xl, vl = self._motor_load()
        return vm if self.bl.sensor_side == "motor" else vl

    @property
    def friction_n(self) -> float:
        return self.side.friction_n

    @property
    def contact_force_n(self) -> float:
        """Force the motor pushes the load with [N] (0 while the play is open)."""
        return self._fc

    # ------------------------------------------------------------------ stepping
    def _contact(self) -> float:
        xm, vm, xl, vl = self._motor_load()
        d = xm - xl
        half = 0.5 * self.bl.gap_m
        if d > half:
            return max(self._k * (d - half) + self._c * (vm - vl), 0.0)
        if d < -half:
            return min(self._k * (d + half) + self._c * (vm - vl), 0.0)
        return 0.0

    def step(self, u_n: float, dt_s: float) -> None:
        """Hold the commanded force ``u_n`` [N] on the motor for ``dt_s`` [s]."""
        n = max(1, math.ceil(dt_s / self.bl.coupling_step_s - 1e-9))
        h = dt_s / n
        u = float(u_n)
        for _ in range(n):
            fc = self._contact()
            self._fc = fc
            f_other = (u - fc) if self.bl.friction_side == "load" else fc  # force on the friction-free body
            f_side = fc if self.bl.friction_side == "load" else (u - fc)
            # friction-free body: semi-implicit Euler
            self._v_o += h * f_other / self._m_other
            self._x_o += h * self._v_o
            self.side.step(f_side, h)
        self._ring.append(self._counts(self.x_m))
        self._ring.pop(0)

    # ------------------------------------------------------------------ sensor
    def _counts(self, x: float) -> int:
        s = self.cfg.sensor
        if s.noise_std_m > 0.0:
            x += float(self._rng.normal(0.0, s.noise_std_m))
        return math.floor(x / s.resolution_m + 0.5)

    def measure(self) -> float:
        """Sensor reading [m] of the sensed side: noise, quantisation, ``delay_steps`` steps of delay."""
        return self._ring[0] * self.cfg.sensor.resolution_m


__all__ = ["BacklashConfig", "BacklashPlant"]
