"""Fuzz targets (hypothesis): bounded in CI, long on request.

Each target runs ``FUZZ_EXAMPLES`` inputs: 120 by default (a few seconds), or what the environment variable
``STAGECTL_FUZZ_EXAMPLES`` says, e.g. the 10⁵-input run documented in docs/testing.md::

    STAGECTL_FUZZ_EXAMPLES=100000 .venv/bin/python -m pytest -q -p no:cacheprovider tests/fuzz

No deadline (a shared, loaded machine must not turn a slow example into a failure); the database is off so a
run does not write into the repository.
"""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

FUZZ_EXAMPLES = int(os.environ.get("STAGECTL_FUZZ_EXAMPLES", "120"))

settings.register_profile(
    "stagectl-fuzz",
    max_examples=FUZZ_EXAMPLES,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
)
FUZZ = settings.get_profile("stagectl-fuzz")
