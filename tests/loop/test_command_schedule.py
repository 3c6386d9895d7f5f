"""The command schedule (``io.command_schedule``, issue 12 item 3): a slot the loop skips gets the controller's
predicted force instead of the held one, in simulated time.

* PlantIO against a plain reference: the force segments a recording plant sees around a skipped slot, with and
  without the schedule (the sequence of an on-time loop with one predicted force in it, or the old force held);
* the prediction is a pure function (feedback held, feed-forward extrapolated over one period, clamped);
* the seed stage's 10 µm cosine under skipped slots (a JitterClock) tracks better with the schedule, and within
  2x of the clean run under the whole disturbance of ``stagectl bench timing`` (the observer stepped once per
  sample with the period's coefficients, not told the scheduled forces: QFilterDob, "Irregular sampling").
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
from stagectl.sim.direct import PlantIO

from stagectl.bench.timing import run_tracking
from stagectl.config import load_app_config
from stagectl.control.controller import StageController, predict_next_force

REPO = Path(__file__).resolve().parents[2]
T = 1e-3


@pytest.fixture(scope="module")
def sim_cfg():
    return load_app_config(REPO / "config" / "sim.yaml")


class Recording:
    """A plant that records the force and duration of every sub-step it is advanced by."""

    def __init__(self):
        self.segments: list[tuple[float, float]] = []

    def step(self, u_n, dt_s):
        self.segments.append((u_n, dt_s))

    def measure(self):
        return 0.0


class Clock:
    def __init__(self):
        self.t_s = 0.0

    def now(self):
        return self.t_s


def _force_at(segments, t):
    """The force a recording plant saw at time ``t`` [s] after its first step."""
    t0 = 0.0
    for u, dt in segments:
        if t0 <= t < t0 + dt - 1e-12:
            return u
        t0 += dt
    raise AssertionError(f"no segment at {t}")


def _run(schedule: bool):
    """SYNC + write at 0, T, then the loop skips the slot at 2T and wakes at 3T, then 4T (writes u = 1, 2, 3,
    each with the prediction u + 0.5)."""
    plant, clock = Recording(), Clock()
    io = PlantIO(plant, T, delay_cycles=1, clock=clock, command_schedule=schedule)
    io.open(), io.configure(), io.enable()
    applied = []
    for t, u in ((0.0, 1.0), (T, 2.0), (3 * T, 3.0), (4 * T, None)):
        clock.t_s = t
        io.sync()
        applied.append(io.applied_force_n)
        if u is not None:
            io.write_schedule(u, u + 0.5)
    return plant.segments, applied, io


def test_plant_io_fills_a_skipped_slot_from_the_schedule():
    seg, applied, io = _run(True)
    # the plain reference: an on-time loop applies each write one period later, here with the skipped cycle's
    # command (it never ran) replaced by the prediction the write before the skip carried; the drive takes its
    # own slot 1.5 T after the last SYNC (it cannot tell a missing SYNC from a late one before then)
    expected = [(0.5 * T, 0.0), (1.5 * T, 1.0), (2.2 * T, 1.0), (2.6 * T, 2.0), (3.5 * T, 2.5), (3.99 * T, 2.5)]
    for t, u in expected:
        assert _force_at(seg, t) == u, (t, seg)
    assert applied == [0.0, 1.0, 2.5, 3.0] and io.own_slots == 1
    assert math.isclose(sum(dt for _, dt in seg), 4 * T)


def test_plant_io_without_a_schedule_holds_the_old_force():
    seg, applied, io = _run(False)
    for t, u in ((1.5 * T, 1.0), (2.2 * T, 1.0), (2.9 * T, 1.0), (3.5 * T, 2.0)):
        assert _force_at(seg, t) == u, (t, seg)
    assert applied == [0.0, 1.0, 2.0, 3.0] and io.own_slots == 0


def test_on_time_cycles_never_use_the_schedule():
    """A SYNC within 1.5 T of the last one (jitter) is that slot's: the schedule changes nothing on time."""
    for schedule in (False, True):
        plant, clock = Recording(), Clock()
        io = PlantIO(plant, T, clock=clock, command_schedule=schedule)
        io.open(), io.configure(), io.enable()
        out = []
        for k, t in enumerate((0.0, 1.2 * T, 2.0 * T, 3.4 * T, 4.1 * T)):
            clock.t_s = t
            io.sync()
            out.append(io.applied_force_n)
            io.write_schedule(float(k + 1), 100.0)
        assert out == [0.0, 1.0, 2.0, 3.0, 4.0] and io.own_slots == 0


def test_the_prediction_holds_the_feedback_and_extrapolates_the_feed_forward():
    # u = fb + ff: ff goes 0.30 -> 0.32 over dt = T; the next period's force is u + 0.02
    assert math.isclose(predict_next_force(1.0, 0.32, 0.30, T, T, 10.0), 1.02)
    # over a 2T interval the increment is halved for one period; clamped to the force limit
    assert math.isclose(predict_next_force(1.0, 0.32, 0.30, 2 * T, T, 10.0), 1.01)
    assert predict_next_force(9.99, 0.5, 0.0, T, T, 10.0) == 10.0
    assert predict_next_force(1.0, math.nan, 0.0, T, T, 10.0) == 1.0


def test_the_controller_exposes_its_prediction(sim_cfg):
    """StageController.next_force_increment_n is the feed-forward's increment: the feedback is held."""
    from stagectl.control.api import Reference

    ctl = StageController(sim_cfg.controller, T)
    ctl.reset(0.0)
    for k in range(20):
        t = k * T
        cmd = ctl.step(T, 0.0, Reference(1e-6 * t, 1e-3, 0.0))
    st = ctl.state
    prev_ff = st.terms["u_ff"] + st.terms["u_inertia"]
    cmd2 = ctl.step(T, 0.0, Reference(1e-6 * 20 * T, 1e-3, 0.0))
    inc = ctl.next_force_increment_n()
    ff = cmd2.terms["u_ff"] + cmd2.terms["u_inertia"]
    assert cmd.force_n != cmd2.force_n
    assert math.isclose(inc, ff - prev_ff, rel_tol=1e-9, abs_tol=1e-15)


def test_skipped_slots_cost_the_cosine_less_with_the_schedule(sim_cfg):
    """PlantIO on a JitterClock (10 % of the wake-ups one period late, U(0, 0.2 T) jitter, 1 % dropped samples):
    the 10 µm cosine, which lives on the stiff pre-sliding spring, tracks markedly better when the skipped slots
    get the predicted force (and the observer is told so) than when the actuator holds the old force."""
    assert sim_cfg.io.command_schedule  # shipped on
    off = dataclasses.replace(sim_cfg, io=dataclasses.replace(sim_cfg.io, command_schedule=False))
    kw = {"stage_kind": "plant_io", "disturbed": True, "duration_s": 2.2, "skip_s": 0.5}
    held = run_tracking(off, "cosine", **kw)
    sched = run_tracking(sim_cfg, "cosine", **kw)
    assert held["fault"] is None and sched["fault"] is None
    assert sched["skipped_slots"] == held["skipped_slots"] > 100
    assert sched["rms_error_nm"] < 0.75 * held["rms_error_nm"], (sched, held)


@pytest.mark.parametrize(("scenario", "seed"), [("cosine", 1), ("cosine", 5), ("triangle", 1)])
def test_skipped_slots_jitter_and_drops_track_within_2x(sim_cfg, scenario, seed):
    """Issue 12's timing target on plant_io, in simulated time: 10 % of the wake-ups one period late (the slot
    skipped), U(0, 0.2 T) wake-up jitter, 1 % of the samples dropped: no fault and the error RMS within 2x of the
    clean run, the 10 µm cosine on the pre-sliding spring included (before: 3.2x and 2.5x for seeds 1 and 5, the
    observer's coefficients following each interval and the observer told the scheduled forces)."""
    kw = {"stage_kind": "plant_io", "duration_s": 2.2, "skip_s": 0.5}
    clean = run_tracking(sim_cfg, scenario, disturbed=False, **kw)
    dist = run_tracking(sim_cfg, scenario, disturbed=True, seed=seed, **kw)
    assert clean["fault"] is None and dist["fault"] is None
    assert dist["skipped_slots"] > 150 and dist["stale_cycles"] > 10  # the disturbance really happened
    assert dist["rms_error_nm"] <= 2.0 * clean["rms_error_nm"], (dist, clean)
