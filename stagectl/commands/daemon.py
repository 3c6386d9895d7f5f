"""``stagectl daemon --config FILE [--runtime-dir DIR] [--state-dir DIR]``: the systemd service entry point.

Validates the configuration exactly like ``stagectl check-config``, starts the loop process (which opens and
configures the devices and runs nothing but the loop; docs/daemon.md), and sends ``READY=1`` to systemd once
the drive is enabled and the loop is healthy. Runs until
SIGTERM/SIGINT (exit 0 after stopping motion, disabling the drive and flushing telemetry); SIGHUP reloads the
controller tuning. Exit codes: 0 clean stop, 1 runtime failure, 2 invalid configuration.

Directories: ``--runtime-dir`` (control socket) defaults to ``$RUNTIME_DIRECTORY`` (set by the unit's
``RuntimeDirectory=``) or ``/run/stagectl``; telemetry goes to ``daemon.telemetry.directory``, else
``--state-dir``/``$STATE_DIRECTORY`` + ``/telemetry``, else ``<runtime dir>/telemetry``.
"""

from __future__ import annotations

import argparse
import logging
import sys

from stagectl.daemon.logging import DaemonLogging
from stagectl.daemon.service import StageService


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("daemon", help="run the control service (systemd Type=notify; see systemd/stagectl.service)")
    p.add_argument("--config", required=True, metavar="FILE", help="stagectl YAML (e.g. /etc/stagectl/stagectl.yaml)")
    p.add_argument("--runtime-dir", metavar="DIR", default=None,
                   help="directory of the control socket (default: $RUNTIME_DIRECTORY or /run/stagectl)")
    p.add_argument("--state-dir", metavar="DIR", default=None,
                   help="state directory; telemetry goes to DIR/telemetry (default: $STATE_DIRECTORY)")
    p.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"),
                   help="log level (default info)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # the assembly (numpy, numba, canopen: ~1 s) only where the daemon runs, not for `stagectl --help`
    from stagectl.daemon.assemble import build_assembly, load_configs

    logs = DaemonLogging(logging.getLevelNamesMapping()[args.log_level.upper()])
    # The loop thread must get the GIL back quickly from helper threads (telemetry formatting, JSON):
    # the default 5 ms switch interval would show up as 5 ms of lateness.
    sys.setswitchinterval(2.5e-4)
    try:
        # the service reads $RUNTIME_DIRECTORY / $STATE_DIRECTORY itself (ServicePaths.from_env, once)
        svc = StageService(args.config, args.runtime_dir, load_config=load_configs, build=build_assembly,
                           state_dir=args.state_dir)
        return svc.run()
    finally:
        logs.close()
