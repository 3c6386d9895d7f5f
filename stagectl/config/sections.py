"""The sections of a stagectl YAML file, each typed by the dataclass of the layer that uses it.

Sections (see ``config/sim.yaml`` for a commented example)::

    loop:        LoopConfig        period_s, realtime {fifo_priority, cpus, mlock, timer_slack_ns, gc_freeze}, ...
    io:          IoConfig          kind: plant_io | embedded_canopen | canopen; sensor: drive | encoder |
                                   interferometer; drive: Cia402Config; encoder: Cia406Config;
                                   interferometer: InterferometerConfig; delay_cycles (plant_io)
    sim:         SimWorldConfig    plant: PlantConfig (+ the virtual devices for embedded_canopen and
                                   ``stagectl sim-plant``); required for plant_io/embedded_canopen
    controller:  ControllerConfig  (stagectl.control.controller)
    safety:      SafetyConfig      soft limits, following error, force/velocity limits, stale position
    demo:        DemoConfig        what ``stagectl run`` does (scenario, repeat)
    ilc:         IlcConfig         learning feed-forward for repeated motions (stagectl.control.ilc)
    daemon:      DaemonConfig      control socket, watchdog, telemetry (stagectl.config.daemon)
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from stagectl.clock import Timing
from stagectl.config.daemon import DaemonConfig
from stagectl.control.controller import ControllerConfig
from stagectl.control.ilc import IlcConfig
from stagectl.drivers.cia402 import Cia402Config
from stagectl.drivers.cia406 import Cia406Config
from stagectl.drivers.interferometer import InterferometerConfig
from stagectl.errors import ConfigError
from stagectl.loop import LoopConfig
from stagectl.safety import SafetyConfig
from stagectl.schema import param

if TYPE_CHECKING:
    from stagectl.world_schema import SimWorldConfig

#: ``AppConfig.sim``'s type, imported only when a ``sim:`` section is parsed or the schema is described
#: (``stagectl.schema.field_type``). It lives in :mod:`stagectl.world_schema`, not in the simulation package: a
#: process whose plant runs elsewhere (a real stage; a HIL controller, plant in ``stagectl sim-plant``) validates
#: the section without importing ``stagectl.sim``
LAZY_TYPES = {"SimWorldConfig": "stagectl.world_schema"}

__all__ = ["AppConfig", "DemoConfig", "IoConfig", "IoKind", "SensorSource"]


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
    """Devices.

    ``io.kind: canopen`` talks to real devices (or a ``stagectl sim-plant`` process), so the driver sections
    of the devices used are required. ``embedded_canopen`` talks to the simulated devices of ``sim:`` in-process:
    there the simulated device is required (``sim.encoder`` / ``sim.interferometer`` for that sensor, checked
    in :mod:`stagectl.config.checks`) and the driver section is optional, one rule for every device: without it
    the driver matches the simulated device; with it, it must agree with the simulated device (node id,
    scaling), and its bus or URL is replaced by the world's.
    """

    kind: IoKind = param(IoKind.PLANT_IO, desc="plant_io | embedded_canopen | canopen")
    sensor: SensorSource = param(SensorSource.DRIVE, desc="position source: drive | encoder | interferometer")
    delay_cycles: int = param(1, desc="plant_io: actuation delay in SYNC periods (1 = like a sync RPDO)",
                              ge=0, le=100)
    command_schedule: bool = param(
        False, desc="plant_io: each write also carries the controller's predicted force for the period after it, "
        "which the actuator applies in a slot the loop skipped (no new write) instead of holding the old force "
        "(sim.direct.PlantIO); no effect on on-time cycles")
    drive: Cia402Config | None = param(
        None, desc="CiA 402 drive; required for canopen; optional for "
        "embedded_canopen (default: matching sim.drive; its can: is the world's bus)")
    encoder: Cia406Config | None = param(
        None, desc="CiA 406 encoder; required for canopen with sensor "
        "encoder; optional for embedded_canopen, which needs sim.encoder (default: matching sim.encoder; its "
        "can: is the world's bus)")
    interferometer: InterferometerConfig | None = param(
        None, desc="serial interferometer; required for "
        "canopen with sensor interferometer; optional for embedded_canopen, which needs sim.interferometer "
        "(default: matching sim.interferometer; its url is the simulated one's)")

    def __post_init__(self) -> None:
        problems = []
        if self.kind is IoKind.CANOPEN and self.drive is None:
            problems.append("io.drive: required for io.kind canopen")
        if self.sensor is SensorSource.ENCODER and self.kind is IoKind.CANOPEN and self.encoder is None:
            problems.append("io.encoder: required for io.sensor encoder")
        if (self.sensor is SensorSource.INTERFEROMETER and self.kind is IoKind.CANOPEN
                and self.interferometer is None):
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
class AppConfig:
    """The whole validated configuration (built by :func:`stagectl.config.load_app_config`).

    Model files are already resolved: ``sim.plant`` holds the merged plant, and
    ``controller.feedforward.model`` the :class:`~stagectl.friction.StageModel` the controller uses.
    """

    safety: SafetyConfig = param(desc="limits and watchdogs")
    controller: ControllerConfig = param(desc="controller tuning (pid, dob, feedforward)")
    loop: LoopConfig = param(default_factory=LoopConfig, desc="loop timing")
    io: IoConfig = param(default_factory=IoConfig, desc="devices")
    demo: DemoConfig = param(default_factory=DemoConfig, desc="demo motion of `stagectl run`")
    ilc: IlcConfig = param(default_factory=IlcConfig, desc="learning feed-forward for repeated motions "
                           "(iterative learning control; off by default)")
    daemon: DaemonConfig = param(default_factory=DaemonConfig, desc="service settings (control socket, watchdog, telemetry)")
    description: str = param("", desc="free text shown by check-config")
    sim: SimWorldConfig | None = param(
        None, desc="simulated stage: plant and virtual devices (its model file resolved by the loader)")
    # filled by load_app_config (not a YAML key)
    path: Path | None = dataclasses.field(default=None, metadata={"desc": "source file", "unit": ""})

    @property
    def base_dir(self) -> Path:
        """The directory of the YAML file (relative paths in it are relative to this)."""
        return self.path.parent if self.path is not None else Path.cwd()

    @property
    def timing(self) -> Timing:
        """The loop's one timing value (every consumer derives its cycle counts from it)."""
        return Timing(self.loop.period_s)
