"""Typed command-line values: a bad number is refused by argparse with the option's name and unit.

``type=number("s", lo=0, lo_open=True)`` accepts a finite float in the range and otherwise raises
:class:`argparse.ArgumentTypeError`, which argparse prints as ``stagectl CMD: error: argument --x: ...``
with exit status 2. Standard library only (the parser must stay fast to build).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def number(unit: str, *, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
           hi_open: bool = False, integer: bool = False) -> Callable[[str], float]:
    """A converter for a finite number in [lo, hi] (``lo_open``/``hi_open`` exclude the bound) in ``unit``."""

    def convert(text: str) -> float:
        try:
            value = int(text) if integer else float(text)
        except ValueError:
            kind = "an integer" if integer else "a number"
            raise argparse.ArgumentTypeError(f"expected {kind} in {unit}, got {text[:40]!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be finite ({unit}), got {text[:40]!r}")
        if lo is not None and (value < lo or (lo_open and value == lo)):
            raise argparse.ArgumentTypeError(f"must be {'>' if lo_open else '>='} {lo:g} {unit}, got {text[:40]}")
        if hi is not None and (value > hi or (hi_open and value == hi)):
            raise argparse.ArgumentTypeError(f"must be {'<' if hi_open else '<='} {hi:g} {unit}, got {text[:40]}")
        return value

    convert.__name__ = "integer" if integer else "number"  # argparse names the type in some messages
    return convert



#: rows of telemetry a foreground ``run`` or ``simulate`` keeps in memory (its recording, preallocated for the
#: duration asked): 2^25, 9.3 h at 1 kHz, about 5 GB at 18 columns
MAX_RECORDED_ROWS = 1 << 25


def recorded_duration_problem(option: str, duration_s: float, period_s: float) -> str | None:
    """Why ``duration_s`` cannot be recorded in memory at ``period_s`` (None: it can); ``option`` names the
    command-line option that set it."""
    rows = duration_s / period_s
    if rows <= MAX_RECORDED_ROWS:
        return None
    return (f"{option}: {duration_s:.6g} s is {rows:.3g} periods of {period_s * 1e3:g} ms; the recording kept in "
            f"memory holds at most {MAX_RECORDED_ROWS} rows ({MAX_RECORDED_ROWS * period_s:.6g} s at this period)")
