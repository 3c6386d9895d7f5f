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
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from types import TracebackType
from typing import Any

from stagectl.clock import Clock, MonotonicClock, SimClock
from stagectl.config import AppConfig, IoKind, SensorSource
from stagectl.control.api import Reference
from stagectl.drivers.base import Device, FaultKind, ForceActuator, PositionSensor, SyncProducer
from stagectl.errors import ConfigError, StageError
from stagectl.loop import ControlLoop
from stagectl.safety import Safety

log = logging.getLogger("stagectl.app")

#: names accepted by ``--scenario`` (besides the benchmark ones from stagectl.control.trajectory)
EXTRA_SCENARIOS = ("demo", "hold")


def scenario_names() -> tuple[str, ...]:
    from stagectl.control.trajectory import benchmark_scenarios

    return (*benchmark_scenarios(), *EXTRA_SCENARIOS)


def get_scenario(name: str, field: str = "--scenario") -> Any:
    """A trajectory scenario by name (``cosine``, ``triangle``, ``steps``, ``demo``, ``hold``); an unknown name
    is a ConfigError naming ``field``."""
    from stagectl.control import trajectory as tr

    if name == "hold":
        return None
    if name == "demo":
        return tr.demo_scenario()
    sc = tr.benchmark_scenarios()
    if name not in sc:
        raise ConfigError(f"{field}: unknown scenario {name!r} (known: {', '.join(scenario_names())})")
    return sc[name]


class TrajectoryReference:
    """Adapts :class:`stagectl.control.trajectory.TrajectoryGenerator` (``step(dt)``) to the loop's
    ``ReferenceSource`` (``sample(t)``, ``hold``, ``move``, ``stop``).

    A scenario given with :meth:`set_scenario` starts at the loop's first ``hold`` (from the measured
    position); with ``repeat`` it restarts whenever it ends, until a ``move``/``stop`` request takes over.
    Real-time safe apart from ``move``/``stop`` (binding one segment).
    """

    def __init__(self, default_velocity_m_s: float = 1e-3) -> None:
        from stagectl.control.trajectory import TrajectoryGenerator

        self.gen = TrajectoryGenerator(0.0)
        self.default_velocity_m_s = default_velocity_m_s
        self._t = 0.0
        self._target = 0.0
        self._scenario: Any = None
        self._repeat = False
        self._started = False

    def set_scenario(self, scenario: Any, repeat: bool = False) -> None:
        self._scenario = scenario
        self._repeat = repeat
        self._started = False

    def hold(self, t_s: float, x_m: float) -> None:
        self.gen.reset(x_m)
        self._t = t_s
        self._target = x_m
        if self._scenario is not None and not self._started:
            self._started = True
            self.gen.load(self._scenario)
            self._target = math.nan

    def sample(self, t_s: float) -> Reference:
        dt = t_s - self._t
        if dt > 0.0:
            self._t = t_s
            ref = self.gen.step(dt)
            if self._repeat and self.gen.done and self._scenario is not None:
                self.gen.load(self._scenario)
            return ref
        return self.gen.sample()

    def move(self, t_s: float, target_m: float, max_velocity_m_s: float | None) -> float:
        self._repeat = False
        self._scenario = None
        self.gen.move(target_m, max_velocity_m_s or self.default_velocity_m_s)
        self._target = target_m
        return float(self.gen.remaining_s())

    def stop(self, t_s: float) -> float:
        """Decelerate (jerk-limited, the generator's default move limits) and hold where the reference comes
        to rest; returns that position [m]."""
        from stagectl.control.trajectory import Move

        self._repeat = False
        self._scenario = None
        self.sample(t_s)
        lim = Move(by_m=0.0)
        end = float(self.gen.stop(lim.max_acceleration_m_s2, lim.max_jerk_m_s3))
        self._target = end
        return end

    @property
    def scenario(self) -> Any:
        """The scenario set with :meth:`set_scenario` (None after a move/stop request took over)."""
        return self._scenario

    @property
    def target_m(self) -> float:
        if math.isnan(self._target):
            return float(self.gen.final_reference().x_m)
        return self._target


class Stage:
    """Assembled devices + loop (see module docstring). Use as a context manager, or call :meth:`close`."""

    def __init__(self, cfg: AppConfig) -> None:
        self.cfg = cfg
        self.clock: Clock = MonotonicClock()
        self.devices: list[Device] = []
        self.closers: list[Callable[[], None]] = []
        self.world: Any = None
        self.plant: Any = None
        self.plant_io: Any = None
        self.sensor: PositionSensor | None = None
        self.actuator: ForceActuator | None = None
        self.sync: SyncProducer | None = None
        self.controller: Any = None
        self.controller_config: Any = cfg.controller
        self.reference: TrajectoryReference | None = None
        self.safety: Safety | None = None
        self.loop: ControlLoop = None  # type: ignore[assignment]
        self.simulated = cfg.io.kind in (IoKind.PLANT_IO, IoKind.EMBEDDED_CANOPEN)
        self._closed = False

    # ------------------------------------------------------------------ daemon Assembly fields
    @property
    def describe(self) -> dict[str, Any]:
        c = self.cfg
        return {
            "config": str(c.path) if c.path else None,
            "io": c.io.kind.value,
            "sensor": c.io.sensor.value,
            "period_s": c.loop.period_s,
            "simulated": self.simulated,
            "columns": list(self.loop.columns) if self.loop else [],
        }

    def inject_fault(self, kind: str = "emcy", **kw: Any) -> dict[str, Any]:
        """Debug: inject a device fault into the simulated stage. Only for simulated stages.

        PlantIO: ``emcy``, ``stale`` (``cycles``), ``nan`` or any :class:`FaultKind` value. Virtual CANopen
        devices: any :class:`stagectl.sim.faults.SimFault` (``drive_fault``, ``heartbeat_stop``, ``drop_tpdo``,
        ``late_tpdo``, ``bus_off``, ``position_jump``) with its FaultSpec fields; ``emcy``, ``stale``,
        ``heartbeat_lost`` and ``nan`` are accepted as aliases."""
        if not self.simulated:
            raise StageError("inject_fault: only available on a simulated stage")
        if self.plant_io is not None:
            io = self.plant_io
            if kind == "stale":
                io.drop_samples(int(kw.get("cycles", 10)))
            elif kind == "nan":
                io.glitch(math.nan)
            else:
                try:
                    fk = FaultKind(kind)
                except ValueError:
                    raise ValueError(f"kind: unknown fault {kind!r} (known: stale, nan, "
                                     f"{', '.join(k.value for k in FaultKind)})") from None
                io.inject_fault(fk, str(kw.get("detail", "injected")), int(kw.get("code", 0)))
            return {"injected": kind}
        if self.world is not None and hasattr(self.world, "inject_fault"):
            # loop-level names mapped onto the virtual devices' faults (stagectl.sim.faults.SimFault)
            alias = {"emcy": "drive_fault", "stale": "drop_tpdo", "heartbeat_lost": "heartbeat_stop",
                     "nan": "position_jump"}
            if kind == "stale":
                kw.setdefault("cycles", 10)
            return {"injected": self.world.inject_fault(alias.get(kind, kind), **kw)}
        raise StageError("inject_fault: no fault injection available for this stage")

    def load_scenario(self, name_or_scenario: Any, repeat: bool = False) -> None:
        """Run a scenario (by name or a Scenario object) from the loop's start."""
        sc = get_scenario(name_or_scenario) if isinstance(name_or_scenario, str) else name_or_scenario
        assert self.reference is not None
        self.reference.set_scenario(sc, repeat)

    # ------------------------------------------------------------------ teardown
    def close(self) -> None:
        """Disable the drive and close every device and bus (idempotent; never raises)."""
        if self._closed:
            return
        self._closed = True
        if self.actuator is not None:
            try:
                self.actuator.disable()
            except Exception:  # noqa: BLE001
                log.exception("disabling the drive failed")
        for d in reversed(self.devices):
            try:
                d.close()
            except Exception:  # noqa: BLE001
                log.exception("closing %s failed", d.name)
        for fn in reversed(self.closers):
            try:
                fn()
            except Exception:  # noqa: BLE001
                log.exception("closing failed")

    def __enter__(self) -> Stage:
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        self.close()


def make_controller(cfg: AppConfig, controller_config: Any = None) -> Any:
    """The StageController for ``controller_config`` (default: the file's), model paths relative to the file."""
    from stagectl.control.controller import StageController

    return StageController(controller_config or cfg.controller, cfg.loop.period_s, base_dir=cfg.base_dir)


def controller_terms() -> tuple[str, ...]:
    from stagectl.control.controller import TERM_NAMES

    return tuple(TERM_NAMES)


def build_stage(
    cfg: AppConfig,
    *,
    clock: Clock | None = None,
    realtime: bool | None = None,
    controller: Any = None,
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
    stage = Stage(cfg)
    stage.clock = clock if clock is not None else MonotonicClock(spin_s=cfg.loop.realtime.spin_us * 1e-6)
    simulated_time = isinstance(stage.clock, SimClock)
    if realtime is None:
        realtime = not simulated_time
    period = cfg.loop.period_s
    try:
        kind = cfg.io.kind
        if kind is IoKind.PLANT_IO:
            from stagectl.sim.direct import PlantIO
            from stagectl.sim.plant import StagePlant

            assert cfg.sim is not None
            stage.plant = StagePlant(cfg.sim.plant)
            io = PlantIO(stage.plant, period, delay_cycles=cfg.io.delay_cycles, clock=stage.clock)
            stage.plant_io = _open_device(stage, io, None)
            stage.sensor = stage.actuator = stage.sync = io
        elif kind is IoKind.EMBEDDED_CANOPEN:
            _build_embedded_canopen(stage, simulated_time)
        else:
            _build_canopen(stage)
        stage.controller = controller if controller is not None else make_controller(cfg)
        stage.safety = Safety(cfg.safety, period)
        stage.reference = TrajectoryReference()
        assert stage.sensor is not None and stage.actuator is not None
        stage.loop = ControlLoop(
            clock=stage.clock,
            sensor=stage.sensor,
            actuator=stage.actuator,
            controller=stage.controller,
            reference=stage.reference,
            safety=stage.safety,
            cfg=cfg.loop,
            sync=stage.sync,
            realtime=realtime,
            term_names=getattr(stage.controller, "term_names", None) or controller_terms(),
            device_time=stage.world is not None,  # virtual CANopen devices step one period per SYNC
        )
    except BaseException:
        stage.close()
        raise
    return stage


def _build_embedded_canopen(stage: Stage, simulated_time: bool) -> None:
    """Virtual CANopen devices in-process (:class:`stagectl.sim.world.SimWorld` on python-can's virtual bus)
    and the real drivers talking to them through the bus; the drivers pump the world (lock-step) in
    simulated and in real time."""
    import dataclasses

    from stagectl.drivers.cia402 import Cia402Config
    from stagectl.sim.world import SimWorld

    cfg = stage.cfg
    assert cfg.sim is not None and cfg.sim.world is not None
    wcfg = cfg.sim.world
    if wcfg.transport.kind != "virtual":
        wcfg = dataclasses.replace(wcfg, transport=dataclasses.replace(wcfg.transport, kind="virtual"))
    world = SimWorld.from_config(wcfg, cfg.base_dir)
    stage.world = world
    stage.plant = world.plant
    stage.closers.append(world.stop)
    world.open()
    # The virtual devices are served synchronously by the loop thread (drivers' set_pump) in simulated AND
    # real time: each SYNC steps the plant by exactly one period, no thread hop can make a TPDO late.
    # A device thread (world.start()) would be needed only for peers that talk on their own (sim-plant).
    info = world.ready_info()
    sd = wcfg.drive
    drive_cfg = cfg.io.drive
    if drive_cfg is None:
        drive_cfg = Cia402Config(node_id=sd.node_id, can=info["can"], resolution_m=sd.resolution_m,
                                 force_per_unit_n=sd.force_per_unit_n)
    else:
        drive_cfg = dataclasses.replace(drive_cfg, can=info["can"])
    _open_drivers(stage, drive_cfg, pump=world.pump, interferometer_url=info.get("interferometer_url"),
                  serial_pump=world.serial_pump)


def _build_canopen(stage: Stage) -> None:
    _open_drivers(stage, stage.cfg.io.drive, pump=None)


def _open_drivers(stage: Stage, drive_cfg: Any, pump: Callable[[], None] | None,
                  interferometer_url: str | None = None, serial_pump: Callable[[], Any] | None = None) -> None:
    from stagectl.drivers.cia402 import Cia402Drive

    cfg = stage.cfg
    drive = _open_device(stage, Cia402Drive(drive_cfg, cfg.loop.period_s), pump)
    stage.actuator = drive
    stage.sync = drive
    src = cfg.io.sensor
    if src is SensorSource.DRIVE:
        stage.sensor = drive
    elif src is SensorSource.INTERFEROMETER:
        from stagectl.drivers.interferometer import SerialInterferometer

        icfg = cfg.io.interferometer
        if interferometer_url is not None:
            import dataclasses

            icfg = dataclasses.replace(icfg, url=interferometer_url)
        # serial_pump returns LinkBytes: a dropped frame costs no lock-step wait
        stage.sensor = _open_device(stage, SerialInterferometer(icfg), (serial_pump or pump) if pump else None)
    else:
        from stagectl.drivers.cia406 import Cia406Encoder  # type: ignore[import-not-found]

        stage.sensor = _open_device(stage, Cia406Encoder(cfg.io.encoder, cfg.loop.period_s), pump)


def _open_device(stage: Stage, dev: Any, pump: Callable[[], Any] | None) -> Any:
    """Lock-step pump (virtual devices), open, register for closing, configure; returns ``dev``."""
    if pump is not None:
        dev.set_pump(pump)
    dev.open()
    stage.devices.append(dev)
    dev.configure()
    return dev


__all__ = ["Stage", "TrajectoryReference", "build_stage", "get_scenario", "scenario_names"]
