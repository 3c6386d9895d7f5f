"""``stagectl run --config FILE [--duration S] [--out DIR]``: the real-time loop in the foreground.

On a simulated stage (``config/sim.yaml``) it runs the configured demo motion on the embedded plant; on a
real stage it holds the position unless ``--scenario`` is given. One progress line per second goes to
stderr; at the end the same outputs as ``simulate`` (telemetry.csv, summary.json, tracking.png) are written
to ``--out`` (default ``./runs/<UTC timestamp>``) and the summary is printed as one JSON line. Ctrl-C stops
cleanly (zero force, drive disabled). The loop runs in a :class:`~stagectl.runtime.host.LoopHost`, like the
daemon's.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from stagectl.commands.args import number, recorded_duration_problem
from stagectl.errors import ConfigError
from stagectl.outputs import prepare_out_dir
from stagectl.runtime.status import LoopResult, LoopStatus

# The assembly, config and controller stack (numpy, numba, canopen: about 1 s) are imported where the command
# runs: `stagectl --help` builds every command's parser.


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("run", help="run the real-time control loop (demo motion on a simulated stage)")
    p.add_argument("--config", required=True, help="stagectl YAML (e.g. config/sim.yaml)")
    p.add_argument("--duration", type=number("s"), default=None, help="seconds to run (default: until Ctrl-C)")
    p.add_argument("--out", default=None, help="output directory (default ./runs/<timestamp>)")
    p.add_argument("--scenario", default=None,
                   help="motion: demo | cosine | triangle | steps | hold, or a scenario file FILE.yaml "
                        "(default: demo.scenario on a "
                        "simulated stage, hold on a real one)")
    p.add_argument("--no-plots", action="store_true", help="skip the plot (tracking.png)")
    p.add_argument("--ilc", action="store_true",
                   help="learn a feed-forward for the repeated motion (ilc: section, learning from the start)")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no start, progress or outputs lines on stderr (for scripts; warnings and errors still)")
    p.set_defaults(func=run)


def progress_line(st: LoopStatus) -> str:
    """The once-a-second stderr line (µm, nm, N, µs)."""
    lat = st.lateness_us
    p99, late_max = (lat.p99, lat.max) if lat is not None else (math.nan, math.nan)
    fault = f" FAULT {st.fault.name}: {st.fault.cause}" if st.fault else ""
    ilc = st.ilc
    learn = ""
    if ilc is not None and ilc.get("motion") is not None:
        r = ilc.get("last_rms_m")
        rms_nm = float(r) * 1e9 if isinstance(r, (int, float)) else math.nan
        learn = (f"  ilc {ilc['motion']} it={ilc['iteration']} rms={rms_nm:.1f} nm"
                 f"{' FROZEN' if ilc.get('frozen') else ''}")
    return (f"t={st.t_s:7.2f} s  x={st.x_m * 1e6:10.4f} um  e={st.e_m * 1e9:9.1f} nm  "
            f"u={st.u_n:7.3f} N  late p99={p99:6.0f} us max={late_max:6.0f} us  "
            f"overruns={st.overruns}  {st.state.value}{fault}{learn}")


def run(args: argparse.Namespace) -> int:
    from stagectl.app import build_stage
    from stagectl.config import load_app_config
    from stagectl.control.reference import get_scenario
    from stagectl.recorder import Recorder, tracking_summary, write_outputs
    from stagectl.runtime.host import LoopHost

    if args.duration is not None and not (args.duration > 0 and math.isfinite(args.duration)):
        raise ConfigError(f"--duration: must be > 0 s (got {args.duration})")
    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    cfg = load_app_config(args.config)
    too_long = None if args.duration is None else recorded_duration_problem("--duration", args.duration,
                                                                            cfg.loop.period_s)
    if too_long:
        raise ConfigError(too_long)
    if getattr(args, "ilc", False):
        cfg = dataclasses.replace(cfg, ilc=dataclasses.replace(cfg.ilc, enabled=True, autostart=True))
    out = Path(args.out) if args.out else Path("runs") / datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    if args.scenario is not None:
        get_scenario(args.scenario)  # unknown names fail before any device is opened
    prepare_out_dir(out)
    res: LoopResult | None
    with build_stage(cfg) as stage:
        loop = stage.loop
        scenario = args.scenario or (cfg.demo.scenario if stage.simulated else "hold")
        stage.load_scenario(scenario, repeat=cfg.demo.repeat)
        cap_s = args.duration if args.duration is not None else 600.0
        rec = Recorder(loop.columns, capacity=int(cap_s / cfg.loop.period_s) + 1024)
        host = LoopHost(loop, sinks=[rec])
        if not args.quiet:
            print(f"stagectl run: {cfg.path.name if cfg.path else '-'} io={cfg.io.kind.value} "
                  f"period={cfg.loop.period_s * 1e3:g} ms scenario={scenario} "
                  f"duration={args.duration or 'until Ctrl-C'}", file=sys.stderr)
        try:  # from the loop's start on: an interrupt anywhere here ends in finish(), never under a running loop
            host.start(duration_s=args.duration)
            t_next = time.monotonic() + 1.0
            while not host.wait(max(0.0, t_next - time.monotonic())):
                if time.monotonic() >= t_next:
                    t_next += 1.0
                    if not args.quiet:
                        print(progress_line(loop.status()), file=sys.stderr, flush=True)
        except KeyboardInterrupt:  # Ctrl-C, or SIGTERM (stagectl.cli turns it into the same clean stop)
            print("stagectl run: stopping (interrupted)", file=sys.stderr)
        res = host.finish(timeout_s=10.0)
    summary: dict[str, Any] = {
        "command": "run",
        "config": str(cfg.path),
        "scenario": scenario,
        "io": cfg.io.kind.value,
        "period_s": cfg.loop.period_s,
        # the settle band is the controller's in-position window, so settling_time_s and in_position_after_s
        # judge the same band (docs/control.md, in-position detector)
        **(tracking_summary(rec, tol_m=cfg.controller.settle.tolerance_m) if rec.n else {}),
        "fault": res.as_dict()["fault"] if res else None,
        "loop": res.as_dict() if res else None,
    }
    if stage.learner is not None:
        summary["ilc"] = stage.learner.status()
    title = f"run {scenario} ({cfg.path.name if cfg.path else ''})"
    summary["out"] = str(out)
    write_outputs(rec, out, summary, plots=not args.no_plots and rec.n > 1, title=title)
    wrote = "telemetry.csv, summary.json" + (" and tracking.png" if (Path(out) / "tracking.png").is_file() else "")
    if not args.quiet:  # -q: the summary on stdout names the directory (``out``)
        print(f"stagectl run: {wrote} in {out}", file=sys.stderr)
    print(json.dumps(summary, default=str, separators=(",", ":")))
    return 1 if summary["fault"] else 0
