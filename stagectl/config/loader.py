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
   (:meth:`stagectl.world_schema.PlantConfig.from_mapping`) and the controller receives its resolved model in
   ``controller.feedforward.model`` (:func:`stagectl.control.controller.resolve_model`);
4. the cross-checks of :mod:`stagectl.config.checks` (force-limit chain, ``can:`` keys, scenario, controller,
   drivers vs the simulated devices), each run whenever the sections it reads parsed, also when another
   section has problems (then on the sections parsed one by one).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from stagectl.config.checks import Sections, cross_checks
from stagectl.config.sections import AppConfig, DemoConfig, IoConfig
from stagectl.control.controller import ControllerConfig, resolve_model
from stagectl.errors import ConfigError, short
from stagectl.friction import StageModel, load_model_file
from stagectl.safety import SafetyConfig
from stagectl.schema import load, load_yaml_file, yaml_kind

if TYPE_CHECKING:
    from stagectl.world_schema import SimWorldConfig

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
            problems.append(f"{key}: expected a path string, got {short(value)}")
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
    """The ``sim:`` mapping → :class:`~stagectl.world_schema.SimWorldConfig`, its plant merged over the model of
    ``sim.plant.model_file`` (loaded through ``models``). Problems are appended; None on any."""
    if data is None:
        return None
    if not isinstance(data, Mapping):
        problems.append(f"{path}: expected a mapping, got {short(data)}")
        return None
    from stagectl.world_schema import SimWorldConfig  # here: a config without sim: never imports it

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


T = TypeVar("T")


def _try_section(cls: type[T], data: Mapping[str, Any], key: str, *, required: bool = False) -> T | None:
    """The section ``key`` of ``data`` parsed alone, or None when it has problems (the full parse reports them)
    or is ``required`` and missing."""
    if required and data.get(key) is None:
        return None
    try:
        return load(cls, data.get(key), key)
    except ConfigError:
        return None


def _with_model(ctl: ControllerConfig, model: StageModel | None) -> ControllerConfig:
    """The controller section with its resolved model in ``feedforward.model``."""
    return dataclasses.replace(ctl, feedforward=dataclasses.replace(ctl.feedforward,
                                                                    model=resolve_model(ctl, model)))


def parse_app_config(data: Any, path: str | Path | None = None) -> AppConfig:
    """Validate a plain mapping (what ``yaml.safe_load`` returned) into an :class:`AppConfig`.

    Relative model paths are taken relative to ``path``'s directory (the current directory without one).
    Every cross-check whose sections parsed runs even when other sections have problems, so all problems are
    reported at once.

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
        raise ConfigError(f"{p or '<config>'}: expected a mapping at the top level, got {yaml_kind(data)}")
    if "friction" in data and not any(k in data for k in ("safety", "controller", "io", "loop", "sim")):
        # a model file where the stage config belongs: one line instead of one per unknown/missing key
        raise ConfigError(f"{p or '<config>'}: is a friction model file, not a stage config; a stage config has "
                          "safety:, controller:, io:/sim: sections and names this file as "
                          "controller.feedforward.model_file or sim.plant.model_file (e.g. config/sim.yaml)")
    problems: list[str] = []
    rest = {k: v for k, v in data.items() if k not in ("sim", "path")}
    if "path" in data:
        problems.append("path: unknown key")
    sim_given = data.get("sim") is not None
    sim = parse_sim_section(data.get("sim"), models, problems)
    n0 = len(problems)
    ff_model = models.load(_get(data, "controller", "feedforward", "model_file"),
                           "controller.feedforward.model_file", problems)
    ff_ok = len(problems) == n0  # else the controller's model is unknown: no follow-up "needs a model"
    cfg: AppConfig | None = None
    try:
        cfg = load(AppConfig, rest, "")
    except ConfigError as exc:
        problems.extend(exc.problems)
    if cfg is not None:
        cfg = dataclasses.replace(cfg, controller=_with_model(cfg.controller, ff_model), sim=sim, path=p)
        sections = Sections.of(cfg)
    else:  # the sections that parsed on their own
        ctl = _try_section(ControllerConfig, rest, "controller", required=True)
        sections = Sections(safety=_try_section(SafetyConfig, rest, "safety", required=True),
                            controller=_with_model(ctl, ff_model) if ctl is not None else None,
                            io=_try_section(IoConfig, rest, "io"), demo=_try_section(DemoConfig, rest, "demo"),
                            sim=sim)
    sections = dataclasses.replace(sections, sim_absent=not sim_given,
                                   controller=sections.controller if ff_ok else None)
    problems.extend(cross_checks(sections))
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
