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

from stagectl.config.daemon import DaemonConfig, TelemetryConfig, load_daemon_config
from stagectl.config.loader import ModelFiles, load_app_config, parse_app_config, parse_sim_section
from stagectl.config.sections import AppConfig, DemoConfig, IoConfig, IoKind, SensorSource

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
