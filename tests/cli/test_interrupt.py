"""Ctrl-C: a real SIGINT to a real `stagectl simulate` process. It says so in one line, exits 130 and keeps
what it had simulated (telemetry and a summary marked interrupted). No wall-clock sleep: the test waits for
the process's own progress line before it sends the signal."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_ctrl_c_in_simulate_keeps_what_was_simulated(tmp_path: Path) -> None:
    out = tmp_path / "run"
    script = Path(sys.executable).with_name("stagectl")
    p = subprocess.Popen([str(script), "simulate", "--config", "config/sim.yaml", "--scenario", "cosine",
                          "--duration", "600", "--out", str(out), "--no-plots"], cwd=REPO, text=True,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**os.environ, "STAGECTL_TRACEBACK": ""})
    try:
        assert p.stderr is not None
        first = p.stderr.readline()  # the first progress line: the loop is running
        assert first.startswith("simulate: "), first
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130, err
    assert "stagectl: interrupted (Ctrl-C)" in err and "Traceback" not in err, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] is True and summary["samples"] > 100
    rows = (out / "telemetry.csv").read_text().splitlines()
    assert len(rows) == summary["samples"] + 1  # header + every simulated row
