"""Glue between the service and the application: the same validation as ``check-config``, and assembly.

* :func:`load_configs` — :func:`stagectl.config.load_app_config` (every problem at once, with paths and
  units), plus the ``daemon:`` section (:class:`~stagectl.config.daemon.DaemonConfig`) it contains.
* :func:`build_assembly` — :func:`stagectl.app.build_stage` on the real monotonic clock, with the
  ``loop.realtime`` settings applied in the loop thread. The returned :class:`~stagectl.app.Stage` provides
  what :class:`~stagectl.daemon.service.Assembly` describes (``loop``, ``close``, ``controller_config``,
  ``simulated``, ``inject_fault``, ``describe``). The reference holds position until a client moves it.
"""

from __future__ import annotations

from pathlib import Path

from stagectl.app import Stage, build_stage
from stagectl.config import AppConfig, DaemonConfig, load_app_config


def load_configs(path: Path) -> tuple[AppConfig, DaemonConfig]:
    """Validate the YAML file exactly like ``stagectl check-config``. Raises ConfigError."""
    cfg = load_app_config(path)
    return cfg, cfg.daemon


def build_assembly(cfg: AppConfig) -> Stage:
    """Open and configure the devices and build the loop (real time). Raises StageError subclasses."""
    return build_stage(cfg)
