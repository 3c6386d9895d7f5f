"""Shared fixtures. No test sleeps on the wall clock: simulated time and lock-step devices only."""

from __future__ import annotations

import os
from pathlib import Path

# One BLAS thread, as every stagectl command sets for itself (stagectl/cli.py: one_blas_thread) before numpy
# is imported: the tests run commands in process after numpy was imported here, and OpenBLAS' default pool
# busy-waits on the shared cores (the in-process commissioning burnt ~55 s of CPU instead of ~12 s).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import sys  # noqa: E402


def _shared_bytecode_cache() -> None:
    """Byte code cached outside the checkout when the environment says not to write it next to the sources.

    With ``PYTHONDONTWRITEBYTECODE`` set, every test process and every ``stagectl`` subprocess (about 90 per
    run) compiles the sources it imports again, and pytest rewrites the asserts of every test module in both
    xdist workers again (~5 s of CPU per worker). Under ``sys.pycache_prefix`` (``PYTHONPYCACHEPREFIX``, passed
    on to the subprocesses) the ``.pyc`` files go to ``$XDG_CACHE_HOME/stagectl/pycache`` instead, not into
    the tree, and are checked against the sources' mtime and size as usual. A subprocess a test starts with
    ``PYTHONDONTWRITEBYTECODE=1`` of its own still reads them. A prefix the user set is kept.
    """
    if not sys.dont_write_bytecode:
        return
    if not sys.pycache_prefix:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "stagectl" / "pycache"
        sys.pycache_prefix = str(base)
        os.environ["PYTHONPYCACHEPREFIX"] = str(base)
    sys.dont_write_bytecode = False
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)


_shared_bytecode_cache()

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


#: the modules of the longest tests, run first (pytest-xdist hands the collection out in order): last in the
#: order, a cold-cache mypy run (~13 s CPU, a minute of wall clock on a loaded machine) kept one worker busy
#: alone after the other had finished; the commissioning fixture (~12 s), compiles into fresh numba caches
FIRST = ("tests/test_typecheck.py", "tests/commission/test_commission.py", "tests/friction/test_jit_cache.py",
         "tests/friction/test_bench_models.py", "tests/loop/test_bench_startup.py")


def _first_rank(item) -> int:
    path = item.nodeid.split("::")[0]
    return FIRST.index(path) if path in FIRST else len(FIRST)


def pytest_collection_modifyitems(config, items):
    items.sort(key=_first_rank)  # stable: every module's tests stay together and in order
    if os.environ.get("STAGECTL_RIG"):
        return
    skip = pytest.mark.skip(reason="hil: set STAGECTL_RIG to a rig file to run")
    for item in items:
        if "hil" in item.keywords:
            item.add_marker(skip)
