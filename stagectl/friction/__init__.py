"""Friction models (pure math) and the stage model file.

Public API (stable; other tools build on it):

* :func:`build` -- a model from the mapping found under ``friction:`` in YAML (``model:`` selects it).
* ``model.force_along(x, t)`` -- friction force [N] along a prescribed trajectory (see ``base``).
* :class:`StageModel` / :func:`load_model_file` / :func:`save_model_file` -- the model file format
  shared by the plant, the feed-forward, ``identify`` and ``discover``::

      mass_kg: 2.0            # optional rigid-body mass [kg]
      friction: {model: gms, ...}
      effects: {offset: {force_n: 0.1}, ...}   # optional, see stagectl.friction.effects
      backlash: {gap_m: 2.0e-5, other_mass_kg: 0.8}  # optional play between motor and load
      meta: {...}             # optional free-form provenance (fit quality, source, notes)

  ``backlash`` is a plant structure, not a force law: :func:`stagectl.sim.backlash.plant_from_model` builds a
  motor + load plant from it (``mass_kg`` stays the total moving mass; the friction side has
  ``mass_kg − other_mass_kg``). The feed-forward uses ``mass_kg``, ``friction`` and ``effects`` and does not
  compensate the play.

Models register themselves with :func:`stagectl.friction.base.register`; this package imports every
model module (at the end of this file) so that all tags are available.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from stagectl.errors import ConfigError, short
from stagectl.friction.base import FrictionKernel, FrictionModel, register, registry
from stagectl.friction.effects import Effects
from stagectl.schema import load, load_yaml_file, param, section_parser

__all__ = [
    "Backlash",
    "Effects",
    "FrictionKernel",
    "FrictionModel",
    "StageModel",
    "build",
    "load_model_file",
    "parse_effects",
    "parse_friction",
    "register",
    "registry",
    "save_model_file",
]

def build(spec: Mapping[str, Any], path: str = "friction") -> FrictionModel:
    """Build a friction model from its YAML mapping.

    Parameters
    ----------
    spec : mapping
        ``{"model": <tag>, <parameter>: <value>, ...}`` in SI units.
    path : str
        Key path used in error messages.

    Raises
    ------
    ConfigError
        Unknown tag, unknown keys, missing keys or out-of-range values, all at once, each naming its key.
    """
    problems: list[str] = []
    model = parse_friction(spec, path, problems)
    if problems or model is None:
        raise ConfigError(problems or [f"{path}: invalid friction model"])
    return model


def parse_friction(value: Any, path: str, problems: list[str]) -> FrictionModel | None:
    """``stagectl.schema`` parse hook for a ``friction:`` field (returns a built model)."""
    if isinstance(value, FrictionModel):
        return value
    if not isinstance(value, Mapping):
        problems.append(f"{path}: expected a mapping with a 'model:' tag, got {short(value)}")
        return None
    tag = value.get("model")
    reg = registry()
    if tag is None:
        problems.append(f"{path}.model: required key missing (the friction model tag, one of: "
                        f"{', '.join(sorted(reg))})")
        return None
    if not isinstance(tag, str) or tag not in reg:
        problems.append(f"{path}.model: unknown friction model {short(tag)} "
                        f"(known: {', '.join(sorted(reg))})")
        return None
    cls = reg[tag]
    rest = {k: v for k, v in value.items() if k != "model"}
    n_before = len(problems)
    try:
        params = load(cls.Params, rest, path)
    except ConfigError as exc:
        problems.extend(exc.problems)
        return None
    if len(problems) > n_before:
        return None
    return cls(params)


#: ``stagectl.schema`` parse hook for an ``effects:`` field (an :class:`Effects` instance passes through)
parse_effects = section_parser(Effects)


@dataclass(frozen=True)
class Backlash:
    """Play between motor and load (ball-screw nut, gear lash); see :mod:`stagectl.sim.backlash`."""

    gap_m: float = param(unit="m", desc="total play b between motor and load", ge=0.0, le=0.01)
    other_mass_kg: float = param(unit="kg", desc="mass of the side without friction (the motor side when "
                                 "friction_side is load); part of mass_kg, which stays the total", gt=0.0)
    friction_side: str = param("load", unit="", desc="side carrying the friction and effects: load or motor",
                               choices=("load", "motor"))
    sensor_side: str = param("motor", unit="", desc="side the position sensor reads: motor or load",
                             choices=("motor", "load"))


@dataclass(frozen=True)
class StageModel:
    """A stage's physical model: rigid-body mass, friction model and additional effects."""

    friction: FrictionModel = param(desc="friction model (model: tag + parameters)", parse=parse_friction)
    effects: Effects = param(default_factory=Effects, desc="additional effects", parse=parse_effects)
    mass_kg: float | None = param(None, unit="kg", desc="moving mass", gt=0.0)
    backlash: Backlash | None = param(None, desc="play between motor and load (a plant structure; the "
                                      "feed-forward ignores it)")
    meta: dict[str, Any] = param(default_factory=dict, desc="free-form provenance (fit quality, source)")

    def __post_init__(self) -> None:
        bl = self.backlash
        if bl is not None and self.mass_kg is not None and bl.other_mass_kg >= self.mass_kg:
            raise ValueError(f"backlash.other_mass_kg: {bl.other_mass_kg:.6g} kg must be below the total moving "
                             f"mass mass_kg = {self.mass_kg:.6g} kg (it is a part of it)")

    def spec(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        if self.mass_kg is not None:
            out["mass_kg"] = float(self.mass_kg)
        out["friction"] = self.friction.spec()
        eff = self.effects.spec()
        if eff:
            out["effects"] = eff
        if self.backlash is not None:
            b = self.backlash
            out["backlash"] = {"gap_m": float(b.gap_m), "other_mass_kg": float(b.other_mass_kg),
                               "friction_side": b.friction_side, "sensor_side": b.sensor_side}
        if self.meta:
            out["meta"] = self.meta
        return out


def load_model_file(path: str | Path) -> StageModel:
    """Load a model file (see module docstring). A bare friction mapping (with ``model:``) is accepted too."""
    data = load_yaml_file(path)
    if data is not None and not isinstance(data, Mapping):
        raise ConfigError(f"{path}: expected a model file mapping (mass_kg, friction, effects, meta), "
                          f"got {type(data).__name__} {data!r:.60}")
    if isinstance(data, Mapping) and "model" in data and "friction" not in data:
        data = {"friction": data}
    if isinstance(data, Mapping) and "friction" not in data and {"controller", "io", "sim"} & set(data):
        raise ConfigError(_stage_config_given(path, data))
    try:
        return load(StageModel, data, "")
    except ConfigError as exc:
        raise ConfigError([f"{path}: {p}" for p in exc.problems]) from None


def _stage_config_given(path: str | Path, data: Mapping[str, Any]) -> str:
    """The one line for a stage config (``controller:``/``io:``/``sim:``) given where a model file belongs,
    naming the model file the config uses (relative names resolved against the config's folder)."""
    named = []
    for keys in (("controller", "feedforward", "model_file"), ("sim", "plant", "model_file")):
        node: Any = data
        for k in keys:
            node = node.get(k) if isinstance(node, Mapping) else None
        if isinstance(node, str) and node:
            p = Path(node) if Path(node).is_absolute() else Path(path).resolve().parent / node
            named.append(f"{'.'.join(keys)} is {p}")
    hint = f"; its {named[0]}" if named else ""
    return (f"{path}: is a stage config, not a model file; expected a friction model file (mass_kg, friction, "
            f"effects, meta){hint}")


def save_model_file(model: StageModel, path: str | Path, header: str = "") -> None:
    """Write a model file that :func:`load_model_file` reads back to an equal model.

    Whole or not at all: the text goes to a temporary file beside it, which then replaces ``path`` (an
    interrupt, Ctrl-C or SIGTERM, while writing over the model a config uses left that file empty)."""
    import os
    import stat
    import tempfile

    import yaml

    text = yaml.safe_dump(model.spec(), sort_keys=False, default_flow_style=None)
    if header:
        text = "".join(f"# {line}\n" for line in header.splitlines()) + text
    p = Path(path).resolve() if Path(path).is_symlink() else Path(path)  # (through a link, as open() writes)
    if p.exists() and not p.is_file():  # a device (/dev/full, /dev/stdout) or a pipe: written to, never replaced
        p.write_text(text, encoding="utf-8")
        return
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    except PermissionError:  # a writable file in a directory we may not create in: in place, as before
        if not p.is_file():
            raise
        p.write_text(text, encoding="utf-8")
        return
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.chmod(tmp, stat.S_IMODE(os.stat(p).st_mode) if p.exists() else 0o644)  # (mkstemp: 0600)
        os.replace(tmp, p)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise



# the model modules: each registers its classes with base.register on import
from stagectl.friction import dahl, gms, hsieh, lugre, maxwell, static  # noqa: E402,F401
