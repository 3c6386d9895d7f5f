"""`stagectl sim-plant` in a subprocess; the real driver connects through python-can's socketcand client.

Real time across processes: timeouts here are failure guards, not waits.
"""

from __future__ import annotations

import json
import selectors
import signal
import subprocess
import sys
import textwrap

import pytest

from stagectl.drivers.base import DeviceState
from stagectl.drivers.cia402 import State402

SIM_YAML = """
sim:
  plant:
    mass_kg: 2.0
    friction: {model: stribeck, fc_n: 1.0, fs_n: 1.5, viscous_n_s_m: 10.0}
    sensor: {resolution_m: 1.0e-9}
  drive: {node_id: 3, resolution_m: 1.0e-9, force_per_unit_n: 0.01}
  transport: {kind: socketcand, host: 127.0.0.1, port: 0}
"""


def read_line(proc, timeout_s):
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    if not sel.select(timeout_s):
        raise AssertionError(f"sim-plant printed no ready line within {timeout_s} s")
    return proc.stdout.readline()


@pytest.fixture
def sim_plant(tmp_path):
    cfg = tmp_path / "hil.yaml"
    cfg.write_text(textwrap.dedent(SIM_YAML))
    proc = subprocess.Popen(
        [sys.executable, "-m", "stagectl.cli", "sim-plant", "--config", str(cfg)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        line = read_line(proc, 60.0)
        info = json.loads(line)
        yield proc, info
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(10.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        proc.stderr.close()


def test_driver_over_socketcand_1000_cycles(sim_plant, make_drive):
    proc, info = sim_plant
    assert info["ready"] is True and info["transport"] == "socketcand"
    assert info["can"]["interface"] == "socketcand" and info["can"]["port"] > 0
    assert info["drive_node_id"] == 3
    # unpaced cycles (each waits for its TPDO): the heartbeat age is counted in cycles, so give it room
    dut = make_drive(info["can"], node_id=3, period_s=0.001, rx_timeout_s=0.5, heartbeat_timeout_s=30.0,
                     drive_consumer_timeout_s=2.0, sdo_timeout_s=2.0)
    dut.open()
    dut.configure()
    dut.enable()
    assert dut.drive_state is State402.OPERATION_ENABLED
    positions = []
    for k in range(1000):
        dut.sync()
        m = dut.read()
        assert m.fresh and m.fault is None, (k, m)
        positions.append(m.counts)
        dut.write(5.0)
    assert positions[-1] - positions[0] > 100_000  # > 0.1 mm under 5 N over 1 s of plant time
    assert all(b >= a for a, b in zip(positions, positions[1:]))  # pushed one way: never goes back
    dut.disable()
    assert dut.state is DeviceState.CONFIGURED and dut.drive_state is State402.READY_TO_SWITCH_ON
    dut.close()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(10.0) == 0
