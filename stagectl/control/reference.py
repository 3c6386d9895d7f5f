"""The loop's reference source and the scenario registry.

* :func:`scenario_names` / :func:`get_scenario`: the motions known by name (``--scenario``, ``demo.scenario``):
  the benchmark scenarios of :func:`stagectl.control.trajectory.benchmark_scenarios` plus ``demo`` (the demo
  motion of ``stagectl run``) and ``hold`` (no motion: ``None``).
* :class:`TrajectoryReference`: adapts :class:`~stagectl.control.trajectory.TrajectoryGenerator`
  (``step(dt)``) to the loop's reference source (``sample(t)``, ``hold``, ``move``, ``stop``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

from stagectl.control.api import Reference
from stagectl.control.ilc import Repetition
from stagectl.control.trajectory import (
    ForceBudget,
    Move,
    Scenario,
    TrajectoryGenerator,
    benchmark_scenarios,
    demo_scenario,
)
from stagectl.errors import ConfigError, short
from stagectl.schema import load, load_yaml_file

__all__ = ["EXTRA_SCENARIOS", "SCENARIO_FILE_SUFFIXES", "TrajectoryReference", "get_scenario", "load_scenario_file",
           "scenario_names"]

#: names accepted besides the benchmark scenarios: ``demo`` (demo motion) and ``hold`` (no motion)
EXTRA_SCENARIOS = ("demo", "hold")


def scenario_names() -> tuple[str, ...]:
    """Every scenario name :func:`get_scenario` knows, benchmark ones first."""
    return (*benchmark_scenarios(), *EXTRA_SCENARIOS)


#: file name endings :func:`get_scenario` reads as a scenario file
SCENARIO_FILE_SUFFIXES = (".yaml", ".yml")


def load_scenario_file(path: str | Path, field: str = "--scenario") -> Scenario:
    """A scenario from a YAML file: ``segments`` (a list of ``{kind: move|cosine|sine|triangle|dwell, ...}``,
    :mod:`stagectl.control.trajectory`), optional ``name`` (default: the file's stem), ``start_m``, ``settle_s``.

    Raises
    ------
    ConfigError
        The file unreadable or not YAML, a bad key or value (``FILE: segments[i].key: ...``), or a segment that
        cannot run (``FILE: segments[i] (triangle): ...``): one line each, prefixed by ``field``.
    """
    p = Path(path)
    try:
        data = load_yaml_file(p, "scenario file")
    except ConfigError as exc:
        raise ConfigError([f"{field}: {line}" for line in exc.problems]) from None
    if isinstance(data, dict) and "name" not in data:
        data = {"name": p.stem, **data}
    where = f"{field}: {p}"
    try:
        sc = load(Scenario, data, "")
    except ConfigError as exc:
        raise ConfigError([f"{where}: {line.lstrip('.')}" for line in exc.problems]) from None
    bad = sc.problems()
    if bad:
        raise ConfigError([f"{where}: {line}" for line in bad])
    return sc


def get_scenario(name: str, field: str = "--scenario") -> Scenario | None:
    """The scenario called ``name`` (``hold`` is None: stand still), or read from the file ``name`` when it ends
    in ``.yaml``/``.yml`` (:func:`load_scenario_file`).

    Raises
    ------
    ConfigError
        An unknown name, naming ``field`` and the known names; a bad scenario file.
    """
    if name.endswith(SCENARIO_FILE_SUFFIXES):
        return load_scenario_file(name, field)
    if name == "hold":
        return None
    if name == "demo":
        return demo_scenario()
    sc = benchmark_scenarios()
    if name not in sc:
        raise ConfigError(f"{field}: unknown scenario {short(name)} (known: {', '.join(scenario_names())})")
    return sc[name]


class TrajectoryReference:
    """Adapts :class:`~stagectl.control.trajectory.TrajectoryGenerator` (``step(dt)``) to the loop's
    ``ReferenceSource`` (``sample(t)``, ``hold``, ``move``, ``stop``).

    A scenario given with :meth:`set_scenario` starts at the loop's first ``hold`` (from the measured
    position); with ``repeat`` it restarts whenever it ends, until a ``move``/``stop`` request takes over.
    Real-time safe apart from ``move``/``stop`` (binding one segment).
    """

    def __init__(self, default_velocity_m_s: float = 1e-3) -> None:
        self.gen = TrajectoryGenerator(0.0)
        self.default_velocity_m_s = default_velocity_m_s
        self._t = 0.0
        self._target = 0.0
        self._scenario: Scenario | None = None
        self._repeat = False
        self._started = False
        self._loads = 0  # scenario (re)starts: the repetition counter of repetition()
        self._t_load = 0.0
        self._length = 0.0

    def set_scenario(self, scenario: Scenario | None, repeat: bool = False) -> None:
        """Run ``scenario`` (None: hold) from the loop's next ``hold``; ``repeat`` restarts it when it ends.
        ConfigError (one line per segment, naming its index) for a segment that cannot run, here and not in the
        loop's first cycle."""
        bad = scenario.problems(path=f"scenario {scenario.name}: segments") if scenario is not None else []
        if bad:
            raise ConfigError(bad)
        self._scenario = scenario
        self._repeat = repeat
        self._started = False

    def set_force_budget(self, budget: ForceBudget | None,
                         on_slowed: Callable[[Move, Move], None] | None = None) -> None:
        """Plan every move (scenario segments, ``move`` and ``stop`` requests) within ``budget`` (None: as
        given); ``on_slowed(asked, planned)`` is called when a move starts planned slower than asked
        (:class:`~stagectl.control.trajectory.ForceBudget`)."""
        self.gen.force_budget = budget
        self.gen.on_move_slowed = on_slowed

    def hold(self, t_s: float, x_m: float) -> None:
        self.gen.reset(x_m)
        self._t = t_s
        self._target = x_m
        if self._scenario is not None and not self._started:
            self._started = True
            self._load(t_s, self._scenario)
            self._target = math.nan

    def _load(self, t_s: float, scenario: Scenario) -> None:
        self.gen.load(scenario)
        self._loads += 1
        self._t_load = t_s
        self._length = float(self.gen.remaining_s())

    def run_scenario(self, t_s: float, name: str) -> float:
        """Start scenario ``name`` now, repeated until a move/stop request (a motion for ``ilc:`` to learn);
        returns the length of one repetition [s]. ConfigError (field ``motion``) for an unknown name or
        while a move is still running."""
        if name.endswith(SCENARIO_FILE_SUFFIXES):  # (this runs in the loop's cycle: no file reading here)
            raise ConfigError("motion: give a scenario name (scenario files are for simulate/run --scenario)")
        sc = get_scenario(name, "motion")
        if sc is None:
            raise ConfigError("motion: 'hold' is no motion to repeat")
        self.sample(t_s)
        if not self.gen.done:
            raise ConfigError("motion: the stage is still moving; start the repeated motion from standstill")
        self._scenario = sc
        self._repeat = True
        self._started = True
        self._target = math.nan
        self._load(t_s, sc)
        return self._length

    def repetition(self) -> Repetition | None:
        """Where a *repeated* scenario (``set_scenario(..., repeat=True)``) is: name, restart counter, time
        since its start [s], length [s]; None when no repeated scenario runs (a move/stop took over)."""
        sc = self._scenario
        if sc is None or not self._repeat or not self._started:
            return None
        return Repetition(sc.name, self._loads, self._t - self._t_load, self._length)

    def sample(self, t_s: float) -> Reference:
        dt = t_s - self._t
        if dt > 0.0:
            self._t = t_s
            ref = self.gen.step(dt)
            if self._repeat and self.gen.done and self._scenario is not None:
                self._load(t_s, self._scenario)
            return ref
        return self.gen.sample()

    def stop_m(self) -> float:
        """Where the reference next comes to rest without reversing first [m] (NaN: a reversal may come first;
        :meth:`~stagectl.control.trajectory.TrajectoryGenerator.stop_m`, with the repeated scenario's restart),
        at the last :meth:`sample`."""
        return self.gen.stop_m(self._scenario if self._repeat and self._started else None)

    def move(self, t_s: float, target_m: float, max_velocity_m_s: float | None) -> float:
        self._repeat = False
        self._scenario = None
        self.gen.move(target_m, max_velocity_m_s or self.default_velocity_m_s)
        self._target = target_m
        return float(self.gen.remaining_s())

    def stop(self, t_s: float) -> float:
        """Decelerate (jerk-limited, the generator's default move limits) and hold where the reference comes
        to rest; returns that position [m]."""
        self._repeat = False
        self._scenario = None
        self.sample(t_s)
        lim = Move(by_m=0.0)
        end = float(self.gen.stop(lim.max_acceleration_m_s2, lim.max_jerk_m_s3))
        self._target = end
        return end

    @property
    def scenario(self) -> Scenario | None:
        """The scenario set with :meth:`set_scenario` (None after a move/stop request took over)."""
        return self._scenario

    @property
    def target_m(self) -> float:
        if math.isnan(self._target):
            return float(self.gen.final_reference().x_m)
        return self._target
