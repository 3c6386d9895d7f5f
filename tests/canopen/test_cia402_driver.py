"""The real CiA 402 driver against the simulated drive on python-can's virtual bus (lock-step, no sleeps)."""

from __future__ import annotations

import pytest

from stagectl.clock import Timing
from stagectl.drivers.base import DeviceState
from stagectl.drivers.cia402 import Cia402Config, Cia402Drive, State402, unwrap32
from stagectl.errors import ConfigError, DriverInitError
from stagectl.sim.cia402_drive import DriveState


def test_configure_in_thread_mode_then_1000_lockstep_cycles(make_world, make_drive):
    world = make_world()
    world.start()  # SDO configuration served by the device thread
    dut = make_drive(world.ready_info()["can"], period_s=0.001)
    dut.open()
    dut.configure()
    sim = world.drive
    assert sim.period_s == pytest.approx(0.001)
    assert sim.mode == 10
    assert sim._hb_period_s == pytest.approx(0.05)
    assert sim._consumer_node == 127 and sim._consumer_timeout_s == pytest.approx(0.1)
    dut.set_pump(world.pump)  # switch to lock-step
    dut.enable()
    assert dut.drive_state is State402.OPERATION_ENABLED and sim.state is DriveState.OPERATION_ENABLED
    t_start = world.plant.t_s
    for k in range(1000):
        dut.sync()
        m = dut.read()
        assert m.fresh and m.fault is None, (k, m)
        assert m.counts == round(world.plant.measure() / 1e-9)
        assert m.position_m == pytest.approx(m.counts * 1e-9, abs=1e-15)
        dut.write(5.0 if k < 500 else -5.0)
    assert world.plant.t_s - t_start == pytest.approx(1.0, abs=0.02)  # one nominal period per SYNC
    assert m.position_m > 1e-3  # the stage moved under 5 N > 1.5 N break-away
    assert sim.force_n == pytest.approx(-5.0)
    dut.disable()
    assert dut.state is DeviceState.CONFIGURED
    assert sim.state is DriveState.READY_TO_SWITCH_ON and sim.force_n == 0.0
    dut.close()
    dut.close()  # idempotent
    assert dut.state is DeviceState.CLOSED


def test_configure_in_lockstep_and_deterministic(lockstep):
    traces = []
    for _ in range(2):
        world, dut = lockstep()
        trace = []
        for k in range(200):
            dut.sync()
            trace.append(dut.read().counts)
            dut.write(3.0)
        traces.append(trace)
        dut.close()
        world.stop()
    assert traces[0] == traces[1]
    assert traces[0][-1] != traces[0][0]


def test_force_scaling_and_clamp(lockstep):
    world, dut = lockstep(force_per_unit_n=0.01, max_force_n=100.0)
    dut.sync()
    dut.read()
    dut.write(1.234)
    dut.sync()
    dut.read()
    assert world.drive.target_torque == 123
    assert world.drive.force_n == pytest.approx(1.23)
    dut.write(1e9)
    dut.sync()
    dut.read()
    assert world.drive.target_torque == 3000  # 100 N / 0.01 N = 10000, but the drive's 0x6072 max torque is 3000
    assert dut.drive_max_units == 3000
    dut.write(float("nan"))
    dut.sync()
    dut.read()
    assert world.drive.target_torque == 0


def test_quick_stop(lockstep):
    world, dut = lockstep()
    dut.sync()
    dut.read()
    dut.write(4.0)
    dut.quick_stop()
    for _ in range(3):
        dut.sync()
        dut.read()
        dut.write(4.0)  # ignored after quick stop: torque stays 0
    assert world.drive.force_n == 0.0
    assert world.drive.state in (DriveState.QUICK_STOP_ACTIVE, DriveState.SWITCH_ON_DISABLED)


def test_position_unwraps_across_32_bits(lockstep):
    world, dut = lockstep(resolution_m=1e-9)
    # move the plant close to +2^31 counts (2.147 m) and push it across
    world.plant.reset(x0_m=2.147483)
    dut.sync()
    m0 = dut.read()
    assert m0.fault is not None  # the jump from 0 to 2.147 m is reported as a glitch
    dut.fault_reset()
    dut.enable()
    seen = []
    for _ in range(100):
        dut.sync()
        m = dut.read()
        assert m.fault is None
        seen.append(m.counts)
        dut.write(10.0)
    assert seen[-1] > 2**31  # beyond the INT32 range: unwrapped
    assert world.drive.position_counts < 0  # the drive's 0x6064 wrapped
    assert seen[-1] == round(world.plant.measure() / 1e-9)


def test_unwrap32():
    assert unwrap32(0x7FFFFFFF, 2**31 - 1, -(2**31)) == 2**31
    assert unwrap32(-(2**31), 2**31, 0x7FFFFFFF) == 2**31 - 1
    assert unwrap32(5, 5, 3) == 3


def test_config_errors():
    with pytest.raises(ConfigError, match="heartbeat_timeout_s"):
        Cia402Config(node_id=1, heartbeat_producer_s=0.1, heartbeat_timeout_s=0.05)
    from stagectl.schema import load

    with pytest.raises(ConfigError) as ei:
        load(Cia402Config, {"node_id": 200, "resolution_m": -1, "bogus": 1}, "drive")
    text = str(ei.value)
    assert "drive.node_id" in text and "drive.resolution_m" in text and "drive.bogus" in text


def test_open_errors_are_typed(tmp_path):
    dut = Cia402Drive(Cia402Config(node_id=1, can={"interface": "no_such_iface", "channel": "x"}), Timing(1e-3))
    with pytest.raises(DriverInitError, match="cannot open CAN bus"):
        dut.open()
    bad = Cia402Drive(Cia402Config(node_id=1, can={"interface": "virtual", "channel": f"x-{id(tmp_path)}"},
                                   eds_file=str(tmp_path / "missing.eds")), Timing(1e-3))
    with pytest.raises(DriverInitError, match="EDS"):
        bad.open()
    assert bad.state is DeviceState.CLOSED


def test_configure_without_a_drive_times_out_with_typed_error(make_drive, tmp_path):
    dut = make_drive({"interface": "virtual", "channel": f"empty-{id(tmp_path)}"}, sdo_timeout_s=0.05)
    dut.open()
    with pytest.raises(DriverInitError, match="0x1000"):
        dut.configure()


def test_wrong_device_type_rejected(make_world, make_drive):
    world = make_world()
    world.start()
    world.drive.node.data_store.setdefault(0x1000, {})[0] = (0x00020196).to_bytes(4, "little")
    dut = make_drive(world.ready_info()["can"])
    dut.open()
    with pytest.raises(DriverInitError, match="not a CiA 402"):
        dut.configure()


@pytest.mark.parametrize("refuse", [False, True])
def test_quick_stop_option_code_selected_at_configure(make_world, make_drive, monkeypatch, refuse):
    """configure writes io.drive.quick_stop_option_code (3) to 0x605A: the drive then brakes itself
    (``brakes_itself``); a drive that refuses the write (SDO abort: object missing) still configures and
    enables, keeps its own code, and ``brakes_itself`` is False (the loop brakes over the bus)."""
    from stagectl.sim import cia402_drive as simd

    if refuse:  # a drive without 0x605A (before the world builds it: canopen keeps the bound callback)
        orig = simd.SimCia402Drive._on_sdo_write

        def no_605a(self, index, subindex, od, data):
            if index == 0x605A:
                raise simd._abort(simd.ABORT_NO_OBJECT)
            return orig(self, index, subindex, od, data)

        monkeypatch.setattr(simd.SimCia402Drive, "_on_sdo_write", no_605a)
    w = make_world()
    dut = make_drive(w.ready_info()["can"])
    dut.set_pump(w.pump)
    dut.open()
    dut.configure()
    dut.enable()
    assert dut.brakes_itself is (not refuse)
    assert w.drive._option(0x605A, 2) == (2 if refuse else 3)
