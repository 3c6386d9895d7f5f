"""Refuse to commission a stage the daemon is driving.

The daemon keeps a run marker (:class:`stagectl.daemon.marker.RunMarker`, ``stagectl.running`` with its pid
and configuration) in its state directory, else its runtime directory (:class:`stagectl.daemon.paths.
ServicePaths`), while the drive may be enabled. Commissioning refuses to start while such a marker names a
live process whose configuration drives the same devices: the same file, or the same CAN bus (interface,
channel, host, port) and drive node id, or the same interferometer URL. Two simulated stages never collide
(each has its own plant).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from stagectl.config import AppConfig, IoKind, load_app_config
from stagectl.daemon.marker import RunMarker
from stagectl.daemon.paths import ServicePaths
from stagectl.errors import StageError


def device_keys(cfg: AppConfig) -> set[str]:
    """Identities of the real devices a configuration opens (empty for a simulated stage)."""
    if cfg.io.kind is not IoKind.CANOPEN:
        return set()
    keys: set[str] = set()
    for dev in (cfg.io.drive, cfg.io.encoder):
        if dev is not None:
            can: dict[str, Any] = dict(dev.can)
            bus = ",".join(f"{k}={can.get(k)}" for k in ("interface", "channel", "host", "port"))
            keys.add(f"can[{bus}] node {dev.node_id}")
    if cfg.io.interferometer is not None:
        keys.add(f"serial {cfg.io.interferometer.url}")
    return keys


def _alive(pid: Any) -> bool:
    try:
        os.kill(int(pid), 0)
    except (OSError, ValueError, TypeError):
        return False
    return True


def check_daemon(cfg: AppConfig, runtime_dir: str | None, state_dir: str | None) -> None:
    """Raise StageError (one line) while a live daemon holds the devices of ``cfg`` (module docstring)."""
    paths = ServicePaths.from_env(cfg.path or "-", runtime_dir, state_dir)
    marker = RunMarker(paths.marker_dir)
    info = marker.read()
    if info is None or not _alive(info.get("pid")):
        return
    other = info.get("config")
    same_file = other is not None and cfg.path is not None and Path(other).resolve() == cfg.path.resolve()
    shared: set[str] = set()
    if not same_file and other is not None:
        try:
            shared = device_keys(cfg) & device_keys(load_app_config(other))
        except (StageError, OSError):
            shared = device_keys(cfg)  # an unreadable configuration: assume it may hold them
    if same_file or shared:
        what = "the same configuration" if same_file else ", ".join(sorted(shared))
        raise StageError(f"the daemon (pid {info.get('pid')}, marker {marker.path}) holds {what}; stop it first "
                         "(systemctl stop stagectl) or give its --runtime-dir/--state-dir if it runs elsewhere")
