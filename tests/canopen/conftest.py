"""Fixtures for the CANopen tests: simulated worlds on unique virtual channels, and a bus-leak guard."""

from __future__ import annotations

import pytest

from stagectl.drivers import canbus
from stagectl.drivers.cia402 import Cia402Config, Cia402Drive

PLANT = {
    "mass_kg": 2.0,
    "friction": {"model": "stribeck", "fc_n": 1.0, "fs_n": 1.5, "viscous_n_s_m": 10.0},
    "sensor": {"resolution_m": 1e-9},
}


@pytest.fixture(autouse=True)
def no_leaked_bus():
    """Fail any test that leaves a CAN bus (driver, world or socketcand client) open."""
    before = set(map(id, canbus.OPEN_BUSES))
    yield
    leaked = [b for b in list(canbus.OPEN_BUSES) if id(b) not in before]
    for b in leaked:
        canbus.close_bus(b)
    assert not leaked, f"test leaked {len(leaked)} open CAN bus(es): {[b.channel_info for b in leaked]}"


def world_config(**sim):
    from stagectl.sim.world import SimWorldConfig

    data = {"plant": PLANT, **sim}
    return SimWorldConfig.from_mapping(data)


@pytest.fixture
def make_world():
    from stagectl.sim.world import SimWorld

    worlds = []

    def make(**sim):
        w = SimWorld.from_config(world_config(**sim))
        worlds.append(w)
        return w

    yield make
    for w in worlds:
        w.stop()


@pytest.fixture
def make_drive():
    drives = []

    def make(can, period_s=0.001, **kw):
        kw.setdefault("sdo_timeout_s", 3.0)  # failure guard only: the machine is shared and loaded
        d = Cia402Drive(Cia402Config(node_id=kw.pop("node_id", 1), can=can, **kw), timing=period_s)
        drives.append(d)
        return d

    yield make
    for d in drives:
        d.close()


@pytest.fixture
def lockstep(make_world, make_drive):
    """A configured + enabled drive on a lock-step world: (world, drive)."""

    def make(world_kw=None, **drive_kw):
        w = make_world(**(world_kw or {}))
        dut = make_drive(w.ready_info()["can"], **drive_kw)
        dut.set_pump(w.pump)
        dut.open()
        dut.configure()
        dut.enable()
        return w, dut

    return make


class Master:
    """An independent CiA 301 master for the conformance tests: canopen's stock ``RemoteNode`` (SDO client) on
    its own bus, plus a raw observer bus, against a lock-step world. SDO transfers run while a helper thread
    pumps the world (simulated time advances only with SYNC or ``advance``); frames are sent and observed raw.
    Never our driver."""

    def __init__(self, world, node_id):
        import canopen

        from stagectl.drivers.cia402 import DEFAULT_EDS

        world.pump()
        ch = {"interface": "virtual", "channel": world.channel}
        self.world = world
        self.node_id = node_id
        self.bus = canbus.open_bus(ch)
        self.raw = canbus.open_bus(ch)
        self.net = canopen.Network(self.bus)
        self.net.notifier = __import__("can").Notifier(self.bus, self.net.listeners, 0.02)
        self.node = canopen.RemoteNode(node_id, str(DEFAULT_EDS))
        self.net.add_node(self.node)
        self.node.sdo.RESPONSE_TIMEOUT = 3.0  # failure guard only (loaded machine)
        self.sync_id = 0x080

    def close(self):
        self.net.notifier.stop(0.5)
        canbus.close_bus(self.bus)
        canbus.close_bus(self.raw)

    # -------------------------------------------------------------- SDO (stock client)
    def download(self, index, sub, fmt, value):
        import struct

        from stagectl.drivers.canbus import pumping

        with pumping(self.world.pump, "master"):
            self.node.sdo.download(index, sub, struct.pack(fmt, value))

    def upload(self, index, sub, fmt):
        import struct

        from stagectl.drivers.canbus import pumping

        with pumping(self.world.pump, "master"):
            return struct.unpack_from(fmt, self.node.sdo.upload(index, sub))[0]

    def abort_code(self, index, sub, fmt, value):
        """The SDO abort code a download gets (None if accepted)."""
        from canopen.sdo.exceptions import SdoAbortedError

        try:
            self.download(index, sub, fmt, value)
        except SdoAbortedError as exc:
            return exc.code
        return None

    # -------------------------------------------------------------- raw frames
    def send(self, cid, data=b"", extended=False):
        import can

        self.bus.send(can.Message(arbitration_id=cid, data=bytes(data), is_extended_id=extended))
        self.world.pump()

    def nmt(self, cmd):
        self.send(0x000, bytes([cmd, self.node_id]))

    def sync(self, n=1):
        for _ in range(n):
            self.send(self.sync_id)

    def frames(self, cid=None):
        """Frames seen on the bus since the last call (optionally only COB-ID ``cid``)."""
        self.world.pump()
        out = []
        while (m := self.raw.recv(0.0)) is not None:
            if cid is None or m.arbitration_id == cid:
                out.append(m)
        return out


@pytest.fixture
def master(make_world):
    """(world, Master) on a lock-step world; ``master_node`` in the drive config via ``node_id``."""
    made = []

    def make(node_id=1, **sim):
        sim.setdefault("drive", {})
        sim["drive"] = {"node_id": node_id, **sim["drive"]}
        w = make_world(**sim)
        m = Master(w, node_id)
        made.append(m)
        return w, m

    yield make
    for m in made:
        m.close()
