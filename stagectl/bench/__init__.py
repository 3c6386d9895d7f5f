"""Benchmarks (``stagectl bench models|io|control|loop|telemetry``). Timing and speed live here, never in tests."""

from __future__ import annotations

import argparse


def tell(args: argparse.Namespace, done: float, total: float, what: str, span: float = 0.0) -> None:
    """Tell ``stagectl bench``'s progress line that ``done`` of ``total`` units of the benchmark are finished
    and ``what`` runs now (``span`` > 0: ``what`` runs for ``span`` wall-clock seconds, the units being
    seconds). The command puts the line's ``tell`` in ``args.progress``; without it (a test, a caller of
    ``run``) this does nothing. The line's time left is the cost per unit so far times the units left."""
    fn = getattr(args, "progress", None)
    if fn is not None:
        fn(done, total, what, span)
