"""Fuzz targets (hypothesis): bounded in CI, long on request.

Each target runs a bounded number of inputs by default (its ``fuzz(n)``: 30 to 200, a few seconds each), or
the number in the environment variable ``STAGECTL_FUZZ_EXAMPLES`` for every target, e.g. the 10⁵-input run
documented in docs/testing.md::

    STAGECTL_FUZZ_EXAMPLES=100000 .venv/bin/python -m pytest -q -p no:cacheprovider tests/fuzz

No deadline (a shared, loaded machine must not turn a slow example into a failure); the example database is
off so a run writes nothing into the repository (hypothesis prints the failing input instead).
"""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

#: the number of inputs per target when set (the long run); None: each target's CI default
FUZZ_EXAMPLES: int | None = int(os.environ["STAGECTL_FUZZ_EXAMPLES"]) if os.environ.get(
    "STAGECTL_FUZZ_EXAMPLES") else None


def fuzz(default: int) -> settings:
    """Hypothesis settings for a fuzz target: ``default`` inputs in CI, ``STAGECTL_FUZZ_EXAMPLES`` if set."""
    return settings(
        max_examples=FUZZ_EXAMPLES if FUZZ_EXAMPLES is not None else default,
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
    )
