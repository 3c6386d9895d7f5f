"""``stagectl bench models|io|control|loop [--json] [...]``.

Each benchmark lives in ``stagectl.bench.<kind>`` and exposes ``add_arguments(parser)`` and
``run(args) -> dict``. This command prints the dict as JSON (``--json``) or as readable lines.
Figures are always measured in the run that prints them, baselines included.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys

KINDS = {
    "models": "friction model + plant steps per second vs a pure-Python GMS baseline",
    "io": "cycle round trip and missed cycles: in-process CAN, socketcand TCP, serial streaming",
    "control": "tracking error of the controller variants on the seed stage",
    "loop": "loop timing: lateness p50/p99/max, overruns, CPU",
}


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("bench", help="run a benchmark (timing lives here, never in tests)")
    kinds = p.add_subparsers(dest="bench_kind", metavar="KIND")
    for kind, help_text in KINDS.items():
        kp = kinds.add_parser(kind, help=help_text)
        kp.add_argument("--json", action="store_true", help="print the result as JSON")
        try:
            mod = importlib.import_module(f"stagectl.bench.{kind}")
        except ModuleNotFoundError as exc:
            if exc.name != f"stagectl.bench.{kind}":
                raise
            kp.set_defaults(func=_missing(kind))
            continue
        if hasattr(mod, "add_arguments"):
            mod.add_arguments(kp)
        kp.set_defaults(func=_runner(mod))
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def _missing(kind: str):  # type: ignore[no-untyped-def]
    def fn(args: argparse.Namespace) -> int:
        print(f"stagectl: error: benchmark {kind!r} is not available in this build", file=sys.stderr)
        return 2

    return fn


def _runner(mod):  # type: ignore[no-untyped-def]
    def fn(args: argparse.Namespace) -> int:
        result = mod.run(args)
        if args.json:
            json.dump(result, sys.stdout, indent=2, default=float)
            sys.stdout.write("\n")
        else:
            _print(result)
        return int(result.get("exit_code", 0)) if isinstance(result, dict) else 0

    return fn


def _print(obj, indent: int = 0) -> None:  # type: ignore[no-untyped-def]
    pad = "  " * indent
    if isinstance(obj, dict):
        for k, v in obj.items():
            if isinstance(v, (dict, list)):
                print(f"{pad}{k}:")
                _print(v, indent + 1)
            else:
                print(f"{pad}{k}: {v:.6g}" if isinstance(v, float) else f"{pad}{k}: {v}")
    elif isinstance(obj, list):
        for item in obj:
            if isinstance(item, (dict, list)):
                print(f"{pad}-")
                _print(item, indent + 1)
            else:
                print(f"{pad}- {item}")
    else:
        print(f"{pad}{obj}")
