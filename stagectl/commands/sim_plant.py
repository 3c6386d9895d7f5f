"""``stagectl sim-plant --config FILE``: run the virtual devices of the file's ``sim:`` section as their own
process, behind a socketcand server on loopback TCP (and the serial interferometer, if configured).

Prints exactly one ready line (JSON) on stdout once everything listens, e.g.::

    {"ready": true, "pid": 1234, "transport": "socketcand",
     "can": {"interface": "socketcand", "host": "127.0.0.1", "port": 29536, "channel": "can0"},
     "drive_node_id": 1}

and runs until SIGTERM or SIGINT, then stops cleanly (exit 0).

Two timings. Default: real time (device time = wall clock; the drive steps the plant at each SYNC and on its
own clock while SYNC is missing). ``--lockstep``: simulated time driven by the client's SYNC frames; each SYNC
advances the plant by exactly one communication cycle period and nothing happens between frames, so a client
that waits for each answer (``stagectl commission --lockstep``) runs deterministically and faster than real
time. The ready line then says ``"lockstep": true``.
"""

from __future__ import annotations

import argparse
import threading

from stagectl.commands.args import number


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("sim-plant", help="run the virtual CANopen/serial devices as their own process")
    p.add_argument("--config", required=True, help="YAML file with a sim: section")
    p.add_argument("--port", type=number("(TCP port)", lo=0, hi=65535, integer=True), default=None, help="override sim.transport.port (0 = ephemeral)")
    p.add_argument("--lockstep", action="store_true",
                   help="simulated time: each SYNC from the client advances the plant by one period (for "
                        "`stagectl commission --lockstep`); default real time")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import signal

    stop = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        stop.set()

    # first thing: a SIGTERM during the (seconds long) start-up must also end cleanly with exit 0
    old = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        return _serve(args, stop)
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def _serve(args: argparse.Namespace, stop: threading.Event) -> int:
    import dataclasses
    import json
    import os
    import sys
    from pathlib import Path

    from stagectl.config import ModelFiles, parse_sim_section
    from stagectl.errors import ConfigError
    from stagectl.schema import load_yaml_file
    from stagectl.sim.world import SimWorld

    path = Path(args.config)
    data = load_yaml_file(path)
    if not isinstance(data, dict) or "sim" not in data:
        raise ConfigError(f"{path}: no sim: section (the virtual devices to run)")
    problems: list[str] = []
    cfg = parse_sim_section(data["sim"], ModelFiles(path.resolve().parent), problems)
    if cfg is None:
        raise ConfigError([f"{path.name}: {p}" for p in problems])
    tr = cfg.transport
    if tr.kind != "socketcand" or args.port is not None:
        port = tr.port if args.port is None else args.port
        tr = dataclasses.replace(tr, kind="socketcand", port=port)
        cfg = dataclasses.replace(cfg, transport=tr)
    world = SimWorld.from_config(cfg, base_dir=path.resolve().parent)
    if stop.is_set():  # terminated during start-up
        return 0
    try:
        lockstep = bool(getattr(args, "lockstep", False))
        world.start(lockstep=lockstep)
        info = {"ready": True, "pid": os.getpid(), **world.ready_info(), "lockstep": lockstep}
        sys.stdout.write(json.dumps(info) + "\n")
        sys.stdout.flush()
        while not stop.wait(0.5):
            pass
    finally:
        world.stop()
    return 0
