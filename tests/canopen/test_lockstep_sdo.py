"""Lock-step configuration does not race the wall clock: with the simulated drive served by ``pump()``, the
SDO client's waiting thread pumps and reads the answer itself, so ``configure`` succeeds however short
``sdo_timeout_s`` is (a loaded machine used to leave the Notifier / pump threads unscheduled past the 0.5 s
time-out: "Transfer aborted by client with code 0x05040000" and a failed start-up)."""

from __future__ import annotations

from pathlib import Path

import yaml

from stagectl.app import build_stage
from stagectl.clock import SimClock
from stagectl.config import parse_app_config

SIM_YAML = Path(__file__).resolve().parents[2] / "config" / "sim.yaml"


def test_embedded_canopen_configures_with_a_1_us_sdo_timeout() -> None:
    data = yaml.safe_load(SIM_YAML.read_text())
    data["io"]["kind"] = "embedded_canopen"
    drive = data["sim"]["drive"]
    # 1 µs: no thread hand-over could ever answer in time; only the lock-step reader can
    data["io"]["drive"] = {"node_id": drive["node_id"], "can": {"interface": "virtual", "channel": "unused"},
                           "resolution_m": drive["resolution_m"], "force_per_unit_n": drive["force_per_unit_n"],
                           "sdo_timeout_s": 1e-6}
    cfg = parse_app_config(data, SIM_YAML)
    assert cfg.io.drive is not None and cfg.io.drive.sdo_timeout_s == 1e-6
    with build_stage(cfg, clock=SimClock()) as stage:
        res = stage.loop.run(duration_s=0.02)  # and the cyclic exchange runs after it
        assert res.fault is None, res.fault
        assert stage.loop.cycle >= 20
