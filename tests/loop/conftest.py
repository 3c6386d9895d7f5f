"""Small real test objects for the loop tests: a rigid mass plant, a PD law and a ramp reference.

They are simple implementations of the same interfaces (not mocks), so the loop's scheduling, request and
safety logic can be tested in simulated time without the friction plant's numba compile time.
"""

from __future__ import annotations

import math

import pytest

from stagectl.clock import SimClock
from stagectl.control.api import Command, Reference
from stagectl.loop import ControlLoop, LoopConfig
from stagectl.safety import Safety, SafetyConfig
from stagectl.sim.direct import PlantIO


class MassPlant:
    """m·a = u + push − c·v, semi-implicit Euler; position quantised to ``resolution_m``."""

    def __init__(self, mass_kg: float = 1.0, c_n_s_m: float = 5.0, resolution_m: float = 1e-9):
        self.m, self.c, self.resolution_m = mass_kg, c_n_s_m, resolution_m
        self.x_m = 0.0
        self.v_m_s = 0.0
        self.t_s = 0.0
        self.push_n = 0.0

    def step(self, u_n: float, dt_s: float) -> None:
        n = max(1, math.ceil(dt_s / 1e-4))
        h = dt_s / n
        for _ in range(n):
            a = (u_n + self.push_n - self.c * self.v_m_s) / self.m
            self.v_m_s += a * h
            self.x_m += self.v_m_s * h
        self.t_s += dt_s

    def measure(self) -> float:
        return round(self.x_m / self.resolution_m) * self.resolution_m

    def measure_counts(self) -> int:
        return round(self.x_m / self.resolution_m)


class PD:
    """u = kp·e + kd·(v_ref − v̂) + m·a_ref; terms u_pid, u_inertia."""

    term_names = ("u_pid", "u_inertia")

    def __init__(self, kp: float = 4e4, kd: float = 400.0, mass: float = 1.0):
        self.kp, self.kd, self.mass = kp, kd, mass
        self.x_prev = 0.0
        self.resets: list[float] = []
        self.fail_next = False

    def reset(self, x_m: float) -> None:
        self.x_prev = x_m
        self.resets.append(x_m)

    def retune(self, cfg: dict) -> None:
        if cfg.get("kp", 1.0) <= 0:
            raise ValueError("kp: must be > 0")
        self.kp = cfg.get("kp", self.kp)

    def step(self, dt: float, x: float, ref: Reference) -> Command:
        if self.fail_next:
            self.fail_next = False
            raise RuntimeError("controller blew up")
        v = (x - self.x_prev) / dt
        self.x_prev = x
        u_pid = self.kp * (ref.x_m - x) + self.kd * (ref.v_m_s - v)
        u_in = self.mass * ref.a_m_s2
        return Command(u_pid + u_in, {"u_pid": u_pid, "u_inertia": u_in})


class RampReference:
    """Constant-velocity moves; implements the loop's ReferenceSource protocol."""

    def __init__(self, v_default: float = 1e-3):
        self.v_default = v_default
        self._x0 = 0.0
        self._t0 = 0.0
        self._target = 0.0
        self._v = 0.0

    def hold(self, t_s: float, x_m: float) -> None:
        self._x0, self._t0, self._target, self._v = x_m, t_s, x_m, 0.0

    def sample(self, t_s: float) -> Reference:
        if self._v == 0.0:
            return Reference(self._target)
        x = self._x0 + self._v * (t_s - self._t0)
        if (self._v > 0 and x >= self._target) or (self._v < 0 and x <= self._target):
            self._x0, self._v = self._target, 0.0
            return Reference(self._target)
        return Reference(x, self._v)

    def move(self, t_s: float, target_m: float, max_velocity_m_s: float | None) -> float:
        x = self.sample(t_s).x_m
        v = max_velocity_m_s or self.v_default
        self._x0, self._t0, self._target = x, t_s, target_m
        self._v = math.copysign(v, target_m - x) if target_m != x else 0.0
        return abs(target_m - x) / v

    def stop(self, t_s: float) -> float:
        x = self.sample(t_s).x_m
        self.hold(t_s, x)
        return x

    @property
    def target_m(self) -> float:
        return self._target


def make_loop(*, safety: dict | None = None, period_s: float = 1e-3, delay_cycles: int = 1, **kw):
    """Build (loop, io, plant, controller, clock) on simulated time; devices configured."""
    clock = SimClock()
    plant = MassPlant()
    io = PlantIO(plant, period_s, delay_cycles=delay_cycles)
    io.open()
    io.configure()
    scfg = dict(min_position_m=-0.01, max_position_m=0.01, following_error_m=1e-4, max_force_n=50.0,
                max_velocity_m_s=0.05, stale_cycles=3)
    scfg.update(safety or {})
    ctl = PD()
    loop = ControlLoop(
        clock=clock, sensor=io, actuator=io, controller=ctl, reference=RampReference(),
        safety=Safety(SafetyConfig(**scfg), period_s), cfg=LoopConfig(period_s=period_s, **kw),
    )
    return loop, io, plant, ctl, clock


class Rows:
    """A telemetry sink that keeps every row."""

    def __init__(self) -> None:
        self.rows: list[tuple[float, ...]] = []

    def append(self, row: tuple[float, ...]) -> None:
        self.rows.append(row)


@pytest.fixture
def rig():
    loop, io, plant, ctl, clock = make_loop()
    sink = Rows()
    loop.add_sink(sink)
    yield loop, io, plant, ctl, clock, sink
    io.close()


@pytest.fixture
def make():
    """The :func:`make_loop` factory (conftest helpers are not importable under importlib mode)."""
    made = []

    def factory(**kw):
        out = make_loop(**kw)
        made.append(out[1])
        return out

    yield factory
    for io in made:
        io.close()


@pytest.fixture
def rows():
    return Rows()
