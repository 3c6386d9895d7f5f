"""Stale samples judged by how far the stage can have gone unseen (``safety.stale_travel_m``), simulated time.

Before: config/sim.yaml and config/stage-canopen.yaml faulted ``stale_position`` after any 3 stale cycles in a
row, which 10 % late cycles give a few times in 3400 (``stagectl bench timing --stages canopen --seed 3``),
whatever the speed. Now the bound D(τ) = max(|v̂|, |v_ref|)·τ + (F̄/m)·τ²/2 on the unseen travel decides while
moving, with ``stale_cycles`` (20) as the hard cap: a slow scan rides out a few stale cycles, a fast blind stage
still faults within a few."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from stagectl.config import load_app_config
from stagectl.runtime.requests import MoveRequest
from stagectl.safety import Safety

REPO = Path(__file__).resolve().parents[2]
T = 1e-3


@pytest.fixture(scope="module")
def sim_cfg():
    return load_app_config(REPO / "config" / "sim.yaml")


def _blind(cfg, v_m_s: float, n: int = 40, force_n: float = 2.0) -> int | None:
    """The stale cycle (1, 2, ...) at which ``Safety`` with ``cfg`` (2 kg) latches, for a stage seen moving at
    ``v_m_s`` (fresh samples on the ramp, reference at the same speed, ``force_n`` written each cycle) that then
    goes blind; None if it rides out ``n`` stale cycles."""
    s = Safety(cfg, T, mass_kg=2.0)
    for k in range(200):  # v̂ settles on the ramp
        s.reference_speed_m_s = v_m_s
        assert not s.check_measurement(k * T, k, v_m_s * k * T, True, None)
        s.limit_force(k * T, k, force_n)
    for j in range(1, n + 1):
        k = 199 + j
        if s.check_measurement(k * T, k, v_m_s * 199 * T, False, None):
            assert s.fault is not None and s.fault.name == "stale_position"
            return j
        s.limit_force(k * T, k, force_n)
    return None


@pytest.mark.parametrize("name", ["sim.yaml", "stage-canopen.yaml"])
def test_shipped_limits_ride_out_a_few_stale_cycles_on_a_scan_not_a_blind_fast_stage(name):
    """The shipped safety sections: 5 stale cycles at the bench's triangle speed (1.57 mm/s, 0.9 N: the seed
    stage's friction) pass; a stage seen at 0.9·max_velocity_m_s faults at the first stale cycle whose plain
    bound passes the allowance (2-3); one crawling at 0.2 mm/s with 0.1 N is stopped by the 20-cycle cap, with
    2 N pushing it (1 m/s² unopposed: 50 µm in 10 ms) earlier."""
    cfg = load_app_config(REPO / "config" / name).safety
    assert cfg.stale_travel_m == cfg.following_error_m and cfg.stale_cycles == 20

    def plain(v, f):
        return next(j for j in range(1, 1000) if v * j * T + 0.5 * (f / 2.0) * (j * T) ** 2 > cfg.stale_travel_m)

    assert _blind(cfg, 1.57e-3, n=5, force_n=0.9) is None and plain(1.57e-3, 0.9) > 5
    v_fast = 0.9 * cfg.max_velocity_m_s
    assert _blind(cfg, v_fast) == plain(v_fast, 2.0) <= 3  # (as before the change: the 3-cycle limit)
    assert _blind(cfg, 2e-4, force_n=0.1) == cfg.stale_cycles < plain(2e-4, 0.1)
    assert _blind(cfg, 2e-4, force_n=2.0) == plain(2e-4, 2.0) < cfg.stale_cycles


def test_unseen_travel_bound_against_a_plain_computation_and_a_friction_plant(sim_cfg):
    """D(τ) from ``Safety.unseen_travel_m`` equals max(|v̂|, |v_ref|)·τ + (F̄/m)·τ²/2 with F̄ the largest force
    written since the cycle before the last fresh sample; and a plain mass with Coulomb + viscous friction
    (semi-implicit Euler, 10 µs), starting at v̂ and pushed by those forces (forwards, braking, reversing),
    never travels further than D."""
    m, v0 = 2.0, 4e-3
    s = Safety(dataclasses.replace(sim_cfg.safety, stale_travel_m=1.0), T, mass_kg=m)
    forces_before = [0.5, -3.0]  # the second is written at the last fresh cycle's predecessor
    for k in range(300):
        s.reference_speed_m_s = 3e-3
        s.check_measurement(k * T, k, v0 * k * T, True, None)
        s.limit_force(k * T, k, forces_before[k == 298])
    v_hat = s.v_est_m_s
    assert v_hat == pytest.approx(v0, rel=1e-6)
    gap_forces = [1.0, -2.0, 2.5, -1.5, 0.5, 12.0]  # the last one is clamped at max_force_n (10 N)
    f_bar = 3.0
    for j, f in enumerate(gap_forces, start=1):
        k = 299 + j
        assert not s.check_measurement(k * T, k, v0 * 299 * T, False, None)
        tau = j * T
        plain = max(abs(v_hat), 3e-3) * tau + 0.5 * (f_bar / m) * tau * tau
        assert s.unseen_travel_m(tau) == pytest.approx(plain, rel=1e-12)
        s.limit_force(k * T, k, f)
        f_bar = max(f_bar, min(abs(f), sim_cfg.safety.max_force_n))
    assert f_bar == 10.0

    def travel(forces, fc=0.3, c=20.0, h=1e-5):
        """|Δx| after len(forces) periods of a stage at v0 with Coulomb fc [N] (stuck below it) and viscous c."""
        x, v = 0.0, v0
        for f in forces:
            for _ in range(round(T / h)):
                if v == 0.0 and abs(f) <= fc:
                    continue
                fr = -math.copysign(fc, v if v != 0.0 else f) - c * v
                v_new = v + (f + fr) / m * h
                if v != 0.0 and v_new * v < 0.0 and abs(f) <= fc:
                    v_new = 0.0  # friction stops it, never pushes it back
                v = v_new
                x += v * h
        return abs(x)

    for forces in ([10.0] * 10, [-10.0] * 10, [3.0, -3.0] * 5, [-1.0] * 3 + [10.0] * 7):
        fb = max(abs(f) for f in forces)
        for n in (1, 3, 10):
            bound = abs(v0) * n * T + 0.5 * (fb / m) * (n * T) ** 2
            assert travel(forces[:n]) <= bound


def test_sim_stage_rides_out_stale_runs_on_a_scan_and_faults_blind_at_speed(sim_cfg):
    """config/sim.yaml's CiA 402 stage (the real driver, virtual drive, simulated time): 3 and 5 dropped TPDOs
    in a row during the triangle scan pass without a fault (before: stale_position, or the drive's
    missed_frame, at the third); the drive going silent during a 10 mm/s move faults stale_position on the
    travel allowance, at the stale cycle the plain bound v·τ + (F̄/m)·τ²/2 passes 50 µm (5-6 cycles), before
    the 20-cycle cap; the real plant's travel from the last fresh sample stays within that bound."""
    from stagectl.sim.faults import FaultSpec, SimFault

    from stagectl.app import build_stage
    from stagectl.clock import SimClock
    from stagectl.recorder import Recorder

    with build_stage(sim_cfg, clock=SimClock()) as stage:
        loop = stage.loop
        stage.load_scenario("triangle")
        rec = Recorder(loop.columns, 2000)
        loop.add_sink(rec)
        stage.world.inject(FaultSpec(kind=SimFault.DROP_TPDO, at_time_s=0.6, cycles=3))
        stage.world.inject(FaultSpec(kind=SimFault.DROP_TPDO, at_time_s=0.9, cycles=5))
        res = loop.run(duration_s=1.2)
    assert res.fault is None, res.fault
    stale = rec.col("stale")
    assert stale.sum() >= 8 and np.all(np.abs(rec.col("v_ref")[stale > 0]) > 1.5e-3)  # the gaps, mid-scan

    with build_stage(sim_cfg, clock=SimClock()) as stage:
        loop, world = stage.loop, stage.world
        rec = Recorder(loop.columns, 2000)
        loop.add_sink(rec)
        truth: list[float] = []
        loop.on_cycle = lambda: truth.append(world.plant.x_m)
        loop.submit(MoveRequest(target_m=4e-3, max_velocity_m_s=1e-2))
        world.inject(FaultSpec(kind=SimFault.DROP_TPDO, at_time_s=0.25, cycles=40))
        res = loop.run(duration_s=0.4)
    f = res.fault
    assert f is not None and f.name == "stale_position" and "stale_travel_m" in f.cause, f
    stale, t = rec.col("stale"), rec.col("t")
    first = int(np.argmax(stale > 0))
    n_stale = round((f.t_s - t[first - 1]) / T)  # stale cycles up to and with the fault
    v = max(abs(rec.col("v")[first - 1]), abs(rec.col("v_ref")[first - 1]))
    assert 9e-3 < v < 1.1e-2
    f_bar = np.max(np.abs(rec.col("u")[first - 2:]))
    expected = next(j for j in range(1, 1000) if v * j * T + 0.5 * (f_bar / 2.0) * (j * T) ** 2 > 5e-5)
    assert n_stale == expected and 4 <= n_stale < sim_cfg.safety.stale_cycles
    # the plant's truth (end of each cycle) over the n_stale periods up to the fault, taken a period early
    # (the last fresh sample is from its cycle's SYNC): the real GMS plant stayed within the bound that faulted
    i_f = first - 1 + n_stale
    moved = abs(truth[i_f - 1] - truth[first - 2])
    assert 0.9 * 5e-5 < moved <= v * n_stale * T + 0.5 * (f_bar / 2.0) * (n_stale * T) ** 2
