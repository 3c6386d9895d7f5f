"""Iterative learning control in the real loop, simulated time (lock-step PlantIO): convergence over repetitions,
freeze on a fault, bumpless on/off (no step in the force), the ``ilc`` requests (status, start with a motion
name, save/load round trip, refusals) and the telemetry columns.

The stage is a rigid 1 kg mass with 5 N·s/m damping and a position-dependent spring force the controller
does not know, run by the real StageController (PID + Q-filter DOB, no friction feed-forward) whose nominal
mass is 20 % low: every repetition of the short motion leaves the same error behind for the learner.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from stagectl.sim.direct import PlantIO

from stagectl.clock import SimClock
from stagectl.control.controller import ControllerConfig, FeedforwardConfig, StageController
from stagectl.control.dob import DobConfig
from stagectl.control.ilc import ILC_COLUMNS, IlcConfig, IlcLearner, IlcPlant
from stagectl.control.pid import PidConfig
from stagectl.control.reference import TrajectoryReference
from stagectl.control.trajectory import Cosine, Scenario
from stagectl.loop import ControlLoop, LoopConfig
from stagectl.runtime.requests import IlcRequest, RequestError
from stagectl.safety import Safety, SafetyConfig

T = 1e-3
PID = PidConfig(kp_n_m=1.96e4, ki_n_m_s=4.93e5, kd_n_s_m=234.0, derivative_cutoff_hz=200.0)
SCAN = Scenario(name="scan", segments=(Cosine(amplitude_m=50e-6, frequency_hz=5.0, cycles=1.0),), settle_s=0.05)


class SpringMass:
    """m·a = u − c·v − k·x (exact enough with 0.1 ms Euler sub-steps); position quantised to 1 nm."""

    resolution_m = 1e-9

    def __init__(self, mass_kg: float = 1.0, c_n_s_m: float = 5.0, k_n_m: float = 2e3) -> None:
        self.m, self.c, self.k = mass_kg, c_n_s_m, k_n_m
        self.x_m = self.v_m_s = 0.0

    def step(self, u_n: float, dt_s: float) -> None:
        n = max(1, math.ceil(dt_s / 1e-4))
        h = dt_s / n
        for _ in range(n):
            self.v_m_s += (u_n - self.c * self.v_m_s - self.k * self.x_m) / self.m * h
            self.x_m += self.v_m_s * h

    def measure(self) -> float:
        return round(self.x_m / 1e-9) * 1e-9

    def measure_counts(self) -> int:
        return round(self.x_m / 1e-9)


class Rows:
    def __init__(self) -> None:
        self.rows: list[tuple[float, ...]] = []

    def append(self, row: tuple[float, ...]) -> None:
        self.rows.append(row)


def build(tmp_path, *, autostart: bool = True, scenario: Scenario | None = SCAN, **ilc_kw):
    io = PlantIO(SpringMass(), T, delay_cycles=1)
    io.open()
    io.configure()
    ctl_cfg = ControllerConfig(mass_kg=0.8, max_force_n=10.0, pid=PID, dob=DobConfig(kind="qfilter", bandwidth_hz=100.0),
                               feedforward=FeedforwardConfig(kind="none", inertia=True))
    ctl = StageController(ctl_cfg, T)
    ref = TrajectoryReference()
    if scenario is not None:
        ref.set_scenario(scenario, repeat=True)
    kw = {"alpha": 0.5, "q_cutoff_hz": 60.0, **ilc_kw}  # pinned: the phases below were chosen with this law
    cfg = IlcConfig(enabled=True, autostart=autostart, store_dir=tmp_path, **kw)
    learner = IlcLearner(cfg, IlcPlant(0.8, T, 1, PID, ctl_cfg.dob), ref.repetition, base_dir=tmp_path)
    if autostart:
        learner.start()
    safety = Safety(SafetyConfig(min_position_m=-0.01, max_position_m=0.01, following_error_m=1e-4,
                                 max_force_n=20.0, max_velocity_m_s=0.05), T)
    loop = ControlLoop(clock=SimClock(), sensor=io, actuator=io, controller=ctl, reference=ref, safety=safety,
                       cfg=LoopConfig(period_s=T), learner=learner, device_time=True)
    rows = Rows()
    loop.add_sink(rows)
    return loop, learner, io, rows


REP_S = SCAN.duration_s(0.0)


def col(loop: ControlLoop, rows: Rows, name: str) -> np.ndarray:
    return np.array([r[loop.columns.index(name)] for r in rows.rows])


def test_learning_converges_over_repetitions_and_is_in_telemetry(tmp_path):
    loop, learner, io, rows = build(tmp_path, alpha=0.8, q_cutoff_hz=100.0)
    try:
        loop.run(duration_s=6 * (REP_S + T) + 0.01)
    finally:
        io.close()
    rms = learner.rms_history
    assert len(rms) >= 5
    assert rms[-1] < 0.2 * rms[0], rms  # the mass error's repeating part is learned away
    assert all(c in loop.columns for c in ILC_COLUMNS)
    it = col(loop, rows, "ilc_iteration")
    assert it[-1] == learner.iteration and np.all(np.diff(it) >= 0)
    st = loop.status().ilc
    assert st is not None and st["motion"] == "scan" and st["design"]["monotonic"]
    # the learned force is what the controller added to its command
    u_ilc = col(loop, rows, "u_ilc")
    assert np.abs(u_ilc).max() > 1e-3


def test_a_fault_freezes_learning_and_drops_the_learned_force(tmp_path):
    loop, learner, io, rows = build(tmp_path)
    k_fault = int(3.5 * REP_S / T)

    def on_cycle() -> None:
        if loop.cycle == k_fault:
            io.inject_fault()

    loop.on_cycle = on_cycle
    try:
        loop.run(duration_s=5 * REP_S)
    finally:
        io.close()
    assert loop.safety.fault is not None
    st = loop.status().ilc
    assert st is not None and st["frozen"] and not st["learning"]
    it = col(loop, rows, "ilc_iteration")
    u_ilc = col(loop, rows, "u_ilc")
    k = int(np.argmax(col(loop, rows, "t") >= k_fault * T)) + 2
    assert np.all(u_ilc[k:] == 0.0)
    assert np.all(it[k:] == it[k])  # no update from the faulted repetition or after it
    assert 1 <= it[k] <= 3


def test_switching_learning_off_and_on_is_bumpless(tmp_path):
    loop, learner, io, rows = build(tmp_path, ramp_s=0.05)
    # switched where the learned force is large and smooth (its size there: ~4.5 mN; a step would show it)
    t_off, t_on = 4 * REP_S + 0.07, 5 * REP_S + 0.17

    def on_cycle() -> None:
        t = loop.cycle * T
        if abs(t - t_off) < T / 2:
            loop.submit(IlcRequest("stop"))
        elif abs(t - t_on) < T / 2:
            loop.submit(IlcRequest("start"))

    loop.on_cycle = on_cycle
    try:
        loop.run(duration_s=6 * REP_S)
    finally:
        io.close()
    u_ilc = col(loop, rows, "u_ilc")
    u = col(loop, rows, "u")
    t = col(loop, rows, "t")
    peak = np.abs(u_ilc).max()
    assert peak > 1e-3
    for ts, before, after in ((t_off, 1.0, 0.0), (t_on, 0.0, 1.0)):
        w = (t > ts - 0.005) & (t < ts + 0.03)
        k = int(np.argmax(t > ts - 0.005))
        # the learned force was there (or not) before the switch and ramps, ≤ |u|·T/ramp + its own slope per cycle
        learned = learner.u[int(round((ts - 0.005) % REP_S / T))]
        assert abs(u_ilc[k] - before * learned) < 0.1 * abs(learned) and abs(learned) > 3e-3
        assert np.abs(np.diff(u_ilc[w])).max() < abs(learned) * T / 0.05 + 2e-4
        # the total force changes no faster than at the same phase one repetition earlier (no kick)
        ref_w = (t > ts - 0.005 - REP_S) & (t < ts + 0.03 - REP_S)
        assert np.abs(np.diff(u[w])).max() < 3 * np.abs(np.diff(u[ref_w])).max() + 1e-3
    assert not learner.learning or learner.gain == 1.0


def test_ilc_requests_start_a_named_motion_and_round_trip_the_learned_signal(tmp_path):
    loop, learner, io, rows = build(tmp_path, autostart=False, scenario=None)
    replies: dict[str, object] = {}

    def on_cycle() -> None:
        k = loop.cycle
        if k == 5:
            replies["status"] = loop.submit(IlcRequest("status"))
            replies["bad"] = loop.submit(IlcRequest("start", "nonesuch"))
            replies["start"] = loop.submit(IlcRequest("start", "cosine"))
        if k == 7000:
            replies["save"] = loop.submit(IlcRequest("save", "cos-a"))
        if k == 7010:
            replies["load"] = loop.submit(IlcRequest("load", "cos-a"))

    loop.on_cycle = on_cycle
    try:
        loop.run(cycles=7020)
    finally:
        io.close()
    assert replies["status"].result()["motion"] is None  # type: ignore[attr-defined]
    with pytest.raises(RequestError, match="motion"):
        replies["bad"].result()  # type: ignore[attr-defined]
    started = replies["start"].result()  # type: ignore[attr-defined]
    assert started["learning"] and started["repetition_s"] == pytest.approx(3.2, abs=0.01)
    saved = replies["save"].result()  # type: ignore[attr-defined]
    assert saved["iteration"] >= 1 and (tmp_path / "cos-a.npz").exists()
    loaded = replies["load"].result()  # type: ignore[attr-defined]
    assert loaded["loaded"].endswith("cos-a.npz") and loaded["iteration"] == saved["iteration"]
    with pytest.raises(RequestError, match="action"):
        IlcRequest("explode")
    with pytest.raises(RequestError, match="motion"):
        IlcRequest("load")


def test_requests_are_refused_without_a_learner(tmp_path):
    loop, learner, io, rows = build(tmp_path)
    bare = ControlLoop(clock=SimClock(), sensor=io, actuator=io, controller=loop.controller, reference=loop.reference,
                       safety=loop.safety, cfg=LoopConfig(period_s=T))
    try:
        with pytest.raises(RequestError, match="ilc.enabled"):
            bare.submit(IlcRequest("start"))
        assert "u_ilc" not in bare.columns and bare.status().ilc is None
    finally:
        io.close()
