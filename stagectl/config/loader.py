"""The one loading pipeline: YAML → schema → model files resolved once → cross-checks.

:func:`load_app_config` is *the* validation: ``stagectl check-config``, ``stagectl run``, ``simulate`` and
the daemon (start-up and SIGHUP reload) all call it. Every problem is reported at once with its key path
and unit (unknown keys included, with a "did you mean" hint), each prefixed with the file name.

Steps:

1. ``yaml.safe_load`` (:func:`stagectl.schema.load_yaml_file`);
2. the model files named in the file (``sim.plant.model_file``, ``controller.feedforward.model_file``),
   relative to the YAML file's directory, are loaded once each into :class:`~stagectl.friction.StageModel`
   objects (:class:`ModelFiles`);
3. the schema builds the typed sections; the plant is merged over its model
   (:meth:`stagectl.sim.plant.PlantConfig.from_mapping`) and the controller receives its resolved model in
   ``controller.feedforward.model`` (:func:`stagectl.control.controller.resolve_model`);
4. the cross-checks of :mod:`stagectl.config.checks` (force-limit chain, ``can:`` keys, scenario, controller).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from stagectl.config.checks import cross_checks
from stagectl.config.sections import AppConfig
from stagectl.control.controller import resolve_model
from stagectl.errors import ConfigError
from stagectl.friction import StageModel, load_model_file
from stagectl.schema import load, load_yaml_file
from stagectl.sim.world import SimWorldConfig

__all__ = ["ModelFiles", "load_app_config", "parse_app_config", "parse_sim_section"]


class ModelFiles:
    """The model files of one configuration, each read once (relative paths against ``base_dir``)."""

    def __init__(self, base_dir: Path | None) -> None:
        self.base_dir = base_dir
        self._loaded: dict[Path, StageModel | ConfigError] = {}

    def path_of(self, value: str | Path) -> Path:
        p = Path(value)
        return p if p.is_absolute() or self.base_dir is None else self.base_dir / p

    def load(self, value: Any, key: str, problems: list[str]) -> StageModel | None:
        """The model of file ``value`` named by ``key`` (None: no file, or a problem appended)."""
        if value is None:
            return None
        if not isinstance(value, (str, Path)):
            problems.append(f"{key}: expected a path string, got {value!r}")
            return None
        p = self.path_of(value)
        if p not in self._loaded:
            try:
                self._loaded[p] = load_model_file(p)
            except ConfigError as exc:
                self._loaded[p] = exc
        got = self._loaded[p]
        if isinstance(got, ConfigError):
            problems.extend(f"{key}: {msg}" for msg in got.problems)
            return None
        return got


def _get(data: Any, *keys: str) -> Any:
    """``data[k0][k1]...`` of a raw mapping, None where a level is missing or not a mapping."""
    for k in keys:
        if not isinstance(data, Mapping):
            return None
        data = data.get(k)
    return data


def parse_sim_section(data: Any, models: ModelFiles, problems: list[str],
                      path: str = "sim") -> SimWorldConfig | None:
    """The ``sim:`` mapping → :class:`~stagectl.sim.world.SimWorldConfig`, its plant merged over the model of
    ``sim.plant.model_file`` (loaded through ``models``). Problems are appended; None on any."""
    if data is None:
        return None
    if not isinstance(data, Mapping):
        problems.append(f"{path}: expected a mapping, got {data!r}")
        return None
    n0 = len(problems)
    model_file = _get(data, "plant", "model_file")
    model = models.load(model_file, f"{path}.plant.model_file", problems)
    if len(problems) > n0:
        return None  # the model file's own error says why; no follow-up noise
    try:
        return SimWorldConfig.from_mapping(data, path, plant_model=model)
    except ConfigError as exc:
        problems.extend(exc.problems)
        return None


def parse_app_config(data: Any, path: str | Path | None = None) -> AppConfig:
    """Validate a plain mapping (what ``yaml.safe_load`` returned) into an :class:`AppConfig`.

    Relative model paths are taken relative to ``path``'s directory (the current directory without one).

    Raises
    ------
    ConfigError
        Every problem found, each with its key path (and the file name when ``path`` is given).
    """
    p = Path(path).resolve() if path is not None else None
    models = ModelFiles(p.parent if p is not None else None)
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"{p or '<config>'}: expected a mapping at the top level, got {type(data).__name__}")
    problems: list[str] = []
    rest = {k: v for k, v in data.items() if k not in ("sim", "path")}
    if "path" in data:
        problems.append("path: unknown key")
    sim_given = data.get("sim") is not None
    sim = parse_sim_section(data.get("sim"), models, problems)
    ff_model = models.load(_get(data, "controller", "feedforward", "model_file"),
                           "controller.feedforward.model_file", problems)
    cfg: AppConfig | None = None
    try:
        cfg = load(AppConfig, rest, "")
    except ConfigError as exc:
        problems.extend(exc.problems)
    if cfg is not None and not (sim_given and sim is None):
        ctl = cfg.controller
        ff = dataclasses.replace(ctl.feedforward, model=resolve_model(ctl, ff_model))
        cfg = dataclasses.replace(cfg, controller=dataclasses.replace(ctl, feedforward=ff), sim=sim, path=p)
        if not problems:
            problems.extend(cross_checks(cfg))
    if problems or cfg is None:
        prefix = f"{p.name}: " if p is not None else ""
        raise ConfigError([prefix + m for m in problems] or [f"{prefix}invalid configuration"])
    return cfg


def load_app_config(path: str | Path) -> AppConfig:
    """Read and validate a stagectl YAML file (the validation ``check-config`` and the daemon run).

    Raises
    ------
    ConfigError
        File/syntax errors, or every validation problem at once (each prefixed with the file name).
    """
    return parse_app_config(load_yaml_file(path), path)
