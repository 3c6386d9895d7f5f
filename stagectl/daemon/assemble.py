"""Glue between the service and the application: the same validation as ``check-config``, and assembly.

* :func:`load_configs` — :func:`stagectl.config.load_app_config` (every problem at once, with paths and
  units), plus the ``daemon:`` section (:class:`~stagectl.config.daemon.DaemonConfig`) it contains.
* :func:`build_assembly` — :func:`stagectl.app.build_stage` on the real monotonic clock, with the
  ``loop.realtime`` settings applied in the loop thread, handed to the service as its
  :class:`~stagectl.daemon.service.Assembly` (``loop``, ``close``, ``controller_config``, ``simulated``,
  ``inject_fault``, ``describe``). The reference holds position until a client moves it.
"""

from __future__ import annotations

from pathlib import Path

from stagectl.app import build_stage
from stagectl.config import AppConfig, DaemonConfig, load_app_config
from stagectl.daemon.lifecycle import Assembly


def load_configs(path: Path) -> tuple[AppConfig, DaemonConfig]:
    """Validate the YAML file exactly like ``stagectl check-config``. Raises ConfigError."""
    cfg = load_app_config(path)
    return cfg, cfg.daemon


def build_assembly(cfg: AppConfig) -> Assembly:
    """Open and configure the devices and build the loop (real time). Raises StageError subclasses."""
    stage = build_stage(cfg)
    return Assembly(loop=stage.loop, close=stage.close, controller_config=stage.controller_config,
                    simulated=stage.simulated, inject_fault=stage.inject_fault if stage.simulated else None,
                    describe=stage.describe)
