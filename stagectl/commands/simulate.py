"""``stagectl simulate --config FILE --scenario NAME --out DIR [--duration S]``.

Closed loop in simulated time (SimClock; the devices in lock-step: PlantIO, or the real CANopen drivers
against the virtual devices; a ``canopen`` config with a ``sim:`` section, e.g. config/hil-canopen.yaml, is
simulated with its virtual devices in-process). Writes ``telemetry.csv`` (docs/recordings.md columns), ``summary.json`` (RMS/max
tracking error, settling times to ±10 nm, faults, loop statistics) and ``tracking.png`` into DIR, and
prints the summary as one JSON line on stdout.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

from stagectl.commands.args import number, recorded_duration_problem
from stagectl.commands.progress import Progress, ProgressSink
from stagectl.errors import ConfigError
from stagectl.outputs import prepare_out_dir

if TYPE_CHECKING:
    from stagectl.config import AppConfig

# The assembly, config and recorder are imported where a command runs, not at module level: `stagectl --help`
# imports every command module and must not pay for numpy/numba/canopen (about 1 s).


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("simulate", help="closed loop in simulated time: telemetry CSV, summary.json, tracking.png")
    p.add_argument("--config", required=True, help="stagectl YAML (e.g. config/sim.yaml)")
    p.add_argument("--scenario", default="cosine",
                   help="cosine | triangle | steps | demo | hold, or a scenario file FILE.yaml "
                        "(default cosine)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--duration", type=number("s"), default=None,
                   help="simulated seconds (default: the scenario's length + 0.2 s)")
    p.add_argument("--tolerance", type=number("m", lo=0, lo_open=True), default=None,
                   help="settling band [m] (default: the in-position window controller.settle.tolerance_m, 1e-8)")
    p.add_argument("--no-plots", action="store_true", help="skip the plot (tracking.png)")
    p.add_argument("--repetitions", type=int, default=None,
                   help="run the scenario this many times back to back (a repeated motion; default once)")
    p.add_argument("--ilc", action="store_true",
                   help="learn a feed-forward over the repetitions (ilc: section, learning from the start)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr (for scripts)")
    p.set_defaults(func=run)


def simulate(cfg: AppConfig, scenario: str, duration_s: float | None, out_dir: str | Path, *,
             tol_m: float | None = None, plots: bool = True, quiet: bool = True,
             repetitions: int | None = None) -> dict[str, Any]:
    """Run one simulation and write its outputs; returns the summary dict.

    Raises
    ------
    ConfigError
        Unknown scenario, bad duration or repetitions, unwritable ``out_dir``, or a canopen config without
        ``sim:``.

    ``repetitions``: the scenario restarts when it ends (a repeated motion, what ``ilc:`` learns), the default
    duration covering that many; the summary then has ``ilc`` (the learner's state, RMS per repetition).
    ``tol_m`` [m]: the settling band (None: the controller's in-position window ``controller.settle.tolerance_m``).
    """
    if tol_m is None:
        tol_m = cfg.controller.settle.tolerance_m
    from stagectl.app import build_stage
    from stagectl.clock import SimClock
    from stagectl.config import IoKind
    from stagectl.control.reference import get_scenario
    from stagectl.recorder import Recorder, tracking_summary, write_outputs

    if cfg.io.kind is IoKind.CANOPEN:
        if cfg.sim is None:
            raise ConfigError(f"{cfg.path}: simulate needs a sim: section (the simulated stage) for io.kind canopen")
        # same drivers, the virtual devices of the sim: section in-process (lock-step)
        cfg = dataclasses.replace(cfg, io=dataclasses.replace(cfg.io, kind=IoKind.EMBEDDED_CANOPEN))
    sc = get_scenario(scenario)
    if repetitions is not None and not 1 <= repetitions <= 100000:
        raise ConfigError(f"--repetitions: must be between 1 and 100000 (got {repetitions})")
    given_s = duration_s
    if duration_s is None:
        x0 = cfg.sim.plant.x0_m if cfg.sim is not None else 0.0
        one = sc.duration_s(x0) if sc is not None else 1.0
        duration_s = (one + cfg.loop.period_s) * (repetitions or 1) + 0.2
    if not (duration_s > 0 and math.isfinite(duration_s)):
        raise ConfigError(f"--duration: must be > 0 s (got {duration_s})")
    too_long = recorded_duration_problem("--duration" if given_s is not None else "--repetitions", duration_s,
                                         cfg.loop.period_s)
    if too_long:
        raise ConfigError(too_long)
    prepare_out_dir(out_dir)
    progress = Progress("simulate", duration_s, "s simulated", quiet=quiet)
    interrupted = False
    with build_stage(cfg, clock=SimClock()) as stage:
        loop = stage.loop
        rec = Recorder(loop.columns, capacity=int(duration_s / cfg.loop.period_s) + 16)
        loop.add_sink(rec)
        loop.add_sink(ProgressSink(progress))
        stage.load_scenario(sc, repeat=repetitions is not None)
        try:
            res = loop.run(duration_s=duration_s)
        except KeyboardInterrupt:  # keep what was simulated: written below, marked, then Ctrl-C goes on
            interrupted = True
        progress.close()
    if interrupted:
        summary = {"command": "simulate", "config": str(cfg.path), "scenario": scenario, "interrupted": True,
                   **(tracking_summary(rec, tol_m=tol_m) if rec.n else {})}
        write_outputs(rec, out_dir, summary, plots=False)
        raise KeyboardInterrupt
    summary = {
        "command": "simulate",
        "config": str(cfg.path),
        "scenario": scenario,
        "io": cfg.io.kind.value,
        "period_s": cfg.loop.period_s,
        **tracking_summary(rec, tol_m=tol_m),
        "fault": res.as_dict()["fault"],
        "loop": {"cycles": res.cycles, "overruns": res.overruns, "ended_by": res.ended_by},
    }
    if stage.learner is not None:
        summary["ilc"] = stage.learner.status()
        summary["ilc"]["rms_m"] = list(stage.learner.rms_history)
    write_outputs(rec, out_dir, summary, plots=plots, title=f"simulate {scenario} ({cfg.path.name if cfg.path else ''})")
    return summary


def run(args: argparse.Namespace) -> int:
    from stagectl.config import load_app_config

    cfg = load_app_config(args.config)
    if args.ilc and args.repetitions is None:
        raise ConfigError("--ilc: learning needs a repeated motion; give --repetitions N")
    if args.ilc:
        cfg = dataclasses.replace(cfg, ilc=dataclasses.replace(cfg.ilc, enabled=True, autostart=True))
    summary = simulate(cfg, args.scenario, args.duration, args.out, tol_m=args.tolerance, plots=not args.no_plots,
                       quiet=args.quiet, repetitions=args.repetitions)
    print(json.dumps(summary, default=str, separators=(",", ":")))
    return 1 if summary["fault"] else 0
