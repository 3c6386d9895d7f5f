"""The HIL's sim-plant held off the CPU (thread mode on a loaded machine) must not judge the master silent
from its own stall: it would run the plant on its own clock through the whole stall under the last torque (a
demo run tracking within 40 nm at 0.9 N saw the stage 39 µm further one period later: ``position_jump``,
what a ~0.3 s take-over at the break-away level does), or fault EMCY 0x8130 (heartbeat consumer, another
run) although the controller's frames were only queued. Device time is driven by
hand here (no wall clock): ``threaded`` marks the drive as served in thread mode."""

from __future__ import annotations

import pytest
from stagectl.sim.cia402_drive import SELF_STALL_GRACE_S, DriveState

SHUTDOWN, SWITCH_ON, ENABLE = 0x06, 0x07, 0x0F


def _enable_cst(m, torque):
    m.download(0x6060, 0, "<b", 10)
    m.nmt(0x01)
    for cw in (SHUTDOWN, SWITCH_ON, ENABLE):
        m.download(0x6040, 0, "<H", cw)
    m.download(0x6071, 0, "<h", torque)
    m.sync(5)


@pytest.mark.parametrize("threaded", [True, False])
def test_a_stall_of_the_drive_process_itself_does_not_run_the_plant_on_its_own_clock(master, threaded):
    world, m = master()
    _enable_cst(m, 300)  # 3 N
    drive = world.drive
    drive.threaded = threaded
    x0 = world.plant.x_m
    world.advance(0.3)  # one timer tick 0.3 s after the last: this process was held off the CPU (threaded)
    if not threaded:  # lock-step / device time: 0.3 s without SYNC is real silence: the drive takes over
        assert world.plant.x_m != x0
        return
    assert world.plant.x_m == x0 and drive.state is DriveState.OPERATION_ENABLED and not drive.judging_silence
    m.sync()  # the queued SYNC is worked off within the grace: one period, no own-clock catch-up
    assert drive.state is DriveState.OPERATION_ENABLED
    # a master that really stays silent is judged so once the grace is over (ticks at the normal rate)
    x1 = world.plant.x_m
    for _ in range(round((SELF_STALL_GRACE_S + 0.3) / 0.005)):
        world.advance(0.005)
    assert drive.judging_silence and world.plant.x_m != x1  # the drive took over after sync_timeout_s / 2
