"""A position force (spring) and the I/O delay in the commissioning's friction and mass reads.

Oracle: a plain rigid mass ``m·ẍ = F(t) − F_c·tanh(ẋ/v_ε) − c·ẋ − k·x`` integrated with 20 sub-steps per loop
period, its force applied one loop period after it was computed (zero-order hold: 1.5 periods on average, as a
sync RPDO), driven by a PD + feed-forward loop along constant-velocity passes both ways over ±1 mm
(the commissioning's ``friction_cv`` and ``slow_passes`` shapes). Read at ``u(t)``, the spring's force enters the
passes as ``k·(x + v·τ)``: an apparent viscous ``k·τ`` (analysis.cv_segments); over the passes' ramps ``k·x``
correlates with ``−m·a`` and lowers the inverse-dynamics mass (fit.slow_pass_slope).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from stagectl.commission import analysis as an
from stagectl.commission import fit
from stagectl.ident.identify import measure
from stagectl.recorder import Recorder

T = 1e-3
M, FC, C, K = 1.0, 0.5, 10.0, 500.0
COLS = ("t", "x", "u", "x_ref", "v_ref", "a_ref", "v")


def _profile(v: float, length: float, a: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x_ref, v_ref, a_ref of one move by ``length`` at ``v`` (trapezoidal speed, acceleration ``a``)."""
    ta = v / a
    tc = (abs(length) - v * ta) / v
    s = math.copysign(1.0, length)
    n = int(round((2 * ta + tc) / T)) + 1
    tt = np.arange(n) * T
    acc = np.where(tt < ta, a, np.where(tt < ta + tc, 0.0, np.where(tt < 2 * ta + tc, -a, 0.0)))
    vel = np.cumsum(acc) * T
    vel = np.where(tt < ta, a * tt, np.where(tt < ta + tc, v, np.maximum(v - a * (tt - ta - tc), 0.0)))
    acc = np.where(np.abs(np.diff(np.concatenate([vel, [0.0]]))) < 1e-15, 0.0, acc)
    pos = np.concatenate([[0.0], np.cumsum(0.5 * (vel[1:] + vel[:-1])) * T])
    return s * pos, s * vel, s * acc


def _run(speeds: list[float], half: float = 1e-3, spring: float = K,
         cog: tuple[float, float, float] = (0.0, 1.0, 0.0)) -> Recorder:
    """Passes from −half to +half and back at each speed (0.1 s dwells), the recording the loop would keep;
    ``cog``: a cogging ``A·sin(2πx/λ + φ)`` as ``(A [N], λ [m], φ)``."""
    xr, vr, ar = [np.full(100, -half)], [np.zeros(100)], [np.zeros(100)]
    for v in speeds:
        a = min(0.5, v * v / (0.1 * half))
        for s in (+1, -1):
            p, vv, aa = _profile(v, 2 * s * half, a)
            xr += [xr[-1][-1] + p, np.full(100, xr[-1][-1] + p[-1])]
            vr += [vv, np.zeros(100)]
            ar += [aa, np.zeros(100)]
    x_ref, v_ref, a_ref = (np.concatenate(c) for c in (xr, vr, ar))
    kp, kd = M * (2 * math.pi * 30) ** 2, 2 * 0.7 * M * 2 * math.pi * 30
    rec = Recorder(COLS, capacity=x_ref.shape[0] + 1)
    x, v, pending = float(x_ref[0]), 0.0, 0.0
    x_prev = x
    h = T / 20
    for i in range(x_ref.shape[0]):
        xm = x
        u = (kp * (x_ref[i] - xm) + kd * (v_ref[i] - (xm - x_prev) / T) + M * a_ref[i]
             + FC * math.tanh(v_ref[i] / 1e-4) + C * v_ref[i] + spring * x_ref[i])
        rec.append((i * T, xm, u, float(x_ref[i]), float(v_ref[i]), float(a_ref[i]), (xm - x_prev) / T))
        x_prev = xm
        f, pending = pending, u  # applied over the next period: one period of delay, then the hold
        for _ in range(20):
            acc = (f - FC * math.tanh(v / 1e-5) - C * v - spring * x
                   - cog[0] * math.sin(2 * math.pi * x / cog[1] + cog[2])) / M
            v += h * acc
            x += h * v
    return rec


@pytest.fixture(scope="module")
def passes() -> tuple[Recorder, list[float]]:
    speeds = [1e-3, 4e-3, 16e-3]
    return _run(speeds), speeds


def _viscous(rec: Recorder, speeds: list[float], delay_s: float) -> float:
    """The passes' viscous coefficient with the spring's force ``K·x`` taken off (as the slow passes give it)."""
    x = np.asarray(rec.col("x"), np.float64)
    segs = an.cv_segments(rec.col("t"), x, rec.col("u"), rec.col("v_ref"), rec.col("a_ref"), M,
                          speeds=np.array(speeds), delay_s=delay_s, position_force_n=K * x)
    return an.cv_friction(segs).viscous_n_s_m


def test_the_passes_read_the_force_where_it_acts(passes: tuple[Recorder, list[float]]) -> None:
    """Aligned by the delay (1.5 periods), the viscous coefficient is the plant's; read at u(t), even with the
    spring's force taken off at x(t), a spring of 500 N/m adds k·τ = 0.75 N s/m (7.5 %)."""
    rec, speeds = passes
    assert _viscous(rec, speeds, 1.5 * T) == pytest.approx(C, rel=0.01)
    assert _viscous(rec, speeds, 0.0) - C == pytest.approx(K * 1.5 * T, rel=0.1)


def test_the_inverse_dynamics_mass_takes_the_spring_off(passes: tuple[Recorder, list[float]]) -> None:
    """The slow passes' slope is the spring's, and with it taken off the passes' force the inverse-dynamics
    mass is the plant's (with it left in, k·x reads as −m·a over the ramps)."""
    rec, _ = passes
    slow = _run([0.2e-3])
    k = fit.slow_pass_slope(slow, M, T)
    assert k == pytest.approx(K, rel=0.03)
    cv = fit.to_recording(rec, "friction_cv")
    m_left = measure(cv).mass_kg
    cv.u = cv.u - k * (cv.x - float(np.mean(cv.x)))
    m_off = measure(cv).mass_kg
    assert m_off == pytest.approx(M, rel=0.05)
    assert m_left is None or abs(m_left - M) > 2 * abs(m_off - M)


def test_the_passes_take_the_position_force_off() -> None:
    """A cogging longer than the slowest pass (0.3 N, 1.3 mm; 0.4 mm at 0.2 mm/s) does not average out over
    it: its mean enters both directions' means. Given the cogging force (the slow passes'), every pass's
    mean is the sliding friction alone."""
    A, lam, ph = 0.3, 1.3e-3, 0.7
    speeds = [0.2e-3, 1e-3]
    rec = _run(speeds, half=0.2e-3, spring=0.0, cog=(A, lam, ph))
    x = np.asarray(rec.col("x"), np.float64)
    args = (rec.col("t"), x, rec.col("u"), rec.col("v_ref"), rec.col("a_ref"), M)
    pf = A * np.sin(2 * np.pi * x / lam + ph)
    for seg in an.cv_segments(*args, speeds=np.array(speeds), delay_s=1.5 * T, position_force_n=pf):
        assert seg.f_n == pytest.approx(math.copysign(FC, seg.v_m_s) + C * seg.v_m_s, abs=3e-3)
    even = [abs(sg.f_n - math.copysign(FC, sg.v_m_s) - C * sg.v_m_s)
            for sg in an.cv_segments(*args, speeds=np.array(speeds), delay_s=1.5 * T)]
    assert max(even) > 0.05                      # left in, the cogging's mean over the pass


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_no_stribeck_drop_beyond_the_fastest_pass(seed: int) -> None:
    """Four pairs on a straight line ``Fc + Fv·v`` (k111's passes with the spring off and the stick-slip pairs
    left out: 1-16 mm/s, 0.3 mN of scatter): a Stribeck curve through them could only drop beyond the fastest
    pass or fits the four pairs exactly and bent the line (main: Coulomb −2 %, viscous +10 % on seed 0's scatter,
    +4 % on seed 2's with vs 12 mm/s); the line's flat curve is
    used instead (analysis.cv_friction)."""
    rng = np.random.default_rng(seed)
    fc, fv, off = 1.63, 9.26, 0.066
    segs = [an.CvSegment(s * v, s * (fc + fv * v) + off + 3e-4 * float(rng.standard_normal()), 1e-4, 200)
            for v in (1.01e-3, 2.54e-3, 6.37e-3, 15.9e-3) for s in (1, -1)]
    cv = an.cv_friction(segs)
    assert cv.coulomb_n == pytest.approx(fc, rel=0.005)
    assert cv.viscous_n_s_m == pytest.approx(fv, rel=0.03)
    assert cv.stribeck is not None and cv.stribeck["vs_m_s"] <= 15.9e-3


def test_a_pass_window_between_equal_cogging_levels_does_not_read_a_delay_error_as_viscous() -> None:
    """Passes of 1 mm under a 0.4 N, 1.35 mm cogging (fresh plant k106's), its force taken off: read with a
    delay 0.35–0.5 ms off the true 1.5 periods, the controller's force, which follows the cogging, enters each
    window's mean as ``dτ·(u_end − u_start)/T_window`` and the viscous reads ±4–6 %; with each window centred on
    a cogging extremum (analysis.cv_segments ``cogging``) its ends sit at one level and it stays within 0.5 %."""
    A, lam, ph = 0.4, 1.35e-3, -2.5
    speeds = [1e-3, 4e-3, 16e-3]
    rec = _run(speeds, half=0.5e-3, spring=0.0, cog=(A, lam, ph))
    x = np.asarray(rec.col("x"), np.float64)
    pos = A * np.sin(2 * math.pi * x / lam + ph)

    def viscous(delay_s: float, cogging: tuple[float, float] | None) -> float:
        segs = an.cv_segments(rec.col("t"), x, rec.col("u"), rec.col("v_ref"), rec.col("a_ref"), M,
                              speeds=np.array(speeds), delay_s=delay_s, position_force_n=pos, cogging=cogging)
        return an.cv_friction(segs).viscous_n_s_m

    for d in (1.0e-3, 1.85e-3, 2.0e-3):
        assert abs(viscous(d, None) / C - 1) > 0.03
        assert viscous(d, (lam, ph)) == pytest.approx(C, rel=0.005)
    assert viscous(1.5 * T, None) == pytest.approx(C, rel=0.005)  # aligned, either window
