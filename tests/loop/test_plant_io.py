"""PlantIO timing: lock-step by construction, actuation delay in SYNC periods, fresh-once reads."""

from __future__ import annotations

import pytest

from stagectl.clock import SimClock
from stagectl.drivers.base import DeviceState
from stagectl.sim.direct import PlantIO


class Recorder:
    """A minimal plant that records the force and duration of every step."""

    resolution_m = 1e-9

    def __init__(self):
        self.steps: list[tuple[float, float]] = []
        self.x_m = 0.0

    def step(self, u_n, dt_s):
        self.steps.append((u_n, dt_s))
        self.x_m += u_n * 1e-9

    def measure(self):
        return self.x_m


def _io(delay, clock=None):
    plant = Recorder()
    dut = PlantIO(plant, 1e-3, delay_cycles=delay, clock=clock)
    dut.open()
    dut.configure()
    dut.enable()
    return dut, plant


@pytest.mark.parametrize("delay", [0, 1, 2])
def test_command_acts_after_delay_cycles(delay):
    dut, plant = _io(delay)
    dut.sync()
    dut.read()
    dut.write(5.0)  # written in cycle 0, after its SYNC
    applied = []
    for _ in range(4):
        dut.sync()
        applied.append(dut.applied_force_n)
    # delay 0: acts at once (ZOH over [t0, t1)); delay d >= 1: from SYNC d on
    expect = [5.0] * 4 if delay == 0 else [0.0] * (delay - 1) + [5.0] * (5 - delay)
    assert applied == expect[:4]
    forces = [u for u, _ in plant.steps]
    assert forces[0] == (5.0 if delay == 0 else 0.0)  # the step from SYNC 0 to 1
    dut.close()


def test_reads_are_fresh_once_and_position_quantised():
    dut, plant = _io(1)
    plant.x_m = 12.3456e-9
    dut.sync()
    m1, m2 = dut.read(), dut.read()
    assert m1.fresh and not m2.fresh
    assert m1.counts == 12 and m1.position_m == pytest.approx(12e-9)
    assert m2.position_m == m1.position_m


def test_clock_mode_follows_the_clock_in_substeps():
    clock = SimClock()
    dut, plant = _io(1, clock)
    dut.sync()
    clock.advance(3.5e-3)
    dut.sync()
    assert [dt for _, dt in plant.steps] == pytest.approx([1e-3, 1e-3, 1e-3, 0.5e-3])


def test_quick_stop_zeroes_and_ignores_writes_until_enabled():
    dut, plant = _io(0)
    dut.sync()
    dut.write(3.0)
    dut.quick_stop()
    dut.write(4.0)
    dut.sync()
    assert dut.applied_force_n == 0.0
    dut.disable()
    dut.enable()
    dut.write(2.0)
    assert dut.applied_force_n == 2.0
    dut.close()
    assert dut.state is DeviceState.CLOSED
