"""Imports point down the architecture chain only (docs/architecture.md section 1)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# source directory -> dotted package prefix
SOURCES = {
    ROOT / "stagectl": "stagectl",
    ROOT / "drivers": "stagectl.drivers",
    ROOT / "sim": "stagectl.sim",
}

# which top-level areas each area must never import
FORBIDDEN = {
    "stagectl.errors": ["stagectl.friction", "stagectl.sim", "stagectl.drivers", "stagectl.control"],
    "stagectl.schema": ["stagectl.friction", "stagectl.sim", "stagectl.drivers", "stagectl.control"],
    "stagectl.friction": [
        "stagectl.sim", "stagectl.drivers", "stagectl.control", "stagectl.loop", "stagectl.app",
        "stagectl.daemon", "stagectl.ident", "stagectl.commands", "stagectl.bench", "stagectl.cli",
    ],
    "stagectl.sim": [
        "stagectl.control", "stagectl.loop", "stagectl.app", "stagectl.daemon", "stagectl.ident",
        "stagectl.commands", "stagectl.bench", "stagectl.cli",
    ],
    "stagectl.drivers": [
        "stagectl.sim", "stagectl.control", "stagectl.loop", "stagectl.app", "stagectl.daemon",
        "stagectl.ident", "stagectl.commands", "stagectl.bench", "stagectl.cli",
    ],
    "stagectl.control": [
        "stagectl.sim", "stagectl.drivers", "stagectl.loop", "stagectl.app", "stagectl.daemon",
        "stagectl.ident", "stagectl.commands", "stagectl.bench", "stagectl.cli",
    ],
    "stagectl.loop": ["stagectl.daemon", "stagectl.ident", "stagectl.commands", "stagectl.cli"],
    "stagectl.app": ["stagectl.daemon", "stagectl.ident", "stagectl.commands", "stagectl.cli"],
    "stagectl.daemon": ["stagectl.commands", "stagectl.cli", "stagectl.ident"],
}

# pure layers must not touch the clock, I/O or logging
PURE_FORBIDDEN_MODULES = {"time", "logging", "socket", "threading", "serial", "can", "canopen"}
PURE = ("stagectl.friction", "stagectl.control")


def _modules():
    for src, prefix in SOURCES.items():
        for path in sorted(src.rglob("*.py")):
            rel = path.relative_to(src).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            if src.name == "stagectl" and parts and parts[0] in ("drivers", "sim"):
                continue
            yield ".".join([prefix, *parts]), path


def _imports(path: Path, modname: str):
    tree = ast.parse(path.read_text(encoding="utf-8"))
    pkg = modname if path.name == "__init__.py" else modname.rsplit(".", 1)[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")
                base = base[: len(base) - (node.level - 1)]
                yield ".".join(base + ([node.module] if node.module else []))
            elif node.module:
                yield node.module


def _area(mod: str) -> str | None:
    for area in sorted(FORBIDDEN, key=len, reverse=True):
        if mod == area or mod.startswith(area + "."):
            return area
    return None


MODULES = list(_modules())


@pytest.mark.parametrize("modname,path", MODULES, ids=[m for m, _ in MODULES])
def test_imports_point_down(modname, path):
    area = _area(modname)
    bad = []
    for imp in _imports(path, modname):
        if area:
            for forbidden in FORBIDDEN[area]:
                if imp == forbidden or imp.startswith(forbidden + "."):
                    bad.append(imp)
        if modname.startswith(PURE) and imp.split(".")[0] in PURE_FORBIDDEN_MODULES:
            bad.append(imp)
    assert not bad, f"{modname} imports {bad} against the layering rules"
