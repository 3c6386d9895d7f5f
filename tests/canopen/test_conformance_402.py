"""CiA 402 conformance of the virtual drive through canopen's stock master (SDO + raw frames), never our driver:
the power state machine with its statusword patterns (CiA 402-2 tables of transitions and state coding), CST
statusword bit 12, 0x6072, quick stop and fault reaction ramps on the drive's own clock, SYNC supervision."""

from __future__ import annotations

import struct

import pytest

from stagectl.sim.cia402_drive import EMCY_SYNC_LOST, DriveState

# statusword state coding (mask, value), CiA 402-2 table 30
SW = {
    "SOD": (0x4F, 0x40), "RTSO": (0x6F, 0x21), "SO": (0x6F, 0x23), "OE": (0x6F, 0x27), "QSA": (0x6F, 0x07),
    "FRA": (0x4F, 0x0F), "FAULT": (0x4F, 0x08),
}
SHUTDOWN, SWITCH_ON, ENABLE, DISABLE_OP, DISABLE_VOLTAGE, QUICK_STOP, RESET = 0x06, 0x07, 0x0F, 0x07, 0x00, 0x02, 0x80

# (transition numbers, controlwords from SWITCH ON DISABLED, resulting state)
TRANSITIONS = [
    ("2", [SHUTDOWN], "RTSO"),
    ("2,3", [SHUTDOWN, SWITCH_ON], "SO"),
    ("2,3,4", [SHUTDOWN, SWITCH_ON, ENABLE], "OE"),
    ("2,3+4", [SHUTDOWN, ENABLE], "OE"),
    ("2,3,4,5", [SHUTDOWN, SWITCH_ON, ENABLE, DISABLE_OP], "SO"),
    ("2,3,6", [SHUTDOWN, SWITCH_ON, SHUTDOWN], "RTSO"),
    ("2,7", [SHUTDOWN, QUICK_STOP], "SOD"),
    ("2,3,4,8", [SHUTDOWN, SWITCH_ON, ENABLE, SHUTDOWN], "RTSO"),
    ("2,3,4,9", [SHUTDOWN, SWITCH_ON, ENABLE, DISABLE_VOLTAGE], "SOD"),
    ("2,3,10", [SHUTDOWN, SWITCH_ON, DISABLE_VOLTAGE], "SOD"),
    ("2,3,4,11", [SHUTDOWN, SWITCH_ON, ENABLE, QUICK_STOP], "QSA"),
    ("2,3,4,11,12", [SHUTDOWN, SWITCH_ON, ENABLE, QUICK_STOP, DISABLE_VOLTAGE], "SOD"),
    ("1 then invalid 4", [ENABLE], "SOD"),  # enable operation from SWITCH ON DISABLED: no transition
]


def _sw(m):
    return m.upload(0x6041, 0, "<H")


def _is(sw, state):
    mask, value = SW[state]
    return sw & mask == value


@pytest.mark.parametrize("path, cws, state", TRANSITIONS, ids=[t[0] for t in TRANSITIONS])
def test_power_state_machine_transitions(master, path, cws, state):
    world, m = master()
    assert _is(_sw(m), "SOD")
    for cw in cws:
        m.download(0x6040, 0, "<H", cw)
    sw = _sw(m)
    assert _is(sw, state), f"{path}: statusword {sw:#06x}"
    assert sw & 0x0200  # remote


def test_fault_reaction_fault_and_reset_13_14_15(master):
    world, m = master()
    m.nmt(0x01)
    for cw in (SHUTDOWN, SWITCH_ON, ENABLE):
        m.download(0x6040, 0, "<H", cw)
    world.inject("drive_fault", code=0x2310)
    m.sync()
    assert _is(_sw(m), "FRA")  # 13: FAULT REACTION ACTIVE, at least one period
    m.sync()
    assert _is(_sw(m), "FAULT")  # 14
    assert m.upload(0x603F, 0, "<H") == 0x2310
    m.download(0x6040, 0, "<H", RESET)  # 15: rising edge of bit 7
    assert _is(_sw(m), "SOD")
    assert m.upload(0x1001, 0, "<B") == 0
    assert [struct.unpack("<H", bytes(f.data[:2]))[0] for f in m.frames(0x081)] == [0x2310, 0x0000]


def _enable_cst(world, m, torque):
    m.download(0x6060, 0, "<b", 10)
    m.nmt(0x01)
    for cw in (SHUTDOWN, SWITCH_ON, ENABLE):
        m.download(0x6040, 0, "<H", cw)
    m.download(0x6071, 0, "<h", torque)
    m.sync()


def test_cst_statusword_bit12_and_max_torque(master):
    world, m = master()
    m.download(0x6072, 0, "<H", 3000)
    _enable_cst(world, m, 5000)
    m.sync()
    sw = _sw(m)
    assert _is(sw, "OE") and sw & 0x1000  # CST: drive follows the target torque
    assert m.upload(0x6077, 0, "<h") == 3000  # 0x6071 = 5000 clamped by 0x6072 = 3000
    assert world.drive.force_n == pytest.approx(30.0)
    m.download(0x6040, 0, "<H", DISABLE_OP)
    assert not _sw(m) & 0x1000


@pytest.mark.parametrize("with_sync", [True, False])
def test_quick_stop_ramps_and_completes_on_the_drives_clock(master, with_sync):
    """0x605A = 2: torque ramps down with 0x6087, then SWITCH ON DISABLED — with SYNC, and without any SYNC
    (device time advanced by the world: the drive's own clock)."""
    world, m = master()
    m.download(0x6087, 0, "<I", 50_000)  # 50 000 ‰/s × 0.01 N = 500 N/s: 3 N take 6 ms
    _enable_cst(world, m, 300)
    m.sync()
    assert world.drive.force_n == pytest.approx(3.0)
    x0 = world.plant.x_m
    m.download(0x6040, 0, "<H", QUICK_STOP)
    assert _is(_sw(m), "QSA")
    forces = []
    for _ in range(10):
        if with_sync:
            m.sync()
        else:
            world.advance(0.001)
        forces.append(world.drive.force_n)
    if with_sync:
        assert forces[0] == pytest.approx(2.5) and forces[1] == pytest.approx(2.0)  # the ramp, 0.5 N per ms
    else:  # the drive takes over after 3 silent periods and catches up period by period
        assert any(0.0 < f < 3.0 for f in forces), forces
    assert all(a >= b for a, b in zip(forces, forces[1:])) and forces[-1] == 0.0
    assert _is(_sw(m), "SOD")
    assert world.plant.x_m != x0  # the stage moved during the ramp: the drive ran the plant on its own clock


def test_quick_stop_option_6_stays_and_16_re_enables(master):
    world, m = master()
    m.download(0x605A, 0, "<h", 6)
    _enable_cst(world, m, 100)
    m.download(0x6040, 0, "<H", QUICK_STOP)
    m.sync(3)
    assert _is(_sw(m), "QSA") and world.drive.force_n == 0.0
    m.download(0x6040, 0, "<H", ENABLE)  # 16
    assert _is(_sw(m), "OE")


def test_fault_reaction_ramp_0x605e(master):
    world, m = master()
    m.download(0x605E, 0, "<h", 2)
    m.download(0x6087, 0, "<I", 100_000)  # 1 N per ms
    _enable_cst(world, m, 400)
    m.sync()
    world.inject("drive_fault", code=0x4310)
    states = []
    for _ in range(6):
        m.sync()
        states.append((world.drive.state, round(world.drive.force_n, 6)))
    fra = DriveState.FAULT_REACTION_ACTIVE
    assert states[:5] == [(fra, 4.0), (fra, 3.0), (fra, 2.0), (fra, 1.0), (DriveState.FAULT, 0.0)]


def test_sync_supervision_faults_and_stage_keeps_moving(master):
    """SYNC stops while 3 N are commanded: the plant keeps moving on the drive's clock (not frozen) until
    SYNC supervision (sim.drive.sync_timeout_s = 0.1 s) faults the drive with EMCY 0x8700 and zero force."""
    world, m = master(drive={"sync_timeout_s": 0.1})
    _enable_cst(world, m, 300)
    m.sync(50)
    m.frames()
    x = world.plant.x_m
    world.advance(0.08)
    assert world.plant.x_m > x  # not frozen: the drive took over after sync_timeout_s / 2
    assert world.drive.state is DriveState.OPERATION_ENABLED
    world.advance(0.03)
    assert world.drive.state is DriveState.FAULT and world.drive.force_n == 0.0
    assert m.upload(0x603F, 0, "<H") == EMCY_SYNC_LOST
    emcy = [struct.unpack("<HB", bytes(f.data[:3])) for f in m.frames(0x081)]
    assert emcy == [(EMCY_SYNC_LOST, 0x11)]
    x = world.plant.x_m
    world.advance(0.5)
    v = world.plant.v_m_s
    assert world.drive.force_n == 0.0 and world.plant.x_m >= x and v >= 0.0


@pytest.mark.parametrize("option", [2, 3, 7])
def test_quick_stop_on_the_current_limit_brakes_a_moving_stage_without_sync(master, option):
    """0x605A = 3 / 7 (slow down on current limit): the drive brakes the moving stage on its own velocity at the
    torque limit 0x6072, on its own clock with no SYNC at all (a starved master), to standstill; then SWITCH ON
    DISABLED (3) or QUICK STOP ACTIVE (7). 0x605A = 2 in a torque mode only ramps the torque away: the stage
    coasts on against its friction, several times farther."""
    world, m = master()
    m.download(0x605A, 0, "<h", option)
    m.download(0x6072, 0, "<H", 500)  # 5 N
    _enable_cst(world, m, 400)  # 4 N accelerate the 2 kg seed stage
    m.sync(20)
    v0, x0 = world.plant.v_m_s, world.plant.x_m
    assert v0 > 0.02
    m.download(0x6040, 0, "<H", QUICK_STOP)
    forces = []
    for _ in range(300):
        if option == 2:
            m.sync()  # (the plant is stepped by SYNC once the power stage is off)
        else:
            world.advance(0.001)
        forces.append(world.drive.force_n)
    dist = world.plant.x_m - x0
    a_lim = 5.0 / 2.0  # m/s^2 at the torque limit, friction only helps
    if option == 2:
        assert _is(_sw(m), "SOD") and dist > 3 * v0 ** 2 / (2 * a_lim), (dist, v0)
        return
    assert min(forces) == pytest.approx(-5.0) and max(forces) <= 1e-9  # braking at the limit, never pushing
    assert abs(world.plant.v_m_s) < 1e-5
    assert 0 < dist <= v0 ** 2 / (2 * a_lim) + v0 * 0.004, (dist, v0)
    assert _is(_sw(m), "SOD" if option == 3 else "QSA")
    assert world.drive.force_n == 0.0
