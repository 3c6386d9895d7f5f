"""Device-time pacing (``loop.pace_cycles``, issue 12 item 3): the HIL's sim-plant steps its plant one period per
SYNC, so a sim-plant process held off the CPU freezes its plant. Unpaced, the loop went on sending SYNCs and
forces it could not see answered, and the drive worked them off afterwards: every one a period of the plant run
blind (``stale_position`` after 50 of them, rightly). Paced, the loop's time waits with the drive's: no fault, and
the stage follows as without the stall. A real drive's silence (no device time: its plant moves on the clock) still
faults after ``safety.stale_cycles``, exactly as before.

Lock-step, simulated time: config/hil-canopen.yaml's driver, controller and safety against the virtual drive on
the in-process bus; the drive's process "held off the CPU" = its frames queue unread (no SYNC handled, no timer
tick, no heartbeat) for a window of the simulated clock, then it works them off in order.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from pathlib import Path

import numpy as np
import pytest

from stagectl.config import IoKind, load_app_config
from stagectl.runtime.requests import MoveRequest

REPO = Path(__file__).resolve().parents[2]


class FrozenDrive:
    """Wraps ``SimWorld.pump``: while ``clock.now()`` is in [t_from, t_to) the drive's process gets no CPU (its
    frames queue); afterwards it handles the queue in order, then runs normally."""

    def __init__(self, world, clock, t_from: float, t_to: float) -> None:
        self.w, self.clock, self.t_from, self.t_to = world, clock, t_from, t_to
        self.queue: deque = deque()

    def pump(self) -> int:
        w = self.w
        if self.t_from <= self.clock.now() < self.t_to:
            while (msg := w._bus.recv(0.0)) is not None:
                self.queue.append(msg)
            return 0
        if not self.queue:
            return w.pump()
        with w._lock:
            while (msg := w._bus.recv(0.0)) is not None:
                self.queue.append(msg)
            n = 0
            while self.queue:
                w._dispatch(self.queue.popleft())
                w._tick()
                n += 1
            w._tick()
        return n


@pytest.fixture(scope="module")
def hil():
    cfg = load_app_config(REPO / "config" / "hil-canopen.yaml")
    assert cfg.loop.device_time and cfg.loop.pace_cycles == 1
    return dataclasses.replace(cfg, io=dataclasses.replace(cfg.io, kind=IoKind.EMBEDDED_CANOPEN))


def _run(cfg, *, pace: int, stall: tuple[float, float] | None = None, drop: int = 0, device_time: bool = True,
         duration_s: float = 0.4):
    """A 300 µm move at 2 mm/s from rest; the drive frozen over ``stall`` (simulated clock, s) or ``drop`` of its
    answers lost from cycle 100 on (its plant running on). Returns (result, loop, rows, true plant x per row)."""
    from stagectl.sim.faults import FaultSpec, SimFault

    from stagectl.app import build_stage
    from stagectl.clock import SimClock
    from stagectl.recorder import Recorder

    cfg = dataclasses.replace(cfg, loop=dataclasses.replace(cfg.loop, pace_cycles=pace))
    clock = SimClock()
    with build_stage(cfg, clock=clock) as stage:
        loop = stage.loop
        loop.device_time = device_time
        stage.load_scenario("hold")
        rec = Recorder(loop.columns, 2000)
        loop.add_sink(rec)
        world = stage.world
        if stall is not None:
            stage.sensor.set_pump(FrozenDrive(world, clock, *stall).pump)  # type: ignore[attr-defined]
        if drop:
            world.inject(FaultSpec(kind=SimFault.DROP_TPDO, at_cycle=100, cycles=drop))
        xs: list[float] = []
        loop.on_cycle = lambda: xs.append(world.plant.x_m)
        loop.submit(MoveRequest(relative_m=300e-6, max_velocity_m_s=2e-3))
        res = loop.run(duration_s=duration_s)
    return res, loop, rec, np.array(xs)


def _true_error(rec, xs) -> float:
    """Largest |reference − the plant's own position| over the rows with a fresh sample (a stale row's plant
    position is the drive's, one step behind while its process is frozen)."""
    n = min(rec.n, len(xs))
    fresh = rec.col("stale")[:n] < 0.5
    return float(np.max(np.abs(rec.col("x_ref")[:n] - xs[:n])[fresh]))


def test_a_frozen_sim_plant_is_waited_for_not_run_blind(hil):
    clean, _, rec0, x0 = _run(hil, pace=1)
    # 100 ms without the drive, mid-move at 2 mm/s (twice safety.stale_cycles)
    paced, _, rec, x = _run(hil, pace=1, stall=(0.1, 0.2))
    blind, _, _, _ = _run(hil, pace=0, stall=(0.1, 0.2))
    assert clean.fault is None and clean.device_waits == 0
    # paced: the loop waited the whole stall, ran no cycle blind and tracked as without it
    assert paced.fault is None, paced.fault
    assert 95 <= paced.device_waits <= 105
    assert rec.col("stale").sum() <= 2  # measured 1 (the cycle whose SYNC the frozen drive left unanswered)
    e0, e = _true_error(rec0, x0), _true_error(rec, x)
    assert e <= 1.1 * e0, (e, e0)  # measured 0.913 µm against 0.903 µm
    # loop time is the drive's: the run covers the same 0.4 s of motion, the reference is where the stage is
    assert rec.n == rec0.n
    # unpaced (the loop before): the SYNCs of the stall ran the plant blind once worked off: stale_position
    assert blind.fault is not None and blind.fault.name == "stale_position", blind.fault
    assert abs(blind.fault.cycle - 100 - hil.safety.stale_cycles) <= 3


def test_a_stop_during_a_paced_wait_is_answered_in_the_slot_it_arrives(hil):
    """A client's stop must not wait on a slow plant (issue 12): while the loop waits for a frozen drive (here 100
    ms mid-move), the stop is answered in the wall slot it arrives in, not when the drive answers again (before:
    after the whole stall, up to io.drive.max_missed slots, 1 s in the HIL configs); the loop's ``on_wait`` hook
    (the daemon takes its clients' requests there) runs in every slot of the wait. The stop is planned at the
    next cycle's loop time, so it acts at that cycle, and the stage comes to rest where the reply said."""
    from stagectl.app import build_stage
    from stagectl.clock import SimClock
    from stagectl.recorder import Recorder
    from stagectl.runtime.requests import StopRequest

    cfg = dataclasses.replace(hil, loop=dataclasses.replace(hil.loop, pace_cycles=1))
    clock = SimClock()
    seen: dict = {}
    with build_stage(cfg, clock=clock) as stage:
        loop = stage.loop
        stage.load_scenario("hold")
        rec = Recorder(loop.columns, 2000)
        loop.add_sink(rec)
        frozen = FrozenDrive(stage.world, clock, 0.1, 0.2)
        hooks = []
        loop.on_wait = lambda: hooks.append(loop.device_waits)

        def pump() -> int:  # the request arrives from "another thread" 5 slots into the wait
            if loop.device_waits == 5 and "fut" not in seen:
                seen["at"] = (loop.device_waits, loop.cycle)
                seen["fut"] = fut = loop.submit(StopRequest())
                fut.add_done_callback(lambda f: seen.setdefault("done", (loop.device_waits, loop.cycle)))
            return frozen.pump()

        stage.sensor.set_pump(pump)  # type: ignore[attr-defined]
        x0 = stage.world.plant.x_m
        loop.submit(MoveRequest(relative_m=300e-6, max_velocity_m_s=2e-3))
        res = loop.run(duration_s=0.4)
    assert res.fault is None, res.fault
    assert 95 <= res.device_waits <= 105
    # answered in the wait slot it arrived in (counted by then), no cycle in between; before: the first cycle after
    # the stall, ~95 slots later
    assert seen["done"] == (seen["at"][0] + 1, seen["at"][1]), seen
    assert len(hooks) == res.device_waits and hooks[0] == 1
    x_stop = seen["fut"].result()["x_m"]
    assert x0 + 100e-6 < x_stop < x0 + 300e-6 - 50e-6  # stopped short of the move's end
    t, v_ref, x_ref = rec.col("t"), rec.col("v_ref"), rec.col("x_ref")
    k = int(np.argmax(t > 0.1 + 1e-6))  # the first cycle after the stall (its loop time: the stall's start)
    assert abs(v_ref[k - 1]) > 1.9e-3  # at full speed when the drive froze
    assert np.all(np.diff(v_ref[k:]) <= 1e-12)  # decelerating from that cycle on: the stop acts there
    assert v_ref[-1] == 0.0 and x_ref[-1] == pytest.approx(x_stop, abs=1e-12)


def test_a_real_drives_silence_still_faults_after_stale_cycles(hil):
    """No device time (a real drive: its plant moves on the clock): pacing is off whatever pace_cycles says, and
    lost answers fault stale_position at the same cycle as without pacing."""
    on, loop, rec, _ = _run(hil, pace=1, drop=200, device_time=False, duration_s=0.3)
    off, _, _, _ = _run(hil, pace=0, drop=200, device_time=False, duration_s=0.3)
    assert loop.device_waits == 0
    assert on.fault is not None and on.fault.name == "stale_position"
    assert off.fault is not None and (off.fault.name, off.fault.cycle) == (on.fault.name, on.fault.cycle)
    first = int(np.argmax(rec.col("stale") > 0))  # the first lost answer (mid-move)
    assert abs(rec.col("v_ref")[first]) > 1e-3
    assert abs(on.fault.cycle - first - hil.safety.stale_cycles) <= 1


def test_a_dead_drive_process_faults_after_max_missed_wall_slots(hil):
    """Paced, a drive process that never comes back: the loop waits at most io.drive.max_missed wall slots, then
    missed_frame; its plant stood still meanwhile (no SYNC was handled)."""
    res, loop, rec, x = _run(hil, pace=1, stall=(0.1, 9.0), duration_s=0.4)
    assert res.fault is not None and res.fault.name == "missed_frame", res.fault
    assert hil.io.drive is not None
    assert abs(loop.device_waits - hil.io.drive.max_missed) <= 2
    assert rec.col("stale")[: res.fault.cycle].sum() <= 1  # no cycle run blind before it (then: FAULT)
    assert np.ptp(x[99:]) < 1e-9  # the plant stood still from the stall on


def test_the_wait_keeps_the_controller_heartbeat_and_ends_on_the_drives(make_lockstep_drive):
    """While the loop waits, the driver still sends the controller heartbeat on the wall clock (the drive's
    consumer must not stop a stage that only waits), and a drive heartbeat arriving during the wait ends it: the
    drive's process runs, so its answers were lost, not delayed (the stale limits then judge them)."""
    w, dut, frozen = make_lockstep_drive
    dut.sync()
    assert not dut.read().fresh  # the frozen drive did not answer
    dut.write(0.0)
    slots = 0
    for _ in range(100):
        assert dut.behind(1, 1)
        slots += 1
    hb = [m for m in frozen if m.arbitration_id == 0x700 + dut.cfg.controller_node_id]
    assert len(hb) == round(slots * 1e-3 / dut.cfg.controller_heartbeat_s)  # 5 beats in 100 ms
    assert sum(m.arbitration_id == 0x080 for m in frozen) == 1  # no SYNC after the unanswered one
    w.drive.send(0x700 + w.drive.node_id, bytes([5]))  # the drive's process runs: its heartbeat
    assert not dut.behind(1, 1)


def test_a_fault_noted_during_the_wait_ends_it(make_lockstep_drive):
    """A fault the driver notes while the loop waits (here a second SYNC producer on the bus; a bus error, an
    EMCY) ends the wait at once, so the next cycle's read() latches it: the wait must not hold it back for up
    to max_missed wall slots (1 s in the HIL configs)."""
    import can

    w, dut, _ = make_lockstep_drive
    dut.sync()
    assert not dut.read().fresh
    dut.write(0.0)
    assert dut.behind(1, 1)
    w._bus.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))  # someone else's SYNC
    assert not dut.behind(1, 1)
    dut.sync()
    m = dut.read()
    assert m.fault is not None and "second SYNC producer" in m.fault.detail, m.fault


@pytest.fixture
def make_lockstep_drive():
    from stagectl.drivers.cia402 import Cia402Config, Cia402Drive
    from stagectl.sim.world import SimWorld, SimWorldConfig

    w = SimWorld.from_config(SimWorldConfig.from_mapping({"plant": {
        "mass_kg": 2.0, "friction": {"model": "stribeck", "fc_n": 1.0, "fs_n": 1.5, "viscous_n_s_m": 10.0},
        "sensor": {"resolution_m": 1e-9}}}))
    dut = Cia402Drive(Cia402Config(node_id=1, can=w.ready_info()["can"], sdo_timeout_s=3.0, max_missed=1000,
                                   heartbeat_timeout_s=1.0), timing=1e-3)
    frozen: list = []
    state = {"frozen": False}

    def pump() -> int:
        if state["frozen"]:
            while (msg := w._bus.recv(0.0)) is not None:
                frozen.append(msg)
            return 0
        return w.pump()

    try:
        dut.set_pump(pump)
        dut.open()
        dut.configure()
        dut.enable()
        for _ in range(5):
            dut.sync()
            assert dut.read().fresh
            dut.write(0.0)
        state["frozen"] = True
        yield w, dut, frozen
    finally:
        dut.close()
        w.stop()
