"""Assembly: a validated :class:`~stagectl.config.AppConfig` → a running-ready :class:`Stage`.

``Stage`` holds the devices (real drivers, or the simulated plant: :class:`~stagectl.sim.direct.PlantIO` or the
virtual CANopen world), the controller, the safety supervisor, the reference generator and the
:class:`~stagectl.loop.ControlLoop`. It is a context manager whose exit *always* disables the drive and
closes every device and bus, also after an exception::

    cfg = load_app_config("config/sim.yaml")
    with build_stage(cfg, clock=SimClock()) as stage:      # simulated time, lock-step devices
        stage.load_scenario("cosine")
        result = stage.loop.run(duration_s=4.0)

With :class:`~stagectl.clock.MonotonicClock` (the default) the loop runs in real time and applies the
``loop.realtime`` settings in its thread. The attributes ``loop``, ``close``, ``controller_config``,
``simulated``, ``inject_fault`` and ``describe`` are what the daemon's ``Assembly`` needs.

The devices come from one builder per :class:`~stagectl.config.IoKind` (:data:`IO_BUILDERS`); every consumer
of the loop period (drive, encoder, safety, PlantIO, controller) is handed the one :class:`~stagectl.clock.Timing`
of ``loop.period_s``.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import TYPE_CHECKING, Any, TypeVar

from stagectl.clock import Clock, MonotonicClock, SimClock, Timing
from stagectl.config import AppConfig, IoKind, SensorSource
from stagectl.config.checks import sim_plant_only_note
from stagectl.control.controller import TERM_NAMES, ControllerConfig, StageController, controller_mass
from stagectl.control.ilc import IlcLearner, IlcPlant
from stagectl.control.reference import TrajectoryReference, get_scenario
from stagectl.control.trajectory import Scenario
from stagectl.drivers.base import Device, ForceActuator, PositionSensor, SyncProducer
from stagectl.drivers.cia402 import Cia402Config, Cia402Drive
from stagectl.drivers.cia406 import Cia406Config, Cia406Encoder
from stagectl.drivers.interferometer import InterferometerConfig, SerialInterferometer
from stagectl.errors import ConfigError, StageError
from stagectl.loop import Controller, ControlLoop
from stagectl.runtime.protocols import NamesTerms
from stagectl.safety import Safety

if TYPE_CHECKING:  # imported where a simulated stage is built: a real stage's process never imports stagectl.sim
    from stagectl.sim.cia402_drive import SimDriveConfig
    from stagectl.sim.cia406_encoder import SimEncoderConfig
    from stagectl.sim.direct import PlantIO
    from stagectl.sim.interferometer import SimInterferometerConfig
    from stagectl.sim.plant import StagePlant
    from stagectl.sim.world import SimWorld

log = logging.getLogger("stagectl.app")

__all__ = ["IO_BUILDERS", "Stage", "StageIO", "build_stage", "embedded_drive_config", "embedded_encoder_config",
           "embedded_interferometer_config", "make_controller"]

D = TypeVar("D", bound=Device)
T = TypeVar("T")


@dataclass
class Teardown:
    """What has been opened so far, in order; :meth:`close` disables the drive and closes it all."""

    devices: list[Device] = field(default_factory=list)
    closers: list[Callable[[], None]] = field(default_factory=list)
    actuator: ForceActuator | None = None
    closed: bool = False

    def open(self, dev: D, pump: Callable[[], object] | None = None) -> D:
        """Lock-step pump (virtual devices), open, register for closing, configure; returns ``dev``."""
        if pump is not None:
            dev.set_pump(pump)
        dev.open()
        self.devices.append(dev)
        dev.configure()
        return dev

    def close(self) -> None:
        """Disable the drive and close every device and bus (idempotent; never raises, but an interrupt).

        A KeyboardInterrupt (Ctrl-C, or the CLI's SIGTERM, in the main thread) landing in one step does not skip
        the others (a drive left enabled, a bus left open): it is raised once every step has been done."""
        if self.closed:
            return
        self.closed = True
        interrupt: KeyboardInterrupt | None = None
        steps: list[tuple[Callable[[], object], str]] = []
        if self.actuator is not None:
            steps.append((self.actuator.disable, "disabling the drive failed"))
        steps += [(d.close, f"closing {d.name} failed") for d in reversed(self.devices)]
        steps += [(fn, "closing failed") for fn in reversed(self.closers)]
        for step, failed in steps:
            try:
                step()
            except KeyboardInterrupt as exc:
                interrupt = exc
                log.warning("%s: interrupted", failed.replace(" failed", ""))
            except Exception:  # noqa: BLE001
                log.exception(failed)
        if interrupt is not None:
            raise interrupt


@dataclass
class StageIO:
    """The devices one I/O builder produced: what the loop reads, writes and syncs on, and the simulation."""

    sensor: PositionSensor
    actuator: ForceActuator
    sync: SyncProducer | None
    plant: StagePlant | None = None
    plant_io: PlantIO | None = None
    world: SimWorld | None = None


@dataclass(frozen=True)
class BuildContext:
    """What an I/O builder gets: the configuration, the clock, the timing and where to register devices."""

    cfg: AppConfig
    clock: Clock
    timing: Timing
    teardown: Teardown


class Stage:
    """Assembled devices + loop (see module docstring). Use as a context manager, or call :meth:`close`."""

    def __init__(self, cfg: AppConfig, *, clock: Clock, timing: Timing, io: StageIO, controller: Controller,
                 safety: Safety, reference: TrajectoryReference, loop: ControlLoop, teardown: Teardown) -> None:
        self.cfg = cfg
        self.clock = clock
        self.timing = timing
        self.sensor = io.sensor
        self.actuator = io.actuator
        self.sync = io.sync
        self.plant = io.plant
        self.plant_io = io.plant_io
        self.world = io.world
        self.controller = controller
        self.controller_config: ControllerConfig = cfg.controller
        self.safety = safety
        self.reference = reference
        self.loop = loop
        self.learner = loop.learner if isinstance(loop.learner, IlcLearner) else None  # ilc: (None: off)
        self.simulated = cfg.io.kind in (IoKind.PLANT_IO, IoKind.EMBEDDED_CANOPEN)
        self._teardown = teardown

    @property
    def devices(self) -> list[Device]:
        """The opened devices, in opening order."""
        return self._teardown.devices

    # ------------------------------------------------------------------ daemon Assembly fields
    @property
    def describe(self) -> dict[str, Any]:
        c = self.cfg
        return {
            "config": str(c.path) if c.path else None,
            "io": c.io.kind.value,
            "sensor": c.io.sensor.value,
            "period_s": self.timing.period_s,
            "simulated": self.simulated,
            "columns": list(self.loop.columns),
        }

    def inject_fault(self, kind: str = "emcy", **kw: Any) -> dict[str, Any]:
        """Debug: inject a device fault into the simulated stage. Only for simulated stages.

        PlantIO: ``emcy``, ``stale`` (``cycles``; ``missed_frame`` after max(3, ``safety.stale_cycles``) in a row,
        as the embedded virtual drive's ``max_missed``), ``nan``, ``position_jump`` (``jump_m``, ``cycles``) or any
        :class:`~stagectl.drivers.base.FaultKind` value. Virtual CANopen devices: any
        :class:`stagectl.sim.faults.SimFault` with its FaultSpec fields, or one of the loop-level aliases of
        :data:`stagectl.sim.faults.FAULT_ALIASES` (``nan`` is refused there: an integer position cannot be NaN).

        Raises
        ------
        StageError
            Not a simulated stage.
        """
        if self.plant_io is not None:
            from stagectl.sim.faults import PLANT_IO_MAX_MISSED, inject_plant_io_fault

            inject_plant_io_fault(self.plant_io, kind, kw, max(PLANT_IO_MAX_MISSED, self.safety.cfg.stale_cycles))
            return {"injected": kind}
        if self.world is not None:
            from stagectl.sim.faults import world_fault

            spec = world_fault(kind, kw)
            return {"injected": self.world.inject_fault(spec.pop("kind"), **spec)}
        raise StageError("inject_fault: only available on a simulated stage")  # simulated: a plant or a world

    def load_scenario(self, name_or_scenario: str | Scenario | None, repeat: bool = False) -> None:
        """Run a scenario (by name, a :class:`~stagectl.control.trajectory.Scenario`, or None: hold) from the
        loop's start. Raises ConfigError for an unknown name."""
        sc = get_scenario(name_or_scenario) if isinstance(name_or_scenario, str) else name_or_scenario
        self.reference.set_scenario(sc, repeat)

    # ------------------------------------------------------------------ teardown
    def close(self) -> None:
        """Disable the drive and close every device and bus (idempotent; never raises)."""
        self._teardown.close()

    def __enter__(self) -> Stage:
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        self.close()


# ====================================================================================== I/O builders
def _build_plant_io(ctx: BuildContext) -> StageIO:
    """The simulated plant wrapped directly (:class:`~stagectl.sim.direct.PlantIO`), no protocol."""
    from stagectl.sim.direct import PlantIO
    from stagectl.sim.plant import StagePlant

    cfg = ctx.cfg
    if cfg.sim is None:  # excluded by the configuration's cross-checks
        raise ConfigError("sim: required for io.kind plant_io (the simulated stage)")
    plant = StagePlant(cfg.sim.plant)
    io = ctx.teardown.open(PlantIO(plant, ctx.timing, delay_cycles=cfg.io.delay_cycles, clock=ctx.clock,
                                         command_schedule=cfg.io.command_schedule))
    ctx.teardown.actuator = io
    return StageIO(sensor=io, actuator=io, sync=io, plant=plant, plant_io=io)


def embedded_drive_config(io_drive: Cia402Config | None, sim_drive: SimDriveConfig,
                          can: dict[str, Any], stale_cycles: int | None = None) -> Cia402Config:
    """The CiA 402 driver's configuration for the in-process virtual drive: ``io.drive`` on the world's bus,
    or, without one, a driver matching ``sim.drive`` (node id, position resolution, force per unit) whose
    ``max_missed`` is ``stale_cycles`` (``safety.stale_cycles``) when that is larger: reads without a TPDO are
    judged by safety's stale limits (the unseen travel, the cycle cap), not by a tighter default count."""
    if io_drive is not None:
        return dataclasses.replace(io_drive, can=can)
    cfg = Cia402Config(node_id=sim_drive.node_id, can=can, resolution_m=sim_drive.resolution_m,
                       force_per_unit_n=sim_drive.force_per_unit_n)
    if stale_cycles is not None and stale_cycles > cfg.max_missed:
        cfg = dataclasses.replace(cfg, max_missed=stale_cycles)
    return cfg


def embedded_encoder_config(io_encoder: Cia406Config | None, sim_encoder: SimEncoderConfig | None,
                            can: dict[str, Any]) -> Cia406Config:
    """The CiA 406 driver's configuration for the in-process virtual encoder (``io.encoder`` on the world's
    bus, or one matching ``sim.encoder``; the configuration checks require ``sim.encoder`` and that both agree).

    Raises
    ------
    ConfigError
        Neither ``io.encoder`` nor ``sim.encoder`` is given.
    """
    if io_encoder is not None:
        return dataclasses.replace(io_encoder, can=can)
    if sim_encoder is None:
        raise ConfigError("io.encoder: required for io.sensor encoder (or give sim.encoder)")
    return Cia406Config(node_id=sim_encoder.node_id, can=can, resolution_m=sim_encoder.resolution_m)


def embedded_interferometer_config(io_ifm: InterferometerConfig | None, sim_ifm: SimInterferometerConfig | None,
                                   url: str | None) -> InterferometerConfig:
    """The serial interferometer driver's configuration for the in-process simulated interferometer
    (``io.interferometer`` at the simulated one's ``url``, or one matching ``sim.interferometer``): the same
    rule as :func:`embedded_encoder_config`.

    Raises
    ------
    ConfigError
        No ``sim.interferometer`` (nothing to read from).
    """
    if sim_ifm is None or url is None:
        raise ConfigError("sim.interferometer: required for io.sensor interferometer with io.kind "
                          "embedded_canopen")
    if io_ifm is not None:
        return dataclasses.replace(io_ifm, url=url)
    return InterferometerConfig(url=url, resolution_m=sim_ifm.resolution_m)


def _build_embedded_canopen(ctx: BuildContext) -> StageIO:
    """Virtual CANopen devices in-process (:class:`~stagectl.sim.world.SimWorld` on python-can's virtual bus)
    and the real drivers talking to them through the bus.

    The virtual devices are served synchronously by the loop thread (the drivers' ``set_pump``) in simulated
    AND real time: each SYNC steps the plant by exactly one period, no thread hop can make a TPDO late.
    """
    from stagectl.sim.world import SimWorld

    cfg = ctx.cfg
    if cfg.sim is None:  # excluded by the configuration's cross-checks
        raise ConfigError("sim: required for io.kind embedded_canopen (the simulated stage)")
    wcfg = cfg.sim
    if wcfg.transport.kind != "virtual":
        wcfg = dataclasses.replace(wcfg, transport=dataclasses.replace(wcfg.transport, kind="virtual"))
    world = SimWorld.from_config(wcfg, cfg.base_dir)
    ctx.teardown.closers.append(world.stop)
    world.open()
    info = world.ready_info()
    can: dict[str, Any] = info["can"]
    drive_cfg = embedded_drive_config(cfg.io.drive, wcfg.drive, can, cfg.safety.stale_cycles)
    io = _open_drivers(
        ctx, drive_cfg, pump=world.pump, serial_pump=world.serial_pump,
        encoder=lambda: embedded_encoder_config(cfg.io.encoder, wcfg.encoder, can),
        interferometer=lambda: embedded_interferometer_config(cfg.io.interferometer, wcfg.interferometer,
                                                              info.get("interferometer_url")))
    return dataclasses.replace(io, plant=world.plant, world=world)


def _build_canopen(ctx: BuildContext) -> StageIO:
    """The real drivers on a real bus (socketcan) or a ``stagectl sim-plant`` process (socketcand)."""
    io = ctx.cfg.io
    if io.drive is None:  # excluded by IoConfig
        raise ConfigError("io.drive: required for io.kind canopen")
    enc, ifm = io.encoder, io.interferometer
    return _open_drivers(ctx, io.drive, pump=None, encoder=lambda: _required("io.encoder", enc),
                         interferometer=lambda: _required("io.interferometer", ifm))


def _required(key: str, section: T | None) -> T:
    if section is None:  # excluded by IoConfig
        raise ConfigError(f"{key}: required for io.sensor {key.removeprefix('io.')}")
    return section


def _open_drivers(ctx: BuildContext, drive_cfg: Cia402Config, *, pump: Callable[[], object] | None,
                  encoder: Callable[[], Cia406Config], interferometer: Callable[[], InterferometerConfig],
                  serial_pump: Callable[[], object] | None = None) -> StageIO:
    """The CiA 402 drive (actuator, SYNC producer) and the position sensor ``io.sensor`` names."""
    cfg, td = ctx.cfg, ctx.teardown
    drive = td.open(Cia402Drive(drive_cfg, ctx.timing), pump)
    td.actuator = drive
    sensor: PositionSensor
    src = cfg.io.sensor
    if src is SensorSource.DRIVE:
        sensor = drive
    elif src is SensorSource.INTERFEROMETER:
        icfg = interferometer()
        # serial_pump returns LinkBytes: a dropped frame costs no lock-step wait
        sensor = td.open(SerialInterferometer(icfg), (serial_pump or pump) if pump else None)
    else:
        sensor = td.open(Cia406Encoder(encoder(), ctx.timing), pump)
    return StageIO(sensor=sensor, actuator=drive, sync=drive)


#: one builder per I/O kind
IO_BUILDERS: dict[IoKind, Callable[[BuildContext], StageIO]] = {
    IoKind.PLANT_IO: _build_plant_io,
    IoKind.EMBEDDED_CANOPEN: _build_embedded_canopen,
    IoKind.CANOPEN: _build_canopen,
}


# ====================================================================================== assembly
def make_controller(cfg: AppConfig, controller_config: ControllerConfig | None = None, *,
                    plain_ff: bool = False) -> StageController:
    """The StageController for ``controller_config`` (default: the file's), with the model the configuration
    loader resolved (``feedforward.model``); ``plain_ff``: its model feed-forward steps as plain Python (no numba),
    as :func:`build_stage` chooses for a stage without a simulated plant in the process."""
    return StageController(controller_config or cfg.controller, cfg.timing, plain_ff=plain_ff)


def make_learner(cfg: AppConfig, reference: TrajectoryReference) -> IlcLearner:
    """The ILC learner of ``cfg.ilc`` for the loop (:mod:`stagectl.control.ilc`), designed for the controller's
    mass, PID and observer and the I/O delay; learning from the start when ``ilc.autostart``."""
    c = cfg.controller
    mass = controller_mass(c, c.feedforward.model)
    if mass is None:  # the configuration check requires one
        raise StageError("ilc: no controller mass (controller.mass_kg or the model file's)")
    plant = IlcPlant(mass_kg=mass, period_s=cfg.loop.period_s, delay_samples=int(cfg.io.delay_cycles), pid=c.pid,
                     dob=c.dob)
    learner = IlcLearner(cfg.ilc, plant, reference.repetition, base_dir=cfg.base_dir)
    if cfg.ilc.autostart:
        learner.start()
    return learner


def build_stage(
    cfg: AppConfig,
    *,
    clock: Clock | None = None,
    realtime: bool | None = None,
    controller: Controller | None = None,
) -> Stage:
    """Open and configure the devices, build controller, safety, reference and loop.

    Parameters
    ----------
    clock : Clock, optional
        :class:`MonotonicClock` (default; real time) or :class:`SimClock` (simulated time: the devices run in
        lock-step with the loop).
    realtime : bool, optional
        Apply ``loop.realtime`` in the loop thread (default: True with a MonotonicClock).
    controller : optional
        A ready controller object (benchmarks); default: ``StageController`` from ``cfg.controller``.

    On any error everything opened so far is closed before the exception propagates.
    """
    clk: Clock = clock if clock is not None else MonotonicClock(spin_s=cfg.loop.realtime.spin_us * 1e-6)
    if realtime is None:
        realtime = not isinstance(clk, SimClock)
    timing = cfg.timing
    td = Teardown()
    try:
        io = IO_BUILDERS[cfg.io.kind](BuildContext(cfg, clk, timing, td))
        # no plant in this process (real drives, or a sim-plant in another): the feed-forward's friction model
        # steps as plain Python and numba is never imported (docs/performance.md §1); a simulated plant runs
        # numba's kernels anyway, and the feed-forward shares the plant's compiled step
        plain_ff = io.plant is None
        ctl: Controller = controller if controller is not None else make_controller(cfg, plain_ff=plain_ff)
        # the moving mass bounds a plausible position step (safety's position_jump check)
        mass = ctl.mass_kg if isinstance(ctl, StageController) else cfg.controller.mass_kg
        safety = Safety(cfg.safety, timing, mass_kg=mass)
        # a move without max_velocity_m_s: 1 mm/s, or slower when the planned fraction of the limit is lower
        reference = TrajectoryReference(min(1e-3, cfg.safety.move_velocity_fraction * cfg.safety.max_velocity_m_s))
        terms = ctl.term_names if isinstance(ctl, NamesTerms) else TERM_NAMES
        learner = make_learner(cfg, reference) if cfg.ilc.enabled else None
        loop = ControlLoop(
            clock=clk,
            sensor=io.sensor,
            actuator=io.actuator,
            controller=ctl,
            reference=reference,
            safety=safety,
            cfg=cfg.loop,
            sync=io.sync,
            realtime=realtime,
            term_names=tuple(terms),
            # virtual CANopen devices (and a sim-plant without wall_clock_plant) step one period per SYNC
            device_time=io.world is not None or cfg.loop.device_time,
            learner=learner,
        )
    except BaseException:
        td.close()
        raise
    note = sim_plant_only_note(cfg)
    if note:
        log.warning("%s", note)
    return Stage(cfg, clock=clk, timing=timing, io=io, controller=ctl, safety=safety, reference=reference,
                 loop=loop, teardown=td)
