"""``stagectl bench startup [--config FILE] [--repeat N]``: time to the first control cycle.

Each run is a fresh interpreter (a real subprocess, ``python -c``) that does what ``stagectl run`` does up to
its first cycle: import the assembly, load the config, build the stage (devices, plant, controller) and run
one control cycle. The time is measured from just before the process is spawned to the end of that cycle
(both on the system-wide ``CLOCK_MONOTONIC``), so interpreter start-up, imports, numba compilation or cache
loading and device start-up are all in it. Two cases, in this order:

* **cold**: an empty, private numba cache directory (``NUMBA_CACHE_DIR`` set to a new temporary
  directory): every kernel the config uses is compiled;
* **warm**: the same directory again, now filled by the cold run: kernels are loaded from the cache.

Targets (issue 14): cold ≤ 2 s, warm ≤ 1 s. The machine's load average is reported alongside.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from stagectl.bench import tell

REPO_CONFIG = Path(__file__).resolve().parents[2] / "config" / "sim.yaml"
TARGET_COLD_S = 2.0
TARGET_WARM_S = 1.0

_CHILD = """
import json, sys, time
t_start = time.monotonic()
from stagectl.app import build_stage
from stagectl.config import load_app_config
t_imp = time.monotonic()
cfg = load_app_config(sys.argv[1])
with build_stage(cfg) as stage:
    t_built = time.monotonic()
    stage.loop.run(cycles=1)
    t_first = time.monotonic()
from stagectl.jit import cache_dir
print(json.dumps({"t_start": t_start, "t_imported": t_imp, "t_built": t_built, "t_first_cycle": t_first,
                  "cache_dir": str(cache_dir())}))
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default=str(REPO_CONFIG), help="config (default config/sim.yaml)")
    p.add_argument("--repeat", type=int, default=1, help="cold/warm pairs; the best of each is reported")


def _one(config: str, cache: Path) -> dict[str, float]:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-c", _CHILD, config], env=env, capture_output=True, text=True,
                         timeout=600)
    if out.returncode != 0:
        raise RuntimeError(f"start-up run failed (exit {out.returncode}): {out.stderr.strip()[-2000:]}")
    r = json.loads(out.stdout.strip().splitlines()[-1])
    return {
        "first_cycle_s": r["t_first_cycle"] - t0,
        "interpreter_s": r["t_start"] - t0,
        "imports_s": r["t_imported"] - r["t_start"],
        "config_and_build_s": r["t_built"] - r["t_imported"],
        "start_and_first_cycle_s": r["t_first_cycle"] - r["t_built"],
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    from stagectl.config import load_app_config

    load_app_config(args.config)  # a bad config is one error line here, not the child's traceback
    load0 = os.getloadavg()
    cold: list[dict[str, float]] = []
    warm: list[dict[str, float]] = []
    n = max(1, int(args.repeat))
    for i in range(n):
        with tempfile.TemporaryDirectory(prefix="stagectl-numba-") as tmp:
            tell(args, 2 * i, 2 * n, f"run {2 * i + 1} of {2 * n}, empty numba cache")
            cold.append(_one(args.config, Path(tmp)))
            tell(args, 2 * i + 1, 2 * n, f"run {2 * i + 2} of {2 * n}, warm numba cache")
            warm.append(_one(args.config, Path(tmp)))
    best_cold = min(cold, key=lambda r: r["first_cycle_s"])
    best_warm = min(warm, key=lambda r: r["first_cycle_s"])
    return {
        "benchmark": "startup",
        "config": args.config,
        "cold": best_cold,
        "warm": best_warm,
        "runs": {"cold_first_cycle_s": [r["first_cycle_s"] for r in cold],
                 "warm_first_cycle_s": [r["first_cycle_s"] for r in warm]},
        "targets": {"cold_le_2s": best_cold["first_cycle_s"] <= TARGET_COLD_S,
                    "warm_le_1s": best_warm["first_cycle_s"] <= TARGET_WARM_S},
        "loadavg_before": list(load0),
        "loadavg_after": list(os.getloadavg()),
        "cpus": os.cpu_count(),
    }
