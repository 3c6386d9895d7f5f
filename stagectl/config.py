"""Application configuration: one YAML file → frozen dataclasses, validated before any hardware is opened.

:func:`load_app_config` is *the* validation: ``stagectl check-config``, ``stagectl run``, ``simulate`` and
the daemon (start-up and SIGHUP reload) all call it. Every problem is reported at once with its key path
and unit (unknown keys included, with a "did you mean" hint); relative paths (model files) are resolved
against the YAML file's directory; derived values are computed once here or when objects are built.

Sections (see ``config/sim.yaml`` for a commented example)::

    loop:        LoopConfig        period_s, realtime {fifo_priority, cpus, mlock, timer_slack_ns, gc_freeze}, ...
    io:          IoConfig          kind: plant_io | embedded_canopen | canopen; sensor: drive | encoder |
                                   interferometer; drive: Cia402Config; encoder: CiA 406 config;
                                   interferometer: InterferometerConfig; delay_cycles (plant_io)
    sim:         simulated stage   plant: PlantConfig (+ the virtual devices for embedded_canopen and
                                   ``stagectl sim-plant``: SimWorldConfig); required for plant_io/embedded_canopen
    controller:  ControllerConfig  (stagectl.control.controller)
    safety:      SafetyConfig      soft limits, following error, force/velocity limits, stale position
    demo:        DemoConfig        what ``stagectl run`` does (scenario, repeat)
    daemon:      DaemonConfig      control socket, watchdog, telemetry (owned by stagectl.daemon.config)
"""

from __future__ import annotations

import dataclasses
import enum
import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from stagectl.errors import ConfigError
from stagectl.loop import LoopConfig
from stagectl.safety import SafetyConfig
from stagectl.schema import load, load_yaml_file, param, section_parser

__all__ = ["AppConfig", "DemoConfig", "IoConfig", "IoKind", "SensorSource", "load_app_config", "parse_app_config"]


def _lazy(module: str, cls_name: str, what: str) -> Callable[[Any, str, list[str]], Any]:
    """Parse hook loading ``module.cls_name`` on first use (keeps ``import stagectl.config`` light)."""

    def hook(value: Any, path: str, problems: list[str]) -> Any:
        if value is None:
            return None
        try:
            cls = getattr(importlib.import_module(module), cls_name)
        except (ModuleNotFoundError, AttributeError):
            problems.append(f"{path}: {what} is not available in this build ({module}.{cls_name})")
            return None
        return section_parser(cls)(value, path, problems)

    return hook


def _default_of(module: str, cls_name: str) -> Any:
    try:
        return getattr(importlib.import_module(module), cls_name)()
    except (ModuleNotFoundError, AttributeError):
        return None


class IoKind(enum.Enum):
    """How the loop reaches the stage."""

    PLANT_IO = "plant_io"  # the simulated plant wrapped directly (sim.direct.PlantIO): fastest, no protocol
    EMBEDDED_CANOPEN = "embedded_canopen"  # real CiA 402 driver <-> virtual drive on the in-process bus
    CANOPEN = "canopen"  # real driver on a real bus (socketcan) or a sim-plant process (socketcand)


class SensorSource(enum.Enum):
    """Where the loop's position comes from."""

    DRIVE = "drive"  # the drive's position actual 0x6064
    ENCODER = "encoder"  # a CiA 406 encoder node
    INTERFEROMETER = "interferometer"  # the serial interferometer


@dataclass(frozen=True)
class IoConfig:
    """Devices."""

    kind: IoKind = param(IoKind.PLANT_IO, desc="plant_io | embedded_canopen | canopen")
    sensor: SensorSource = param(SensorSource.DRIVE, desc="position source: drive | encoder | interferometer")
    delay_cycles: int = param(1, desc="plant_io: actuation delay in SYNC periods (1 = like a sync RPDO)",
                              ge=0, le=100)
    drive: Any = param(None, desc="CiA 402 drive (stagectl.drivers.cia402.Cia402Config)",
                       parse=_lazy("stagectl.drivers.cia402", "Cia402Config", "the CiA 402 driver"))
    encoder: Any = param(None, desc="CiA 406 encoder (stagectl.drivers.cia406.Cia406Config)",
                         parse=_lazy("stagectl.drivers.cia406", "Cia406Config", "the CiA 406 driver"))
    interferometer: Any = param(
        None, desc="serial interferometer (stagectl.drivers.interferometer.InterferometerConfig)",
        parse=_lazy("stagectl.drivers.interferometer", "InterferometerConfig", "the interferometer driver"),
    )

    def __post_init__(self) -> None:
        problems = []
        if self.kind is IoKind.CANOPEN and self.drive is None:
            problems.append("io.drive: required for io.kind canopen")
        if self.sensor is SensorSource.ENCODER and self.kind is IoKind.CANOPEN and self.encoder is None:
            problems.append("io.encoder: required for io.sensor encoder")
        if self.sensor is SensorSource.INTERFEROMETER and self.kind is not IoKind.PLANT_IO and self.interferometer is None:
            problems.append("io.interferometer: required for io.sensor interferometer")
        if self.kind is IoKind.PLANT_IO and self.sensor is not SensorSource.DRIVE:
            problems.append("io.sensor: plant_io measures through the plant itself; use sensor: drive")
        if problems:
            raise ConfigError(problems)


@dataclass(frozen=True)
class DemoConfig:
    """What ``stagectl run`` moves when no daemon client is commanding."""

    scenario: str = param("demo", desc="scenario name (demo, cosine, triangle, steps, hold)")
    repeat: bool = param(True, desc="restart the scenario when it ends")


@dataclass(frozen=True)
class SimSection:
    """Simulated stage. ``plant`` always; ``world`` (virtual devices) when the sim world is available."""

    plant: Any = param(desc="the stage plant (stagectl.sim.plant.PlantConfig)")
    world: Any = param(None, desc="virtual devices (stagectl.sim.world.SimWorldConfig; embedded_canopen, "
                                  "sim-plant)")
    raw: Mapping[str, Any] = param(default_factory=dict, desc="the sim: mapping as written in the file")


@dataclass(frozen=True)
class AppConfig:
    """The whole validated configuration (built by :func:`load_app_config`)."""

    safety: SafetyConfig = param(desc="limits and watchdogs")
    controller: Any = param(
        desc="controller tuning (stagectl.control.controller.ControllerConfig)",
        parse=_lazy("stagectl.control.controller", "ControllerConfig", "the stage controller"),
    )
    loop: LoopConfig = param(default_factory=LoopConfig, desc="loop timing")
    io: IoConfig = param(default_factory=IoConfig, desc="devices")
    demo: DemoConfig = param(default_factory=DemoConfig, desc="demo motion of `stagectl run`")
    daemon: Any = param(
        default_factory=lambda: _default_of("stagectl.daemon.config", "DaemonConfig"),
        desc="service settings (stagectl.daemon.config.DaemonConfig)",
        parse=_lazy("stagectl.daemon.config", "DaemonConfig", "the daemon"),
    )
    description: str = param("", desc="free text shown by check-config")
    # filled by load_app_config (not YAML keys)
    sim: SimSection | None = dataclasses.field(default=None, metadata={"desc": "simulated stage", "unit": ""})
    path: Path | None = dataclasses.field(default=None, metadata={"desc": "source file", "unit": ""})

    @property
    def base_dir(self) -> Path:
        return self.path.parent if self.path is not None else Path.cwd()

    @property
    def period_s(self) -> float:
        return self.loop.period_s

    def resolve(self, p: str | Path) -> Path:
        """A path from the file, relative to the file's directory."""
        q = Path(p)
        return q if q.is_absolute() else self.base_dir / q


def _parse_sim(data: Any, base_dir: Path | None, problems: list[str]) -> SimSection | None:
    if data is None:
        return None
    if not isinstance(data, Mapping):
        problems.append(f"sim: expected a mapping, got {data!r}")
        return None
    try:
        from stagectl.sim.plant import PlantConfig
    except ModuleNotFoundError:
        problems.append("sim: the simulated plant is not available in this build")
        return None
    world_cls = None
    try:
        world_cls = importlib.import_module("stagectl.sim.world").SimWorldConfig
    except (ModuleNotFoundError, AttributeError):
        world_cls = None
    if world_cls is not None and hasattr(world_cls, "from_mapping"):
        try:
            world = world_cls.from_mapping(data, "sim", base_dir)
        except ConfigError as exc:
            problems.extend(exc.problems)
            return None
        return SimSection(plant=world.plant, world=world, raw=dict(data))
    unknown = [k for k in data if k != "plant"]
    if world_cls is None and unknown:
        for k in unknown:
            problems.append(f"sim.{k}: unknown key (the virtual-device world is not available in this build; "
                            f"known keys: plant)")
    if "plant" not in data:
        problems.append("sim.plant: required key missing (the simulated stage)")
        return None
    try:
        plant = PlantConfig.from_mapping(data["plant"], "sim.plant", base_dir)
    except ConfigError as exc:
        problems.extend(exc.problems)
        return None
    return SimSection(plant=plant, world=None, raw=dict(data))


def parse_app_config(data: Any, path: str | Path | None = None) -> AppConfig:
    """Validate a plain mapping (what ``yaml.safe_load`` returned) into an :class:`AppConfig`.

    Raises
    ------
    ConfigError
        Every problem found, each with its key path (and the file name when ``path`` is given).
    """
    p = Path(path).resolve() if path is not None else None
    base_dir = p.parent if p is not None else None
    problems: list[str] = []
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"{p or '<config>'}: expected a mapping at the top level, got {type(data).__name__}")
    rest = {k: v for k, v in data.items() if k != "sim"}
    sim = _parse_sim(data.get("sim"), base_dir, problems)
    cfg: AppConfig | None = None
    try:
        cfg = load(AppConfig, {k: v for k, v in rest.items() if k not in ("path",)}, "")
    except ConfigError as exc:
        problems.extend(exc.problems)
    if "path" in rest:
        problems.append("path: unknown key")
    if cfg is not None:
        problems.extend(_cross_checks(cfg, sim, base_dir, sim_given=data.get("sim") is not None))
    if problems:
        prefix = f"{p.name}: " if p is not None else ""
        raise ConfigError([prefix + m for m in problems])
    assert cfg is not None
    return dataclasses.replace(cfg, sim=sim, path=p)


def _cross_checks(cfg: AppConfig, sim: SimSection | None, base_dir: Path | None, *,
                  sim_given: bool = True) -> list[str]:
    problems: list[str] = []
    kind = cfg.io.kind
    from stagectl.app import scenario_names

    if cfg.demo.scenario not in scenario_names():
        problems.append(f"demo.scenario: unknown scenario {cfg.demo.scenario!r} (known: {', '.join(scenario_names())})")
    if kind in (IoKind.PLANT_IO, IoKind.EMBEDDED_CANOPEN) and sim is None and not sim_given:
        problems.append(f"sim: required for io.kind {kind.value} (the simulated stage)")
    if kind is IoKind.EMBEDDED_CANOPEN and sim is not None and sim.world is None:
        problems.append("io.kind: embedded_canopen needs the virtual-device world (stagectl.sim.world), "
                        "not available in this build; use plant_io")
    if cfg.controller is not None and not problems:
        # build the controller once: model files, masses and derived gains are checked exactly as at start-up
        try:
            from stagectl.control.controller import StageController

            StageController(cfg.controller, cfg.loop.period_s, base_dir=base_dir)
        except ConfigError as exc:
            problems.extend(exc.problems)
        except ValueError as exc:
            problems.append(f"controller: {exc}")
    s = cfg.safety
    drive = cfg.io.drive
    if drive is not None:
        try:
            from stagectl.drivers.canbus import bus_kwargs

            bus_kwargs(drive.can, path="io.drive.can")
        except ModuleNotFoundError:
            pass
        except ConfigError as exc:
            problems.extend(exc.problems)
    if drive is not None and getattr(drive, "max_force_n", None) is not None and drive.max_force_n < s.max_force_n:
        problems.append(
            f"safety.max_force_n: {s.max_force_n:g} N exceeds io.drive.max_force_n {drive.max_force_n:g} N"
        )
    return problems


def load_app_config(path: str | Path) -> AppConfig:
    """Read and validate a stagectl YAML file (the validation ``check-config`` and the daemon run).

    Raises
    ------
    ConfigError
        File/syntax errors, or every validation problem at once (each prefixed with the file name).
    """
    data = load_yaml_file(path)
    return parse_app_config(data, path)
