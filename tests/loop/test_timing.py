"""Robust to a shared PC's timing (issue 12 item 3), in simulated time.

* the controller steps with the measured sample interval: a skipped slot or stale samples give it the whole
  gap (no derivative kick when samples resume), a sample right after the last one is not stepped on;
* late and dropped TPDOs (the virtual drive's fault injection) and a jittery clock with skipped slots keep
  the seed stage tracking (RMS within 2x of the clean run) without a fault;
* the fault reaction brakes the stage to standstill within the force limit before the drive is released,
  after following_error / velocity_limit / position_limit; faults where braking is unsafe still release
  at once.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from stagectl.bench.timing import run_fault_reaction, run_tracking
from stagectl.config import IoKind, load_app_config
from stagectl.control.api import Reference
from stagectl.control.dob import DobConfig, QFilterDob
from stagectl.drivers.base import FaultKind
from stagectl.loop import LoopState
from stagectl.runtime.requests import MoveRequest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def sim_cfg():
    return load_app_config(REPO / "config" / "sim.yaml")


class StallingClock:
    """SimClock whose cycles take extra time (a loaded machine): ``stalls[k]`` s after cycle k."""

    def __init__(self, stalls):
        self.t_s, self.stalls, self.k = 0.0, stalls, 0

    def now(self):
        return self.t_s

    def sleep_until(self, t):
        self.t_s = max(self.t_s, t)

    def on_cycle(self):
        self.t_s += self.stalls.get(self.k, 0.0)
        self.k += 1


def test_controller_gets_the_measured_interval_and_no_kick_after_stale(make, rows):
    """dt = time since the last stepped sample: 2T after a skipped slot, 3T after two stale samples; the
    velocity the PD law sees stays the real one (no derivative kick when samples resume)."""
    loop, io, plant, ctl, _ = make(safety={"stale_cycles": 5})
    clock = StallingClock({20: 2.0e-3})  # cycle 20 ends one period after the next deadline: slot skipped
    loop.clock, loop.on_cycle = clock, None
    dts, vs = [], []
    step = ctl.step

    def spy(dt, x, ref):
        dts.append(dt)
        cmd = step(dt, x, ref)
        vs.append((x, dt))
        return cmd

    ctl.step = spy

    def on_cycle():
        clock.on_cycle()
        if loop.cycle == 40:
            io.drop_samples(2)

    loop.on_cycle = on_cycle
    loop.add_sink(rows)
    loop.submit(MoveRequest(target_m=100e-6, max_velocity_m_s=2e-3))
    res = loop.run(cycles=60)
    assert res.fault is None and res.overruns == 1
    dt = np.array(dts) / 1e-3
    assert sorted(set(np.round(dt, 9))) == [1.0, 2.0, 3.0]
    assert np.count_nonzero(np.isclose(dt, 2.0)) == 1 and np.count_nonzero(np.isclose(dt, 3.0)) == 1
    # the velocity the law computed over the 3T gap matches its neighbours (within 10 %): no kick
    v = np.diff([x for x, _ in vs]) / np.array([d for _, d in vs][1:])
    i = int(np.flatnonzero(np.isclose(dt[1:], 3.0))[0])
    assert abs(v[i] - v[i - 1]) < 0.1 * abs(v[i - 1]) + 1e-6
    # the old nominal dt (T) would have read three times the velocity
    assert abs(3 * v[i] - v[i - 1]) > 0.5 * abs(v[i - 1])


def test_a_sample_right_after_a_late_one_is_held_not_stepped(make, rows):
    """A wake-up 0.95 T late followed by an on-time one: two samples 0.05 T apart; the second one is not
    stepped on (its row is marked stale, the force held), the next step gets the whole interval."""
    loop, io, plant, ctl, _ = make()
    clock = StallingClock({10: 1.95e-3})  # cycle 11 wakes 0.95 T late, cycle 12 on time
    loop.clock, loop.on_cycle = clock, clock.on_cycle
    dts = []
    step = ctl.step
    ctl.step = lambda dt, x, ref: (dts.append(dt), step(dt, x, ref))[1]
    loop.add_sink(rows)
    res = loop.run(cycles=20)
    assert res.fault is None and res.overruns == 0
    stale = np.array([r[loop.columns.index("stale")] for r in rows.rows])
    assert list(np.flatnonzero(stale)) == [12]
    assert min(dts) >= 0.5e-3 and len(dts) == 19


def test_qfilter_dob_estimate_does_not_jump_when_dt_changes():
    """At constant velocity and force the Q-filter DOB's estimate stays put when dt changes (T -> 2T -> T):
    w is re-based with the new K_v."""
    dob = QFilterDob(DobConfig(kind="qfilter", bandwidth_hz=100.0), 2.0)
    dob.reset(0.0)
    x, v, u = 0.0, 1.5e-3, 0.4
    d = 0.0
    for k in range(200):
        dt = 2e-3 if k in (150, 170) else 1e-3
        x += v * dt
        d = dob.step(dt, x, v, u)
        if k == 149:
            d_before = d
        if k >= 150:
            assert d == pytest.approx(d_before, abs=1e-9)
    assert d == pytest.approx(u, abs=1e-6)  # the estimate is the force that does not accelerate the mass


@pytest.mark.parametrize("scenario", ["cosine", "triangle"])
def test_late_and_dropped_tpdos_track_within_2x_without_fault(sim_cfg, scenario):
    """Lock-step CANopen: late_tpdo on 10 % of the SYNCs and drop_tpdo on 1 % (seeded): no fault (before,
    two late TPDOs in a row already tripped missed_frame / stale_position with the 3-cycle limits) and RMS
    within 2x of the clean run (issue 12), the 10 um cosine in pre-sliding included."""
    clean = run_tracking(sim_cfg, scenario, stage_kind="canopen", disturbed=False, duration_s=2.2, skip_s=0.5)
    dist = run_tracking(sim_cfg, scenario, stage_kind="canopen", disturbed=True, duration_s=2.2, skip_s=0.5)
    assert clean["fault"] is None and dist["fault"] is None
    assert 150 < dist["stale_cycles"] < 300  # the disturbance really happened (~10 % of 2200 cycles)
    assert dist["rms_error_nm"] <= 2.0 * clean["rms_error_nm"], (dist, clean)


def test_holding_the_feedback_on_every_stale_sample_misses_the_cosine_target(sim_cfg):
    """What the predicted stale steps are for: with ``stale_predict_cycles: 0`` (every stale cycle holds the
    feedback and the observer, the next sample brings an interval of 2T) the same disturbance costs the
    pre-sliding cosine more than 1.5x (1.9x; 2.9x while the observer's coefficients followed the interval,
    before it stepped every sample with the period's: QFilterDob, "Irregular sampling")."""
    hold = dataclasses.replace(sim_cfg, controller=dataclasses.replace(sim_cfg.controller, stale_predict_cycles=0))
    clean = run_tracking(hold, "cosine", stage_kind="canopen", disturbed=False, duration_s=2.2, skip_s=0.5)
    dist = run_tracking(hold, "cosine", stage_kind="canopen", disturbed=True, duration_s=2.2, skip_s=0.5)
    assert dist["fault"] is None and dist["rms_error_nm"] > 1.5 * clean["rms_error_nm"], (dist, clean)


def test_lost_force_writes_alone_cost_the_pre_sliding_cosine(sim_cfg):
    """bench timing's held_force_only reference: every sample on time, but 10 % of the force writes lost (the
    actuator holds the previous force one more period, as in a skipped slot): the 10 um cosine's error grows
    although the controller misses nothing, so the skipped slots' cost is the held force, not the sampling."""
    clean = run_tracking(sim_cfg, "cosine", stage_kind="plant_io", disturbed=False, duration_s=2.2, skip_s=0.5)
    held = run_tracking(sim_cfg, "cosine", stage_kind="plant_io", disturbed=False, duration_s=2.2, skip_s=0.5,
                        lose_writes=True)
    assert held["fault"] is None and held["stale_cycles"] == 0 and held["skipped_slots"] == 0
    assert held["rms_error_nm"] > 1.5 * clean["rms_error_nm"], (held, clean)


def test_jitter_and_skipped_slots_keep_tracking_without_fault(sim_cfg):
    """PlantIO on a JitterClock: 10 % of the wake-ups one period late (slot skipped, the plant moves on
    under the held force), U(0, 0.2 T) jitter, 1 % of the samples dropped: no fault, triangle RMS within 2x
    (the 10 um cosine in pre-sliding is not: see bench timing)."""
    clean = run_tracking(sim_cfg, "triangle", stage_kind="plant_io", disturbed=False, duration_s=2.2, skip_s=0.5)
    dist = run_tracking(sim_cfg, "triangle", stage_kind="plant_io", disturbed=True, duration_s=2.2, skip_s=0.5)
    assert dist["fault"] is None and dist["skipped_slots"] > 150
    assert dist["rms_error_nm"] <= 2.0 * clean["rms_error_nm"], (dist, clean)


def test_velocity_fault_brakes_to_standstill_within_the_force_limit(sim_cfg):
    """velocity_limit at ~15 mm/s: the loop brakes on a ramp (force never above max_force_n), the stage
    stops within v0^2/(2 a_max) + the distance of the detection and I/O delay, then the drive is released;
    releasing at once (the old reaction) lets it coast more than 10x further."""
    brake = run_fault_reaction(sim_cfg, braking=True)
    coast = run_fault_reaction(sim_cfg, braking=False)
    T = sim_cfg.loop.period_s
    assert brake["fault"] == coast["fault"] == "velocity_limit"
    assert brake["brake_ended"] == "standstill"
    assert brake["max_applied_force_n"] <= sim_cfg.safety.max_force_n + 1e-9
    v0 = brake["v0_m_s"]
    assert v0 > 0.013
    assert brake["stop_distance_um"] <= brake["bound_v2_over_2amax_um"] + v0 * 3 * T * 1e6 + 1.0
    assert abs(brake["final_velocity_m_s"]) < 1e-5
    assert coast["stop_distance_um"] > 10 * brake["stop_distance_um"]


def _brake_run(cfg, change):
    from stagectl.app import build_stage
    from stagectl.clock import SimClock
    from stagectl.recorder import Recorder

    cfg = dataclasses.replace(cfg, io=dataclasses.replace(cfg.io, kind=IoKind.PLANT_IO))
    with build_stage(cfg, clock=SimClock()) as stage:
        loop, io = stage.loop, stage.actuator
        rec = Recorder(loop.columns, 2000)
        loop.add_sink(rec)
        applied = []
        loop.add_sink(type("P", (), {"append": lambda self, row: applied.append(io.applied_force_n)})())
        loop.submit(MoveRequest(target_m=3e-3, max_velocity_m_s=0.01))
        loop.on_cycle = lambda: loop.cycle == 300 and change(loop, stage)
        loop.run(duration_s=0.8)
        return loop, rec, np.array(applied), stage.sensor.plant


@pytest.mark.parametrize("name", ["following_error", "position_limit"])
def test_tracking_and_limit_faults_brake_then_release(sim_cfg, name):
    def change(loop, stage):
        c = loop.safety.cfg
        if name == "following_error":  # a disturbance pushes the stage off: emulated by a tiny window
            loop.safety.cfg = dataclasses.replace(c, following_error_m=1e-9, following_error_time_s=0.0)
        else:
            loop.safety.cfg = dataclasses.replace(c, max_position_m=stage.sensor.plant.x_m + 1e-6)

    loop, rec, applied, plant = _brake_run(sim_cfg, change)
    st = loop.status()
    assert st.state is LoopState.FAULT and st.fault.name == name
    b = loop.last_brake
    assert b is not None and b.why == "standstill" and abs(b.v0_m_s) > 5e-3
    k = st.fault.cycle
    assert np.max(np.abs(applied)) <= sim_cfg.safety.max_force_n + 1e-9
    assert np.min(applied[k:k + 5]) < -5.0  # braking force, not a release
    a_max = sim_cfg.safety.max_force_n / sim_cfg.controller.mass_kg
    x = rec.col("x")
    dist = abs(x[-1] - x[k])
    assert dist <= b.v0_m_s ** 2 / (2 * a_max) + abs(b.v0_m_s) * 3e-3 + 1e-6
    assert np.all(applied[-50:] == 0.0) and abs(plant.v_m_s) < 1e-5  # released, standing


@pytest.mark.parametrize("name", ["emcy", "not_finite", "stale_position"])
def test_unsafe_faults_still_release_at_once(sim_cfg, name):
    """Device fault, NaN position, stale position: no braking (no valid position or the drive does not
    obey), the force is zero within 3 cycles as before."""
    def change(loop, stage):
        io = stage.sensor
        if name == "emcy":
            io.inject_fault(FaultKind.EMCY, "overcurrent", 0x2310)
        elif name == "not_finite":
            io.glitch(math.nan)
        else:
            io.drop_samples(10)

    loop, rec, applied, plant = _brake_run(sim_cfg, change)
    st = loop.status()
    assert st.fault.name == name and loop.last_brake is None
    k = st.fault.cycle
    assert np.all(applied[k + 3:] == 0.0)


def test_stage_controller_predicts_short_stale_gaps_then_holds(sim_cfg):
    """The first stale_predict_cycles (2) stale cycles step the controller on x_r - e_last (the observer and the
    integrator move on, at the loop's rate); from the third stale cycle on the feedback is held; the next fresh
    sample is stepped with the rest of its interval since the last prediction (2T, the held cycle included)."""
    from stagectl.control.controller import StageController

    ctl = StageController(sim_cfg.controller, sim_cfg.timing)
    ctl.reset(0.0)
    for k in range(50):
        ctl.step(1e-3, 1e-9 * k, Reference(1e-9 * k + 2e-9, 1e-6, 0.0))
    i0 = ctl.pid.state.i_n
    p1 = ctl.hold(1e-3, Reference(52e-9, 1e-6, 0.0))
    assert p1.limited[:2] == ("stale", "predicted")
    assert ctl.state.x_prev_m == pytest.approx(50e-9)  # x_r - e_last (e_last = 2 nm)
    assert ctl.pid.state.i_n > i0  # the integrator went on with e_last
    p2 = ctl.hold(1e-3, Reference(53e-9, 1e-6, 0.0))
    assert "predicted" in p2.limited and ctl.state.x_prev_m == pytest.approx(51e-9)
    i2, d2 = ctl.pid.state.i_n, ctl.state.d_hat_n
    h3 = ctl.hold(1e-3, Reference(54e-9, 1e-6, 0.0))
    assert h3.limited == ("stale",) and ctl.pid.state.i_n == i2 and ctl.state.d_hat_n == d2
    ctl.step(4e-3, 53e-9, Reference(55e-9, 1e-6, 0.0))  # 4T since the last fresh sample, 2T of them predicted
    assert ctl.state.v_hat_m_s == pytest.approx((53e-9 - 51e-9) / 2e-3)


def test_stage_controller_hold_keeps_feedback_and_follows_the_feed_forward(sim_cfg):
    from stagectl.control.controller import StageController

    cfg = dataclasses.replace(sim_cfg.controller, stale_predict_cycles=0)
    ctl = StageController(cfg, sim_cfg.timing)
    ctl.reset(0.0)
    for k in range(50):
        cmd = ctl.step(1e-3, 1e-9 * k, Reference(1e-9 * k + 2e-9, 1e-6, 0.0))
    held = ctl.hold(1e-3, Reference(5.2e-8, 1e-6, 0.01))
    fb = cmd.force_n - cmd.terms["u_ff"] - cmd.terms["u_inertia"]
    assert held.terms["u_pid"] == cmd.terms["u_pid"] and held.terms["u_dob"] == cmd.terms["u_dob"]
    assert held.terms["u_inertia"] == pytest.approx(sim_cfg.controller.mass_kg * 0.01)
    assert held.force_n == pytest.approx(fb + held.terms["u_ff"] + held.terms["u_inertia"], abs=1e-12)
    assert ctl.pid.state.i_n == cmd.terms["u_i"]  # nothing integrated


def test_loop_slows_the_feedback_down_when_cycles_are_skipped_a_lot(sim_cfg, monkeypatch):
    """40 % of the wake-ups two periods late: the average sample interval passes 2 T, the loop divides the
    feedback crossover by the level reached (set_timing_scale) and tracks better than at full gain."""
    import stagectl.bench.timing as bench
    import stagectl.sim.jitter as jitter

    orig = jitter.JitterClock.__init__

    def init(self, *a, **k):
        k["late_periods"] = 2.0
        orig(self, *a, **k)

    monkeypatch.setattr(jitter.JitterClock, "__init__", init)
    monkeypatch.setattr(bench, "LATE_FRACTION", 0.4)
    # a design that relies on its full period: 40 Hz PID + 100 Hz DOB (PM 25.8 deg at one period of delay, the
    # shipped gains before the margins were raised), which two periods of delay nearly destabilise
    from stagectl.control.pid import PidConfig

    thin = dataclasses.replace(sim_cfg, controller=dataclasses.replace(
        sim_cfg.controller, pid=PidConfig(kp_n_m=3.92e4, ki_n_m_s=9.86e5, kd_n_s_m=468.0, derivative_cutoff_hz=200.0)))
    out = {}
    for tau in (0.0, 0.5):
        cfg = dataclasses.replace(thin, loop=dataclasses.replace(thin.loop, slow_down_time_s=tau))
        out[tau] = run_tracking(cfg, "cosine", stage_kind="plant_io", disturbed=True, duration_s=2.5, skip_s=1.0)
    assert out[0.5]["fault"] is None
    assert out[0.5]["rms_error_nm"] < 0.6 * out[0.0]["rms_error_nm"], out
    # the shipped (healthy) design slowed down the same way: still no fault; the slower feedback then costs
    # tracking (the price of keeping its margins at 2 T), bounded here
    shipped = run_tracking(sim_cfg, "cosine", stage_kind="plant_io", disturbed=True, duration_s=2.5, skip_s=1.0)
    assert shipped["fault"] is None and shipped["rms_error_nm"] < 500.0, shipped


def test_set_timing_scale_is_bumpless_and_scales_the_gains(sim_cfg):
    from stagectl.control.controller import StageController

    ctl = StageController(sim_cfg.controller, sim_cfg.timing)
    ctl.reset(0.0)
    for k in range(30):
        cmd = ctl.step(1e-3, 1e-9 * k, Reference(2e-9 * k, 2e-6, 0.0))
    ctl.set_timing_scale(2.0)
    p0, p = sim_cfg.controller.pid, ctl.pid.cfg
    assert p.kp_n_m == pytest.approx(p0.kp_n_m / 4) and p.ki_n_m_s == pytest.approx(p0.ki_n_m_s / 8)
    assert p.kd_n_s_m == pytest.approx(p0.kd_n_s_m / 2)
    assert ctl.dob.cfg.bandwidth_hz == pytest.approx(sim_cfg.controller.dob.bandwidth_hz / 2)
    nxt = ctl.step(1e-3, 3e-8, Reference(6e-8, 2e-6, 0.0))
    assert abs(nxt.force_n - cmd.force_n) < 0.05  # no bump
    ctl.set_timing_scale(1.0)
    assert ctl.pid.cfg == p0


def test_braking_through_the_virtual_cia402_drive_respects_its_torque_limit(sim_cfg):
    """Lock-step CANopen: the brake works through the real driver and respects the drive's own force limit
    (0x6072 max torque, 3 N here, below safety.max_force_n); then the drive's quick stop (controlword) ends in
    SWITCH ON DISABLED with the stage at rest."""
    from stagectl.app import build_stage
    from stagectl.clock import SimClock

    from stagectl.app import embedded_drive_config

    drive = dataclasses.replace(embedded_drive_config(None, sim_cfg.sim.drive, {}), quick_stop_option_code=2)
    sim = dataclasses.replace(sim_cfg.sim, drive=dataclasses.replace(sim_cfg.sim.drive, max_force_n=3.0))
    cfg = dataclasses.replace(sim_cfg, io=dataclasses.replace(sim_cfg.io, drive=drive), sim=sim)
    with build_stage(cfg, clock=SimClock()) as stage:
        loop, world = stage.loop, stage.world
        forces = []
        xs = []
        loop.add_sink(type("P", (), {"append": lambda self, row: (forces.append(world.drive.force_n),
                                                                   xs.append(row[1]))})())
        loop.submit(MoveRequest(target_m=4e-3, max_velocity_m_s=0.015))
        low = dataclasses.replace(loop.safety.cfg, max_velocity_m_s=0.013)

        def hook():
            if loop.safety.fault is None and loop.safety.v_est_m_s > 0.0145:
                loop.safety.cfg = low

        loop.on_cycle = hook
        res = loop.run(duration_s=0.6)
        lim = stage.actuator.force_limit_n
        b = loop.last_brake
        assert res.fault.name == "velocity_limit" and b is not None and b.why == "standstill"
        assert lim < sim_cfg.safety.max_force_n and b.max_force_n == pytest.approx(lim)
        assert max(abs(f) for f in forces) <= lim + 1e-9
        assert min(forces) <= -0.9 * lim  # it did brake
        k = res.fault.cycle
        v0, a_max = b.v0_m_s, lim / sim_cfg.controller.mass_kg
        assert abs(xs[-1] - xs[k]) <= v0 ** 2 / (2 * a_max) + v0 * 3e-3 + 1e-6
        assert world.drive.state.name == "SWITCH_ON_DISABLED" and abs(world.plant.v_m_s) < 1e-5


def test_safety_tolerates_a_longer_gap_only_while_the_stage_stands():
    """stale_rest_cycles applies while the reference speed and the last measured velocity are both below the
    quick-stop standstill (0.1 mm/s); moving (or unset) the stale limit stays stale_cycles. A stale sample
    never feeds the following-error window (it is the old position held)."""
    from stagectl.safety import Safety, SafetyConfig

    def gap(v_ref, v, rest=20):
        s = Safety(SafetyConfig(min_position_m=-1, max_position_m=1, stale_cycles=3, stale_rest_cycles=rest,
                                following_error_m=1e-6), 1e-3)
        s.check_measurement(0.0, 0, 0.0, True, None)
        s.v_est_m_s = v
        s.reference_speed_m_s = v_ref
        for k in range(1, 40):
            if s.check_measurement(k * 1e-3, k, 0.0, False, None):
                return k
        return None

    assert gap(0.0, 0.0) == 20
    assert gap(3e-5, 2e-5) == 20  # a slow scan (0.03 mm/s): at most 0.1 mm/s x the gap unseen
    assert gap(0.0, 0.0, rest=None) == 3
    assert gap(2e-3, 0.0) == 3  # the reference moves
    assert gap(0.0, 5e-4) == 3  # the stage still moves (above quick_stop_standstill_m_s)
    s = Safety(SafetyConfig(min_position_m=-1, max_position_m=1, following_error_m=1e-6), 1e-3)
    assert not s.check_tracking(0.0, 0, 0.0, 5e-6, fresh=False)  # a stale x against a moving reference
    assert s.check_tracking(0.001, 1, 0.0, 5e-6) and s.fault.name == "following_error"


@pytest.fixture(scope="module")
def hil_lockstep():
    """config/hil-canopen.yaml's driver, controller and safety on the in-process virtual bus (lock-step), unpaced
    (``loop.pace_cycles`` 0: lost answers of a drive whose plant runs on, as a real drive's; paced:
    tests/loop/test_device_pacing.py)."""
    cfg = load_app_config(REPO / "config" / "hil-canopen.yaml")
    return dataclasses.replace(cfg, io=dataclasses.replace(cfg.io, kind=IoKind.EMBEDDED_CANOPEN),
                               loop=dataclasses.replace(cfg.loop, pace_cycles=0))


@pytest.mark.parametrize("moving", [False, True])
def test_hil_config_rides_out_a_silent_drive_at_rest_not_while_moving(hil_lockstep, moving):
    """The HIL's sim-plant process is held off the CPU for 50-400 ms on a loaded machine (its TPDOs stop, the
    controller keeps its 1 kHz): 400 dropped TPDOs with the stage at rest are ridden out (feedback held, no
    fault, the stage stays put); the same silence during a 5 mm/s move is stale_position after 50 cycles,
    not a following error computed from the held position."""
    from stagectl.app import build_stage
    from stagectl.clock import SimClock
    from stagectl.recorder import Recorder
    from stagectl.sim.faults import FaultSpec, SimFault

    with build_stage(hil_lockstep, clock=SimClock()) as stage:
        loop = stage.loop
        rec = Recorder(loop.columns, 1000)
        loop.add_sink(rec)
        if moving:
            loop.submit(MoveRequest(target_m=1e-3, max_velocity_m_s=5e-3))
        stage.world.inject(FaultSpec(kind=SimFault.DROP_TPDO, at_cycle=100, cycles=400))
        res = loop.run(duration_s=0.7)
        x_end = stage.world.plant.x_m
    stale = rec.col("stale")
    if moving:
        assert res.fault is not None and res.fault.name == "stale_position"
        assert res.fault.cycle - 99 <= hil_lockstep.safety.stale_cycles + 1
    else:
        assert res.fault is None and stale.sum() >= 390
        assert abs(x_end) < 1e-8 and np.max(np.abs(rec.col("e")[stale == 0])) < 1e-8


def test_loop_device_time_from_the_config(sim_cfg):
    """loop.device_time (the HIL's sim-plant steps its plant one period per SYNC): the loop's time is its
    executed cycles, so with a clock that skips slots the reference advances one period per cycle."""
    from stagectl.app import build_stage
    from stagectl.recorder import Recorder
    from stagectl.sim.jitter import JitterClock

    cfg = dataclasses.replace(sim_cfg, io=dataclasses.replace(sim_cfg.io, kind=IoKind.PLANT_IO),
                              loop=dataclasses.replace(sim_cfg.loop, device_time=True))
    with build_stage(cfg, clock=JitterClock(1e-3, late_fraction=0.3, seed=2)) as stage:
        assert stage.loop.device_time
        rec = Recorder(stage.loop.columns, 200)
        stage.loop.add_sink(rec)
        stage.loop.run(cycles=100)
    assert np.allclose(np.diff(rec.col("t")), 1e-3) and rec.col("skipped").sum() > 10


def test_a_held_cycle_carries_the_learned_force_once(sim_cfg):
    """hold(dt, ref, u_learn_n): the learned feed-forward replaces the last cycle's instead of adding to it
    (before, the loop added the learner's force to a held command that already held the last one). The stale
    force limit is off here (.inf): it would clamp this stuck stage's 1.8 N (test_stale_policy.py)."""
    from stagectl.control.controller import StageController

    cfg = dataclasses.replace(sim_cfg.controller, stale_predict_cycles=0, stale_force_limit_n=math.inf)
    ctl = StageController(cfg, sim_cfg.timing)
    ctl.reset(0.0)
    ref = Reference(0.0, 0.0, 0.0)
    for _ in range(20):
        cmd = ctl.step(1e-3, 0.0, ref, 0.3)
    held = ctl.hold(1e-3, ref, 0.3)
    assert held.force_n == pytest.approx(cmd.force_n, abs=1e-12)
    held2 = ctl.hold(1e-3, ref, 0.1)
    assert held2.force_n == pytest.approx(cmd.force_n - 0.2, abs=1e-12)


def _starved_fault_stop(cfg, option):
    """A velocity_limit fault at 15 mm/s through the virtual CiA 402 drive with quick stop option ``option``;
    from the cycle after the fault 40 TPDOs in a row are lost (the sim-plant held off the CPU on a loaded
    machine). Returns (distance from the fault to rest [m], v0 [m/s], the loop's brake or None, drive state)."""
    from stagectl.app import build_stage
    from stagectl.clock import SimClock
    from stagectl.sim.faults import FaultSpec, SimFault

    from stagectl.app import embedded_drive_config

    drive = dataclasses.replace(embedded_drive_config(cfg.io.drive, cfg.sim.drive, {}), quick_stop_option_code=option)
    cfg = dataclasses.replace(cfg, io=dataclasses.replace(cfg.io, drive=drive))
    with build_stage(cfg, clock=SimClock()) as stage:
        loop, world = stage.loop, stage.world
        loop.submit(MoveRequest(target_m=4e-3, max_velocity_m_s=0.015))
        low = dataclasses.replace(loop.safety.cfg, max_velocity_m_s=0.013)
        at = {}

        def hook():
            if loop.safety.fault is None and loop.safety.v_est_m_s > 0.0145:
                loop.safety.cfg = low
            elif loop.safety.fault is not None and not at:
                at["x"], at["v"] = world.plant.x_m, world.plant.v_m_s
                world.inject(FaultSpec(kind=SimFault.DROP_TPDO, cycles=40))

        loop.on_cycle = hook
        res = loop.run(duration_s=0.8)
        assert res.fault is not None and res.fault.name == "velocity_limit"
        return (abs(world.plant.x_m - at["x"]), at["v"], loop.last_brake, world.drive.state.name,
                abs(world.plant.v_m_s), stage.actuator.force_limit_n)


def test_fault_stop_with_a_starved_master(sim_cfg):
    """Mechanism of the HIL's post-fault travel: the loop brakes over the bus, so its stop depends on fresh
    samples; when they stop coming (a starved master / stalled drive process) its brake gives up and the drive's
    torque-mode quick stop (0x605A = 2, a torque ramp) lets the stage coast on past the braking distance. With
    quick stop option 3 (the default now: slow down on the current limit) the drive brakes on its own velocity
    and clock, the loop releases to it at once, and the stage stops within v0²/(2·F_lim/m) + 3 periods."""
    m = sim_cfg.controller.mass_kg
    dist, v0, brake, _, _, lim = _starved_fault_stop(sim_cfg, 2)  # torque ramp: the loop brakes over the bus
    bound = v0 ** 2 / (2 * lim / m) + v0 * 3e-3
    assert brake is not None and dist > bound, (dist, bound)  # the bus brake gave up: the stage coasted
    dist3, v03, brake3, state3, v_end, lim3 = _starved_fault_stop(sim_cfg, 3)
    assert brake3 is None  # released to the drive at once
    assert state3 == "SWITCH_ON_DISABLED" and v_end < 1e-5
    assert dist3 < 0.5 * dist and dist3 <= v03 ** 2 / (2 * lim3 / m) + v03 * 3e-3, (dist3, v03)


def test_bus_brake_holds_its_force_only_briefly_without_samples():
    """The loop's bus brake (a drive without a braking quick stop): through a gap without fresh samples it holds
    its last force 2 cycles, then applies 0 (it held up to F_max blind for stale_cycles, pushing a stage that
    had stopped on); the next fresh sample resumes braking."""
    from stagectl.runtime.quickstop import HOLD_STALE_CYCLES, QuickStopBrake

    b = QuickStopBrake(0.0, 0.0, 0.01, mass_kg=2.0, max_force_n=10.0, deceleration_m_s2=4.5,
                       standstill_m_s=1e-4, stale_limit=50)
    u0 = b.step(0.001, 1e-5, True)
    assert u0 < -5.0
    held = [b.step(0.001 * (2 + i), 1e-5, False) for i in range(6)]
    assert held[:HOLD_STALE_CYCLES] == [u0] * HOLD_STALE_CYCLES and held[HOLD_STALE_CYCLES:] == [0.0] * 4
    assert not b.done and b.step(0.008, 5e-5, True) < 0.0
