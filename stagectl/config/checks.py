"""Cross-section checks of a parsed configuration: each returns problem lines (empty = fine).

* :func:`force_chain_problems` -- the force limits, from the controller to the actuator, must get looser
  along the force path, so that the limit that binds is one that is watched::

      controller.max_force_n  <=  safety.max_force_n  <=  io.drive.max_force_n  <=  sim.plant.actuator.max_force_n
                                  safety.max_force_n  <=  32767 x force_per_unit_n (the drive's INT16 torque range)

  The controller clamps its output (its anti-windup knows it); the safety supervisor clamps again and latches
  ``force_limit`` when clamped too long; the drive clamps silently (and saturates at its INT16 target-torque
  range); the simulated actuator saturates silently. A tighter limit further down the path would clip the
  force without the controller or the safety supervisor knowing.
* :func:`can_problems` -- the ``can:`` keys of every CANopen device against the chosen python-can interface.
* :func:`demo_problems`, :func:`controller_problems` -- the demo scenario name, and what the controller
  needs (a model for ``kind: model``, a mass) checked on the resolved model, without designing a controller.
* :func:`device_match_problems` -- a real driver (``io.drive``, ``io.encoder``, ``io.interferometer``) and the
  simulated device it talks to (``sim.drive``, ``sim.encoder``, ``sim.interferometer``: in-process for
  ``embedded_canopen``, served by ``stagectl sim-plant`` otherwise) must agree on node id and scaling.
* :func:`time_base_problems` -- a HIL file (``io.kind: canopen`` to the ``stagectl sim-plant`` its own ``sim:``
  section serves) whose sim-plant steps its plant one period per SYNC must run the loop on device time.
* :func:`sim_device_problems` -- what the simulated world needs: for ``embedded_canopen`` the simulated sensor
  ``io.sensor`` names, distinct node ids on its bus, and ``sim.faults`` naming configured devices only.

The checks run on :class:`Sections`, the sections that parsed: the loader runs every check whose inputs parsed
even when another section has problems, so one file reports everything at once.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from stagectl.config.sections import AppConfig, DemoConfig, IoConfig, IoKind, SensorSource
from stagectl.control.controller import ControllerConfig, check_controller
from stagectl.control.reference import scenario_names
from stagectl.drivers.canbus import bus_kwargs, can_key_problems
from stagectl.errors import ConfigError, short
from stagectl.runtime.config import LoopConfig
from stagectl.safety import SafetyConfig

if TYPE_CHECKING:
    from stagectl.world_schema import SimWorldConfig

__all__ = ["INT16_MAX", "Sections", "can_problems", "controller_problems", "cross_checks", "demo_problems",
           "device_match_problems", "force_chain_problems", "sim_device_problems", "time_base_problems"]

#: largest target torque 0x6071 (INT16) a CiA 402 drive accepts, in units of force_per_unit_n
INT16_MAX = 32767


@dataclass(frozen=True)
class Sections:
    """The sections of one configuration that parsed, as the cross-checks see them: None where a section has
    problems of its own (reported by the schema), so that a check runs exactly when its inputs parsed."""

    safety: SafetyConfig | None = None
    controller: ControllerConfig | None = None  # with its model resolved (None also: its model file failed)
    io: IoConfig | None = None
    demo: DemoConfig | None = None
    sim: SimWorldConfig | None = None
    loop: LoopConfig | None = None
    #: no ``sim:`` key at all (``sim`` None with ``sim_absent`` False: the section has problems)
    sim_absent: bool = True

    @classmethod
    def of(cls, cfg: AppConfig) -> Sections:
        """Every section of a complete configuration."""
        return cls(safety=cfg.safety, controller=cfg.controller, io=cfg.io, demo=cfg.demo, sim=cfg.sim,
                   loop=cfg.loop, sim_absent=cfg.sim is None)


def _sections(cfg: AppConfig | Sections) -> Sections:
    return cfg if isinstance(cfg, Sections) else Sections.of(cfg)


def _link(lower: tuple[str, float], upper: tuple[str, float]) -> str | None:
    """One link of the chain: ``lower`` must not exceed ``upper`` (both finite or inf)."""
    (k_lo, v_lo), (k_up, v_up) = lower, upper
    if v_lo > v_up:
        return (f"{k_lo}: {v_lo:g} N exceeds {k_up} {v_up:g} N (the force limits must satisfy "
                f"controller <= safety <= drive <= actuator)")
    return None


def force_chain_problems(cfg: AppConfig | Sections) -> list[str]:
    """The force-limit chain (module docstring), one line per violated link naming both keys and values; a link
    is checked when both its ends parsed."""
    s = _sections(cfg)
    ctl = ("controller.max_force_n", s.controller.max_force_n) if s.controller is not None else None
    safety = ("safety.max_force_n", s.safety.max_force_n) if s.safety is not None else None
    links: list[tuple[tuple[str, float] | None, tuple[str, float] | None]] = [(ctl, safety)]
    drive = s.io.drive if s.io is not None else None
    drive_limit: tuple[str, float] | None = None
    int16: tuple[str, float] | None = None
    if s.io is not None and drive is not None and s.io.kind is not IoKind.PLANT_IO:
        if math.isfinite(drive.max_force_n):
            drive_limit = ("io.drive.max_force_n", drive.max_force_n)
        int16 = (f"the drive's torque range {INT16_MAX} x io.drive.force_per_unit_n",
                 INT16_MAX * drive.force_per_unit_n)
    elif s.io is not None and s.io.kind is IoKind.EMBEDDED_CANOPEN and s.sim is not None:
        int16 = (f"the drive's torque range {INT16_MAX} x sim.drive.force_per_unit_n",
                 INT16_MAX * s.sim.drive.force_per_unit_n)
    if drive_limit is not None:
        links.append((safety, drive_limit))
    if int16 is not None:
        links.append((safety, int16))
    if s.sim is not None:  # the simulated actuator (also what `simulate` drives for a canopen config)
        act = s.sim.plant.actuator.max_force_n
        if math.isfinite(act) and s.io is not None:  # which limit it follows depends on io
            links.append((drive_limit or safety, ("sim.plant.actuator.max_force_n", act)))
    return [msg for lo, up in links if lo is not None and up is not None and (msg := _link(lo, up)) is not None]


def can_problems(cfg: AppConfig | Sections) -> list[str]:
    """The ``can:`` mapping of each configured CANopen device: required keys (:func:`bus_kwargs`) and keys the
    chosen python-can interface does not accept (:func:`can_key_problems`, with a did-you-mean)."""
    io = _sections(cfg).io
    if io is None:
        return []
    problems: list[str] = []
    devices: list[tuple[str, Mapping[str, Any]]] = []
    if io.drive is not None:
        devices.append(("io.drive.can", io.drive.can))
    if io.encoder is not None:
        devices.append(("io.encoder.can", io.encoder.can))
    for path, mapping in devices:
        problems.extend(can_key_problems(mapping, path=path))
        try:
            bus_kwargs(mapping, path=path)
        except ConfigError as exc:
            problems.extend(exc.problems)
    return problems


def _differs(io_key: str, io_value: float, sim_key: str, sim_value: float, unit: str = "") -> str | None:
    """One line when a driver setting and the simulated device's disagree (floats to 1e-9 relative)."""
    if math.isclose(io_value, sim_value, rel_tol=1e-9, abs_tol=0.0):
        return None
    u = f" {unit}" if unit else ""
    return (f"{io_key}: {io_value:g}{u} differs from {sim_key} {sim_value:g}{u} (the driver and the simulated "
            f"device it talks to must agree)")


def device_match_problems(cfg: AppConfig | Sections) -> list[str]:
    """Each real driver and the simulated device it talks to, where both are configured: ``io.drive`` vs
    ``sim.drive`` (node_id, force_per_unit_n, resolution_m), ``io.encoder`` vs ``sim.encoder`` (node_id,
    resolution_m), ``io.interferometer`` vs ``sim.interferometer`` (resolution_m). A mismatch would simulate a
    scaled force or position error (e.g. 10x force_per_unit_n), or fail at run time (node id)."""
    s = _sections(cfg)
    io, sim = s.io, s.sim
    if io is None or sim is None or io.kind is IoKind.PLANT_IO:
        return []
    found: list[str | None] = []
    if io.drive is not None:
        d, sd = io.drive, sim.drive
        found += [_differs("io.drive.node_id", d.node_id, "sim.drive.node_id", sd.node_id),
                  _differs("io.drive.force_per_unit_n", d.force_per_unit_n, "sim.drive.force_per_unit_n",
                           sd.force_per_unit_n, "N"),
                  _differs("io.drive.resolution_m", d.resolution_m, "sim.drive.resolution_m", sd.resolution_m, "m")]
    if io.encoder is not None and sim.encoder is not None:
        e, se = io.encoder, sim.encoder
        found += [_differs("io.encoder.node_id", e.node_id, "sim.encoder.node_id", se.node_id),
                  _differs("io.encoder.resolution_m", e.resolution_m, "sim.encoder.resolution_m",
                           se.resolution_m, "m")]
    if io.interferometer is not None and sim.interferometer is not None:
        found.append(_differs("io.interferometer.resolution_m", io.interferometer.resolution_m,
                              "sim.interferometer.resolution_m", sim.interferometer.resolution_m, "m"))
    return [m for m in found if m is not None]


def sim_device_problems(cfg: AppConfig | Sections) -> list[str]:
    """What the simulated world needs to run:

    * ``embedded_canopen``: the sensor ``io.sensor`` names must be simulated (``sim.encoder`` for ``encoder``,
      ``sim.interferometer`` for ``interferometer``); the matching ``io.`` section is optional there (driver
      settings; its bus or URL is the world's);
    * the virtual drive and encoder share one bus: distinct node ids;
    * ``sim.faults`` may name only a configured virtual device.
    """
    s = _sections(cfg)
    io, sim = s.io, s.sim
    problems: list[str] = []
    if sim is None:
        return problems
    if io is not None and io.kind is IoKind.EMBEDDED_CANOPEN:
        if io.sensor is SensorSource.ENCODER and sim.encoder is None:
            problems.append("sim.encoder: required for io.sensor encoder with io.kind embedded_canopen (the "
                            "simulated encoder the driver talks to; io.encoder is optional)")
        if io.sensor is SensorSource.INTERFEROMETER and sim.interferometer is None:
            problems.append("sim.interferometer: required for io.sensor interferometer with io.kind "
                            "embedded_canopen (the simulated interferometer the driver reads; io.interferometer "
                            "is optional)")
    if sim.encoder is not None and sim.encoder.node_id == sim.drive.node_id:
        problems.append(f"sim.encoder.node_id: {sim.encoder.node_id} is also sim.drive.node_id (two CANopen "
                        "nodes on one bus need distinct node ids)")
    devices = {"drive": True, "encoder": sim.encoder is not None}
    for i, spec in enumerate(sim.faults):
        if not devices.get(spec.device, False):
            problems.append(f"sim.faults[{i}].device: {spec.device} is not configured (no sim.{spec.device})")
    return problems


def time_base_problems(cfg: AppConfig | Sections) -> list[str]:
    """``loop.device_time`` where the loop talks to the ``stagectl sim-plant`` of this file's own ``sim:`` section
    (``io.kind: canopen``, ``io.drive.can`` at ``sim.transport``'s host and port) and that sim-plant steps its
    plant exactly one period per SYNC (``sim.drive.wall_clock_plant: false``): the stage's time is then the
    number of SYNCs it answered. On the wall clock every skipped loop slot (a loaded PC without real-time
    scheduling skips 2-25 %) puts the reference one period ahead of the stage for good: at 2 mm/s, 2 µm per
    slot, and ``config/hil-serial.yaml`` ran up a 37 µm error in 60 s at load 3 and faulted ``following_error``
    after 10 s at load 8-10 (docs/platform.md §7.3). With device time the reference waits with the plant.

    The other way round, ``loop.device_time`` towards a drive not reached over socketcand (the only transport a
    sim-plant speaks) is a real drive, whose stage moves on the clock: refused. ``loop.pace_cycles`` without
    device time towards any CANopen drive is ignored by the loop: refused, so that it is not taken for a
    protection."""
    s = _sections(cfg)
    io, sim, loop = s.io, s.sim, s.loop
    if io is not None and loop is not None and io.kind is IoKind.CANOPEN and io.drive is not None:
        iface = str(io.drive.can.get("interface", ""))
        if loop.device_time and iface != "socketcand":
            # a sim-plant is reached over socketcand only: anything else is a bus with a real drive on it
            return [(f"loop.device_time: true, but io.drive.can.interface is {short(iface)}: a real drive, whose "
                     "stage moves on the clock; on device time each skipped loop slot is a period the stage moved "
                     "and the controller did not count (wrong dt, reference behind); remove it (it is for a "
                     "sim-plant stepped one period per SYNC)")]
    own = _own_sim_plant_problems(io, sim, loop)
    if own or io is None or loop is None or io.kind is not IoKind.CANOPEN:
        return own
    if loop.pace_cycles and not loop.device_time:
        return [(f"loop.pace_cycles: {loop.pace_cycles} cycles does nothing without loop.device_time: true (a "
                 "real drive's silence is judged on the clock, safety.stale_cycles); remove it, or set "
                 "device_time for a sim-plant stepped one period per SYNC")]
    return []


def _own_sim_plant_problems(io: IoConfig | None, sim: SimWorldConfig | None, loop: LoopConfig | None) -> list[str]:
    """Wall-clock time towards this file's own sim-plant stepped per SYNC (:func:`time_base_problems`)."""
    if (io is None or sim is None or loop is None or io.kind is not IoKind.CANOPEN or io.drive is None
            or loop.device_time or sim.drive.wall_clock_plant or sim.transport.kind != "socketcand"):
        return []
    can = io.drive.can
    if str(can.get("interface", "")) != "socketcand" or can.get("port") != sim.transport.port or \
            str(can.get("host", "")) != sim.transport.host:
        return []
    return [(f"loop.device_time: false, but io.drive talks to the sim-plant of this file's sim: section "
             f"({sim.transport.host}:{sim.transport.port}), which steps its plant one period per SYNC "
             "(sim.drive.wall_clock_plant: false): each skipped loop slot would put the reference a period ahead "
             "of the stage; set loop.device_time: true")]


def sim_plant_only_note(cfg: AppConfig) -> str | None:
    """A note (not a problem) for ``loop.device_time`` / ``loop.pace_cycles`` in a file without a ``sim:``
    section: both take the stage's time from the drive and, paced, stop sending forces while a SYNC is
    unanswered. That is right for a ``stagectl sim-plant`` stepped per SYNC (its plant waits too), wrong for a
    real drive, whose stage moves on the clock while the loop waits. The file alone cannot tell the two apart
    (a HIL stage PC talks to a sim-plant elsewhere), so this is said, not refused."""
    loop = cfg.loop
    if cfg.sim is not None or not (loop.device_time or loop.pace_cycles > 0):
        return None
    keys = " and ".join(k for k, on in (("loop.device_time", loop.device_time),
                                        ("loop.pace_cycles", loop.pace_cycles > 0)) if on)
    return (f"{keys}: set for a stage whose plant is a `stagectl sim-plant` stepped per SYNC; on a real drive set "
            "loop.device_time: false and loop.pace_cycles: 0 (the stage moves on the clock while the loop waits)")


def demo_problems(cfg: AppConfig | Sections) -> list[str]:
    """``demo.scenario`` must name a scenario of :func:`stagectl.control.reference.scenario_names`."""
    demo = _sections(cfg).demo
    if demo is None:
        return []
    names = scenario_names()
    if demo.scenario not in names:
        return [f"demo.scenario: unknown scenario {short(demo.scenario)} (known: {', '.join(names)})"]
    return []


def controller_problems(cfg: AppConfig | Sections) -> list[str]:
    """What the controller needs from the resolved model (:func:`stagectl.control.controller.check_controller`)."""
    ctl = _sections(cfg).controller
    return check_controller(ctl) if ctl is not None else []


#: coarsest plausible position step, as a fraction of the stroke (a precision stage resolves far finer)
MAX_RESOLUTION_OF_STROKE = 0.01


def plausibility_problems(cfg: AppConfig | Sections) -> list[str]:
    """Values each in range on their own but physically implausible together, one line each:

    * ``safety.following_error_m`` at least the whole stroke (``max_position_m − min_position_m``): the
      window could never trip;
    * a ``safety.quick_stop_deceleration_m_s2`` a so weak that the brake's stop distance from
      ``max_velocity_m_s`` v, v²/(2a) [m], exceeds the stroke (the brake holds the ramp's speed on meanwhile);
    * a sensor's ``resolution_m`` coarser than 1 % of the stroke (metres given where µm or nm were meant);
    * a filter or observer at or above the Nyquist frequency ``1/(2·loop.period_s)``: a discrete filter
      cannot act there (the observer, the PID's derivative low-pass, the velocity filters);
    * a settle move (``controller.settle.move_s``) shorter than two loop periods.
    """
    s = _sections(cfg)
    problems: list[str] = []
    stroke = None
    if s.safety is not None:
        stroke = s.safety.max_position_m - s.safety.min_position_m
        if stroke > 0 and s.safety.following_error_m >= stroke:
            problems.append(f"safety.following_error_m: {s.safety.following_error_m:g} m is not smaller than the "
                            f"stroke {stroke:g} m between the soft limits (the window could never trip)")
        a = s.safety.quick_stop_deceleration_m_s2
        if stroke > 0 and a is not None:
            v = s.safety.max_velocity_m_s
            stop_m = v * v / (2.0 * a)
            if stop_m > stroke:
                problems.append(f"safety.quick_stop_deceleration_m_s2: {a:g} m/s^2 stops the stage from "
                                f"max_velocity_m_s {v:g} m/s in {stop_m:g} m, more than the stroke {stroke:g} m "
                                "between the soft limits (the fault reaction's brake would push it on into the "
                                "end stop)")
    if stroke is not None and stroke > 0:
        sensors: list[tuple[str, float]] = []
        if s.io is not None:
            for name in ("drive", "encoder", "interferometer"):
                dev = getattr(s.io, name)
                if dev is not None:
                    sensors.append((f"io.{name}.resolution_m", dev.resolution_m))
        if s.sim is not None:
            sensors.append(("sim.plant.sensor.resolution_m", s.sim.plant.sensor.resolution_m))
            for name in ("drive", "encoder", "interferometer"):
                dev = getattr(s.sim, name, None)
                if dev is not None and hasattr(dev, "resolution_m"):
                    sensors.append((f"sim.{name}.resolution_m", dev.resolution_m))
        for key, res in sensors:
            if res > MAX_RESOLUTION_OF_STROKE * stroke:
                problems.append(f"{key}: {res:g} m per count is coarser than {100 * MAX_RESOLUTION_OF_STROKE:g} % "
                                f"of the stroke {stroke:g} m (a value in µm or nm written as metres?)")
    if s.loop is not None:
        nyquist = 0.5 / s.loop.period_s
        filters: list[tuple[str, float | None]] = []
        if s.controller is not None:
            ctl = s.controller
            filters += [("controller.dob.bandwidth_hz", ctl.dob.bandwidth_hz if ctl.dob.kind != "none" else None),
                        ("controller.pid.derivative_cutoff_hz", ctl.pid.derivative_cutoff_hz),
                        ("controller.velocity_cutoff_hz", ctl.velocity_cutoff_hz)]
        if s.safety is not None:
            filters.append(("safety.velocity_filter_hz", s.safety.velocity_filter_hz))
        for key, hz in filters:
            if hz is not None and hz >= nyquist:
                problems.append(f"{key}: {hz:g} Hz is at or above the Nyquist frequency {nyquist:g} Hz of "
                                f"loop.period_s {s.loop.period_s:g} s (a sampled filter cannot act there)")
        move_s = s.controller.settle.move_s if s.controller is not None else 0.0
        if 0.0 < move_s < 2.0 * s.loop.period_s:
            problems.append(f"controller.settle.move_s: {move_s:g} s is shorter than two loop periods "
                            f"({2.0 * s.loop.period_s:g} s): the settle move would end before it acts (0 turns it "
                            "off)")
    return problems


def cross_checks(cfg: AppConfig | Sections) -> list[str]:
    """Every cross-section check whose inputs parsed, in a stable order."""
    s = _sections(cfg)
    problems: list[str] = []
    if s.io is not None and s.io.kind in (IoKind.PLANT_IO, IoKind.EMBEDDED_CANOPEN) and s.sim_absent:
        problems.append(f"sim: required for io.kind {s.io.kind.value} (the simulated stage)")
    problems += demo_problems(s)
    problems += controller_problems(s)
    problems += can_problems(s)
    problems += force_chain_problems(s)
    problems += device_match_problems(s)
    problems += sim_device_problems(s)
    problems += time_base_problems(s)
    problems += plausibility_problems(s)
    return problems
