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

from stagectl.bench import tell

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
    p.add_argument("--breakdown-cycles", type=int, default=3000,
                   help="cycles of the per-cycle cost breakdown run (0: skip; default 3000)")


#: the parts of one cycle timed by the breakdown run: (label, object attribute on the loop, method)
PARTS = (
    ("sync", "sync", "sync"),
    ("sensor_read", "sensor", "read"),
    ("requests", "_inbox", "serve"),
    ("safety_checks", "safety", "check_measurement"),
    ("reference", "reference", "sample"),
    ("safety_checks", "safety", "check_tracking"),
    ("controller", "controller", "step"),
    ("safety_checks", "safety", "limit_force"),
    ("actuator_write", "actuator", "write"),
    ("telemetry_sinks", "_sinks", "emit"),
)


def breakdown(cfg: Any, cycles: int) -> dict[str, Any]:
    """Per-cycle cost of each part of the cycle (µs, mean and p50 over ``cycles`` real-time cycles).

    A separate stage is built and every part's method is replaced, on that instance only, by a timing wrapper
    (``perf_counter`` before and after); ``loop_other`` is the cycle's execution time minus the timed parts
    (the loop body itself: statistics, the telemetry row, bookkeeping, from the p50s) and ``wrapper_overhead_us`` the cost of
    one wrapper, measured here, which is subtracted from every part."""
    import numpy as np

    from stagectl.app import build_stage

    perf = time.perf_counter
    acc: dict[str, list[float]] = {}

    def timed(label: str, fn: Any) -> Any:
        store = acc.setdefault(label, [])

        def w(*a: Any, **k: Any) -> Any:
            t0 = perf()
            try:
                return fn(*a, **k)
            finally:
                store.append(perf() - t0)

        return w

    # the cost of a wrapper around a no-op, to subtract
    probe: list[float] = []

    def noop() -> None:
        return None

    def wn() -> None:
        t0 = perf()
        try:
            return noop()
        finally:
            probe.append(perf() - t0)

    t0 = perf()
    for _ in range(20000):
        wn()
    overhead = (perf() - t0) / 20000 - float(np.median(probe))  # outer call cost not seen by the inner timer
    overhead = max(overhead, 0.0)

    with build_stage(cfg) as stage:
        loop = stage.loop
        stage.load_scenario(cfg.demo.scenario, repeat=True)
        seen: set[tuple[int, str]] = set()
        n_wrapped: dict[str, int] = {}
        for label, attr, meth in PARTS:
            obj = getattr(loop, attr, None)
            if obj is None or (id(obj), meth) in seen or not hasattr(obj, meth):
                continue
            seen.add((id(obj), meth))
            setattr(obj, meth, timed(label, getattr(obj, meth)))
            n_wrapped[label] = n_wrapped.get(label, 0) + 1
        # the simulated devices (virtual drive, encoder, plant) are served inside the loop thread through the
        # drivers' lock-step pump: on a real stage that work is done by the drive, so it is timed apart
        dev_wall: list[float] = []
        dev_cpu: list[float] = []
        pumped: set[int] = set()
        for attr in ("sync", "sensor", "actuator"):
            drv = getattr(loop, attr, None)
            pump = getattr(drv, "_pump", None)
            if pump is None or id(drv) in pumped:
                continue
            pumped.add(id(drv))

            def timed_pump(fn: Any = pump) -> Any:
                w0, c0 = perf(), time.thread_time()
                try:
                    return fn()
                finally:
                    dev_cpu.append(time.thread_time() - c0)
                    dev_wall.append(perf() - w0)

            setattr(drv, "_pump", timed_pump)
        cpu0 = time.thread_time()
        res = loop.run(cycles=cycles)
        cpu_cycles = time.thread_time() - cpu0
    n = max(1, res.cycles)
    # skip the first 10 % (warm-up: caches, branch predictors, first-touch)
    parts: dict[str, dict[str, float]] = {}
    total_parts = 0.0
    for label, xs in acc.items():
        arr = np.asarray(xs[len(xs) // 10:]) if xs else np.zeros(1)
        calls_per_cycle = len(xs) / n
        mean = max(float(arr.mean()) - overhead, 0.0) * calls_per_cycle * 1e6
        parts[label] = {"mean_us": mean, "p50_us": max(float(np.median(arr)) - overhead, 0.0) * 1e6 * calls_per_cycle,
                        "calls_per_cycle": calls_per_cycle}
        total_parts += parts[label]["p50_us"]
    exec_p50 = float(res.exec_us.p50)
    wrappers = sum(p["calls_per_cycle"] for p in parts.values())
    parts["loop_other"] = {"p50_us": exec_p50 - total_parts - wrappers * overhead * 1e6}
    own: dict[str, float] | None = None
    if dev_wall:
        dev_w = sum(dev_wall) / n * 1e6
        dev_c = sum(dev_cpu) / n * 1e6
        own = {"loop_thread_cpu_per_cycle_us": cpu_cycles / n * 1e6,
               "simulated_devices_cpu_per_cycle_us": dev_c,
               "simulated_devices_wall_per_cycle_us": dev_w,
               "own_cpu_per_cycle_us": cpu_cycles / n * 1e6 - dev_c}
    return {"cycles": res.cycles, "exec_p50_us_with_wrappers": exec_p50, "wrapper_overhead_us": overhead * 1e6,
            "parts": parts, "without_simulated_devices": own,
            "note": "p50 per part, wrapper overhead subtracted; loop_other = exec p50 − Σ parts; "
                    "without_simulated_devices: means over the run (thread CPU time), the virtual devices and "
                    "the plant served through the drivers' lock-step pump counted apart (a real drive does "
                    "that work), including the timing wrappers' own cost"}


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
        tell(args, 0.0, args.duration, f"running the loop for {args.duration:g} s", span=args.duration)
        try:
            res = stage.loop.run(stop=stop)
        finally:
            timer.cancel()
        wall_run = time.monotonic() - t_run
        proc_cpu = (time.process_time() - cpu_run) / max(1e-9, wall_run)
    total = res.cycles + res.overruns
    period_us = cfg.loop.period_s * 1e6
    tell(args, args.duration, args.duration, f"cycle breakdown ({int(args.breakdown_cycles)} cycles)")
    parts = breakdown(cfg, int(args.breakdown_cycles)) if args.breakdown_cycles > 0 else None
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
        "cycle_breakdown": parts,
        "setup_s": t_run - wall0,
        "total_cpu_s": time.process_time() - cpu0,
    }
