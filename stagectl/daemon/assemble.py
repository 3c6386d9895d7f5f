"""Glue between the service and the application: the same validation as ``check-config``, and assembly.

* :func:`load_configs` — :func:`stagectl.config.load_app_config` (every problem at once, with paths and
  units), plus the ``daemon:`` section (:class:`~stagectl.daemon.config.DaemonConfig`) it contains.
* :func:`build_assembly` — :func:`stagectl.app.build_stage` on the real monotonic clock, with the
  ``loop.realtime`` settings applied in the loop thread. The returned ``Stage`` provides what
  :class:`~stagectl.daemon.service.Assembly` describes (``loop``, ``close``, ``controller_config``,
  ``simulated``, ``inject_fault``, ``describe``). The reference holds position until a client moves it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from stagectl.daemon.config import DaemonConfig


def load_configs(path: Path) -> tuple[Any, DaemonConfig]:
    """Validate the YAML file exactly like ``stagectl check-config``. Raises ConfigError."""
    from stagectl.config import load_app_config

    cfg = load_app_config(path)
    daemon = getattr(cfg, "daemon", None)
    if not isinstance(daemon, DaemonConfig):
        daemon = DaemonConfig()
    return cfg, daemon


def build_assembly(cfg: Any) -> Any:
    """Open and configure the devices and build the loop (real time). Raises StageError subclasses."""
    from stagectl.app import build_stage

    return build_stage(cfg)
