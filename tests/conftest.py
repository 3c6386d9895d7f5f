"""Shared fixtures. No test sleeps on the wall clock: simulated time and lock-step devices only."""

from __future__ import annotations

import os
from pathlib import Path

# One BLAS thread, as every stagectl command sets for itself (stagectl/cli.py: one_blas_thread) before numpy
# is imported: the tests run commands in process after numpy was imported here, and OpenBLAS' default pool
# busy-waits on the shared cores (the in-process commissioning burnt ~55 s of CPU instead of ~12 s).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import pytest  # noqa: E402 - after the BLAS threads are set

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
EMPS_DIR = SHARED / "data" / "emps"


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def emps_dir() -> Path:
    if not (EMPS_DIR / "DATA_EMPS.csv").exists():
        pytest.skip("../shared/data/emps not present")
    return EMPS_DIR


def pytest_collection_modifyitems(config, items):
    if os.environ.get("STAGECTL_RIG"):
        return
    skip = pytest.mark.skip(reason="hil: set STAGECTL_RIG to a rig file to run")
    for item in items:
        if "hil" in item.keywords:
            item.add_marker(skip)
