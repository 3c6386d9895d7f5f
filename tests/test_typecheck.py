"""``mypy --strict`` over the whole installed package, drivers and sim included.

The repository keeps ``drivers/`` and ``sim/`` at the top level and installs them as ``stagectl.drivers`` and
``stagectl.sim`` (pyproject's package-dir mapping), which a type checker run on the source tree cannot
see. This test builds the installed shape as a tree of links in a temporary directory and type-checks it
as the package ``stagectl`` with the project's mypy configuration, so every seam between the layers is
checked.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def link_tree(dest: Path) -> Path:
    """``dest/stagectl`` laid out as installed: the package's entries plus ``drivers`` and ``sim``."""
    pkg = dest / "stagectl"
    pkg.mkdir(parents=True)
    for entry in (ROOT / "stagectl").iterdir():
        if entry.name not in ("__pycache__", "drivers", "sim"):
            (pkg / entry.name).symlink_to(entry)
    (pkg / "drivers").symlink_to(ROOT / "drivers")
    (pkg / "sim").symlink_to(ROOT / "sim")
    return dest


def mypy_cache_dir() -> Path:
    """mypy's incremental cache for this checkout, kept between runs (outside the tree).

    An empty cache costs ~13 s of CPU (numpy's, scipy's and the package's stubs and modules); a kept one
    ~0.5 s when nothing changed. mypy re-checks every module whose source (by hash, the tree of links moves
    with ``tmp_path``) or whose dependencies' interfaces changed, and replays the errors it cached, so the
    verdict is the one of a run on an empty cache. One directory per checkout: two trees never overwrite
    each other's entries.
    """
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "stagectl" / "mypy"
    return base / hashlib.sha256(str(ROOT).encode()).hexdigest()[:16]


def test_mypy_strict_over_the_whole_package(tmp_path):
    tree = link_tree(tmp_path / "tree")
    cmd = [sys.executable, "-m", "mypy", "--config-file", str(ROOT / "pyproject.toml"),
           "--cache-dir", str(mypy_cache_dir()), "--no-error-summary", "-p", "stagectl"]
    r = subprocess.run(cmd, cwd=tree, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, f"mypy --strict found problems:\n{r.stdout}{r.stderr}"


def test_link_tree_has_the_installed_shape(tmp_path):
    pkg = link_tree(tmp_path) / "stagectl"
    assert (pkg / "drivers" / "cia402.py").is_file()
    assert (pkg / "sim" / "plant.py").is_file()
    assert (pkg / "friction" / "gms.py").is_file()
