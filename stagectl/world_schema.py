"""The schema of the ``sim:`` section: the simulated world's plant, virtual devices, transport and scripted faults.

Only the typed configuration (dataclasses with their parse rules, :meth:`PlantConfig.from_mapping` and
:meth:`SimWorldConfig.from_mapping`); the simulation itself (plant kernels, virtual CANopen devices, the
socketcand server, the interferometer) lives in :mod:`stagectl.sim`, which re-exports every name here. Kept
apart so that a controller process whose plant runs elsewhere (a HIL config: the plant in ``stagectl
sim-plant``) validates its file's ``sim:`` section exactly as ``check-config`` does without importing the
simulation (issue 14: ``stagectl run`` / the daemon on config/hil-canopen.yaml import no ``stagectl.sim*``).

Units: SI, as the field names say (``_m``, ``_s``, ``_n``, ``_hz``).
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from stagectl.errors import ConfigError, short
from stagectl.friction import Effects, FrictionModel, StageModel, parse_effects, parse_friction
from stagectl.schema import load, param, section_parser

__all__ = [
    "ActuatorConfig",
    "FaultSpec",
    "PlantConfig",
    "SensorConfig",
    "SerialFaultKind",
    "SimDriveConfig",
    "SimEncoderConfig",
    "SimFault",
    "SimInterferometerConfig",
    "SimInterferometerFault",
    "SimTransportConfig",
    "SimWorldConfig",
]


# ================================================================================================ scripted faults
class SimFault(enum.Enum):
    DRIVE_FAULT = "drive_fault"
    HEARTBEAT_STOP = "heartbeat_stop"
    DROP_TPDO = "drop_tpdo"
    LATE_TPDO = "late_tpdo"
    BUS_OFF = "bus_off"
    POSITION_JUMP = "position_jump"


@dataclass(frozen=True)
class FaultSpec:
    """One scripted fault (YAML ``sim.faults[i]``)."""

    kind: SimFault = param(desc="drive_fault, heartbeat_stop, drop_tpdo, late_tpdo, bus_off or position_jump")
    device: str = param("drive", desc="which virtual CANopen device: drive or encoder", choices=("drive", "encoder"))
    at_cycle: int | None = param(None, desc="first SYNC (counted from 1) affected", ge=1)
    at_time_s: float | None = param(None, unit="s", desc="first SYNC at or after this simulated time", ge=0)
    cycles: int = param(0, desc="number of SYNCs the fault lasts (0 = for ever; drive_fault is one-shot)", ge=0)
    code: int = param(0x2310, desc="drive_fault: CiA 301 error code sent by EMCY and shown in 0x603F", ge=1,
                      le=0xFFFF)
    jump_m: float = param(0.005, unit="m", desc="position_jump: offset added to the reported position")
    sync_fraction: float = param(1.0, desc="fraction of the SYNCs in the window the fault hits, drawn at random "
                               "per SYNC (1 = every SYNC; not for drive_fault)", ge=0, le=1)
    seed: int = param(0, desc="seed of the random draws for sync_fraction < 1 (reproducible runs)", ge=0)

    def __post_init__(self) -> None:
        if self.at_cycle is not None and self.at_time_s is not None:
            raise ValueError("give at_cycle or at_time_s, not both")


# ================================================================================================ plant
@dataclass(frozen=True)
class SensorConfig:
    """Position sensor model: noise, then quantisation, then a delay in whole plant steps."""

    resolution_m: float = param(1e-9, unit="m", desc="quantisation step (one count)", ge=1e-15)
    noise_std_m: float = param(0.0, unit="m", desc="white Gaussian noise std added before quantisation", ge=0.0,
                               le=1.0)
    delay_steps: int = param(0, unit="", desc="measurement delay in plant.step() calls", ge=0, le=100000)


@dataclass(frozen=True)
class ActuatorConfig:
    """Force actuator limit (its delay is ``effects.delay``, the single source of truth)."""

    max_force_n: float = param(math.inf, unit="N", desc="force saturation |u| <= max_force_n", gt=0.0,
                               allow_inf=True)


def _unresolved_model_file(value: Any, path: str, problems: list[str]) -> None:
    """Parse hook of ``PlantConfig.model_file``: the schema never accepts the key by itself (through
    :func:`~stagectl.schema.load`, a section parser or an enclosing section), since nothing there reads the
    file; only :meth:`PlantConfig.from_mapping`, handed the resolved model, takes it."""
    if value is None:
        return None
    if not isinstance(value, str):
        problems.append(f"{path}: expected a path string, got {short(value)}")
    else:
        problems.append(f"{path}: {value} is not loaded (load the configuration with stagectl.config, or pass "
                        "the StageModel to PlantConfig.from_mapping as model=)")
    return None


@dataclass(frozen=True)
class PlantConfig:
    """Stage plant configuration (YAML block, e.g. ``plant:``). Build from YAML with :meth:`from_mapping`."""

    mass_kg: float = param(unit="kg", desc="moving mass m", gt=0.0)
    friction: FrictionModel = param(desc="friction model (model: tag + parameters)", parse=parse_friction)
    effects: Effects = param(default_factory=Effects, desc="additional effects (offset, ripple, cogging, ...)",
                             parse=parse_effects)
    substep_s: float = param(1e-5, unit="s", desc="maximum integration sub-step h", ge=1e-7, le=1e-2)
    sensor: SensorConfig = param(default_factory=SensorConfig, desc="position sensor model")
    actuator: ActuatorConfig = param(default_factory=ActuatorConfig, desc="force actuator model")
    x0_m: float = param(0.0, unit="m", desc="initial position")
    seed: int = param(0, unit="", desc="seed of the sensor-noise generator", ge=0)
    model_file: str | None = param(None, desc="model file (StageModel) supplying mass/friction/effects; "
                                   "inline keys override; relative to the YAML file's directory (loaded by "
                                   "the configuration layer and handed to from_mapping as model=)",
                                   parse=_unresolved_model_file)

    def __post_init__(self) -> None:
        # explicit-integration stability (module docstring): h·√(K/m) < 2 and h·c/m < 1, checked with margin
        # for models that declare their pre-sliding stiffness K / total damping c
        k = getattr(self.friction, "stiffness_n_m", None)
        if isinstance(k, float) and k > 0.0 and self.substep_s * math.sqrt(k / self.mass_kg) > 1.0:
            h_max = 1.0 / math.sqrt(k / self.mass_kg)
            raise ValueError(f"substep_s: must be <= {h_max:.3g} s for stiffness {k:.4g} N/m and mass "
                             f"{self.mass_kg:g} kg (h·√(K/m) <= 1; got {self.substep_s:g} s)")
        c = getattr(self.friction, "damping_n_s_m", None)
        if isinstance(c, float) and c > 0.0 and self.substep_s * c / self.mass_kg > 0.5:
            raise ValueError(f"substep_s: must be <= {0.5 * self.mass_kg / c:.3g} s for damping {c:.4g} N·s/m "
                             f"and mass {self.mass_kg:g} kg (h·c/m <= 0.5; got {self.substep_s:g} s)")

    @classmethod
    def from_mapping(cls, data: Any, path: str = "plant", model: StageModel | None = None) -> PlantConfig:
        """Validate a YAML mapping into a :class:`PlantConfig`, merged over ``model``.

        ``model`` is the stage model of ``model_file`` as loaded by the configuration layer (this method
        reads no file): its ``mass_kg``, ``friction`` and ``effects`` are the defaults; inline keys override
        them. An inline ``friction`` mapping without ``model:`` updates the model's friction parameters; an
        inline ``effects`` mapping updates the model's effects one effect at a time.

        Raises
        ------
        ConfigError
            Every problem at once, each prefixed with its key path; ``model_file`` given without ``model``.
        """
        if data is None:
            data = {}
        if not isinstance(data, Mapping):
            raise ConfigError(f"{path}: expected a mapping, got {type(data).__name__} {short(data)}")
        merged: dict[str, Any] = dict(data)
        mf = merged.get("model_file")
        if mf is not None and not isinstance(mf, str):
            raise ConfigError(f"{path}.model_file: expected a path string, got {short(mf)}")
        if mf is not None and model is None:
            problems: list[str] = []
            _unresolved_model_file(mf, f"{path}.model_file", problems)
            raise ConfigError(problems)
        if mf is not None:
            del merged["model_file"]  # resolved: given to the dataclass below, past the schema's refusal
        sm = model
        if sm is not None:
            if "mass_kg" not in merged and sm.mass_kg is not None:
                merged["mass_kg"] = sm.mass_kg
            fr = merged.get("friction")
            if fr is None:
                merged["friction"] = sm.friction
            elif isinstance(fr, Mapping) and "model" not in fr:
                merged["friction"] = {**sm.friction.spec(), **fr}
            eff = merged.get("effects")
            if eff is None:
                merged["effects"] = sm.effects
            elif isinstance(eff, Mapping):
                merged["effects"] = {**sm.effects.spec(), **eff}
        cfg = load(cls, merged, path)
        return dataclasses.replace(cfg, model_file=mf) if mf is not None else cfg


# ================================================================================================ virtual devices
@dataclass(frozen=True)
class SimDriveConfig:
    """The simulated drive (YAML ``sim.drive``)."""

    node_id: int = param(1, desc="CANopen node id", ge=1, le=127)
    resolution_m: float = param(1e-9, unit="m", desc="position per count of 0x6064", ge=1e-15)
    force_per_unit_n: float = param(0.01, unit="N", desc="newtons per unit of target torque 0x6071", gt=0)
    velocity_resolution_m_s: float = param(1e-6, unit="m/s", desc="velocity per unit of 0x606C", gt=0)
    max_force_n: float | None = param(
        None, unit="N", desc="the drive's current limit, stored in its max torque 0x6072 as an integrator sets it "
        "on a real drive: 0x6072 = floor(max_force_n / force_per_unit_n), at most 65535 (None: "
        "sim.plant.actuator.max_force_n, the force the simulated actuator gives; the EDS default when that is "
        "infinite)", gt=0)
    sync_timeout_s: float = param(
        0.5, unit="s", desc="SYNC supervision in CST OPERATION ENABLED: no SYNC for this long -> EMCY 0x8700, "
        "fault (0 = off)", ge=0)
    eds_file: str = param("", desc="EDS (empty = config/eds/stagectl_cia402.eds)")
    wall_clock_plant: bool = param(
        False, desc="thread mode (stagectl sim-plant): at each SYNC step the plant by the whole periods of wall "
        "time since its last step (at most MAX_CATCH_UP_PERIODS, the first ones under the held force), so a "
        "skipped controller cycle lets the stage move on as a real one does; false: one period per SYNC "
        "(deterministic). Lock-step runs are one period per SYNC either way")


@dataclass(frozen=True)
class SimEncoderConfig:
    """The simulated CiA 406 encoder (YAML ``sim.encoder``)."""

    node_id: int = param(2, desc="CANopen node id", ge=1, le=127)
    resolution_m: float = param(1e-9, unit="m", desc="measuring step (position per count of 0x6004)",
                                 ge=1e-15)
    eds_file: str = param("", desc="EDS (empty = config/eds/stagectl_cia406.eds)")


class SerialFaultKind(enum.Enum):
    CORRUPT = "corrupt"
    DROP = "drop"
    GARBAGE = "garbage"
    SIGNAL_LOST = "signal_lost"
    LASER_UNLOCKED = "laser_unlocked"
    GLITCH = "glitch"
    LOW_SIGNAL = "low_signal"
    STOP = "stop"
    DISCONNECT = "disconnect"


@dataclass(frozen=True)
class SimInterferometerFault:
    """One scripted fault: ``kind`` on ``count`` sample slots starting at slot ``at_frame``."""

    kind: SerialFaultKind = param(desc="fault kind: corrupt, drop, garbage, signal_lost, laser_unlocked, "
                                  "glitch, low_signal, stop, disconnect")
    at_frame: int = param(0, desc="first sample slot (frame index since start) affected", ge=0)
    count: int = param(1, desc="number of consecutive sample slots affected", ge=1)
    garbage_bytes: int = param(16, unit="B", desc="garbage: bytes inserted before each affected frame", ge=1)
    glitch_m: float = param(1e-6, unit="m", desc="glitch: position jump added to affected frames")
    flag: bool = param(True, desc="glitch: also set the GLITCH status bit")
    signal: int = param(10, desc="low_signal: signal strength byte sent (0..255)", ge=0, le=255)


@dataclass(frozen=True)
class SimInterferometerConfig:
    """Virtual interferometer settings (YAML block ``interferometer_sim`` or built in tests)."""

    transport: str = param("pty", desc="pty (a pseudo-terminal with a symlink) or tcp (loopback server)",
                           choices=("pty", "tcp"))
    link_path: str | None = param(None, desc="pty: symlink path published to clients (None: unique temp path)")
    host: str = param("127.0.0.1", desc="tcp: listen address")
    port: int = param(0, desc="tcp: listen port (0: ephemeral, see .url)", ge=0, le=65535)
    rate_hz: float = param(1000.0, unit="Hz", desc="streaming rate (start()) and lock-step plant_time rate", gt=0)
    resolution_m: float = param(1e-9, unit="m", desc="position resolution per count", ge=1e-15)
    signal: int = param(230, desc="signal strength byte sent when healthy (0..255)", ge=0, le=255)
    baudrate: int | None = param(None, unit="bit/s", desc="pace frames as on an 8N1 line (None: unpaced)", gt=0)
    lockstep: str = param("per_pump", desc="pump(): per_pump = one frame per call; plant_time = one frame "
                          "per elapsed 1/rate_hz of plant time", choices=("per_pump", "plant_time"))
    trigger: str = param("rate", desc="rate = free-running at rate_hz; sync = one frame per CANopen SYNC, sampled "
                         "right after the drive stepped the plant (external trigger input; SimWorld only)",
                         choices=("rate", "sync"))
    seed: int = param(0, desc="seed of the garbage generator", ge=0)
    faults: tuple[SimInterferometerFault, ...] = param((), desc="scripted faults")


# ================================================================================================ the world
def _parse_faults(value: Any, path: str, problems: list[str]) -> tuple[FaultSpec, ...] | None:
    if value is None:
        return ()
    if not isinstance(value, (list, tuple)):
        problems.append(f"{path}: expected a list of faults, got {short(value)}")
        return None
    out: list[FaultSpec] = []
    n0 = len(problems)
    for i, item in enumerate(value):
        try:
            out.append(load(FaultSpec, item, f"{path}[{i}]"))
        except ConfigError as exc:
            problems.extend(exc.problems)
    return tuple(out) if len(problems) == n0 else None


@dataclass(frozen=True)
class SimTransportConfig:
    """Where the virtual devices listen (YAML ``sim.transport``)."""

    kind: str = param("virtual", desc="virtual (in-process python-can bus) or socketcand (loopback TCP server)",
                      choices=("virtual", "socketcand"))
    channel: str = param("", desc="virtual bus channel name (empty = a unique name per world)")
    host: str = param("127.0.0.1", desc="socketcand: listen address")
    port: int = param(0, desc="socketcand: listen port (0 = ephemeral, see ready_info)", ge=0, le=65535)
    can_name: str = param("can0", desc="socketcand: CAN interface name announced to clients")


@dataclass(frozen=True)
class SimWorldConfig:
    """The simulated world (YAML ``sim:`` section)."""

    plant: PlantConfig = param(desc="stage plant (mass, friction, sensor, actuator)",
                               parse=section_parser(PlantConfig))
    drive: SimDriveConfig = param(default_factory=SimDriveConfig, desc="simulated CiA 402 drive")
    encoder: SimEncoderConfig | None = param(None, desc="simulated CiA 406 encoder (optional)")
    interferometer: SimInterferometerConfig | None = param(
        None, desc="simulated serial interferometer (optional; SimInterferometerConfig)")
    transport: SimTransportConfig = param(default_factory=SimTransportConfig, desc="how clients connect")
    faults: tuple[FaultSpec, ...] = param((), desc="scripted faults (list of {kind, device, at_cycle|at_time_s, ...})",
                                          parse=_parse_faults)

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any] | None, path: str = "sim",
                     plant_model: StageModel | None = None) -> SimWorldConfig:
        """Validate the ``sim:`` mapping (all problems at once, as :class:`ConfigError`).

        ``plant_model`` is ``sim.plant.model_file`` as loaded by the configuration layer (this method reads
        no file; see :meth:`stagectl.sim.plant.PlantConfig.from_mapping`).
        """
        data = dict(data or {})
        problems: list[str] = []
        if "plant" in data and not isinstance(data["plant"], PlantConfig):
            try:
                data["plant"] = PlantConfig.from_mapping(data["plant"], f"{path}.plant", plant_model)
            except ConfigError as exc:
                problems.extend(exc.problems)
                del data["plant"]
        try:
            cfg = load(cls, data, path)
        except ConfigError as exc:
            if problems:  # the plant's own problems, not a follow-up "required key missing"
                problems.extend(p for p in exc.problems if not p.startswith(f"{path}.plant: required"))
                raise ConfigError(problems) from None
            raise
        if problems:
            raise ConfigError(problems)
        return cfg
