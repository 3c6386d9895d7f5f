"""Small real test objects for the loop tests: a rigid mass plant, a PD law and a ramp reference.

They are simple implementations of the same interfaces (not mocks), so the loop's scheduling, request and
safety logic can be tested in simulated time without the friction plant's numba compile time.
"""

from __future__ import annotations

import math

import pytest

from support import RampReference
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
