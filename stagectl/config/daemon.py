"""Daemon settings: the ``daemon:`` section of the stagectl YAML (control socket, watchdog, telemetry).

Example (every key optional; the defaults are shown)::

    daemon:
      socket_name: control.sock        # in the runtime directory (/run/stagectl under systemd)
      socket_group: null               # group of the socket file; null = the daemon's group (unit Group=)
      max_clients: 32
      max_line_bytes: 65536
      client_idle_timeout_s: 600
      reply_timeout_s: 5
      ready_timeout_s: 10              # drive enabled + loop healthy within this, or start-up fails
      status_interval_s: 1             # STATUS= updates
      allow_fault_injection: false     # `fault` debug request; only honoured on a simulated plant
      isolation: process               # the loop in its own process (docs/daemon.md); thread: in the daemon
      health: auto                     # auto | realtime | liveness (docs/daemon.md)
      observer_socket_name: observer.sock   # read-only: status, gains, telemetry; null = none
      observer_group: null
      telemetry:
        enabled: true
        directory: null                # null: $STATE_DIRECTORY/telemetry, else <runtime dir>/telemetry
        continuous: true               # always-on rotating files (besides named recordings)
        buffer_s: 60                   # ring capacity = buffer_s / period_s rows
        rotate_mb: 100
        rotate_s: 3600
        keep_files: 48
        flush_interval_s: 0.2
        on_error: report               # unwritable directory at start: report (run, say so) | refuse
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from stagectl.schema import load, param


@dataclass(frozen=True)
class TelemetryConfig:
    """Telemetry recording (CSV per docs/recordings.md)."""

    enabled: bool = param(True, desc="record telemetry at all")
    directory: str | None = param(
        None, desc="directory of telemetry files; null = $STATE_DIRECTORY/telemetry or <runtime dir>/telemetry"
    )
    continuous: bool = param(True, desc="write rotating files continuously (named recordings work either way)")
    buffer_s: float = param(60.0, unit="s", desc="ring buffer length in loop time (backlog the writer may lag)",
                            ge=1.0, le=3600.0)
    rotate_mb: float = param(100.0, unit="MB", desc="start a new continuous file after this size", gt=0)
    rotate_s: float = param(3600.0, unit="s", desc="start a new continuous file after this age (0 = never)", ge=0)
    keep_files: int = param(48, desc="continuous files kept; older ones are deleted (0 = keep all)", ge=0)
    flush_interval_s: float = param(0.2, unit="s", desc="writer wake-up / flush interval", gt=0, le=10)
    retry_s: float = param(5.0, unit="s", desc="retry interval after a write error (full disk...)", gt=0)
    on_error: str = param(
        "report", choices=("report", "refuse"),
        desc="telemetry directory not writable at start: report = run, say so in READY/STATUS/status and the "
        "journal, count every row as lost; refuse = do not start (exit 1)")


@dataclass(frozen=True)
class DaemonConfig:
    """Service shell settings."""

    socket_name: str = param("control.sock", desc="control socket file name inside the runtime directory")
    socket_group: str | None = param(None, desc="group owning the control socket; null = the daemon's group")
    max_clients: int = param(32, desc="simultaneous control connections", ge=1, le=1024)
    max_line_bytes: int = param(65536, unit="B", desc="longest accepted request line", ge=256)
    max_out_bytes: int = param(1 << 20, unit="B", desc="reply bytes queued for a client before it is dropped",
                               ge=4096)
    client_idle_timeout_s: float = param(600.0, unit="s", desc="close connections idle this long", gt=0)
    reply_timeout_s: float = param(5.0, unit="s", desc="longest wait for the loop to apply a request", gt=0)
    ready_timeout_s: float = param(10.0, unit="s", desc="time for the loop to become healthy at start", gt=0)
    status_interval_s: float = param(1.0, unit="s", desc="interval of STATUS= updates to systemd", gt=0)
    stop_timeout_s: float = param(5.0, unit="s", desc="budget for stopping the loop and flushing on SIGTERM",
                                  gt=0)
    allow_fault_injection: bool = param(False, desc="accept the `fault` debug request (simulated plants only)")
    isolation: str = param(
        "process", choices=("process", "thread"),
        desc="process = the loop runs in its own process that owns the devices (shared-memory rings to the "
        "daemon; no client can take its interpreter lock); thread = a thread of the daemon (tests, debugging)")
    health: str = param(
        "auto", choices=("auto", "realtime", "liveness"),
        desc="what READY and the watchdog require: realtime = cycling with at most loop.healthy_overrun_fraction "
        "skipped slots; liveness = cycling (late cycles lose nothing on a simulated stage); auto = liveness for a "
        "simulated stage, realtime for real devices")
    observer_socket_name: str | None = param(
        "observer.sock", desc="read-only socket (status, gains, telemetry stream) in the runtime directory; "
        "null = none")
    observer_group: str | None = param(None, desc="group owning the observer socket; null = the daemon's group")
    telemetry: TelemetryConfig = param(default_factory=TelemetryConfig, desc="telemetry recording")


def load_daemon_config(section: Mapping[str, Any] | None, path: str = "daemon") -> DaemonConfig:
    """Build :class:`DaemonConfig` from the ``daemon:`` mapping (None = defaults). Raises ConfigError."""
    return load(DaemonConfig, dict(section or {}), path=path)
