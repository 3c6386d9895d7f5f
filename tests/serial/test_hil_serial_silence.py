"""config/hil-serial.yaml against a silent interferometer, in lock-step on the in-process bus (simulated time).

The HIL's interferometer frames come from the sim-plant process, which a loaded machine holds off the CPU for
50-150 ms at a time (docs/platform.md section 1.3). The config rides that out at rest, and a device that really
falls silent still faults: while the stage moves after safety.stale_cycles (50 ms), at rest after 0.5 s."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from stagectl.config import IoKind, load_app_config
from stagectl.runtime.requests import MoveRequest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def hil_serial():
    cfg = load_app_config(REPO / "config" / "hil-serial.yaml")
    assert cfg.sim is not None and cfg.sim.interferometer is not None
    sim = dataclasses.replace(cfg.sim, interferometer=dataclasses.replace(cfg.sim.interferometer, port=0))
    return dataclasses.replace(cfg, io=dataclasses.replace(cfg.io, kind=IoKind.EMBEDDED_CANOPEN), sim=sim)


@pytest.mark.parametrize("moving, silent", [(False, 400), (True, 400), (False, 700)],
                         ids=["rest-400", "moving-400", "rest-700"])
def test_silent_interferometer_ridden_out_at_rest_faults_when_moving_or_dead(hil_serial, moving, silent):
    from stagectl.app import build_stage
    from stagectl.clock import SimClock
    from stagectl.recorder import Recorder

    with build_stage(hil_serial, clock=SimClock()) as stage:
        loop = stage.loop
        rec = Recorder(loop.columns, 1000)
        loop.add_sink(rec)
        if moving:
            loop.submit(MoveRequest(target_m=1e-3, max_velocity_m_s=5e-3))
        ifm = stage.world.interferometer
        assert ifm is not None and ifm.cfg.trigger == "sync"
        ifm.inject("stop", at_frame=ifm.slot + 100, count=silent)  # no frame, sequence held: a silent device
        res = loop.run(duration_s=0.9)
        x_end = stage.world.plant.x_m
    stale = rec.col("stale")
    first = int(np.argmax(stale > 0))  # the first cycle without a frame
    if moving:
        assert res.fault is not None and res.fault.name == "stale_position"
        assert abs(res.fault.cycle - first - hil_serial.safety.stale_cycles) <= 2
    elif silent < hil_serial.safety.stale_rest_cycles:
        assert res.fault is None and stale.sum() >= silent - 10
        assert abs(x_end) < 1e-8 and np.max(np.abs(rec.col("e")[stale == 0])) < 1e-8
    else:
        assert res.fault is not None and res.fault.name in ("stale_position", "missed_frame")
        assert abs(res.fault.cycle - first - hil_serial.safety.stale_rest_cycles) <= 2
