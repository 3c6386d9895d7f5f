"""``stagectl commission --config STAGE.yaml --out DIR [--max-stroke M] [--max-force N] [--max-velocity M_S]``.

From an unknown stage to a tuned, friction-compensated controller in one command (``docs/commissioning.md``):
sanity probe, closed-loop FRF, friction experiments, identify/discover, gains with margins checked on the
measured FRF, verification before/after. Writes ``DIR/model.yaml``, ``DIR/stage.yaml``,
``DIR/recordings/*.csv``, ``DIR/report.md`` (+ PNGs) and ``DIR/report.json``; progress lines on stderr, the
summary as one JSON line on stdout. Exit 0 when complete, 1 when a fault aborted it (drive disabled,
recordings kept), 130 on Ctrl-C (143 on SIGTERM), 2 on bad input or a stage that fails the sanity checks.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from stagectl.commands.args import number
from stagectl.errors import ConfigError, interrupt_exit_code, short
from stagectl.outputs import prepare_out_dir


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("commission", help="identify, tune and verify a stage in one run (report, model, config)")
    p.add_argument("--config", required=True, help="stagectl YAML of the stage")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--max-stroke", type=number("m"), default=None, metavar="M",
                   help="lower the travel used by the experiments [m] (default: soft limits less 5 %% margins)")
    p.add_argument("--max-force", type=number("N"), default=None, metavar="N",
                   help="lower the force limit of the experiments [N] (default: the configured one)")
    p.add_argument("--max-velocity", type=number("m/s"), default=None, metavar="M_S",
                   help="lower the velocity limit of the experiments [m/s]")
    p.add_argument("--no-verify", action="store_true", help="skip the before/after verification runs")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--runtime-dir", default=None, help="the daemon's runtime directory (refusal check)")
    p.add_argument("--state-dir", default=None, help="the daemon's state directory (refusal check)")
    p.add_argument("--inject-fault", default=None, metavar="EXPERIMENT@T",
                   help="debug, simulated stages only: inject a drive fault T s into EXPERIMENT")
    p.add_argument("--lockstep", action="store_true",
                   help="the stage is a `stagectl sim-plant --lockstep` process: simulated time, each SYNC "
                        "answered before the next (deterministic, faster than real time)")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress lines on stderr (for scripts; the summary, verdict and errors still)")
    p.set_defaults(func=run)


def _parse_fault(spec: str | None) -> tuple[str, float] | None:
    if spec is None:
        return None
    from stagectl.commission.sequence import EXPERIMENTS, REST_STAGE_SCENARIOS, VERIFY

    name, _, t = spec.partition("@")
    try:
        at = float(t or "0")
    except ValueError:
        raise ConfigError(f"--inject-fault: expected EXPERIMENT@SECONDS, got {short(spec)}") from None
    known = [*EXPERIMENTS, *(f"{kind}_{which}_{n}" for which in ("before", "after") for n in VERIFY
                             for kind in ("wipe", "verify")),
             *(f"{kind}_rest_{which}_{n}" for which in ("with", "without") for n in REST_STAGE_SCENARIOS
               for kind in ("wipe", "verify"))]
    if name not in known:  # a fault that is never injected would let the whole commissioning run
        raise ConfigError(f"--inject-fault: unknown experiment {short(name)} (one of {', '.join(known)})")
    if not (at >= 0 and at < float("inf")):
        raise ConfigError(f"--inject-fault: the time must be a finite number of seconds >= 0, got {short(t)}")
    return name, at


def run(args: argparse.Namespace) -> int:
    from stagectl.commission.guard import check_daemon
    from stagectl.commission.outputs import write_config, write_report
    from stagectl.commission.sequence import Commissioning, Options
    from stagectl.config import load_app_config

    cfg = load_app_config(args.config)
    fault = _parse_fault(args.inject_fault)
    check_daemon(cfg, args.runtime_dir, args.state_dir)
    out = prepare_out_dir(args.out)
    held = [n for n in ("report.json", "model.yaml", "stage.yaml", "recordings") if (out / n).exists()]
    if held:  # a previous commissioning's recordings and report are never overwritten
        raise ConfigError(f"--out: {str(out)!r} already holds a commissioning ({', '.join(held)}); choose a new "
                          "directory or remove that one (nothing was written)")

    def progress(line: str) -> None:
        if not args.quiet:
            print(line, file=sys.stderr, flush=True)

    opts = Options(max_stroke_m=args.max_stroke, max_force_n=args.max_force, max_velocity_m_s=args.max_velocity,
                   verify=not args.no_verify, plots=not args.no_plots, inject_fault=fault, progress=progress,
                   lockstep=args.lockstep)
    com = Commissioning(cfg, Path(out), opts, lambda res: write_config(res, Path(out)))
    res = com.run()
    rep = write_report(res, Path(out), plots=opts.plots)
    summary = {"command": "commission", "status": rep["status"], "out": str(out),
               "fitted": rep.get("fitted"), "verdict": rep.get("verdict", {}).get("recommend"),
               "aborted": rep.get("aborted")}
    print(json.dumps(summary, default=str, separators=(",", ":")))
    if res.error is not None:
        raise res.error  # one `stagectl: error:` line, exit 2 (report.json written)
    if res.aborted is not None:
        print(f"stagectl: error: {res.aborted}", file=sys.stderr)
        return interrupt_exit_code() if res.aborted.interrupted else 1
    print(f"stagectl commission: {rep['verdict']['text']}", file=sys.stderr)
    print(f"stagectl commission: model.yaml, stage.yaml, report.md in {out}", file=sys.stderr)
    return 0
