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
from support import stop_process

from stagectl.clock import Timing
from stagectl.drivers.base import DeviceState, FaultKind
from stagectl.drivers.cia402 import State402

SIM_YAML = """
sim:
  plant:
    mass_kg: 2.0
    friction: {model: stribeck, fc_n: 1.0, fs_n: 1.5, viscous_n_s_m: 10.0}
    sensor: {resolution_m: 1.0e-9}
  drive: {node_id: 3, resolution_m: 1.0e-9, force_per_unit_n: 0.01}
  transport: {kind: socketcand, host: 127.0.0.1, port: 0}
  faults:
    - {kind: bus_off, at_cycle: 1300}
"""


def read_line(proc, timeout_s):
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    if not sel.select(timeout_s):
        raise AssertionError(f"sim-plant printed no ready line within {timeout_s} s")
    return proc.stdout.readline()


@pytest.fixture
def sim_plant(tmp_path, request):
    cfg = tmp_path / "hil.yaml"
    cfg.write_text(textwrap.dedent(getattr(request, "param", SIM_YAML)))
    proc = subprocess.Popen(
        [sys.executable, "-m", "stagectl.cli", "sim-plant", "--config", str(cfg)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        line = read_line(proc, 60.0)
        info = json.loads(line)
        yield proc, info
    finally:
        stop_process(proc, 10.0)


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
    # the scripted bus-off at the drive's SYNC 1300 crosses the process boundary as an error frame
    assert dut._cycle < 1300
    fault = None
    while fault is None and dut._cycle < 1303:
        dut.sync()
        fault = dut.read().fault
        dut.write(0.0)
    assert fault is not None and fault.kind is FaultKind.BUS_OFF
    assert 1300 <= dut._cycle <= 1302
    dut.close()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(10.0) == 0


def test_socketcand_framing_rules():
    import can

    from stagectl.sim.socketcand import format_frame, parse_send

    sync = format_frame(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False), ts=1.5)
    assert sync == b"< frame 080 1.500000  >"  # 0-byte frame keeps the trailing space
    tpdo = format_frame(can.Message(arbitration_id=0x181, data=b"\x01\x02\xab", is_extended_id=False), ts=2.0)
    assert tpdo == b"< frame 181 2.000000 0102AB >"  # 3-digit std id, contiguous hex
    ext = format_frame(can.Message(arbitration_id=0x1ABCDEF, data=b"\x00", is_extended_id=True), ts=0.0)
    assert ext.startswith(b"< frame 01ABCDEF ")
    err = format_frame(can.Message(arbitration_id=0x40, is_error_frame=True, data=b""), ts=0.0)
    assert err.startswith(b"< error 040 ")  # the daemon prints the error class with %03X
    msg = parse_send("< send 601 8 40 0 10 0 0 0 0 0 ")
    assert msg.arbitration_id == 0x601 and bytes(msg.data) == bytes([0x40, 0, 0x10, 0, 0, 0, 0, 0])
    assert not msg.is_extended_id
    assert parse_send("< send 601 3 1 2 >") is None  # length mismatch
    assert parse_send("< bogus >") is None
    # the stock client parses what we send
    from can.interfaces.socketcand.socketcand import convert_ascii_message_to_can_message as parse

    for raw in (sync, tpdo, ext, err):
        m = parse(raw.decode())
        assert m is not None
    assert parse(sync.decode()).dlc == 0 and bytes(parse(tpdo.decode()).data) == b"\x01\x02\xab"
    assert parse(err.decode()).is_error_frame and parse(err.decode()).arbitration_id == 0x40


def test_socketcand_port_in_use_is_a_clear_error(make_world):
    import socket

    from stagectl.errors import ConfigError

    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    try:
        world = make_world(transport={"kind": "socketcand", "port": busy.getsockname()[1]})
        with pytest.raises(ConfigError, match="sim.transport.port: cannot listen"):
            world.start()
    finally:
        busy.close()


@pytest.mark.parametrize("text, message", [
    ("io: {}\n", "no sim: section"),
    ("sim:\n  plant: {mass_kg: -1, friction: {model: stribeck, fc_n: 1, fs_n: 1}}\n  bogus: 1\n",
     "sim.plant.mass_kg"),
])
def test_sim_plant_config_errors_are_clear(tmp_path, capsys, text, message):
    import signal as _signal

    from stagectl.cli import main

    cfg = tmp_path / "bad.yaml"
    cfg.write_text(text)
    before = _signal.getsignal(_signal.SIGTERM)
    assert main(["sim-plant", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("stagectl: error:") and message in err and "Traceback" not in err
    assert _signal.getsignal(_signal.SIGTERM) is before  # handlers restored


def test_two_socketcand_clients_share_the_bus(make_world, make_drive):
    """Drive and encoder drivers on separate socketcand connections: the encoder sees the drive's SYNC."""
    from stagectl.drivers.cia406 import Cia406Config, Cia406Encoder

    world = make_world(transport={"kind": "socketcand", "port": 0}, encoder={"node_id": 4})
    world.start()
    can_cfg = world.ready_info()["can"]
    dut = make_drive(can_cfg, rx_timeout_s=0.5, heartbeat_timeout_s=30.0, drive_consumer_timeout_s=2.0)
    enc = Cia406Encoder(Cia406Config(node_id=4, can=can_cfg, rx_timeout_s=0.5, heartbeat_timeout_s=30.0,
                                     sdo_timeout_s=3.0), Timing(1e-3))
    try:
        dut.open()
        enc.open()
        dut.configure()
        enc.configure()
        dut.enable()
        for k in range(200):
            dut.sync()
            m = dut.read()
            e = enc.read()
            assert m.fresh and e.fresh and m.fault is None and e.fault is None, (k, m, e)
            assert e.counts == m.counts  # same plant, same resolution, same SYNC
            dut.write(3.0)
        assert m.counts > 0
    finally:
        enc.close()


def test_thread_mode_answers_each_sync_in_the_reader_thread(make_world, make_drive):
    """Real-time thread mode over socketcand (what `stagectl sim-plant` runs): every SYNC is answered (drive TPDO
    and the SYNC-triggered interferometer frame over TCP) in the socketcand reader thread that received it, none
    waits in the queue for the world's own thread (the hand-over that held SYNCs for 53-69 ms on a loaded
    machine, docs/platform.md section 1.3)."""
    from stagectl.drivers.interferometer import InterferometerConfig, SerialInterferometer

    world = make_world(transport={"kind": "socketcand", "port": 0},
                       interferometer={"transport": "tcp", "port": 0, "trigger": "sync"})
    world.start()
    info = world.ready_info()
    dut = make_drive(info["can"], rx_timeout_s=0.5, heartbeat_timeout_s=30.0, drive_consumer_timeout_s=2.0)
    ifm = SerialInterferometer(InterferometerConfig(url=info["interferometer_url"], rx_timeout_s=0.5,
                                                    stale_cycles=3))  # 0.5 s: failure guard only
    try:
        dut.open()
        dut.configure()
        ifm.open()
        dut.enable()
        ifm.configure()
        served0 = world.server.served_in_reader
        for k in range(100):
            dut.sync()
            m = ifm.read()
            assert m.fresh and m.fault is None, (k, m)
            dut.write(2.0)
        # each cycle: SYNC + RPDO (+ the controller heartbeat now and then), all served where they arrived
        assert world.server.served_in_reader - served0 >= 200
        assert world.server.recv(0) is None
        assert ifm.stats.sequence_gaps == 0 and m.counts > 0
    finally:
        ifm.close()


CHILD = """
import os, signal, sys, threading
from stagectl.cli import main

def fire():  # SIGTERM as soon as sim-plant's handler is in place (no sleeps: poll the handler)
    while signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, None):
        threading.Event().wait(0.0005)
    sys.stderr.write("heavy=%d\\n" % ("numpy" in sys.modules))
    os.kill(os.getpid(), signal.SIGTERM)

threading.Thread(target=fire, daemon=True).start()
sys.exit(main(["sim-plant", "--config", sys.argv[1]]))
"""


def test_sigterm_during_sim_plant_start_up_exits_cleanly(tmp_path):
    """SIGTERM while the plant is still being built: exit 0, and the handler is installed before any heavy
    import (the CLI builds only the sim-plant parser), which keeps the unprotected start-up window short."""
    cfg = tmp_path / "hil.yaml"
    cfg.write_text(textwrap.dedent(SIM_YAML))
    proc = subprocess.run([sys.executable, "-c", CHILD, str(cfg)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "heavy=0" in proc.stderr and "Traceback" not in proc.stderr


def test_socketcand_server_forwards_a_client_frame_before_the_devices_see_it():
    """Other clients must receive a SYNC before any device answer to it (as on a real bus); the world reads
    client frames from the server's queue, so the forward has to happen before the frame is queued."""
    import can

    from stagectl.sim.socketcand import SocketcandServer

    server = SocketcandServer()
    try:
        seen: list[bytes] = []

        class Peer:
            def send(self, data):
                seen.append(data)

        class Checked:
            def put(self, msg):
                assert seen, "frame queued for the devices before it was forwarded to the other clients"
                seen.append(b"queued")

        server._clients = [(Peer(), None)]
        server._incoming = Checked()
        server.from_client(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False, timestamp=1.0),
                           origin=object())
        assert seen == [b"< frame 080 1.000000  >", b"queued"]
    finally:
        server._clients = []
        server.stop()


PLAIN_YAML = SIM_YAML.replace("node_id: 3", "node_id: 1").split("  faults:")[0]


@pytest.mark.parametrize("sim_plant", [PLAIN_YAML], indirect=True)
def test_stock_canopen_master_over_socketcand_drives_sim_plant(sim_plant):
    """Clients no one here wrote, from outside: python-can's socketcand client + canopen's RemoteNode SDO and
    BaseNode402 master against ``stagectl sim-plant``: read 0x1000/0x1018, OPERATION ENABLED in CST, move."""
    import can
    import canopen

    from stagectl.drivers.cia402 import DEFAULT_EDS

    proc, info = sim_plant
    c = info["can"]
    bus = can.Bus(interface="socketcand", host=c["host"], port=c["port"], channel=c["channel"], tcp_tune=True)
    net = canopen.Network(bus)
    net.notifier = can.Notifier(bus, net.listeners, 0.05)
    node = canopen.BaseNode402(1, str(DEFAULT_EDS))
    net.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 3.0  # failure guard (loaded machine)
    try:
        node.nmt.state = "PRE-OPERATIONAL"
        assert int.from_bytes(node.sdo.upload(0x1000, 0), "little") == 0x00020192
        assert node.sdo[0x1018][2].raw == node.object_dictionary[0x1018][2].default  # product code
        assert node.sdo[0x1008].raw.startswith("stagectl")
        node.sdo[0x1017].raw = 20
        node.nmt.wait_for_heartbeat(5.0)
        node.setup_402_state_machine()
        node.op_mode = "CYCLIC SYNCHRONOUS TORQUE"
        node.nmt.state = "OPERATIONAL"
        net.sync.start(0.002)
        node.rpdo[1].start(0.002)
        node.state = "OPERATION ENABLED"
        assert node.state == "OPERATION ENABLED"
        x0 = None
        node.rpdo[1]["Target torque"].raw = 500  # 5 N > 1.5 N break-away
        for _ in range(2000):  # TPDO receptions, not sleeps
            node.tpdo[1].wait_for_reception(2.0)
            x = node.tpdo_values[0x6064]
            x0 = x if x0 is None else x0
            if x - x0 > 10_000:
                break
        assert x - x0 > 10_000, "the stage did not move under CST torque"
        node.rpdo[1]["Target torque"].raw = 0
        node.state = "SWITCH ON DISABLED"
    finally:
        net.sync.stop()
        node.rpdo[1].stop()
        net.notifier.stop(1.0)
        bus.shutdown()


def test_socketcand_handshake_ok_is_never_coalesced_with_a_frame():
    """python-can's client reads the rawmode ``< ok >`` with one recv(256) and an exact compare: traffic on
    the bus must not land in that read, even if the client is slow to read it."""
    import select
    import socket

    import can

    from stagectl.sim.socketcand import SocketcandServer

    server = SocketcandServer()
    server.start()
    sock = socket.create_connection((server.host, server.port), timeout=5.0)
    try:
        assert sock.recv(256) == b"< hi >"
        sock.sendall(b"< open can0 >")
        assert sock.recv(256) == b"< ok >"
        sock.sendall(b"< rawmode >")
        for _ in range(10_000):  # until the server has sent its ok (poll the server state; no sleeps)
            clients = [c for c, _ in server._clients]
            if clients and clients[0].raw:
                break
            select.select([], [], [], 0.001)
        hb = can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False)
        server.send(hb)  # bus traffic while the client has not read the ok yet
        assert sock.recv(256) == b"< ok >"
        sock.sendall(b"< send 080 0 >")  # the client talks: it has read the ok, frames flow from now on
        assert server.recv(5.0).arbitration_id == 0x080
        server.send(hb)
        assert select.select([sock], [], [], 5.0)[0]
        assert sock.recv(256).startswith(b"< frame 701 ")
    finally:
        sock.close()
        server.stop()


def test_stock_master_over_socketcand_gets_the_standard_aborts(sim_plant):
    """As a new user would: canopen's RemoteNode with the shipped EDS over python-can's socketcand client,
    against `stagectl sim-plant` in another process: PDO rules answered with CiA 301 abort codes."""
    import can
    import canopen
    from canopen.sdo.exceptions import SdoAbortedError

    from stagectl.drivers import canbus
    from stagectl.drivers.cia402 import DEFAULT_EDS

    _, info = sim_plant
    bus = canbus.open_bus(info["can"])
    net = canopen.Network(bus)
    net.notifier = can.Notifier(bus, net.listeners, 0.05)
    try:
        node = canopen.RemoteNode(info["drive_node_id"], str(DEFAULT_EDS))
        net.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = 10.0  # failure guard (loaded machine)
        codes = []
        for index, sub, value in ((0x1800, 1, 0x80000183), (0x1A00, 0, 0), (0x1A00, 1, 0x60720010),
                                  (0x1A00, 1, 0x20000010), (0x1A00, 1, 0x60640018)):
            try:
                node.sdo.download(index, sub, value.to_bytes(4 if sub or index != 0x1A00 else 1, "little"))
                codes.append(None)
            except SdoAbortedError as exc:
                codes.append(exc.code)
        assert codes == [None, None, 0x06040041, 0x06020000, 0x06040043]
    finally:
        net.notifier.stop(1.0)
        canbus.close_bus(bus)
