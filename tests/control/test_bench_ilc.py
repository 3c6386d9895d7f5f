"""``stagectl bench ilc`` on a short run (steps scenario, 4 repetitions, friction change after 2): structure, the
plot, the learning trend; and ``simulate --ilc`` without a repeated motion is one clear error (exit 2)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from stagectl.bench import ilc as bench

REPO = Path(__file__).resolve().parents[2]


def test_bench_ilc_short_run(tmp_path):
    p = argparse.ArgumentParser()
    bench.add_arguments(p)
    res = bench.run(p.parse_args(["--scenario", "steps", "--repetitions", "4", "--change-after", "2",
                                  "--out", str(tmp_path)]))
    json.dumps(res)  # JSON-serialisable as printed by --json
    assert Path(res["plot"]).stat().st_size > 1000
    assert res["design"]["monotonic"]
    nominal, changed = res["runs"]["nominal"], res["runs"]["friction_change"]
    assert nominal["fault"] is None and changed["fault"] is None and changed["friction_changed"]
    rms = nominal["rms_nm"]
    assert len(rms) >= 3 and rms[-1] < 0.7 * rms[0], rms  # learning on the 20 %-wrong model
    assert changed["rms_nm"][:2] == rms[:2]  # the same run until the change (deterministic)
    assert isinstance(res["all_targets_met"], bool)


def test_simulate_ilc_needs_repetitions(tmp_path):
    exe = Path(sys.executable).parent / "stagectl"
    r = subprocess.run([str(exe), "simulate", "--config", str(REPO / "config" / "sim.yaml"), "--scenario", "steps",
                        "--ilc", "--out", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--repetitions" in r.stderr and "Traceback" not in r.stderr, r.stderr
