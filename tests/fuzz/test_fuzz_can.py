"""Fuzz the CAN side: random frames from another participant on the python-can virtual bus, between the cycles
of our CiA 402 driver and the virtual drive (lock-step world, the real canopen stacks on both ends).

Invariants, per example (a fresh world and driver each time, so a failure replays):

* no exception escapes the virtual drive (its frame handling runs inside the world's pump, called from the
  driver's ``sync``) or the driver's receive path, except :class:`~stagectl.errors.DriverError` (a defined
  error the loop turns into a latched fault);
* every measurement is a finite position or carries a named fault; a fault latches (the driver's state is
  FAULT, a force written then is not sent as a torque);
* after the foreign frames stop, ``fault_reset()`` + ``enable()`` either recovers to fault-free cycling or
  raises a DriverError (a drive that another master reconfigured cannot always be recovered silently).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import can
from hypothesis import given
from hypothesis import strategies as st

from stagectl.drivers import canbus
from stagectl.drivers.base import DeviceState
from stagectl.drivers.cia402 import Cia402Config, Cia402Drive
from stagectl.errors import DriverError
from stagectl.sim.world import SimWorld, SimWorldConfig

sys.path.insert(0, str(Path(__file__).parent))
from fuzzing import fuzz  # noqa: E402

PLANT = {"mass_kg": 2.0, "friction": {"model": "stribeck", "fc_n": 1.0, "fs_n": 1.5, "viscous_n_s_m": 10.0},
         "sensor": {"resolution_m": 1e-9}}
NODE = 1
#: the COB-IDs that matter for node 1 (NMT, SYNC, EMCY, TPDO/RPDO 1-4, SDO, heartbeat) and their neighbours
KNOWN_IDS = [0x000, 0x080, 0x081, 0x082, 0x100, 0x181, 0x201, 0x281, 0x301, 0x381, 0x401, 0x481, 0x501,
             0x581, 0x601, 0x701, 0x702, 0x7E5, 0x7E4]

FRAME = st.builds(
    lambda cid, data, ext, rtr: can.Message(arbitration_id=cid if not ext else cid | (1 << 20), data=data,
                                            is_extended_id=ext, is_remote_frame=rtr,
                                            dlc=len(data) if not rtr else min(len(data), 8)),
    st.sampled_from(KNOWN_IDS) | st.integers(0, 0x7FF),
    st.binary(max_size=8),
    st.sampled_from([False] * 9 + [True]),  # mostly standard ids, some extended
    st.sampled_from([False] * 9 + [True]),
)


def _world_and_drive() -> tuple[SimWorld, Cia402Drive, can.BusABC]:
    world = SimWorld.from_config(SimWorldConfig.from_mapping({"plant": PLANT}))
    # the SDO timeout is a failure guard (a loaded machine), and the wait when a foreign frame silenced the drive
    dut = Cia402Drive(Cia402Config(node_id=NODE, can=world.ready_info()["can"], sdo_timeout_s=1.5), timing=1e-3)
    dut.set_pump(world.pump)
    dut.open()
    dut.configure()
    dut.enable()
    bus = canbus.open_bus({"interface": "virtual", "channel": world.channel})
    return world, dut, bus


def _cycle(dut: Cia402Drive, n: int) -> object:
    """``n`` loop cycles; returns the last measurement (or the first with a fault)."""
    m = None
    for _ in range(n):
        dut.sync()
        m = dut.read()
        assert m.fault is not None or (m.fresh is not None and math.isfinite(m.position_m)), m
        if m.fault is not None:
            assert m.fault.kind is not None and isinstance(m.fault.detail, str) and len(m.fault.detail) < 2000
            return m
        dut.write(0.2)
    return m


@fuzz(30)  # a fresh world and driver per input: ~0.2 s each
@given(st.lists(st.tuples(st.integers(0, 3), st.lists(FRAME, min_size=1, max_size=4)), min_size=1, max_size=3))
def test_foreign_frames_never_escape_as_exceptions(bursts: list[tuple[int, list[can.Message]]]) -> None:
    world, dut, bus = _world_and_drive()
    try:
        assert _cycle(dut, 3).fault is None
        faulted = False
        try:
            for gap, frames in bursts:
                for msg in frames:
                    bus.send(msg)
                m = _cycle(dut, 1 + gap)
                if m is not None and m.fault is not None:
                    faulted = True
                    assert dut.state is DeviceState.FAULT
                    break
        except DriverError:
            faulted = True  # a defined error: the loop latches it as a fault
        assert world.drive is not None and world.drive.state is not None  # the virtual drive still answers
        if faulted:
            try:
                dut.fault_reset()
                dut.enable()
            except DriverError:
                return  # refused to recover: defined
            m = _cycle(dut, 20)
            assert m.fault is None, m.fault
        else:
            assert _cycle(dut, 5).fault is None
    finally:
        canbus.close_bus(bus)
        dut.close()
        world.stop()
