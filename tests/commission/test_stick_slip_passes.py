"""A constant-velocity pass that stick-slips is read from its sliding phases, at their speeds.

Oracle: the plain stage of ``test_analysis._cv_plant_record`` (a mass with Stribeck + viscous friction, Karnopp
stick, a cogging force; a PD + integral loop with one period of I/O delay; the commissioning's pass layout),
not the simulator. The stage is k106-like (1.36 kg, F_s 2.04 N, F_c 1.70 N, v_s 1.06 mm/s, δ 2, 2.42 N s/m,
a 0.42 N cogging of 1.35 mm). Under a 22 Hz loop its 1 mm/s passes (the Stribeck dip) slip and nearly stop in
turn: their speed over short windows falls below a quarter of the pass's mean. On main such a pass was left
as it was (the ripple correction skips it): its mean force, the curve averaged over speeds from ~0.2 to 1.7×
the mean, lies well above the curve at the mean speed, and the Stribeck curve fitted through it had v_s +11 %
and the viscous +12 %. The passes are read as the sequence reads them after the slow passes (the cogging
taken off, the windows centred on a cogging extremum).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from stagectl.commission import analysis as an

sys.path.insert(0, str(Path(__file__).parent))
from test_analysis import _cv_plant_record

M, FC, FS, VS, FV = 1.36, 1.70, 2.04, 1.06e-3, 2.42
COG_N, COG_L = 0.42, 1.35e-3
TAU = 1.5e-3  # one period of delay plus half a period of zero-order hold


def _curve(v: float) -> float:
    return math.copysign(FC + (FS - FC) * math.exp(-((v / VS) ** 2)), v) + FV * v


def test_stick_slip_passes_are_read_from_their_sliding_phases() -> None:
    speeds = np.geomspace(16e-3 / 100, 16e-3, 6)
    t, x, u, v_ref, a_ref = _cv_plant_record(M, FC, FS, VS, FV, COG_N, COG_L, 0.0, speeds, 8e-3, loop_hz=22.0,
                                             delay_cycles=1)
    pf = COG_N * np.sin(2 * math.pi * x / COG_L)
    dropped: list[an.CvSegment] = []
    segs = an.cv_segments(t, x, u, v_ref, a_ref, M, speeds=speeds, delay_s=TAU, position_force_n=pf,
                          cogging=(COG_L, 0.0), dropped=dropped)
    assert len(segs) == 12 and not dropped  # none stood long enough to be dropped as stick-slip
    # the oracle's own record: both 1 mm/s passes fall below a quarter of their mean speed over 5 samples, and
    # read whole they lie > 10 mN off the curve at their mean speed (the curve averaged over the rung speeds)
    T = float(t[1] - t[0])
    ii = np.arange(u.size, dtype=np.float64)
    u_acting = np.interp(ii - TAU / T, ii, u) - pf
    for sgn in (1.0, -1.0):
        i = np.flatnonzero((np.abs(v_ref - sgn * float(speeds[2])) < 1e-12) & (a_ref == 0.0))
        i = i[i.size // 5: -(i.size // 5)]
        vw = (x[i[5:]] - x[i[:-5]]) / (5 * T)
        v_mean = float((x[i[-1]] - x[i[0]]) / (t[i[-1]] - t[i[0]]))
        assert float(np.min(vw / v_mean)) < an.STUCK_SPEED_FRACTION
        assert abs(float(np.mean(u_acting[i])) - _curve(v_mean)) > 0.01
    got = an.cv_friction(segs)
    c = got.stribeck
    assert c is not None
    assert c["vs_m_s"] == pytest.approx(VS, rel=0.03)  # main: +11 %
    assert c["fs_n"] == pytest.approx(FS, rel=0.02)
    assert c["fc_n"] == pytest.approx(FC, rel=0.01)
    assert c["viscous_n_s_m"] == pytest.approx(FV, rel=0.08)  # main: +12 %
    assert got.coulomb_n == pytest.approx(FC, rel=0.01)
    # those passes were read from their sliding phases: most of the pass, at a speed near its mean, with their
    # window speeds for the correction; report.json names them
    slid = [s for s in segs if s.sliding_fraction < 1.0]
    ring = [s for s in slid if abs(abs(s.v_pass_m_s) / float(speeds[2]) - 1) < 0.1]
    assert len(ring) == 2 and {s.v_m_s > 0 for s in ring} == {True, False}
    assert all(0.8 < s.sliding_fraction < 1.0 and s.v_window is not None and abs(s.v_m_s / s.v_pass_m_s - 1) < 0.1
               for s in ring)
    rows = [r for r in got.as_dict()["segments"] if r.get("stick_slip")]
    assert len(rows) == len(slid) and all(0.8 < r["sliding_fraction"] < 1.0 for r in rows)


def test_stick_slip_passes_on_a_maxwell_slip_stage_under_the_real_controller() -> None:
    """The same stage as the plain Maxwell-slip stage of ``plain_stage.py`` (pre-sliding stiffness 1 MN/m, no
    cogging) under the real :class:`StageController` with the experiments' tuning (PID + observer, Coulomb
    feed-forward of 80 % of F_c, the FRF's mass 4 % low) at a 12 Hz crossover, through the sequence's pass
    layout. Its 1 mm/s passes stick-slip (their 5-sample speed falls below a quarter of the mean); main read them
    whole and its v_s came out +9.5 %, the branch reads their sliding phases: v_s +0.3 %."""
    from plain_stage import MaxwellSlipStage, pass_segments

    from stagectl.commission import sequence as seq
    from stagectl.control.controller import StageController
    from stagectl.control.trajectory import Scenario, TrajectoryGenerator

    T, m_est, v_max, stroke = 1e-3, 1.30, 0.016, 2e-3
    st = {"mass": M, "fs": FS, "fc": FC, "visc": FV, "vs": VS, "k": 1.0e6}
    cfg = seq.commission_tuning(m_est, T, 7.0, 0.8 * FC, crossover_x_period=12.0 * T)
    ctl = StageController(cfg, T)
    budget = seq.pass_budget(cfg, T, 1, M, 0.02, FS, 0.0, 50e-6)
    gen = TrajectoryGenerator(0.0)
    gen.load(Scenario(name="cv", segments=tuple(
        pass_segments(budget, m_est, 2e-3, 2e-3 ** 2 / (0.04 * stroke), T, v_max, stroke))))
    ctl.reset(0.0)
    stage = MaxwellSlipStage(st)
    rows = []
    while not gen.done:
        ref = gen.step(T)
        u = ctl.step(T, stage.x, ref).force_n
        rows.append((stage.x, u, ref.v_m_s, ref.a_m_s2))
        stage.period(u, T)
    x, u, v_ref, a_ref = (np.array(c) for c in zip(*rows))
    t = np.arange(x.size) * T
    speeds = np.geomspace(v_max / seq.CV_SPAN, v_max, seq.CV_SPEEDS)
    dropped: list[an.CvSegment] = []
    segs = an.cv_segments(t, x, u, v_ref, a_ref, m_est, speeds=speeds, delay_s=1.5 * T, dropped=dropped)
    assert len(segs) == 12 and not dropped
    got = an.cv_friction(segs).stribeck
    assert got is not None
    assert got["vs_m_s"] == pytest.approx(VS, rel=0.03)  # main: +9.5 %
    assert got["fs_n"] == pytest.approx(FS, rel=0.01)
    assert got["fc_n"] == pytest.approx(FC, rel=0.01)
    assert got["viscous_n_s_m"] == pytest.approx(FV, rel=0.1)
    slid = [s for s in segs if s.sliding_fraction < 1.0]
    assert len(slid) == 2 and all(abs(abs(s.v_pass_m_s) / float(speeds[2]) - 1) < 0.1 for s in slid)
