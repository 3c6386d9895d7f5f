"""Fault injection for the virtual CANopen devices, scriptable from tests and from YAML.

YAML (``sim.faults``)::

    faults:
      - {kind: drive_fault, at_cycle: 500, code: 0x2310}      # FAULT + EMCY 0x2310 at SYNC 500
      - {kind: heartbeat_stop, device: drive, at_time_s: 1.0} # drive stops producing heartbeats
      - {kind: drop_tpdo, at_cycle: 100, cycles: 5}           # 5 TPDOs not sent
      - {kind: late_tpdo, at_cycle: 200, cycles: 10}          # each TPDO sent one cycle late
      - {kind: bus_off, at_cycle: 300}                        # error frame (bus-off), then silence
      - {kind: position_jump, device: encoder, at_cycle: 50, jump_m: 0.005}
      - {kind: late_tpdo, sync_fraction: 0.1, seed: 3}        # 10 % of the SYNCs, drawn at random, for ever

Tests: ``world.inject(FaultSpec(kind=SimFault.DROP_TPDO, cycles=3))`` (``at_cycle``/``at_time_s`` unset =
from the device's next SYNC on).

Semantics, per device (``drive`` or ``encoder``); ``cycles`` = how many SYNCs the fault lasts (0 = for
ever); a fault is active for SYNC number ``n`` (counted by the device from 1) when
``start <= n < start + cycles``, where ``start`` is ``at_cycle`` or the first SYNC at or after
``at_time_s`` of simulated time, and (``sync_fraction`` p < 1) a draw of a seeded generator per SYNC is
below p: a random fraction p of the SYNCs in the window (timing disturbances of a loaded machine):

* ``drive_fault``   : one-shot; the drive enters FAULT (statusword bit 3) with 0x603F = ``code`` and sends
  EMCY ``code`` before that SYNC's TPDO.
* ``heartbeat_stop``: no heartbeat frames while active.
* ``drop_tpdo``     : TPDOs are not sent while active.
* ``late_tpdo``     : each TPDO is held and sent 0.9 period after its SYNC (thread mode), or (lock-step) at
  the next ``pump()`` that finds a controller frame on the bus (its RPDO, or the next SYNC when it writes
  none), i.e. after the controller has stopped waiting for it.
* ``bus_off``       : one error frame with the SocketCAN bus-off class (0x40), then the device is silent
  (no TPDO, heartbeat, EMCY or SDO answer) while active.
* ``position_jump`` : ``jump_m`` is added to the reported position while active (a step glitch).

Loop-level names (the daemon's ``fault`` debug request) are aliases, resolved here for both simulated stages:
:data:`FAULT_ALIASES` maps them onto the virtual devices' faults (:func:`world_fault`), and
:func:`inject_plant_io_fault` applies them to the directly wrapped plant (:class:`~stagectl.sim.direct.PlantIO`).
"""

from __future__ import annotations

import math
import random
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from stagectl.drivers.base import FaultKind
from stagectl.sim.direct import PlantIO

from stagectl.errors import short
from stagectl.world_schema import FaultSpec as FaultSpec
from stagectl.world_schema import SimFault as SimFault


@dataclass
class _Armed:
    spec: FaultSpec
    start: int | None = None  # resolved first SYNC number
    fired: bool = False
    rng: random.Random | None = None  # draws for sync_fraction < 1


@dataclass
class FaultSchedule:
    """The faults of one device, resolved against its SYNC counter and simulated time."""

    device: str
    armed: list[_Armed] = field(default_factory=list)

    def add(self, spec: FaultSpec, next_cycle: int) -> None:
        a = _Armed(spec, rng=random.Random(spec.seed) if spec.sync_fraction < 1.0 else None)
        if spec.at_cycle is not None:
            a.start = spec.at_cycle
        elif spec.at_time_s is None:
            a.start = next_cycle
        self.armed.append(a)

    def clear(self) -> None:
        self.armed.clear()

    def at_sync(self, cycle: int, t_s: float) -> set[SimFault]:
        """Kinds active at SYNC number ``cycle`` (simulated time ``t_s``); one-shots fire once."""
        active: set[SimFault] = set()
        for a in self.armed:
            if a.start is None:
                if a.spec.at_time_s is not None and t_s + 1e-12 >= a.spec.at_time_s:
                    a.start = cycle
                else:
                    continue
            if cycle < a.start:
                continue
            if a.spec.kind is SimFault.DRIVE_FAULT:
                if not a.fired:
                    a.fired = True
                    active.add(SimFault.DRIVE_FAULT)
                continue
            if a.spec.cycles == 0 or cycle < a.start + a.spec.cycles:
                if a.rng is not None and a.rng.random() >= a.spec.sync_fraction:
                    continue
                active.add(a.spec.kind)
        return active

    def spec_of(self, kind: SimFault) -> FaultSpec | None:
        """The most recently added spec of ``kind`` (for its parameters)."""
        for a in reversed(self.armed):
            if a.spec.kind is kind:
                return a.spec
        return None

    def jump_m(self, active: set[SimFault]) -> float:
        if SimFault.POSITION_JUMP not in active:
            return 0.0
        spec = self.spec_of(SimFault.POSITION_JUMP)
        return spec.jump_m if spec else 0.0


#: loop-level fault names accepted by the ``fault`` request → the virtual devices' faults
FAULT_ALIASES: dict[str, SimFault] = {
    "emcy": SimFault.DRIVE_FAULT,
    "stale": SimFault.DROP_TPDO,
    "heartbeat_lost": SimFault.HEARTBEAT_STOP,
}
#: why ``nan`` exists on the directly wrapped plant only (it used to alias a 5 mm jump here: one name, two causes)
NAN_ON_CANOPEN = ("kind: nan needs a floating-point position (io.kind plant_io); a CANopen position is an "
                  "integer count, so it cannot be NaN: use position_jump (jump_m, cycles) for a sensor glitch")
#: how many cycles a ``stale`` fault lasts when the request does not say (longer than the shipped stale caps,
#: ``safety.stale_cycles`` 20: the drive's silence is a fault, not a gap the stage rides out)
STALE_CYCLES = 50
#: the plant_io stage's ``stale``: MISSED_FRAME after this many dropped samples (the CiA 402 driver's default;
#: the stage passes ``safety.stale_cycles`` when larger, as the embedded virtual drive's ``max_missed``)
PLANT_IO_MAX_MISSED = 3


def world_fault(kind: str, fields: Mapping[str, Any]) -> dict[str, Any]:
    """The :class:`FaultSpec` mapping (``kind`` + fields) for a fault request on the virtual devices:
    aliases (:data:`FAULT_ALIASES`) replaced by their :class:`SimFault` value, ``stale`` lasting
    :data:`STALE_CYCLES` unless ``cycles`` is given."""
    if kind == "nan":
        raise ValueError(NAN_ON_CANOPEN)
    out = dict(fields)
    if kind == "stale":
        out.setdefault("cycles", STALE_CYCLES)
    alias = FAULT_ALIASES.get(kind)
    out["kind"] = alias.value if alias is not None else kind
    return out


def inject_plant_io_fault(io: PlantIO, kind: str, fields: Mapping[str, Any],
                          max_missed: int = PLANT_IO_MAX_MISSED) -> None:
    """Apply a fault request to the directly wrapped plant, latching the names the virtual CANopen stage
    latches for the same request: ``stale`` (the next ``cycles`` reads are not fresh; ``missed_frame`` after
    ``max_missed``), ``emcy`` (``drive_fault`` with the EMCY ``code``), ``nan`` (the next read is NaN), ``position_jump`` (``jump_m`` added to the next ``cycles`` reads,
    default 1; as on the virtual devices) or a device fault by :class:`~stagectl.drivers.base.FaultKind` value
    (``detail``, ``code``).

    Raises
    ------
    ValueError
        An unknown fault name.
    """
    # the same fault names as the virtual CANopen drive: a drive misses its TPDOs (missed_frame after its
    # max_missed) and an EMCY comes with the drive entering FAULT (drive_fault)
    if kind == "stale":
        io.drop_samples(int(fields.get("cycles", STALE_CYCLES)), missed_after=max_missed)
    elif kind == "emcy":
        code = int(fields.get("code", FaultSpec.code))
        io.inject_fault(FaultKind.DRIVE_FAULT, str(fields.get("detail", f"drive in FAULT (EMCY 0x{code:04X})")),
                        code)
    elif kind == "nan":
        io.glitch(math.nan)
    elif kind == "position_jump":
        io.jump(float(fields.get("jump_m", FaultSpec.jump_m)), int(fields.get("cycles", 1)))
    else:
        try:
            fk = FaultKind(kind)
        except ValueError:
            raise ValueError(f"kind: unknown fault {short(kind)} (known: stale, nan, position_jump, "
                             f"{', '.join(k.value for k in FaultKind)})") from None
        io.inject_fault(fk, str(fields.get("detail", "injected")), int(fields.get("code", 0)))
