"""Every injected fault is detected by the driver and reported as the right typed fault within 3 cycles."""

from __future__ import annotations

import math

import pytest

from stagectl.drivers.base import DeviceState, FaultKind
from stagectl.drivers.cia402 import State402
from stagectl.sim.cia402_drive import DriveState
from stagectl.sim.faults import FaultSpec, SimFault


def run_until_fault(dut, n):
    for k in range(1, n + 1):
        dut.sync()
        m = dut.read()
        dut.write(1.0)
        if m.fault is not None:
            return k, m
    return None, m


@pytest.mark.parametrize(
    "kind, expected, within",
    [
        (SimFault.DRIVE_FAULT, FaultKind.DRIVE_FAULT, 1),
        (SimFault.DROP_TPDO, FaultKind.MISSED_FRAME, 3),
        (SimFault.BUS_OFF, FaultKind.BUS_OFF, 1),
        (SimFault.POSITION_JUMP, FaultKind.SENSOR_ERROR, 1),
    ],
)
def test_injected_fault_detected_within_3_cycles(lockstep, kind, expected, within):
    world, dut = lockstep()
    for _ in range(10):  # healthy first
        dut.sync()
        assert dut.read().fault is None
        dut.write(1.0)
    world.inject(FaultSpec(kind=kind, code=0x2310))
    k, m = run_until_fault(dut, 3)
    assert m.fault is not None and m.fault.kind is expected, m
    assert k <= within
    assert dut.state is DeviceState.FAULT and dut.fault == m.fault  # latched
    if kind is SimFault.DRIVE_FAULT:
        assert m.fault.code == 0x2310
        assert dut.drive_state in (State402.FAULT_REACTION_ACTIVE, State402.FAULT)
    # after a latched fault the driver only sends quick stop + zero torque
    dut.sync()
    dut.read()
    dut.write(7.0)
    world.pump()
    assert world.drive.target_torque == 0 or world.drive._silent


def test_missed_frames_below_threshold_are_not_a_fault(lockstep):
    world, dut = lockstep()
    world.inject(FaultSpec(kind=SimFault.DROP_TPDO, cycles=2))
    dut.sync()
    m1 = dut.read()
    dut.sync()
    m2 = dut.read()
    dut.sync()
    m3 = dut.read()
    assert (m1.fresh, m2.fresh, m3.fresh) == (False, False, True)
    assert m1.fault is None and m2.fault is None and m3.fault is None
    assert m1.position_m == m2.position_m  # last good value held
    assert dut.missed_total == 2


def test_late_tpdo_is_never_taken_for_the_next_cycle(lockstep):
    """A TPDO that arrives after the read gave up is stale: drained, not accepted one cycle later."""
    world, dut = lockstep(max_missed=100)
    world.inject(FaultSpec(kind=SimFault.LATE_TPDO, cycles=1))
    dut.sync()
    assert not dut.read().fresh
    dut.write(2.0)
    for _ in range(5):
        dut.sync()
        m = dut.read()
        assert m.fresh and m.counts == round(world.plant.measure() / 1e-9)
        dut.write(2.0)


def test_late_tpdos_are_used_one_period_old_then_a_lasting_lateness_faults(lockstep):
    """Every TPDO late (lock-step: it arrives after the read gave up): from the second cycle on read()
    returns the late answer to the previous SYNC as a fresh sample with age_cycles = 1 (a loaded machine
    answering late is not a missing drive); ``max_late_cycles`` such cycles in a row latch MISSED_FRAME."""
    world, dut = lockstep(max_late_cycles=6)
    for _ in range(5):
        dut.sync()
        dut.read()
        dut.write(2.0)
    world.inject(FaultSpec(kind=SimFault.LATE_TPDO))
    dut.sync()
    m = dut.read()
    assert not m.fresh and m.fault is None
    dut.write(2.0)
    seen = []
    for _ in range(6):
        x_before = world.plant.measure()
        dut.sync()
        m = dut.read()
        seen.append(m)
        dut.write(2.0)
        if m.fault is None:
            assert m.fresh and m.age_cycles == 1
            assert m.counts == round(x_before / 1e-9)  # the sample of the previous SYNC
    # the 6th cycle without an on-time TPDO (the stale first one counts) latches the fault
    assert [m.fault is None for m in seen[:5]] == [True] * 4 + [False]
    assert seen[4].fault.kind is FaultKind.MISSED_FRAME and "max_late_cycles" in seen[4].fault.detail


def test_emcy_without_fault_state_is_reported(lockstep):
    world, dut = lockstep()
    world.drive.send_emcy(0x4210)  # temperature warning: drive keeps running
    dut.sync()
    m = dut.read()
    assert m.fault is not None and m.fault.kind is FaultKind.EMCY and m.fault.code == 0x4210


def test_drive_heartbeat_stop_detected(lockstep):
    world, dut = lockstep(heartbeat_producer_s=0.01, heartbeat_timeout_s=0.025)
    for _ in range(30):
        dut.sync()
        assert dut.read().fault is None
        dut.write(0.0)
    world.inject(FaultSpec(kind=SimFault.HEARTBEAT_STOP))
    timeout_cycles = math.ceil(0.025 / 0.001)
    k, m = run_until_fault(dut, 100)
    assert m.fault.kind is FaultKind.HEARTBEAT_LOST
    # the last heartbeat came at most one producer period (10 cycles) before the stop
    assert timeout_cycles - 10 < k <= timeout_cycles + 3


def test_fault_reset_recovers_drive_fault(lockstep):
    world, dut = lockstep()
    world.inject(FaultSpec(kind=SimFault.DRIVE_FAULT, code=0x7500))
    k, m = run_until_fault(dut, 3)
    assert m.fault.kind is FaultKind.DRIVE_FAULT and m.fault.code == 0x7500
    assert world.drive.state in (DriveState.FAULT_REACTION_ACTIVE, DriveState.FAULT)
    assert world.drive.error_code == 0x7500
    dut.fault_reset()
    assert dut.fault is None and dut.state is DeviceState.CONFIGURED
    assert world.drive.state is DriveState.SWITCH_ON_DISABLED
    dut.enable()
    dut.sync()
    assert dut.read().fault is None
    assert world.drive.state is DriveState.OPERATION_ENABLED


def test_faults_from_yaml_schedule(lockstep):
    world, dut = lockstep(world_kw={"faults": [{"kind": "position_jump", "at_cycle": 40, "jump_m": 0.01}]})
    n0 = world.drive.sync_count
    assert n0 < 40
    k, m = run_until_fault(dut, 60)
    assert m.fault.kind is FaultKind.SENSOR_ERROR
    assert world.drive.sync_count == 40


def test_fault_yaml_errors_are_reported_with_paths():
    from stagectl.errors import ConfigError
    from stagectl.sim.world import SimWorldConfig

    with pytest.raises(ConfigError) as ei:
        SimWorldConfig.from_mapping({
            "plant": {"mass_kg": 1.0, "friction": {"model": "stribeck", "fc_n": 1.0, "fs_n": 1.0}},
            "faults": [{"kind": "explode"}, {"kind": "drop_tpdo", "at_cycle": 0, "cycles": -1}],
        })
    text = str(ei.value)
    assert "sim.faults[0].kind" in text
    assert "sim.faults[1].at_cycle" in text and "sim.faults[1].cycles" in text


def test_drive_faults_latched_when_drive_is_only_the_actuator(lockstep):
    """Another device is the sensor (read() never called): write() still picks up the drive's faults."""
    world, dut = lockstep()
    for _ in range(5):
        dut.sync()
        dut.write(1.0)
        assert dut.fault is None
    world.inject(FaultSpec(kind=SimFault.DRIVE_FAULT, code=0x3210))
    for _ in range(2):
        dut.sync()
        dut.write(1.0)
    assert dut.fault is not None and dut.fault.kind is FaultKind.DRIVE_FAULT and dut.fault.code == 0x3210
    assert dut.state is DeviceState.FAULT


def test_actuator_only_drive_takes_a_tpdo_that_arrives_after_write(lockstep):
    """Across processes the drive's TPDO may arrive after write() (the interferometer was the sensor): it is
    the answer to this SYNC and is evaluated at the next sync(), not counted as missed. Here the devices are
    pumped only after write(), i.e. they answer late in the period."""
    world, dut = lockstep()
    dut.set_pump(lambda: None)  # the devices run only when the test pumps them, after write()
    for _ in range(20):
        dut.sync()
        dut.write(1.0)
        world.pump()
        assert dut.fault is None
    assert dut.missed_total == 0
    world.inject(FaultSpec(kind=SimFault.DROP_TPDO))
    for k in range(1, 6):
        dut.sync()
        dut.write(1.0)
        world.pump()
        if dut.fault is not None:
            break
    assert dut.fault.kind is FaultKind.MISSED_FRAME and k <= 4  # max_missed 3, seen one cycle later


def test_can_error_frame_is_a_bus_error_and_bus_off_is_bus_off(lockstep):
    """Controller error frames (SocketCAN error class in the id) become BUS_ERROR, bus-off BUS_OFF."""
    import can

    from stagectl.drivers import canbus

    for cls, expected in ((0x04, FaultKind.BUS_ERROR), (0x40, FaultKind.BUS_OFF)):
        world, dut = lockstep()
        peer = canbus.open_bus({"interface": "virtual", "channel": world.channel})
        try:
            dut.sync()
            assert dut.read().fault is None
            peer.send(can.Message(arbitration_id=cls, is_error_frame=True, is_extended_id=True, data=b"\0" * 8))
            dut.sync()
            m = dut.read()
            assert m.fault is not None and m.fault.kind is expected, m
        finally:
            canbus.close_bus(peer)
