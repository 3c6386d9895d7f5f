"""``stagectl bench startup [--config FILE] [--repeat N] [--against PYTHON]``: time to the first control cycle.

Each run is a fresh interpreter (a real subprocess) running the real command
``stagectl run --config FILE --duration 0.05 --no-plots --out TMP`` through ``stagectl.cli.main``. The child
only adds time stamps: it wraps ``load_app_config``, ``build_stage`` and ``LoopHost.start`` (a telemetry sink
that notes the first row) as their modules are imported, without importing anything early. The time is
measured from just before the process is spawned to the first telemetry row, i.e. the end of the first
control cycle (both on the system-wide ``CLOCK_MONOTONIC``), so interpreter start-up, imports, config
validation, numba compilation or cache loading and device start-up are all in it. Two cases, in this order:

* **cold**: an empty, private numba cache directory (``NUMBA_CACHE_DIR`` set to a new temporary
  directory): every kernel the command uses is compiled;
* **warm**: the same directory again, now filled by the cold run: kernels are loaded from the cache.

Python byte code is cached in both cases, as in an installed package: before its measured runs each interpreter
runs the same command once, unmeasured, writing the byte code of everything it imports into a private
``PYTHONPYCACHEPREFIX``, which the measured runs then read (and do not write). Without it an environment with
``PYTHONDONTWRITEBYTECODE`` set would compile stagectl's sources on every start (~0.1 s of CPU) and the figures
would depend on whether ``__pycache__`` happened to be writable.

``--against PYTHON`` measures a second installation (e.g. a virtualenv of the previous release) the same way,
alternated with this one run by run (its own private cache), and reports the ratios: a before/after comparison
on a shared machine whose load drifts.

``--stage`` measures a real stage's start instead (default config ``config/hil-canopen.yaml``): the config's
``sim:`` section runs once in a ``stagectl sim-plant`` process (socketcand on an ephemeral loopback port, this
build's interpreter), and every measured start runs the config *without* its ``sim:`` section against it, as a
stage PC runs it (real drivers, no simulated plant in the process: no numba, the feed-forward in plain Python).
``--stage --hil``: the measured starts run the whole file, ``sim:`` included (its transport pointed at the same
sim-plant), as ``stagectl run --config config/hil-canopen.yaml`` does on the HIL: the controller validates the
``sim:`` section but runs no plant.

Targets (issue 14): cold ≤ 2 s, warm ≤ 1 s. The machine's load average is reported alongside.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from stagectl.bench import tell
from stagectl.errors import StageError

REPO_CONFIG = Path(__file__).resolve().parents[2] / "config" / "sim.yaml"
STAGE_CONFIG = REPO_CONFIG.with_name("hil-canopen.yaml")
TARGET_COLD_S = 2.0
TARGET_WARM_S = 1.0

_CHILD = r"""
import time
T = {"start": time.monotonic()}
import importlib.abc, importlib.util, json, sys

def _patch(mod):
    name = mod.__name__
    if name == "stagectl.config":
        f0 = mod.load_app_config
        def load_app_config(*a, **k):
            T.setdefault("config", time.monotonic())
            return f0(*a, **k)
        mod.load_app_config = load_app_config
    elif name == "stagectl.app":
        f1 = mod.build_stage
        def build_stage(*a, **k):
            T.setdefault("build", time.monotonic())
            st = f1(*a, **k)
            T.setdefault("built", time.monotonic())
            return st
        mod.build_stage = build_stage
    elif name == "stagectl.runtime.host":
        start0 = mod.LoopHost.start
        class First:
            def append(self, row):
                if "first" not in T:
                    T["first"] = time.monotonic()
                    # the tier the first cycle ran on: numba's compiled kernels, or plain Python (no numba)
                    T["first_tier"] = "compiled" if "numba" in sys.modules else "plain"
        def start(self, **kw):
            T.setdefault("host_start", time.monotonic())
            self.sinks = (*self.sinks, First())
            return start0(self, **kw)
        mod.LoopHost.start = start

class Hook(importlib.abc.MetaPathFinder):
    names = {"stagectl.config", "stagectl.app", "stagectl.runtime.host"}
    def find_spec(self, name, path, target=None):
        if name not in self.names:
            return None
        sys.meta_path.remove(self)
        try:
            spec = importlib.util.find_spec(name)
        finally:
            sys.meta_path.insert(0, self)
        ex = spec.loader.exec_module
        def exec_module(module):
            ex(module)
            _patch(module)
        spec.loader.exec_module = exec_module
        return spec

sys.meta_path.insert(0, Hook())
from stagectl.cli import main
rc = main(["run", "--config", sys.argv[1], "--duration", "0.05", "--no-plots", "--out", sys.argv[2]])
from stagectl.jit import cache_dir
T["rc"] = rc
T["cache_dir"] = str(cache_dir())
with open(sys.argv[3], "w") as fh:
    json.dump(T, fh)
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default=str(REPO_CONFIG), help="config (default config/sim.yaml)")
    p.add_argument("--repeat", type=int, default=1, help="cold/warm pairs; the best of each is reported")
    p.add_argument("--against", default=None, metavar="PYTHON",
                   help="interpreter of another stagectl installation, measured alternately as the baseline")
    p.add_argument("--stage", action="store_true",
                   help="a real stage's start: the config's sim: section in a sim-plant process, the measured starts "
                        "on the config without it (default config config/hil-canopen.yaml)")
    p.add_argument("--hil", action="store_true",
                   help="with --stage: the measured starts run the whole config, sim: section included (a HIL "
                        "controller, whose plant runs in the sim-plant process)")
    p.add_argument("--switch", action="store_true",
                   help="also measure a tiered start (plain-Python kernels first, numba's loaded in a background "
                        "thread, then switched to): loop lateness around the switch vs plain and compiled runs "
                        "(stagectl.bench.tier)")
    p.add_argument("--switch-cycles", type=int, default=2000, help="cycles per --switch run (default 2000)")
    p.add_argument("--switch-interval", type=float, default=None, metavar="S",
                   help="sys.setswitchinterval in the --switch runs [s] (default Python's, 0.005)")


def _one(python: str, config: str, cache: Path, pyc: Path, prime: bool = False) -> dict[str, Any]:
    """One start of ``python`` with the numba cache ``cache`` and the byte-code cache ``pyc`` (written only
    when ``prime``)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPYCACHEPREFIX=str(pyc))
    if prime:
        env.pop("PYTHONDONTWRITEBYTECODE", None)
    else:
        env["PYTHONDONTWRITEBYTECODE"] = "1"
    with tempfile.TemporaryDirectory(prefix="stagectl-startup-") as tmp:
        stamps = Path(tmp) / "stamps.json"
        ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.monotonic()
        # run in the temporary directory: ``python -c`` puts the working directory first on sys.path, and from a
        # checkout's root the baseline interpreter would import *this* checkout's stagectl package
        out = subprocess.run([python, "-c", _CHILD, os.path.abspath(config), str(Path(tmp) / "out"), str(stamps)],
                             env=env, capture_output=True, text=True, timeout=600, cwd=tmp)
        ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        if out.returncode != 0 or not stamps.exists():
            last = (out.stderr.strip().splitlines() or ["no output"])[-1][:300]
            raise StageError(f"bench startup: the start with {python} failed (exit {out.returncode}): {last}")
        r = json.loads(stamps.read_text())
    if "first" not in r:
        raise StageError(f"bench startup: the start with {python} ran no control cycle this bench can see (an "
                         "older stagectl lacks the module it hooks, stagectl.runtime.host); give --against an "
                         "installation of the same layout")
    return {
        "first_cycle_s": r["first"] - t0,
        "interpreter_s": r["start"] - t0,
        "imports_s": r["config"] - r["start"],
        "config_s": r["build"] - r["config"],
        "build_s": r["built"] - r["build"],
        "start_and_first_cycle_s": r["first"] - r["built"],
        # which kernels the first cycle ran on, and from when (after the spawn) the compiled ones ran
        "first_cycle_tier": r.get("first_tier", "compiled"),
        "compiled_tier_from_s": r["first"] - t0 if r.get("first_tier", "compiled") == "compiled" else None,
        # CPU time of the whole child (to its exit: includes the 0.05 s run and writing its outputs); less
        # disturbed by other load than the wall-clock figures above
        "process_cpu_s": (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime),
    }


def _pairs(args: argparse.Namespace, python: str, pyc: Path, done: int,
           total: int) -> tuple[dict[str, Any], dict[str, Any]]:
    """A cold and a warm run of ``python`` with a new private cache (runs ``done`` and ``done + 1`` of ``total``)."""
    who = "baseline" if python != sys.executable else "this build"
    with tempfile.TemporaryDirectory(prefix="stagectl-numba-") as tmp:
        tell(args, done, total, f"run {done + 1} of {total} ({who}), empty numba cache")
        cold = _one(python, args.config, Path(tmp), pyc)
        tell(args, done + 1, total, f"run {done + 2} of {total} ({who}), warm numba cache")
        warm = _one(python, args.config, Path(tmp), pyc)
    return cold, warm


def _prime(args: argparse.Namespace, python: str, pyc: Path) -> None:
    """The unmeasured start that writes ``python``'s byte code into ``pyc`` (module docstring)."""
    who = "baseline" if python != sys.executable else "this build"
    tell(args, 0, 1, f"byte code of {who} (one unmeasured start)")
    with tempfile.TemporaryDirectory(prefix="stagectl-numba-") as tmp:
        _one(python, args.config, Path(tmp), pyc, prime=True)


def _summary(cold: list[dict[str, Any]], warm: list[dict[str, Any]]) -> dict[str, Any]:
    best_cold = min(cold, key=lambda r: r["first_cycle_s"])
    best_warm = min(warm, key=lambda r: r["first_cycle_s"])
    return {"cold": best_cold, "warm": best_warm,
            "runs": {"cold_first_cycle_s": [r["first_cycle_s"] for r in cold],
                     "warm_first_cycle_s": [r["first_cycle_s"] for r in warm],
                     "cold_process_cpu_s": [r["process_cpu_s"] for r in cold],
                     "warm_process_cpu_s": [r["process_cpu_s"] for r in warm]}}


class _SimPlant:
    """``stagectl sim-plant`` on the ``sim:`` section of ``config`` (socketcand, ephemeral port) and the same config
    without ``sim:`` pointed at it (``stage_config``), for ``--stage``. A context manager; stops the process."""

    def __init__(self, config: str, tmp: Path, keep_sim: bool = False) -> None:
        import yaml

        from stagectl.errors import ConfigError
        from stagectl.schema import absolute_paths, load_yaml_file

        data = load_yaml_file(config)
        if not isinstance(data, dict) or not isinstance(data.get("sim"), dict):
            raise ConfigError(f"--stage: {config} has no sim: section (the stage for the sim-plant process)")
        data = absolute_paths(data, Path(config).resolve().parent)
        drive = (data.get("io") or {}).get("drive") or {}
        if (data["io"].get("kind") != "canopen" or (drive.get("can") or {}).get("interface") != "socketcand"):
            raise ConfigError(f"--stage: {config}: needs io.kind canopen with io.drive.can.interface socketcand "
                              "(a controller that talks to a sim-plant process)")
        plant = dict(data, sim=dict(data["sim"], transport=dict(data["sim"].get("transport") or {},
                                                                kind="socketcand", port=0)))
        self._plant_cfg = tmp / "plant.yaml"
        self._plant_cfg.write_text(yaml.safe_dump(plant))
        self._data = data
        self._keep_sim = keep_sim
        self.stage_config = tmp / "stage.yaml"
        self._proc: subprocess.Popen[str] | None = None

    def __enter__(self) -> _SimPlant:
        import selectors

        import yaml

        self._proc = subprocess.Popen([sys.executable, "-m", "stagectl.cli", "sim-plant", "--config",
                                       str(self._plant_cfg)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                      text=True)
        assert self._proc.stdout is not None
        sel = selectors.DefaultSelector()
        sel.register(self._proc.stdout, selectors.EVENT_READ)
        line = self._proc.stdout.readline() if sel.select(300.0) else ""
        if not line:
            self.__exit__(None, None, None)
            raise StageError("bench startup --stage: the sim-plant process printed no ready line")
        port = json.loads(line)["can"]["port"]
        stage = {k: v for k, v in self._data.items() if k != "sim"}
        if self._keep_sim:  # the HIL file itself: its sim: describes the sim-plant it talks to
            stage["sim"] = dict(self._data["sim"], transport=dict(self._data["sim"].get("transport") or {},
                                                                  kind="socketcand", port=port))
        stage["io"]["drive"]["can"]["port"] = port
        self.stage_config.write_text(yaml.safe_dump(stage))
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._proc is not None and self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(10.0)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait(10.0)


def run(args: argparse.Namespace) -> dict[str, Any]:
    if getattr(args, "hil", False) and not getattr(args, "stage", False):
        from stagectl.errors import ConfigError

        raise ConfigError("--hil: only with --stage (the HIL controller's start against a sim-plant process)")
    if getattr(args, "stage", False):
        if args.config == str(REPO_CONFIG):
            args.config = str(STAGE_CONFIG)
        hil = bool(getattr(args, "hil", False))
        with tempfile.TemporaryDirectory(prefix="stagectl-stage-") as tmp, \
                _SimPlant(args.config, Path(tmp), keep_sim=hil) as sp:
            source = args.config
            args.config = str(sp.stage_config)
            try:
                res = _run(args)
            finally:
                args.config = source
            what = "the whole config (sim: included, its plant in the sim-plant)" if hil else \
                "the config without its sim: section"
            res["stage"] = {"source_config": source, "hil": hil, "note": f"measured starts run {what} against a "
                            "stagectl sim-plant process (socketcand on loopback)"}
            return res
    return _run(args)


def _run(args: argparse.Namespace) -> dict[str, Any]:
    from stagectl.config import load_app_config
    from stagectl.errors import ConfigError

    cfg = load_app_config(args.config)  # a bad config is one error line here, not the child's traceback
    against = getattr(args, "against", None)
    if against and not (os.path.isfile(against) and os.access(against, os.X_OK)):
        raise ConfigError(f"--against: {against} is not an executable Python interpreter")
    load0 = os.getloadavg()
    cold: list[dict[str, Any]] = []
    warm: list[dict[str, Any]] = []
    b_cold: list[dict[str, Any]] = []
    b_warm: list[dict[str, Any]] = []
    n = max(1, int(args.repeat))
    per = 4 if against else 2
    with tempfile.TemporaryDirectory(prefix="stagectl-pyc-") as pyc_root:
        pyc = Path(pyc_root) / "this"
        b_pyc = Path(pyc_root) / "baseline"
        if against:
            _prime(args, against, b_pyc)
        _prime(args, sys.executable, pyc)
        for i in range(n):
            if against:
                c, w = _pairs(args, against, b_pyc, per * i, per * n)
                b_cold.append(c)
                b_warm.append(w)
            c, w = _pairs(args, sys.executable, pyc, per * i + per - 2, per * n)
            cold.append(c)
            warm.append(w)
    res: dict[str, Any] = {"benchmark": "startup", "command": "stagectl run --config CONFIG --duration 0.05 "
                           "--no-plots (time to its first telemetry row)", "config": args.config,
                           "byte_code": "cached (written by one unmeasured start per interpreter)",
                           **_summary(cold, warm)}
    res["targets"] = {"cold_le_2s": res["cold"]["first_cycle_s"] <= TARGET_COLD_S,
                      "warm_le_1s": res["warm"]["first_cycle_s"] <= TARGET_WARM_S}
    if against:
        base = _summary(b_cold, b_warm)
        res["baseline"] = {"python": against, **base}
        res["vs_baseline"] = {
            "cold_speedup": base["cold"]["first_cycle_s"] / res["cold"]["first_cycle_s"],
            "warm_speedup": base["warm"]["first_cycle_s"] / res["warm"]["first_cycle_s"],
            "cold_cpu_ratio": min(base["runs"]["cold_process_cpu_s"]) / min(res["runs"]["cold_process_cpu_s"]),
            "warm_cpu_ratio": min(base["runs"]["warm_process_cpu_s"]) / min(res["runs"]["warm_process_cpu_s"]),
        }
    res.update({"loadavg_before": list(load0), "loadavg_after": list(os.getloadavg()), "cpus": os.cpu_count()})
    if getattr(args, "switch", False):
        from stagectl.bench import tier

        def progress(done: float, total: float, what: str) -> None:
            tell(args, done, total, f"tiered start: {what}")

        res["switch"] = tier.run_switch(cfg, max(1, int(args.switch_cycles)), args.switch_interval, progress)
    return res
