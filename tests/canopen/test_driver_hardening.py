"""The driver against the virtual drive when the bus misbehaves (issue 16, CAN side): a second sender of our
RPDO or SYNC, an NMT reset node from another participant, a bus-off drive during reset, an external SYNC
producer, a socketcand link that dies; ``persisting_faults()`` says which causes are still present."""

from __future__ import annotations

import contextlib
import struct
import time

import can
import pytest
from stagectl.drivers import canbus
from stagectl.drivers.base import DeviceState, FaultKind
from stagectl.drivers.cia406 import Cia406Config, Cia406Encoder
from stagectl.sim.cia402_drive import NMT_OPERATIONAL, DriveState
from stagectl.sim.faults import SimFault
from support import cycle_drive

from stagectl.errors import DriverInitError, DriverTimeoutError


@pytest.fixture
def raw_bus():
    buses = []

    def make(world):
        b = canbus.open_bus({"interface": "virtual", "channel": world.channel})
        buses.append(b)
        return b

    yield make
    for b in buses:
        canbus.close_bus(b)


def _cycles(dut, n, force=0.5):
    return cycle_drive(dut, n, force)


@pytest.mark.parametrize("cid, what", [(0x201, "RPDO1"), (0x080, "SYNC")])
def test_second_sender_of_our_rpdo_or_sync_faults(lockstep, raw_bus, cid, what):
    world, dut = lockstep()
    bus = raw_bus(world)
    assert _cycles(dut, 20).fault is None
    data = struct.pack("<Hh", 0x0F, 2280) if cid == 0x201 else b""
    bus.send(can.Message(arbitration_id=cid, data=data, is_extended_id=False))  # a foreign frame
    m = _cycles(dut, 3)
    assert m.fault is not None and m.fault.kind is FaultKind.BUS_ERROR and "second" in m.fault.detail
    assert what in m.fault.detail and dut.state is DeviceState.FAULT


def test_reset_reconfigures_a_drive_reset_by_another_node(lockstep, raw_bus):
    """``0x000 [81 01]`` from another participant: the drive reboots into PRE-OPERATIONAL with its default PDOs;
    the fault latches and the reset runs the configuration again, so cycling resumes."""
    world, dut = lockstep(heartbeat_producer_s=0.01, heartbeat_timeout_s=0.05)
    bus = raw_bus(world)
    assert _cycles(dut, 20).fault is None
    bus.send(can.Message(arbitration_id=0x000, data=b"\x81\x01", is_extended_id=False))
    m = _cycles(dut, 10)
    assert m.fault is not None
    assert world.drive.nmt_state != NMT_OPERATIONAL
    dut.fault_reset()
    assert world.drive.nmt_state == NMT_OPERATIONAL
    assert world.drive.node.get_data(0x1017, 0) == struct.pack("<H", 10)  # configuration written again
    dut.enable()
    assert _cycles(dut, 50).fault is None
    assert world.drive.state is DriveState.OPERATION_ENABLED


def test_reset_against_a_silent_drive_is_bounded(lockstep):
    """Bus-off drive: the reset gives up after ``no_answer_timeout_s`` without a TPDO (not state_timeout_s), and
    persisting_faults() names the cause while it lasts."""
    world, dut = lockstep(no_answer_timeout_s=0.005, state_timeout_s=0.5)
    world.inject("bus_off")
    m = _cycles(dut, 10)
    assert m.fault is not None and m.fault.kind is FaultKind.BUS_OFF
    assert any(p.startswith("bus_off") for p in dut.persisting_faults())
    s0 = world.drive.sync_count
    with pytest.raises(DriverTimeoutError, match="not answering"):
        dut.fault_reset()
    assert world.drive.sync_count - s0 <= 6  # 5 silent cycles, not 500


def test_external_sync_producer(lockstep, raw_bus, make_world, make_drive):
    world = make_world()
    dut = make_drive(world.ready_info()["can"], sync_producer=False)
    dut.set_pump(world.pump)
    bus = raw_bus(world)
    dut.open()
    dut.configure()
    sync = can.Message(arbitration_id=0x080, data=b"", is_extended_id=False)

    def cycle(force):
        bus.send(sync)  # another node produces SYNC
        dut.sync()
        m = dut.read()
        dut.write(force)
        return m

    dut._pump = lambda: (bus.send(sync), world.pump())  # enable() steps cycles: the producer keeps going
    dut.enable()
    dut._pump = world.pump
    while bus.recv(0.0) is not None:
        pass
    for _ in range(50):
        m = cycle(1.0)
        assert m.fault is None and m.fresh
    assert world.drive.force_n == pytest.approx(1.0)
    seen = []
    while (f := bus.recv(0.0)) is not None:
        seen.append(f.arbitration_id)
    assert 0x080 not in seen  # our driver sent no SYNC of its own (the raw bus does not see its own)


def test_dead_socketcand_link_faults_without_spinning(make_world, make_drive):
    """The socketcand server goes away: the driver reports DISCONNECTED, stops waiting on the closed socket
    (python-can's client would return from recv at once, forever: a busy loop) and names the cause."""
    world = make_world(transport={"kind": "socketcand"})
    world.start()  # thread mode: frames cross real TCP
    dut = make_drive(world.ready_info()["can"], rx_timeout_s=0.05, max_missed=1000, heartbeat_timeout_s=5.0)
    dut.open()
    dut.configure()
    dut.enable()
    world.stop()
    m = _cycles(dut, 5)
    assert m.fault is not None and m.fault.kind in (FaultKind.DISCONNECTED, FaultKind.BUS_ERROR), m
    for _ in range(3):  # cycles go on; the closed link is not waited on any more
        dut.sync()
        assert not dut.read().fresh
    assert dut._link_dead
    assert "disconnected: CAN link closed" in dut.persisting_faults()


def test_dead_socketcand_link_ends_a_device_time_wait(make_world, make_drive):
    """The socketcand server goes away while the loop waits for the drive (loop.pace_cycles): behind() stops
    waiting and the next read() reports DISCONNECTED, instead of waiting out max_missed wall slots on a link
    that can never answer."""
    world = make_world(transport={"kind": "socketcand"})
    world.start()
    dut = make_drive(world.ready_info()["can"], rx_timeout_s=0.05, max_missed=1000, heartbeat_timeout_s=5.0)
    dut.open()
    dut.configure()
    dut.enable()
    world.stop()
    dut.sync()
    dut._wait_tpdo = lambda: None  # (this cycle's answer is simply not there yet: no link check in read())
    dut.read()
    del dut._wait_tpdo
    dut.write(0.0)
    slots = 0
    deadline = time.monotonic() + 5.0
    while dut.behind(1, 1) and time.monotonic() < deadline:
        slots += 1
        time.sleep(0.001)
    assert slots < 100, slots  # measured 999 before (the whole max_missed)
    dut.sync()
    m = dut.read()  # (the controller heartbeat sent while waiting may find the broken pipe first)
    assert m.fault is not None and m.fault.kind in (FaultKind.DISCONNECTED, FaultKind.BUS_ERROR), m


def test_encoder_persisting_faults(make_world):
    world = make_world(encoder={"node_id": 2})
    enc = Cia406Encoder(Cia406Config(node_id=2, can=world.ready_info()["can"], sync_producer=True,
                                     sdo_timeout_s=3.0), 0.001)
    enc.set_pump(world.pump)
    try:
        enc.open()
        enc.configure()
        for _ in range(5):
            enc.sync()
            assert enc.read().fault is None
        assert enc.persisting_faults() == ()
        world.inject(SimFault.HEARTBEAT_STOP, device="encoder")
        for _ in range(400):
            enc.sync()
            if enc.read().fault is not None:
                break
        assert any(p.startswith("heartbeat_lost") for p in enc.persisting_faults())
    finally:
        enc.close()


def test_loop_reset_after_nmt_reset_node_from_another_node():
    """Whole stage (lock-step): one ``0x000 [81 01]`` frame from another participant reboots the drive; the
    loop latches a fault; its reset re-configures the drive and the stage moves again."""
    from pathlib import Path

    import yaml

    from stagectl.app import build_stage
    from stagectl.clock import SimClock
    from stagectl.config import parse_app_config
    from stagectl.loop import LoopState
    from stagectl.runtime.requests import MoveRequest, ResetRequest

    sim_yaml = Path(__file__).resolve().parents[2] / "config" / "sim.yaml"
    data = yaml.safe_load(sim_yaml.read_text())
    data["io"].update(kind="embedded_canopen")
    cfg = parse_app_config(data, sim_yaml)
    with build_stage(cfg, clock=SimClock()) as stage:
        loop, world = stage.loop, stage.world
        bus = canbus.open_bus({"interface": "virtual", "channel": world.channel})
        try:
            reset_node = can.Message(arbitration_id=0x000, data=b"\x81\x01", is_extended_id=False)
            loop.on_cycle = lambda: loop.cycle == 50 and bus.send(reset_node)
            loop.run(cycles=100)
            loop.on_cycle = None
            assert loop.status().state is LoopState.FAULT
            fut = loop.submit(ResetRequest())
            loop.run(cycles=5)
            assert fut.result(timeout=0)["state"] == "active"
            assert world.drive.nmt_state == NMT_OPERATIONAL
            mv = loop.submit(MoveRequest(relative_m=2e-6))
            loop.run(cycles=400)
            assert mv.result(timeout=0)["target_m"] == pytest.approx(loop.status().x_ref_m)
            assert loop.status().fault is None
        finally:
            canbus.close_bus(bus)


def test_persisting_heartbeat_loss_clears_when_beats_return(lockstep):
    """persisting_faults() looks at the bus when asked: after a heartbeat loss, once the drive beats again the
    cause is gone even if no cycle ran in between."""
    world, dut = lockstep(heartbeat_producer_s=0.01, heartbeat_timeout_s=0.05)
    world.inject("heartbeat_stop")
    m = _cycles(dut, 200)
    assert m.fault is not None and m.fault.kind is FaultKind.HEARTBEAT_LOST
    assert any(p.startswith("heartbeat_lost") for p in dut.persisting_faults())
    world.advance(0.05)
    assert any(p.startswith("heartbeat_lost") for p in dut.persisting_faults())  # still silent
    world.clear_faults()
    world.drive._hb_stopped = False  # the drive's heartbeat producer runs again (no SYNC needed)
    world.advance(0.02)
    assert dut.persisting_faults() == ()


def test_a_closed_socketcand_port_is_one_line_at_once(monkeypatch):
    """Nothing listens on the port (a typo, the sim-plant not started): one line naming host and port, without
    python-can's 10 s of refused retries. A listening server is accepted (the probe only connects)."""
    import socket

    free = socket.socket()
    free.bind(("127.0.0.1", 0))
    port = free.getsockname()[1]
    free.close()  # bound once, now closed: nothing listens there
    monkeypatch.setattr(canbus, "SOCKETCAND_PROBE_S", 0.0)
    with pytest.raises(DriverInitError) as ei:
        canbus.open_bus({"interface": "socketcand", "host": "127.0.0.1", "port": port, "channel": "can0"})
    msg = str(ei.value)
    assert "\n" not in msg and f"port={port}" in msg and "nothing accepts a connection" in msg, msg
    with _one_shot_server(b"< hi >") as port:
        canbus.probe_socketcand("127.0.0.1", port, wait_s=0.0)


def test_a_socketcand_host_that_does_not_resolve_is_named_as_such():
    """A mistyped host name (``.invalid`` never resolves, RFC 6761) is one line saying the name was not found,
    not "nothing accepts a connection there", which sent the user looking for a server that is not started."""
    with pytest.raises(DriverInitError) as ei:
        canbus.open_bus({"interface": "socketcand", "host": "stage-pc.invalid", "port": 29536, "channel": "can0"})
    msg = str(ei.value)
    assert "\n" not in msg and "host name not found" in msg and "stage-pc.invalid" in msg, msg
    assert "nothing accepts" not in msg


@contextlib.contextmanager
def _one_shot_server(greeting: bytes | None):
    """A TCP server on loopback that accepts one connection, sends ``greeting`` (None: nothing) and holds it."""
    import socket
    import threading

    srv = socket.create_server(("127.0.0.1", 0))
    done = threading.Event()

    def serve() -> None:
        conn, _ = srv.accept()
        with conn:
            if greeting is not None:
                conn.sendall(greeting)
            done.wait(10)

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    try:
        yield srv.getsockname()[1]
    finally:
        done.set()
        t.join(10)
        srv.close()


@pytest.mark.parametrize(("greeting", "expect"), [
    (None, "no greeting '< hi >' within 0.3 s; is that port a socketcand server"),
    (b"SSH-2.0-OpenSSH_9.6\r\n>", "not a socketcand server (it said 'SSH-2.0-OpenSSH_9.6"),
])
def test_a_port_that_is_not_a_socketcand_server_is_one_line(monkeypatch, greeting, expect):
    """Something listens but never says '< hi >' (another service, a hung server): python-can's client waited for
    the greeting without a time-out and `stagectl run` hung for ever (audit16). One line instead."""
    monkeypatch.setattr(canbus, "SOCKETCAND_GREETING_S", 0.3)
    with _one_shot_server(greeting) as port:
        with pytest.raises(DriverInitError) as ei:
            canbus.open_bus({"interface": "socketcand", "host": "127.0.0.1", "port": port, "channel": "can0"})
    msg = str(ei.value)
    assert "\n" not in msg and f"127.0.0.1:{port}" in msg and expect in msg, msg
