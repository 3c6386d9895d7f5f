"""Application configuration: one YAML file → typed, frozen sections, validated before any hardware is opened.

Public API:

* :func:`load_app_config` ``(path) -> AppConfig`` and :func:`parse_app_config` ``(data, path=None) -> AppConfig``:
  the one loading pipeline (:mod:`stagectl.config.loader`) that ``check-config``, ``run``, ``simulate`` and the
  daemon all call;
* :class:`AppConfig` and its sections (:mod:`stagectl.config.sections`), :class:`DaemonConfig`
  (:mod:`stagectl.config.daemon`);
* the cross-checks (:mod:`stagectl.config.checks`): force-limit chain, ``can:`` keys, scenario, controller.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from stagectl.config.daemon import DaemonConfig, TelemetryConfig, load_daemon_config

if TYPE_CHECKING:
    from stagectl.config.loader import ModelFiles, load_app_config, parse_app_config, parse_sim_section
    from stagectl.config.sections import AppConfig, DemoConfig, IoConfig, IoKind, SensorSource

#: names served on first use (PEP 562): the loader and the sections import the controller, plant and driver
#: configurations (numpy, numba, canopen: about 1 s), which a control-socket client importing
#: :mod:`stagectl.config.daemon` must not pay for
_LAZY = {
    "ModelFiles": "loader", "load_app_config": "loader", "parse_app_config": "loader",
    "parse_sim_section": "loader",
    "AppConfig": "sections", "DemoConfig": "sections", "IoConfig": "sections", "IoKind": "sections",
    "SensorSource": "sections",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'stagectl.config' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"stagectl.config.{module}"), name)
    globals()[name] = value
    return value

__all__ = [
    "AppConfig",
    "DaemonConfig",
    "DemoConfig",
    "IoConfig",
    "IoKind",
    "ModelFiles",
    "SensorSource",
    "TelemetryConfig",
    "load_app_config",
    "load_daemon_config",
    "parse_app_config",
    "parse_sim_section",
]
