"""``stagectl bench loop``: real-time loop timing on the embedded simulated stage.

Runs the same :class:`~stagectl.loop.ControlLoop` as ``stagectl run`` (MonotonicClock, absolute-deadline
``clock_nanosleep``, ``loop.realtime`` settings: timer slack 1 ns, gc.freeze, optional FIFO/affinity/mlock)
at the config's rate (1 kHz in config/sim.yaml) for ``--duration`` seconds of wall time (with virtual
devices served by the loop thread, loop time advances one period per executed cycle and lags the wall
clock by the skipped slots), with the demo motion
on the embedded plant and every cycle's telemetry row appended to an in-memory recorder. Reports wake-up
lateness (now − deadline) p50/p99/max, loop execution time per cycle, overruns (skipped slots) and CPU
(loop thread and whole process, fraction of one core). Targets: lateness p99 ≤ 100 µs, overruns ≤ 0.1 %.
Timing is measured, never asserted in tests; the machine's load is reported alongside (``os.getloadavg``).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import threading
import time
from pathlib import Path
from typing import Any

# The assembly, config and controller stack (numpy, numba, canopen: about 1 s) are imported where the benchmark
# runs: `stagectl --help` builds every command's parser, and with it this module's arguments.

REPO_CONFIG = Path(__file__).resolve().parents[2] / "config" / "sim.yaml"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default=str(REPO_CONFIG), help="config (default config/sim.yaml)")
    p.add_argument("--duration", type=float, default=30.0, help="seconds of real time (default 30)")
    p.add_argument("--io", choices=("config", "plant_io", "embedded_canopen"), default="config",
                   help="override io.kind (default: as in the config)")
    p.add_argument("--fifo", type=int, default=None, help="SCHED_FIFO priority (needs privileges)")
    p.add_argument("--spin-us", type=float, default=None, help="hybrid wake-up: busy-wait the last N µs")


def run(args: argparse.Namespace) -> dict[str, Any]:
    from stagectl.app import build_stage
    from stagectl.config import IoKind, load_app_config
    from stagectl.recorder import Recorder

    cfg = load_app_config(args.config)
    rt = cfg.loop.realtime
    if args.fifo is not None:
        rt = dataclasses.replace(rt, fifo_priority=args.fifo)
    if args.spin_us is not None:
        rt = dataclasses.replace(rt, spin_us=args.spin_us)
    io = cfg.io if args.io == "config" else dataclasses.replace(cfg.io, kind=IoKind(args.io))
    cfg = dataclasses.replace(cfg, loop=dataclasses.replace(cfg.loop, realtime=rt), io=io)
    load0 = os.getloadavg()
    cpu0 = time.process_time()
    wall0 = time.monotonic()
    with build_stage(cfg) as stage:
        stage.load_scenario(cfg.demo.scenario, repeat=True)
        rec = Recorder(stage.loop.columns, int(args.duration / cfg.loop.period_s) + 1024)
        stage.loop.add_sink(rec)
        stop = threading.Event()
        timer = threading.Timer(args.duration, stop.set)  # wall-clock bound (loop time may lag it, see below)
        t_run = time.monotonic()
        cpu_run = time.process_time()
        timer.start()
        try:
            res = stage.loop.run(stop=stop)
        finally:
            timer.cancel()
        wall_run = time.monotonic() - t_run
        proc_cpu = (time.process_time() - cpu_run) / max(1e-9, wall_run)
    total = res.cycles + res.overruns
    period_us = cfg.loop.period_s * 1e6
    summary = res.as_dict()
    late, ex = summary["lateness_us"], summary["exec_us"]
    return {
        "benchmark": "loop",
        "config": str(cfg.path),
        "io": cfg.io.kind.value,
        "rate_hz": 1.0 / cfg.loop.period_s,
        "wall_s": wall_run,
        "loop_time_s": res.duration_s,
        "cycles": res.cycles,
        "overruns": res.overruns,
        "overrun_percent": 100.0 * res.overruns / max(1, total),
        "lateness_us": late,
        "exec_us": ex,
        "cpu_loop_thread_percent": 100.0 * res.cpu_fraction,
        "cpu_process_percent": 100.0 * proc_cpu,
        "fault": summary["fault"],
        "realtime": res.realtime,
        "spin_us": rt.spin_us,
        "loadavg_before": list(load0),
        "loadavg_after": list(os.getloadavg()),
        "targets": {
            "lateness_p99_le_100us": late["p99"] <= 100.0,
            "overruns_le_0.1_percent": 100.0 * res.overruns / max(1, total) <= 0.1,
        },
        "period_us": period_us,
        "setup_s": t_run - wall0,
        "total_cpu_s": time.process_time() - cpu0,
    }
