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

