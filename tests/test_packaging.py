"""pyproject's explicit package list names every package of the source tree (a missing one installs in
editable mode but is absent from a wheel)."""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_package_directory_is_listed_in_pyproject():
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    st = meta["tool"]["setuptools"]
    listed = set(st["packages"])
    dirs = {pkg: ROOT / d for pkg, d in st["package-dir"].items()}
    found: set[str] = set()
    for init in (ROOT / "stagectl").rglob("__init__.py"):
        found.add(".".join(("stagectl", *init.parent.relative_to(ROOT / "stagectl").parts)).rstrip("."))
    for pkg, d in dirs.items():
        for init in d.rglob("__init__.py"):
            found.add(".".join((pkg, *init.parent.relative_to(d).parts)))
    assert found == listed, f"missing from pyproject: {sorted(found - listed)}; stale: {sorted(listed - found)}"


def test_filterpy_is_a_test_dependency_only() -> None:
    """Issue 15: the observer's test oracle (filterpy) is not installed with stagectl, and no module uses it."""
    import tomllib

    root = Path(__file__).resolve().parents[1]
    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    assert not any(d.lower().startswith("filterpy") for d in project["dependencies"])
    assert any(d.lower().startswith("filterpy") for d in project["optional-dependencies"]["test"])
    for pkg in ("stagectl", "drivers", "sim"):
        for f in (root / pkg).rglob("*.py"):
            assert "filterpy" not in f.read_text(encoding="utf-8"), f
