"""The simulated drive on its own: heartbeat consumer in simulated time, NMT, EDS, canopen's own master."""

from __future__ import annotations

import threading

import canopen
import pytest

from stagectl.drivers import canbus
from stagectl.drivers.base import FaultKind
from stagectl.sim.cia402_drive import EMCY_HEARTBEAT, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL, DriveState

from stagectl.drivers.cia402 import DEFAULT_EDS, EDS_DIR  # noqa: E402


@pytest.mark.parametrize("name, profile", [("stagectl_cia402.eds", 402), ("stagectl_cia406.eds", 406)])
def test_eds_loads_in_canopens_parser(name, profile):
    od = canopen.import_od(str(EDS_DIR / name), 5)
    assert od[0x1000].default & 0xFFFF == profile
    assert od[0x1A00][1].default >> 16 in (0x6041, 0x6004)
    assert od[0x1800][1].default == 0x185  # $NODEID+0x180 resolved
    assert od.device_information.nr_of_TXPDO >= 1
    if profile == 402:
        assert od[0x6502].default & (1 << 9)  # CST supported
        for idx in (0x6040, 0x6041, 0x6060, 0x6061, 0x6064, 0x6071, 0x1016, 0x1017, 0x1006):
            assert idx in od
    else:
        assert 0x6004 in od


def test_drive_heartbeat_consumer_stops_drive_in_simulated_time(lockstep):
    """The controller goes silent (no SYNC, heartbeat, RPDO): the drive faults itself after 0x1016."""
    world, dut = lockstep(drive_consumer_timeout_s=0.1, controller_heartbeat_s=0.02)
    for _ in range(300):  # 0.3 s of simulated time > 0.1 s: our heartbeat keeps the drive alive
        dut.sync()
        assert dut.read().fault is None
        dut.write(3.0)
    sim = world.drive
    assert sim.heartbeat_lost_events == 0 and sim._consumer_armed
    assert sim.state is DriveState.OPERATION_ENABLED and sim.force_n == pytest.approx(3.0)
    world.pump()
    last = sim._consumer_last_t
    world.advance(last + 0.099 - world.now())  # just inside the consumer time
    assert sim.state is DriveState.OPERATION_ENABLED
    world.advance(0.002)  # just past it
    assert sim.state is DriveState.FAULT and sim.error_code == EMCY_HEARTBEAT
    assert sim.force_n == 0.0 and sim.emcy_sent[-1] == EMCY_HEARTBEAT
    # the controller comes back and sees why
    dut.sync()
    m = dut.read()
    assert m.fault.kind is FaultKind.DRIVE_FAULT and m.fault.code == EMCY_HEARTBEAT


def test_nmt_reset_sends_boot_up_and_restores_eds_values(make_world, make_drive):
    world = make_world()
    world.pump()
    bus = canbus.open_bus({"interface": "virtual", "channel": world.channel})
    try:
        sim = world.drive
        sim.node.data_store.setdefault(0x1017, {})[0] = (100).to_bytes(2, "little")
        bus.send(canopen_msg(0x000, bytes([0x01, 1])))  # NMT start node 1
        world.pump()
        assert sim.nmt_state == NMT_OPERATIONAL
        bus.send(canopen_msg(0x000, bytes([0x81, 0])))  # reset node (broadcast)
        world.pump()
        assert sim.nmt_state == NMT_PRE_OPERATIONAL
        assert 0x1017 not in sim.node.data_store  # restored to the EDS value
        frames = drain(bus)
        assert any(m.arbitration_id == 0x701 and bytes(m.data) == b"\x00" for m in frames)  # boot-up
    finally:
        canbus.close_bus(bus)


def canopen_msg(cid, data):
    import can

    return can.Message(arbitration_id=cid, data=data, is_extended_id=False)


def drain(bus):
    out = []
    while (m := bus.recv(0.0)) is not None:
        out.append(m)
    return out


def test_canopen_basenode402_master_drives_the_sim(make_world):
    """canopen's own CiA 402 master: OPERATION ENABLED in CST, then torque moves the stage."""
    world = make_world()
    world.start()
    bus = canbus.open_bus({"interface": "virtual", "channel": world.channel})
    net = canopen.Network(bus)
    net.notifier = __import__("can").Notifier(bus, net.listeners, 0.05)
    try:
        node = canopen.BaseNode402(1, str(DEFAULT_EDS))
        # canopen's state and mode switches give up after 0.8 / 0.5 s of wall clock: on a loaded machine the
        # drive's thread answered later than that; generous guards, each loop still ends when the state is reached
        node.TIMEOUT_SWITCH_STATE_FINAL = node.TIMEOUT_SWITCH_OP_MODE = 30.0
        net.add_node(node)
        node.nmt.state = "PRE-OPERATIONAL"
        node.sdo[0x1017].raw = 20
        node.nmt.wait_for_heartbeat(2.0)
        node.setup_402_state_machine()
        assert node.is_op_mode_supported("CYCLIC SYNCHRONOUS TORQUE")
        node.op_mode = "CYCLIC SYNCHRONOUS TORQUE"
        assert node.op_mode == "CYCLIC SYNCHRONOUS TORQUE"
        node.nmt.state = "OPERATIONAL"
        net.sync.start(0.002)
        node.rpdo[1].start(0.002)
        node.state = "OPERATION ENABLED"
        assert node.state == "OPERATION ENABLED"
        assert world.drive.state is DriveState.OPERATION_ENABLED
        x0 = world.plant.x_m
        node.rpdo[1]["Target torque"].raw = 500  # 5 N > 1.5 N break-away
        tpdo = node.tpdo[1]
        moved = threading.Event()
        for _ in range(500):  # TPDO receptions, not wall-clock sleeps
            tpdo.wait_for_reception(1.0)
            if abs(node.tpdo_values[0x6064] * 1e-9 - x0) > 1e-4:
                moved.set()
                break
        assert moved.is_set(), "the stage did not move under CST torque"
        assert world.drive.force_n == pytest.approx(5.0)
        node.rpdo[1]["Target torque"].raw = 0
        node.state = "SWITCH ON DISABLED"
        assert world.drive.state is DriveState.SWITCH_ON_DISABLED
    finally:
        net.sync.stop()
        for pdo in (node.rpdo[1],):
            pdo.stop()
        net.notifier.stop(1.0)
        canbus.close_bus(bus)


def test_world_includes_interferometer_when_configured(make_world):
    pytest.importorskip("stagectl.sim.interferometer")
    world = make_world(interferometer={"transport": "tcp", "lockstep": "plant_time"})
    info = world.ready_info()
    assert info["interferometer_url"].startswith("socket://127.0.0.1:")
    assert world.interferometer.plant is world.plant
    world.pump()  # lock-step pumps the interferometer too (no client yet: nothing to send, no error)


def test_world_serial_pump_lets_the_interferometer_driver_skip_a_stopped_frame(lockstep, tmp_path):
    """Drive + serial interferometer in one lock-step world: with ``world.serial_pump`` (LinkBytes) a frame
    the device does not send costs no wait; the driver's lock-step guard (10 s here) is never reached."""
    import time

    from stagectl.drivers.interferometer import InterferometerConfig, SerialInterferometer
    from stagectl.drivers.interferometer_protocol import LinkBytes

    world, dut = lockstep(world_kw={"interferometer": {"transport": "pty", "link_path": str(tmp_path / "ifm"),
                                                       "lockstep": "plant_time"}})
    ifm = SerialInterferometer(InterferometerConfig(url=world.ready_info()["interferometer_url"],
                                                    lockstep_timeout_s=10.0, stale_cycles=5))
    ifm.set_pump(world.serial_pump)
    with ifm:
        ifm.configure()
        assert isinstance(world.serial_pump(), LinkBytes)
        for _ in range(5):
            dut.sync()
            m = ifm.read()
            dut.write(2.0)
            assert m.fresh and m.counts == round(world.plant.measure() / 1e-9)
        world.interferometer.inject("stop", count=2)
        t0 = time.monotonic()
        fresh = []
        for _ in range(4):
            dut.sync()
            m = ifm.read()
            dut.write(2.0)
            fresh.append(m.fresh)
            assert m.fault is None
        assert time.monotonic() - t0 < 5.0  # failure guard: a regression waits 10 s per stopped frame
        assert fresh == [False, False, True, True]
        assert m.counts == round(world.plant.measure() / 1e-9)


def test_sync_triggered_interferometer_samples_with_the_drive(lockstep, tmp_path):
    """``trigger: sync``: one frame per SYNC, sampled right after the drive stepped the plant, so the
    interferometer and the drive's TPDO report the same sample."""
    from stagectl.drivers.interferometer import InterferometerConfig, SerialInterferometer

    world, dut = lockstep(world_kw={"interferometer": {"transport": "tcp", "trigger": "sync"}})
    ifm = SerialInterferometer(InterferometerConfig(url=world.ready_info()["interferometer_url"]))
    ifm.set_pump(world.serial_pump)
    with ifm:
        ifm.configure()
        n0 = world.interferometer.frames_sent
        for k in range(50):
            dut.sync()
            m = dut.read()
            i = ifm.read()
            dut.write(3.0)
            assert i.fresh and i.counts == m.counts, k
        assert world.interferometer.frames_sent - n0 == 50  # exactly one frame per SYNC
        assert m.counts > 0


def test_thread_mode_timers_run_during_a_flood_of_frames(make_world):
    """Thread mode: frames that keep arriving (never an idle ``recv``) must not starve the timers (heartbeat).
    The world thread is fed 3000 frames back to back by a stand-in bus; its timers must have run while the
    flood lasted, not only after it."""
    import can

    world = make_world()
    world.open()
    frames = [can.Message(arbitration_id=0x7F0, data=b"\0", is_extended_id=False) for _ in range(3000)]
    ticks_during_flood = []
    left = [len(frames)]

    class FloodBus:
        def recv(self, timeout=None):
            if left[0] == 0:
                world._stop_evt.set()
                return None
            left[0] -= 1
            return frames[left[0]]

        def send(self, msg):
            pass

    real_tick = world._tick

    def tick():
        if left[0] > 0:
            ticks_during_flood.append(left[0])
        real_tick()

    world._bus, bus = FloodBus(), world._bus
    world._tick = tick
    try:
        world._run()
    finally:
        world._bus = bus
    assert left[0] == 0 and ticks_during_flood  # timers ran while frames were still coming
