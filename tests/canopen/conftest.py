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
