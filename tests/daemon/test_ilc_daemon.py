"""The learning feed-forward through the real daemon (subprocess, loop in its own process, embedded simulated plant
of config/sim.yaml with ``ilc.enabled``): ``ilc`` requests start a named motion and learn it, ``status`` shows
the iteration, save/load round trip per motion name, a fault freezes learning, the ``stagectl ilc`` client, and
refusals naming the field. Waits are on replies; timeouts are failure guards only.
"""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

import pytest
import yaml
from support import absolutize_paths, stagectl_cmd

from stagectl.daemon.control import ControlClient

REPO = Path(__file__).resolve().parents[2]
SIM_YAML = REPO / "config" / "sim.yaml"




def _until(c: ControlClient, req: dict, cond, guard_s: float = 60.0) -> dict:
    end = time.monotonic() + guard_s
    while time.monotonic() < end:
        r = c.request(req)
        if cond(r):
            return r
        time.sleep(0.1)
    raise TimeoutError(f"{req} did not reach the condition within {guard_s} s")


def test_ilc_through_the_daemon(tmp_path, notify_socket):
    cfg = absolutize_paths(yaml.safe_load(SIM_YAML.read_text()), SIM_YAML.parent)
    cfg["loop"]["healthy_overrun_fraction"] = 0.5
    cfg["loop"]["realtime"] = {**cfg["loop"]["realtime"], "fifo_priority": None, "mlock": False}
    cfg["daemon"] = {"allow_fault_injection": True, "status_interval_s": 0.1, "ready_timeout_s": 60,
                     "telemetry": {"directory": str(tmp_path / "telemetry")}}
    cfg["ilc"] = {"enabled": True, "store_dir": str(tmp_path / "learned")}
    path = tmp_path / "stagectl.yaml"
    path.write_text(yaml.safe_dump(cfg))
    run = tmp_path / "run"
    env = {**os.environ, "NOTIFY_SOCKET": str(notify_socket.path), "WATCHDOG_USEC": "2000000", "PYTHONUNBUFFERED": "1"}
    env.pop("WATCHDOG_PID", None)
    proc = subprocess.Popen([*stagectl_cmd(), "daemon", "--config", str(path), "--runtime-dir", str(run)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        try:
            notify_socket.wait_for("READY", "1", timeout=120, alive=lambda: proc.poll() is None)
        except TimeoutError:
            proc.kill()
            pytest.fail("no READY=1; daemon stderr:\n" + proc.communicate(timeout=30)[1][-4000:])
        sock = run / "control.sock"
        with ControlClient(sock, timeout_s=30) as c:
            r = c.request({"request": "ilc", "action": "status"})
            assert r["ok"] and r["motion"] is None and not r["learning"], r
            r = c.request({"request": "ilc", "action": "dance"})
            assert r["ok"] is False and r["field"] == "action", r
            r = c.request({"request": "ilc", "action": "start", "motion": "nonesuch"})
            assert r["ok"] is False and r["field"] == "motion", r
            r = c.request({"request": "ilc", "action": "start", "motion": "steps"})  # ~1.2 s per repetition
            assert r["ok"] and r["learning"] and r["repetition_s"] > 0.5, r
            # learned from at least one full repetition; status (from the telemetry) shows the iteration
            _until(c, {"request": "ilc", "action": "status"}, lambda r: r["iteration"] >= 1)
            st = _until(c, {"request": "status"}, lambda r: (r["status"]["loop"].get("ilc") or {}).get("iteration"))
            assert st["status"]["loop"]["ilc"]["iteration"] >= 1
            r = c.request({"request": "ilc", "action": "save", "motion": "steps-a"})
            assert r["ok"] and Path(r["saved"]) == tmp_path / "learned" / "steps-a.npz", r
            r = c.request({"request": "ilc", "action": "load", "motion": "steps-a"})
            assert r["ok"] and r["loaded"].endswith("steps-a.npz") and r["motion"] == "steps" and r["iteration"] >= 1, r
            # the client command
            out = subprocess.run([*stagectl_cmd(), "ilc", "status", "--socket", str(sock)], capture_output=True,
                                 text=True, timeout=60)
            assert out.returncode == 0 and "motion steps " in out.stdout and "iteration 0" not in out.stdout, out.stdout
            # a fault freezes learning
            assert c.request({"request": "fault", "kind": "emcy"})["ok"]
            r = _until(c, {"request": "ilc", "action": "status"}, lambda r: r["frozen"])
            assert not r["learning"] and r["gain"] == 0.0
            r = c.request({"request": "ilc", "action": "start", "motion": "steps"})
            assert r["ok"] is False and "reset" in r["error"], r
            assert c.request({"request": "ilc", "action": "stop"})["ok"]
        proc.terminate()
        assert proc.wait(60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
        proc.stdout.close()
        proc.stderr.close()
