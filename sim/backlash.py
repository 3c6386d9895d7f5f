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

Integration: one compiled call per ``step`` (:func:`loop_for`, a numba kernel specialised on the friction
side's model kernel like the plant's own loop): per coupling step h the contact force, then the friction-free
body (semi-implicit Euler), then the friction side in ``ceil(h/substep_s)`` sub-steps of the plant's own
general sub-step (:func:`stagectl.sim.plant.substep`, inlined: effects, Karnopp band of static models; the body
exists once). :meth:`BacklashPlant.step_reference` is the same
integration in plain Python over :meth:`StagePlant.step`, kept as the oracle the kernel is tested against.
A friction side with an actuation delay (``effects.delay``) uses the reference path (the kernel has no
command history).

A model file can carry the play (``backlash:`` of :class:`stagectl.friction.StageModel`, written by
``stagectl discover``); :func:`plant_from_model` builds the motor + load plant from it.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from stagectl.sim.plant import _T, PlantConfig, StagePlant, load_state, store_state, substep
from stagectl.sim.plant import plant_from_model as _rigid_plant_from_model

from stagectl.friction import StageModel
from stagectl.jit import kernel
from stagectl.schema import load, param

FloatArray = npt.NDArray[np.float64]

# bp (backlash parameters) layout: side mass, breakaway, stick velocity, other mass, k_c, c_c, b/2,
# friction on the load (1) or motor (0), coupling step h, side sub-steps per h
_BP_N = 10
# bs (backlash state): x_other, v_other, contact force
_BS_N = 3


def _make_loop(kstep: Any) -> Any:
    """The fused motor + load loop specialised on the friction side's kernel ``kstep`` (see module docstring)."""

    @kernel(_nrt=False)  # allocates nothing; no reference counting of the arrays handed to the inlined sub-step
    def run(kp, fs, ep, bp, ps, bs, u, nh):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
        """Hold ``u`` on the motor for ``nh`` coupling steps; side state ``ps``/``fs``, other body ``bs``."""
        m = bp[0]
        inv_m = 1.0 / m
        fb = bp[1]
        dvs = bp[2]
        inv_mo = 1.0 / bp[3]
        kc = bp[4]
        cc = bp[5]
        half = bp[6]
        on_load = bp[7] != 0.0
        h = bp[8]
        ns = int(bp[9])
        hs = h / ns
        x, v, ff, stuck, win, wf, wo = load_state(ps)
        xo = bs[0]
        vo = bs[1]
        fcon = bs[2]
        for _ in range(nh):
            if on_load:
                d = xo - x
                dv = vo - v
            else:
                d = x - xo
                dv = v - vo
            fcon = 0.0
            if d > half:
                fcon = max(kc * (d - half) + cc * dv, 0.0)
            elif d < -half:
                fcon = min(kc * (d + half) + cc * dv, 0.0)
            if on_load:
                f_o = u - fcon
                ua = fcon
            else:
                f_o = fcon
                ua = u - fcon
            vo = vo + h * f_o * inv_mo
            xo = xo + h * vo
            for i in range(ns):  # the plant's general sub-step with the contact force held (tau = 0)
                x, v, ff, stuck, win, wf, wo = substep(kstep, kp, fs, ep, fb, dvs, inv_m, hs, ua, x, v, ff, stuck,
                                                       win, wf, wo)
            ps[_T] = ps[_T] + h
        store_state(ps, x, v, ff, stuck, win, wf, wo)
        bs[0] = xo
        bs[1] = vo
        bs[2] = fcon

    return run


@functools.cache  # keyed on the kernel object itself (identity), which the cache keeps alive
def loop_for(kstep: Any) -> Any:
    """:func:`_make_loop` made once per friction kernel."""
    return _make_loop(kstep)


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

    def __init__(self, cfg: PlantConfig, bl: BacklashConfig, fused: bool = True) -> None:
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
        side = self.side
        self._fused = fused and side._tau == 0.0
        if self._fused:
            self._loop = loop_for(side._kstep)
            self._bp = np.zeros(_BP_N)
            self._bp[:9] = [cfg.mass_kg, side._par[1], side._par[2], self._m_other, self._k, self._c,
                            0.5 * float(bl.gap_m), 1.0 if bl.friction_side == "load" else 0.0, 0.0]
            self._bs = np.array([self._x_o, 0.0, 0.0])

    @classmethod
    def from_mapping(cls, plant: Any, backlash: Any, fused: bool = True) -> BacklashPlant:
        return cls(PlantConfig.from_mapping(plant), load(BacklashConfig, backlash, "backlash"), fused=fused)

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
        """Hold the commanded force ``u_n`` [N] on the motor for ``dt_s`` [s] (one compiled call)."""
        if not self._fused:
            self.step_reference(u_n, dt_s)
            return
        if not (dt_s > 0.0 and math.isfinite(dt_s)):
            raise ValueError(f"dt_s must be > 0 and finite (got {dt_s})")
        n = max(1, math.ceil(dt_s / self.bl.coupling_step_s - 1e-9))
        h = dt_s / n
        side = self.side
        self._bp[8] = h
        self._bp[9] = side._nsub(h)
        self._loop(side._kp, side._fs, side._ep, self._bp, side._ps, self._bs, side._clamp(u_n), n)
        self._x_o, self._v_o, self._fc = float(self._bs[0]), float(self._bs[1]), float(self._bs[2])
        self._ring.append(self._counts(self.x_m))
        self._ring.pop(0)

    def step_reference(self, u_n: float, dt_s: float) -> None:
        """:meth:`step` in plain Python over :meth:`StagePlant.step` (the oracle of the compiled loop)."""
        if self._fused:
            raise RuntimeError("step_reference: build the plant with fused=False to use the reference path")
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


def plant_from_model(model: StageModel, backlash: Any = None, **overrides: Any) -> StagePlant | BacklashPlant:
    """The plant a model file describes: a :class:`BacklashPlant` when it has a ``backlash:`` section (the
    friction side gets ``mass_kg − other_mass_kg``; ``backlash`` maps extra :class:`BacklashConfig` keys such as
    ``contact_stiffness_n_m``), else a rigid :class:`StagePlant`. ``overrides`` are ``plant:`` keys."""
    bl = model.backlash
    if bl is None:
        return _rigid_plant_from_model(model, **overrides)
    mass = overrides.pop("mass_kg", model.mass_kg)
    if mass is None:
        raise ValueError("plant_from_model: mass_kg is in neither the model nor the overrides")
    side = float(mass) - float(bl.other_mass_kg)
    if side <= 0.0:
        raise ValueError(f"backlash.other_mass_kg: {bl.other_mass_kg:.6g} kg must be below mass_kg = {mass:.6g} kg")
    cfg = PlantConfig.from_mapping({**overrides, "mass_kg": side}, path="plant", model=model)
    keys = {"gap_m": bl.gap_m, "other_mass_kg": bl.other_mass_kg, "friction_side": bl.friction_side,
            "sensor_side": bl.sensor_side, **dict(backlash or {})}
    return BacklashPlant(cfg, load(BacklashConfig, keys, "backlash"))


__all__ = ["BacklashConfig", "BacklashPlant", "loop_for", "plant_from_model"]
