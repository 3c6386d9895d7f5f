"""A real stage's controller process imports neither numba nor the simulation (issue 14, docs/performance.md §1),
nor does a HIL config's controller, whose plant runs in the other process.

A config without ``sim:`` (CANopen drive over socketcand, as a stage PC with a socketcand adapter would have) runs
``stagectl run`` in a real subprocess against ``stagectl sim-plant`` in another: the controller's feed-forward steps
its GMS model as plain Python, and after the run (and after importing the daemon's modules) ``numba`` and
``stagectl.sim`` are absent from the controller's ``sys.modules``, while the run moved the stage with a non-zero
feed-forward. The same with the whole HIL file, ``sim:`` section included (config/hil-canopen.yaml as shipped,
ports aside): the controller validates that section (:mod:`stagectl.world_schema`) without importing
``stagectl.sim``, whose plant runs in ``stagectl sim-plant``. Real time across processes: timeouts are failure
guards, not waits.
"""

from __future__ import annotations

import json
import selectors
import subprocess
import sys

import yaml
from support import absolutize_paths, shipped_config_mapping, stop_process

from stagectl.resources import config_dir

#: the controller process: the real command through stagectl.cli.main, then what it imported
PROBE = r"""
import json, sys
from stagectl.cli import main
rc = main(["run", "--config", sys.argv[1], "--duration", "0.3", "--scenario", "cosine", "--no-plots", "-q",
           "--out", sys.argv[2]])
import stagectl.commands.daemon, stagectl.daemon.assemble  # the daemon's own modules add no numba either
heavy = sorted(m for m in sys.modules if m == "numba" or m.startswith(("numba.", "stagectl.sim")))
print(json.dumps({"rc": rc, "heavy": heavy}))
"""


def read_line(proc, timeout_s: float) -> str:
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    if not sel.select(timeout_s):
        raise AssertionError(f"sim-plant printed no ready line within {timeout_s} s: {proc.poll()}")
    return str(proc.stdout.readline())


def test_a_real_stage_run_imports_no_numba_and_no_simulation(tmp_path) -> None:
    hil = shipped_config_mapping("hil-canopen.yaml")
    plant_cfg = tmp_path / "plant.yaml"
    hil["sim"]["transport"]["port"] = 0
    plant_cfg.write_text(yaml.safe_dump(absolutize_paths(hil, config_dir())))
    proc = subprocess.Popen([sys.executable, "-m", "stagectl.cli", "sim-plant", "--config", str(plant_cfg)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        info = json.loads(read_line(proc, 120.0))
        hil["io"]["drive"]["can"]["port"] = hil["sim"]["transport"]["port"] = info["can"]["port"]
        runs = []
        # what a stage PC has (no simulated stage), then the HIL file itself: its sim: section is validated, its
        # plant runs in the sim-plant process
        for name, cfg in (("stage", {k: v for k, v in hil.items() if k != "sim"}), ("hil", hil)):
            path = tmp_path / f"{name}.yaml"
            path.write_text(yaml.safe_dump(absolutize_paths(cfg, config_dir())))
            out = tmp_path / name
            r = subprocess.run([sys.executable, "-c", PROBE, str(path), str(out)], capture_output=True, text=True,
                               timeout=300)
            runs.append((name, r, out))
    finally:
        stop_process(proc, 10.0)
    for name, r, out in runs:
        assert r.returncode == 0, (name, r.stderr[-2000:])
        got = json.loads(r.stdout.strip().splitlines()[-1])
        assert got == {"rc": 0, "heavy": []}, name
        tele = (out / "telemetry.csv").read_text().splitlines()
        head = tele[0].split(",")
        rows = [dict(zip(head, line.split(","))) for line in tele[1:] if line and not line.startswith("#")]
        assert len(rows) > 50, name  # it ran cycles against the drive
        assert any(abs(float(r["u_ff"])) > 0.0 for r in rows), name  # the plain feed-forward pushed
