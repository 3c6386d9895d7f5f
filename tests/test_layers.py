"""Imports point down the architecture only (docs/architecture.md, the layer map).

Every module of the package has a rank. A module may import modules of its own rank or lower, never a
higher one, and no two modules may import each other through any chain (no cycles). Every import form
counts: ``import a.b``, ``from a import b`` (``b`` a submodule or a name), relative imports, imports inside
functions, ``importlib.import_module("a.b")`` / ``__import__("a.b")`` and ``import_module(f"a.{name}")``
(which counts as importing every module under ``a``). The mutation tests at the end feed the checker an
upward import of each form and a cycle, and expect it to fail.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: source directory -> dotted package it is installed as (pyproject's package-dir mapping)
SOURCES = {
    ROOT / "stagectl": "stagectl",
    ROOT / "drivers": "stagectl.drivers",
    ROOT / "sim": "stagectl.sim",
}

#: rank -> module patterns ("a.b" matches a.b and everything below it, the longest pattern wins; the bare
#: package "stagectl" matches only its own __init__, so a new top-level module must be given a rank here)
RANKS: dict[int, tuple[str, ...]] = {
    0: ("stagectl", "stagectl.errors", "stagectl.outputs", "stagectl.resources", "stagectl.clock",
        "stagectl.rt", "stagectl.jit"),
    1: ("stagectl.schema",),
    2: ("stagectl.friction", "stagectl.drivers", "stagectl.safety"),
    3: ("stagectl.control", "stagectl.sim", "stagectl.world_schema"),
    4: ("stagectl.ident", "stagectl.plots"),
    5: ("stagectl.loop", "stagectl.runtime", "stagectl.recorder"),
    6: ("stagectl.config",),
    7: ("stagectl.app", "stagectl.host"),
    8: ("stagectl.daemon",),
    9: ("stagectl.bench", "stagectl.commission"),
    10: ("stagectl.commands", "stagectl.cli"),
}
#: ranks whose groups are independent of each other: friction, drivers and safety know nothing of each
#: other, nor do control and sim (the plant and the control laws share only the friction math below them)
INDEPENDENT_GROUPS = {2, 3}
#: modules outside a group's package that belong to its group: the schema of the ``sim:`` section is the
#: simulation's own, kept outside ``stagectl.sim`` so that a controller whose plant runs in another process
#: validates the section without importing the simulation (control must not import it: sideways)
GROUP_OF_MODULE = {"stagectl.world_schema": "stagectl.sim"}
RANK_NAMES = {0: "foundations", 1: "schema", 2: "friction/drivers/safety", 3: "control/sim", 4: "ident",
              5: "runtime", 6: "config", 7: "assembly", 8: "daemon", 9: "bench", 10: "commands/cli"}

# pure layers must not touch the clock, I/O, logging or threads
PURE_FORBIDDEN_MODULES = {"time", "logging", "socket", "threading", "serial", "can", "canopen"}
PURE = ("stagectl.friction", "stagectl.control")


def discover_modules() -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (path, is_package) for every source file of the installed package."""
    out: dict[str, tuple[Path, bool]] = {}
    for src, prefix in SOURCES.items():
        for path in sorted(src.rglob("*.py")):
            rel = path.relative_to(src).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            if src.name == "stagectl" and parts and parts[0] in ("drivers", "sim"):
                continue
            out[".".join([prefix, *parts])] = (path, path.name == "__init__.py")
    return out


MODULES = discover_modules()


def group_of(mod: str) -> tuple[int, str] | None:
    """(rank, pattern) of module ``mod`` (the longest matching pattern), None when no pattern matches."""
    best: tuple[int, str] | None = None
    for rank, patterns in RANKS.items():
        for pat in patterns:
            below = mod.startswith(pat + ".") and pat != "stagectl"
            if (mod == pat or below) and (best is None or len(pat) > len(best[1])):
                best = (rank, pat)
    if best is not None and best[1] in GROUP_OF_MODULE:
        best = (best[0], GROUP_OF_MODULE[best[1]])
    return best


def rank_of(mod: str) -> int | None:
    """The rank of module ``mod``, None when no pattern matches."""
    g = group_of(mod)
    return None if g is None else g[0]


def _resolve(name: str, modules: dict[str, tuple[Path, bool]]) -> list[str]:
    """Internal modules an imported dotted name refers to (the longest existing module prefix)."""
    parts = name.split(".")
    while parts:
        cand = ".".join(parts)
        if cand in modules:
            return [cand]
        parts.pop()
    return []


def _dynamic_name(call: ast.Call) -> tuple[str, bool] | None:
    """(name, is_prefix) of ``import_module(...)`` / ``__import__(...)`` with a literal or f-string name."""
    f = call.func
    fname = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
    if fname not in ("import_module", "__import__") or not call.args:
        return None
    arg = call.args[0]
    if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
        return arg.value, False
    if isinstance(arg, ast.JoinedStr) and arg.values and isinstance(arg.values[0], ast.Constant):
        prefix = str(arg.values[0].value)
        return prefix.rstrip("."), True
    return None


def imports_of(modname: str, source: str, is_package: bool,
               modules: dict[str, tuple[Path, bool]]) -> Iterator[tuple[str, int]]:
    """(imported internal module or external top-level name, line) for every import form in ``source``."""
    tree = ast.parse(source)
    pkg = modname if is_package else modname.rsplit(".", 1)[0]
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = pkg.split(".")
                base_parts = base_parts[: len(base_parts) - (node.level - 1)]
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            for a in node.names:
                full = f"{base}.{a.name}"
                names.append(full if full in modules else base)
        elif isinstance(node, ast.Call):
            dyn = _dynamic_name(node)
            if dyn is not None:
                name, is_prefix = dyn
                if is_prefix:
                    under = [m for m in modules if m == name or m.startswith(name + ".")]
                    names = under or [name]
                else:
                    names = [name]
        for name in names:
            internal = _resolve(name, modules) if name.startswith("stagectl") else []
            if internal:
                yield internal[0], node.lineno
            elif name:
                yield name, node.lineno


def upward_imports(modname: str, source: str, is_package: bool,
                   modules: dict[str, tuple[Path, bool]]) -> list[str]:
    """Problems of one module: imports of a higher rank, and impure imports in the pure layers."""
    own = group_of(modname)
    bad: list[str] = []
    for imp, line in imports_of(modname, source, is_package, modules):
        other = group_of(imp) if imp.startswith("stagectl") else None
        if own is None or other is None:
            pass
        elif other[0] > own[0]:
            bad.append(f"line {line}: {imp} (rank {other[0]} {RANK_NAMES[other[0]]}) above {modname} "
                       f"(rank {own[0]} {RANK_NAMES[own[0]]})")
        elif other[0] == own[0] in INDEPENDENT_GROUPS and other[1] != own[1]:
            bad.append(f"line {line}: {imp} sideways from {modname} ({own[1]} and {other[1]} are independent)")
        if modname.startswith(PURE) and imp.split(".")[0] in PURE_FORBIDDEN_MODULES:
            bad.append(f"line {line}: {imp} in a pure layer")
    return bad


def import_graph(sources: dict[str, tuple[str, bool]],
                 modules: dict[str, tuple[Path, bool]]) -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {}
    for mod, (src, is_pkg) in sources.items():
        key = (mod, src, is_pkg, id(modules))  # a module's imports are parsed once per source text (a mutated
        if key not in _EDGES:  # module's new text is parsed afresh)
            _EDGES[key] = frozenset(imp for imp, _ in imports_of(mod, src, is_pkg, modules)
                                    if imp in modules and imp != mod)
        graph[mod] = set(_EDGES[key])
    return graph


#: import_graph's parsed edges by (module, source text, is package, id of the module table)
_EDGES: dict[tuple[str, str, bool, int], frozenset[str]] = {}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work: list[tuple[str, Iterator[str]]] = [(root, iter(sorted(graph.get(root, ()))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, it = work[-1]
            nxt = next(it, None)
            if nxt is not None:
                if nxt not in index:
                    index[nxt] = low[nxt] = counter
                    counter += 1
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(graph.get(nxt, ())))))
                elif nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                comp = []
                while True:
                    m = stack.pop()
                    on_stack.discard(m)
                    comp.append(m)
                    if m == node:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


SOURCE_TEXT = {m: (p.read_text(encoding="utf-8"), is_pkg) for m, (p, is_pkg) in MODULES.items()}


@pytest.mark.parametrize("modname", sorted(MODULES))
def test_every_module_has_a_rank(modname):
    assert rank_of(modname) is not None, f"{modname}: add it to RANKS in tests/test_layers.py"


@pytest.mark.parametrize("modname", sorted(MODULES))
def test_imports_point_down(modname):
    src, is_pkg = SOURCE_TEXT[modname]
    bad = upward_imports(modname, src, is_pkg, MODULES)
    assert not bad, f"{modname} imports against the layer map:\n" + "\n".join(bad)


def test_no_import_cycles():
    found = cycles(import_graph(SOURCE_TEXT, MODULES))
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


# ---------------------------------------------------------------------------------------------- mutations
# Each case puts one upward import of one form into a real module's source; the checker must flag it.
UPWARD_CASES = {
    "from-package-import-submodule": ("stagectl.friction.gms", "from stagectl import sim\n"),
    "plain-import": ("stagectl.control.pid", "import stagectl.loop\n"),
    "from-import-name": ("stagectl.safety", "from stagectl.control.controller import StageController\n"),
    "function-level": ("stagectl.schema", "def f():\n    from stagectl.friction import build\n    return build\n"),
    "relative": ("stagectl.control.dob", "from ..app import build_stage\n"),
    "relative-package": ("stagectl.friction", "from .. import loop\n"),
    "import_module-sideways": ("stagectl.control.controller",
                      "import importlib\nW = importlib.import_module('stagectl.sim.world')\n"),
    "import_module-fstring": ("stagectl.config", "import importlib\n"
                              "def f(n):\n    return importlib.import_module(f'stagectl.daemon.{n}')\n"),
    "dunder-import": ("stagectl.drivers.cia402", "m = __import__('stagectl.sim.plant')\n"),
    "drivers-to-control": ("stagectl.drivers.base", "from stagectl.control import api\n"),
    "safety-to-friction-sideways": ("stagectl.safety", "from stagectl.friction import build\n"),
    "config-to-app": ("stagectl.config", "from stagectl.app import build_stage\n"),
    "loop-to-assembly": ("stagectl.loop", "def f():\n    import stagectl.app\n"),
    "daemon-to-commands": ("stagectl.daemon", "from stagectl.commands import run\n"),
    "impure-friction": ("stagectl.friction.base", "import time\n"),
}


@pytest.mark.parametrize("case", sorted(UPWARD_CASES))
def test_checker_catches_each_upward_import_form(case):
    modname, extra = UPWARD_CASES[case]
    assert modname in MODULES, f"mutation target {modname} no longer exists; pick another"
    src, is_pkg = SOURCE_TEXT[modname]
    assert not upward_imports(modname, src, is_pkg, MODULES)  # clean before the mutation
    assert upward_imports(modname, src + "\n" + extra, is_pkg, MODULES), f"{case} not caught"


def test_checker_catches_cycles_of_each_form():
    # same-rank cycle through a function-level import
    mutated = dict(SOURCE_TEXT)
    src, is_pkg = mutated["stagectl.control.pid"]
    mutated["stagectl.control.pid"] = (src + "\ndef _f():\n    from stagectl.control import dob\n", is_pkg)
    assert any({"stagectl.control.pid", "stagectl.control.dob"} <= set(c)
               for c in cycles(import_graph(mutated, MODULES)))
    # cycle through a package __init__ (from a package import a name)
    mutated = dict(SOURCE_TEXT)
    src, is_pkg = mutated["stagectl.friction.base"]
    mutated["stagectl.friction.base"] = (src + "\nfrom stagectl.friction import build\n", is_pkg)
    assert any({"stagectl.friction", "stagectl.friction.base"} <= set(c)
               for c in cycles(import_graph(mutated, MODULES)))


def test_rank_table_resolves_as_documented():
    assert rank_of("stagectl") == 0
    assert rank_of("stagectl.friction.gms") == 2
    assert rank_of("stagectl.sim.plant") == 3
    assert rank_of("stagectl.drivers.cia402") == 2
    assert rank_of("stagectl.daemon.service") == 8
    assert rank_of("stagectl.nonexistent") is None  # a new top-level module needs a rank
