"""``stagectl bench models|io|control|ilc|timing|loop|startup|telemetry|flood [--json] [...]``.

Each benchmark lives in ``stagectl.bench.<kind>`` and exposes ``add_arguments(parser)`` and
``run(args) -> dict`` (and optionally ``exit_code(result) -> int``; otherwise the result's ``exit_code``
entry, default 0, is the exit code). This command prints the dict as JSON (``--json``) or as readable
lines. Figures are always measured in the run that prints them, baselines included.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from types import ModuleType
from typing import Any

from stagectl.bench import control, flood, ilc, io, loop, models, startup, telemetry, timing

KINDS: dict[str, tuple[ModuleType, str]] = {
    "models": (models, "friction model + plant steps per second vs a pure-Python GMS baseline"),
    "io": (io, "cycle round trip and missed cycles: in-process CAN, socketcand TCP, serial streaming"),
    "control": (control, "tracking error of the controller variants on the seed stage"),
    "ilc": (ilc, "learning feed-forward: RMS per repetition of the repeated triangle scan, 20 %%-wrong model"),
    "timing": (timing, "tracking and fault reaction with late/dropped samples and jitter (simulated time)"),
    "loop": (loop, "loop timing: lateness p50/p99/max, overruns, CPU"),
    "startup": (startup, "time to the first control cycle from an empty and from a warm numba cache"),
    "telemetry": (telemetry, "telemetry ring + writer at 1 kHz (or the real daemon): dropped/lost rows"),
    "flood": (flood, "the real daemon under flooding + half-open clients: missed cycles, watchdog gaps, stop latency"),
}


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("bench", help="run a benchmark (timing lives here, never in tests)")
    kinds = p.add_subparsers(dest="bench_kind", metavar="KIND")
    for kind, (mod, help_text) in KINDS.items():
        kp = kinds.add_parser(kind, help=help_text)
        kp.add_argument("--json", action="store_true", help="print the result as JSON")
        kp.add_argument("-q", "--quiet", action="store_true",
                        help="no progress line (case, elapsed, time left) on stderr (for scripts)")
        mod.add_arguments(kp)
        kp.set_defaults(func=_runner(mod))
    p.set_defaults(func=_no_kind)


def _no_kind(args: argparse.Namespace) -> int:
    from stagectl.errors import ConfigError

    raise ConfigError(f"bench: name a benchmark: {', '.join(KINDS)} (see: stagectl bench --help)")


def _runner(mod: ModuleType) -> Callable[[argparse.Namespace], int]:
    def fn(args: argparse.Namespace) -> int:
        from stagectl.commands.progress import Ticker

        with Ticker(f"bench {args.bench_kind}", quiet=args.quiet) as ticker:
            args.progress = ticker.tell  # the benchmark tells its cases: stagectl.bench.tell
            result = mod.run(args)
        if args.json:
            json.dump(result, sys.stdout, indent=2, default=float)
            sys.stdout.write("\n")
        else:
            _print(result)
        if hasattr(mod, "exit_code"):
            return int(mod.exit_code(result))
        return int(result.get("exit_code", 0)) if isinstance(result, dict) else 0

    return fn


def _print(obj: Any, indent: int = 0) -> None:
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
