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
from stagectl.commands.args import number

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
        _check_numbers(kp)
        kp.set_defaults(func=_runner(mod))
    p.set_defaults(func=_no_kind)


#: the benchmarks' numeric options: unit and lower bound (exclusive when True); any other number must be
#: finite and >= 0 in the unit "(a count)"
_NUMBERS: dict[str, tuple[str, float, bool]] = {
    "duration": ("s", 0.0, True), "duration_s": ("s", 0.0, True), "phase_s": ("s", 0.0, True),
    "hold": ("s", 0.0, True), "skip": ("s", 0.0, False), "rate": ("Hz", 0.0, True), "rate_hz": ("Hz", 0.0, True),
    "spin_us": ("µs", 0.0, False), "min_phase_margin": ("deg", 0.0, False), "min_gain_margin": ("dB", 0.0, False),
    "target_nm": ("nm", 0.0, True), "friction_scale": ("(a factor)", 0.0, True), "baudrate": ("bit/s", 0.0, True),
    "fifo": ("(a priority)", 1.0, False), "switch_interval": ("s", 0.0, True),
    **{k: ("(a count)", 0.0, True) for k in ("steps", "sets", "repeat", "first_steps", "clients", "repetitions",
                                           "within", "columns", "switch_cycles")},
}


def _check_numbers(p: argparse.ArgumentParser) -> None:
    """Every numeric option of a benchmark refuses what it cannot run with (not finite, negative, zero where
    it counts or divides) in one argparse line with its unit, before any work (benchmarks sit below this layer
    and declare plain ``type=float``/``int``)."""
    for action in p._actions:
        if action.type in (float, int):
            unit, lo, lo_open = _NUMBERS.get(action.dest, ("(a count)", 0.0, False))
            action.type = number(unit, lo=lo, lo_open=lo_open, hi=99.0 if action.dest == "fifo" else None,
                                 integer=action.type is int)


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
