"""``stagectl check-config FILE``: the exact validation the daemon runs; prints OK or every problem (exit 2).

Every problem is one ``stagectl: error: FILE: key.path: ...`` line (after a count), like the errors of the
other commands; nothing is opened (no bus, no device, no controller design).
"""

from __future__ import annotations

import argparse
import sys

from stagectl.errors import ConfigError


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("check-config", help="validate a configuration file (exactly as the daemon does)")
    p.add_argument("file", nargs="?", help="stagectl YAML file")
    p.add_argument("--config", dest="config_file", metavar="FILE",
                   help="the same file, given the way the other commands take it")
    p.add_argument("-q", "--quiet", action="store_true", help="print nothing when the file is valid")
    p.set_defaults(func=run, parser=p)


def run(args: argparse.Namespace) -> int:
    """Validate ``args.file`` as :func:`stagectl.config.load_app_config` does; 0 when valid, 2 otherwise."""
    # the YAML first (the bounded loader: light), the validation's heavy imports only for a readable file, so a
    # refused file (alias bomb, syntax) costs the interpreter's start and a few ms; load_app_config is exactly
    # parse_app_config(load_yaml_file(path), path)
    from stagectl.schema import load_yaml_file

    config_file = getattr(args, "config_file", None)
    if (args.file is None) == (config_file is None):
        args.parser.error("give the file once: check-config FILE or check-config --config FILE")
    if args.file is None:
        args.file = config_file
    try:
        data = load_yaml_file(args.file)
        from stagectl.config import parse_app_config  # here, not at module level: keeps `stagectl --help` light

        cfg = parse_app_config(data, args.file)
    except ConfigError as exc:
        n = len(exc.problems)
        print(f"{args.file}: {n} problem{'s' if n != 1 else ''}", file=sys.stderr)
        for line in exc.shown():
            print(f"stagectl: error: {line}", file=sys.stderr)
        return 2
    if not args.quiet:
        sensor = cfg.io.sensor.value
        print(
            f"{args.file}: OK (io {cfg.io.kind.value}, sensor {sensor}, period {cfg.loop.period_s * 1e3:g} ms, "
            f"limits [{cfg.safety.min_position_m:g}, {cfg.safety.max_position_m:g}] m)"
        )
    from stagectl.config.checks import sim_plant_only_note

    note = sim_plant_only_note(cfg)
    if note:
        print(f"stagectl: note: {args.file}: {note}", file=sys.stderr)
    return 0
