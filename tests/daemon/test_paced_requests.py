"""A client's stop must not wait on a slow plant (issue 12): the daemon on config/hil-canopen.yaml (device time,
``loop.pace_cycles: 1``) against a real ``stagectl sim-plant`` process, which is then frozen with SIGSTOP (its
process held off the CPU: it answers no SYNC and its plant stands still). The loop waits for it, and a ``stop``
sent over the control socket meanwhile is answered while the plant is still frozen; before, the loop process
took requests only at a cycle boundary, so the reply waited for the drive (here: for ever, the daemon's own
``reply_timeout_s`` ending it with an error; in the shipped config up to ``io.drive.max_missed``, 1 s).

Every wait is on a ready line, a notify datagram or a reply; timeouts are failure guards, not waits.
"""

from __future__ import annotations

import json
import os
import selectors
import signal
import subprocess
import sys
import time

import pytest
import yaml
from support import absolutize_paths, shipped_config_mapping, stagectl_cmd, stop_process

from stagectl.daemon.control import ControlClient
from stagectl.resources import config_dir

pytest.importorskip("can")


def _ready_line(proc: subprocess.Popen, timeout_s: float) -> dict:
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    for _ in range(20):  # the ready line is JSON; anything else on stdout is skipped
        if not sel.select(timeout_s):
            break
        line = proc.stdout.readline()
        if not line:
            break
        try:
            info = json.loads(line)
        except ValueError:
            continue
        if isinstance(info, dict) and info.get("ready") is True:
            return info
    raise AssertionError(f"sim-plant not ready: {proc.poll()}")


def test_a_stop_is_answered_while_the_sim_plant_is_frozen(tmp_path, notify_socket) -> None:
    hil = shipped_config_mapping("hil-canopen.yaml")
    hil["sim"]["transport"]["port"] = 0
    plant_cfg = tmp_path / "plant.yaml"
    plant_cfg.write_text(yaml.safe_dump(absolutize_paths(hil, config_dir())))
    plant = subprocess.Popen([*stagectl_cmd(), "sim-plant", "--config", str(plant_cfg)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    daemon = None
    frozen = False
    try:
        info = _ready_line(plant, 120.0)
        cfg = dict(hil)
        cfg["io"]["drive"]["can"]["port"] = info["can"]["port"]
        # the drive's silence must outlast the daemon's reply time-out (5 s): the wait ends on the answer only,
        # so a reply that waits for the drive cannot arrive (max_missed: 1000 in the shipped file)
        cfg["io"]["drive"]["max_missed"] = 60_000
        cfg["loop"]["healthy_overrun_fraction"] = 0.5  # a loaded CI machine: this test is about the wait
        cfg["daemon"] = {"ready_timeout_s": 60, "health": "liveness", "telemetry": {"enabled": False}}
        path = tmp_path / "hil.yaml"
        path.write_text(yaml.safe_dump(absolutize_paths(cfg, config_dir())))
        env = {**os.environ, "NOTIFY_SOCKET": str(notify_socket.path)}
        daemon = subprocess.Popen([*stagectl_cmd(), "daemon", "--config", str(path), "--runtime-dir",
                                   str(tmp_path / "run")], env=env, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.PIPE, text=True, start_new_session=True)
        try:
            notify_socket.wait_for("READY", "1", timeout=120, alive=lambda: daemon.poll() is None)
        except TimeoutError:
            daemon.kill()
            pytest.fail("daemon never READY:\n" + daemon.communicate(timeout=30)[1][-4000:])
        with ControlClient(tmp_path / "run" / "control.sock", timeout_s=30) as c:
            assert c.request({"request": "status"})["status"]["state"] == "active"
            move = c.request({"request": "move", "relative_m": 1e-3, "max_velocity_m_s": 2e-3})
            assert move.get("ok"), move
            os.kill(plant.pid, signal.SIGSTOP)  # the drive's process held off the CPU: no answer, plant frozen
            frozen = True
            t0 = time.perf_counter()
            rep = c.request({"request": "stop"})
            dt = time.perf_counter() - t0
            st = c.request({"request": "status"})["status"]
            assert plant.poll() is None  # still frozen (SIGSTOP) when the replies came
        assert rep.get("ok"), rep  # before: "request: not applied by the loop within 5 s"
        assert st["state"] == "active", st
        print(f"stop reply during the paced wait: {dt * 1e3:.2f} ms")
    finally:
        if frozen:
            os.kill(plant.pid, signal.SIGCONT)
        if daemon is not None:
            stop_process(daemon, 30)
        stop_process(plant, 30)


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q", "-s"]))
