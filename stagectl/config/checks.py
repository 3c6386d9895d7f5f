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
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from stagectl.config.sections import AppConfig, IoKind
from stagectl.control.controller import check_controller
from stagectl.control.reference import scenario_names
from stagectl.drivers.canbus import bus_kwargs, can_key_problems
from stagectl.errors import ConfigError

__all__ = ["INT16_MAX", "can_problems", "controller_problems", "cross_checks", "demo_problems",
           "force_chain_problems"]

#: largest target torque 0x6071 (INT16) a CiA 402 drive accepts, in units of force_per_unit_n
INT16_MAX = 32767


def _link(lower: tuple[str, float], upper: tuple[str, float]) -> str | None:
    """One link of the chain: ``lower`` must not exceed ``upper`` (both finite or inf)."""
    (k_lo, v_lo), (k_up, v_up) = lower, upper
    if v_lo > v_up:
        return (f"{k_lo}: {v_lo:g} N exceeds {k_up} {v_up:g} N (the force limits must satisfy "
                f"controller <= safety <= drive <= actuator)")
    return None


def force_chain_problems(cfg: AppConfig) -> list[str]:
    """The force-limit chain (module docstring), one line per violated link naming both keys and values."""
    ctl = ("controller.max_force_n", cfg.controller.max_force_n)
    safety = ("safety.max_force_n", cfg.safety.max_force_n)
    links: list[tuple[tuple[str, float], tuple[str, float]]] = [(ctl, safety)]
    drive = cfg.io.drive
    drive_limit: tuple[str, float] | None = None
    int16: tuple[str, float] | None = None
    if drive is not None and cfg.io.kind is not IoKind.PLANT_IO:
        if math.isfinite(drive.max_force_n):
            drive_limit = ("io.drive.max_force_n", drive.max_force_n)
        int16 = (f"the drive's torque range {INT16_MAX} x io.drive.force_per_unit_n",
                 INT16_MAX * drive.force_per_unit_n)
    elif cfg.io.kind is IoKind.EMBEDDED_CANOPEN and cfg.sim is not None:
        int16 = (f"the drive's torque range {INT16_MAX} x sim.drive.force_per_unit_n",
                 INT16_MAX * cfg.sim.drive.force_per_unit_n)
    if drive_limit is not None:
        links.append((safety, drive_limit))
    if int16 is not None:
        links.append((safety, int16))
    if cfg.sim is not None:  # the simulated actuator (also what `simulate` drives for a canopen config)
        act = cfg.sim.plant.actuator.max_force_n
        if math.isfinite(act):
            actuator = ("sim.plant.actuator.max_force_n", act)
            links.append((drive_limit or safety, actuator))
    return [msg for lo, up in links if (msg := _link(lo, up)) is not None]


def can_problems(cfg: AppConfig) -> list[str]:
    """The ``can:`` mapping of each configured CANopen device: required keys (:func:`bus_kwargs`) and keys the
    chosen python-can interface does not accept (:func:`can_key_problems`, with a did-you-mean)."""
    problems: list[str] = []
    devices: list[tuple[str, Mapping[str, Any]]] = []
    if cfg.io.drive is not None:
        devices.append(("io.drive.can", cfg.io.drive.can))
    if cfg.io.encoder is not None:
        devices.append(("io.encoder.can", cfg.io.encoder.can))
    for path, mapping in devices:
        problems.extend(can_key_problems(mapping, path=path))
        try:
            bus_kwargs(mapping, path=path)
        except ConfigError as exc:
            problems.extend(exc.problems)
    return problems


def demo_problems(cfg: AppConfig) -> list[str]:
    """``demo.scenario`` must name a scenario of :func:`stagectl.control.reference.scenario_names`."""
    names = scenario_names()
    if cfg.demo.scenario not in names:
        return [f"demo.scenario: unknown scenario {cfg.demo.scenario!r} (known: {', '.join(names)})"]
    return []


def controller_problems(cfg: AppConfig) -> list[str]:
    """What the controller needs from the resolved model (:func:`stagectl.control.controller.check_controller`)."""
    return check_controller(cfg.controller)


def cross_checks(cfg: AppConfig) -> list[str]:
    """Every cross-section check, in a stable order."""
    problems: list[str] = []
    kind = cfg.io.kind
    if kind in (IoKind.PLANT_IO, IoKind.EMBEDDED_CANOPEN) and cfg.sim is None:
        problems.append(f"sim: required for io.kind {kind.value} (the simulated stage)")
    problems += demo_problems(cfg)
    problems += controller_problems(cfg)
    problems += can_problems(cfg)
    problems += force_chain_problems(cfg)
    return problems
