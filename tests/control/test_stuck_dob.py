"""Observer anti-wind-up against the friction feed-forward (``controller.stuck_dob_fraction``), in simulated time.

The HIL under load (docs/control.md §5): with the feedback slowed down (crossover/3) the stage stuck while the
reference moved on, and the observer's estimate stood at −0.8 N against 0.9 N of Coulomb feed-forward: the
command had lost the feed-forward and the stage stayed stuck until ``following_error``. Here, lock-step on the
seed stage (exact GMS model, one cycle of I/O delay, the shipped HIL gains at crossover/3): a 20 µm move, a
1.5 N knock for 5 ms at rest that slides the stage ~10 µm past its target (the observer then winds towards
pulling it back, as at the HIL's stick-slip overshoots), then a 100 µm move at 0.2 mm/s in the same direction.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from control_harness import controller_cfg, make_plant, seed_model  # noqa: E402

from stagectl.control.api import Reference  # noqa: E402
from stagectl.control.controller import StageController  # noqa: E402

T = 1e-3
V = 2e-4  # m/s
N1, NR, N2 = 100, 500, 500  # 20 µm move, rest, 100 µm move (cycles)
KNOCK = (N1 + 50, N1 + 55, 1.5)  # cycles [from, to) and force [N]


def _run(knock: bool, first: float = 1.0, scale: float = 3.0, **extra):
    """``first``: the first step's interval in T (the rest on time); ``scale``: the loop's slow-down level."""
    sm = seed_model()
    plant = make_plant(sm, io_delay_s=T)
    cfg = controller_cfg(pid={"kp_n_m": 9847.0, "ki_n_m_s": 1.237e5, "kd_n_s_m": 235.1, "derivative_cutoff_hz": 100.0},
                         dob={"kind": "qfilter", "bandwidth_hz": 100.0, "command_delay_samples": 1},
                         feedforward={"kind": "model", "inertia": True, "lookahead_s": 0.0015}, **extra)
    ctl = StageController(cfg, T, sm)
    plant.reset(0.0)
    ctl.reset(plant.measure())
    ctl.set_timing_scale(scale)  # the loop's slow-down level (crossover/3)
    seq = [V] * N1 + [0.0] * NR + [V] * N2 + [0.0] * 100
    xr = 0.0
    out = {k: np.empty(len(seq)) for k in ("x", "x_ref", "v", "u", "u_dob", "u_ff", "eps")}
    for k, vk in enumerate(seq):
        xr += vk * T
        cmd = ctl.step(first * T if k == 0 else T, plant.measure(), Reference(xr, vk, 0.0))
        f = cmd.force_n + (KNOCK[2] if knock and KNOCK[0] <= k < KNOCK[1] else 0.0)
        plant.step(f, T)
        out["x"][k], out["x_ref"][k], out["v"][k], out["u"][k] = plant.x_m, xr, plant.v_m_s, cmd.force_n
        out["u_dob"][k], out["u_ff"][k] = cmd.terms["u_dob"], cmd.terms["u_ff"]
        out["eps"][k] = ctl.stuck_excess_fraction()
    out["e"] = out["x_ref"] - out["x"]
    return out


@pytest.fixture(scope="module", params=[1.0, 1.001])
def runs(request):
    """The two runs, the first interval on time or 1.001 T: the observer's filter follows its period (s·T) whatever
    the intervals were (before, a slowed-down observer kept T's coefficients until an interval differed from the
    last one: with the first interval 1.001 T the reproduction stuck 96 cycles and the limit let the estimate reach
    −0.43 N)."""
    return (_run(True, request.param, stuck_dob_fraction=math.inf),
            _run(True, request.param, stuck_dob_fraction=0.2))


def test_the_observer_winds_up_against_the_feed_forward_while_the_stage_sticks(runs):
    """Reproduction (the limit off): the reference passes the stuck stage, and the estimate still cancels the
    whole feed-forward; the stage stays stuck for > 150 ms and falls 30 µm behind."""
    old, _ = runs
    mv = slice(N1 + NR, N1 + NR + N2)
    behind_stuck = (old["e"][mv] > 0.0) & (np.abs(old["v"][mv]) < 0.25 * V)
    assert behind_stuck.sum() > 150
    net = old["u_ff"][mv][behind_stuck] + old["u_dob"][mv][behind_stuck]
    assert np.min(net) < 0.1 * 0.897  # feed-forward 0.897 N, the estimate −0.93 N: measured net −0.03 N
    assert np.max(np.abs(old["e"][mv])) > 25e-6  # measured 31.5 µm


def test_the_limit_keeps_the_feed_forward_and_halves_the_stuck_time(runs):
    old, new = runs
    mv = slice(N1 + NR, N1 + NR + N2)

    def stuck(r):
        return (r["e"][mv] > 0.0) & (np.abs(r["v"][mv]) < 0.25 * V)

    s_old, s_new = stuck(old), stuck(new)
    assert s_new.sum() < 0.6 * s_old.sum()  # measured 26 against 193 cycles
    assert np.max(np.abs(new["e"][mv])) < 0.6 * np.max(np.abs(old["e"][mv]))  # measured 14.8 against 40.9 µm
    # by the last sample the stage stands stuck behind the moving reference, the estimate cancels at most the allowed
    # 20 % of the feed-forward (before: still 94 %). (The first move ends with v_ref stepping to 0: the friction
    # feed-forward's latch keeps its direction there, so the stop synchronisation treats the stage that the knock
    # slid past the target as ahead; the estimate then stands at −1.5 N at rest and is brought back over the stuck
    # samples, 26 of them here (measured −0.16 N at the last against 0.897 N; before that fix the latch reversed at
    # the stop, the model stood unloaded at 0.63 N and 30 ms after the reference passed the stage the estimate was
    # within the bound; 61 stuck samples, 16.0 µm)
    stuck_at = np.flatnonzero(s_new) + N1 + NR
    k = int(stuck_at[-1])
    # the bound is δ + ε, ε the model's excess seen while the stage followed: small with the exact model (the
    # first move's observer transient at crossover/3: 0.015)
    assert 0.0 <= new["eps"][k] < 0.05
    assert new["u_dob"][k] >= -(0.2 + new["eps"][k]) * new["u_ff"][k] - 0.03
    assert old["u_dob"][k] < -0.9 * old["u_ff"][k]
    # bumpless: the excess (1.27 N at the first stuck sample) is handed back at the observer's rate, no step in the
    # command beyond that rate's first step (1 − a)·excess, a = exp(−2π·f_DOB/s·T) (measured 0.24 N)
    k0 = int(stuck_at[0])
    excess = -(0.2 + new["eps"][k0]) * new["u_ff"][k0] - new["u_dob"][k0 - 1]
    du = np.abs(np.diff(new["u"][mv]))
    assert np.max(du) < (1.0 - math.exp(-2.0 * math.pi * 100.0 / 3.0 * T)) * excess + 0.02
    # the same up to the start of the move (the limit acts only while the reference moves)
    assert np.array_equal(new["u"][: N1 + NR], old["u"][: N1 + NR])


def test_without_stick_slip_nothing_changes():
    """The same motion without the knock: the limit never acts (bit-identical commands)."""
    a = _run(False, stuck_dob_fraction=math.inf)
    b = _run(False, stuck_dob_fraction=0.2)
    assert np.max(np.abs(a["e"][N1 + NR:])) > 5e-6  # a slowed-down feedback: the second move lags (12 µm)
    assert np.array_equal(a["u"], b["u"])


def _gap_case(delta: float, crawl: float, kind: str = "qfilter", slow: float = 1.0, gap_cycles: int = 20,
              eps: list[float] | None = None) -> float:
    """The stage follows 0.2 mm/s for 0.3 s (evidence: ε ≈ 0), the observer is wound 0.7 N against the 0.8 N
    Coulomb feed-forward, then one fresh sample after a 20 ms gap that the loop passes on capped at its dt limit
    (10 T), the stage having crawled ``crawl`` × the reference's travel in it. Returns d̂ after that step [N]."""
    cfg = controller_cfg(pid={"kp_n_m": 9847.0, "ki_n_m_s": 1.237e5, "kd_n_s_m": 235.1},
                         dob={"kind": kind, "bandwidth_hz": 100.0, "command_delay_samples": 1},
                         feedforward={"kind": "coulomb", "coulomb_n": 0.8, "inertia": True},
                         stuck_dob_fraction=delta)
    ctl = StageController(cfg, T)
    ctl.reset(0.0)
    ctl.set_timing_scale(slow)
    xr = 0.0
    for _ in range(300):
        xr += V * T
        ctl.step(T, xr - 1e-7, Reference(xr, V, 0.0))
    if eps is not None:
        eps.append(ctl.stuck_excess_fraction())
    ctl.dob.shift(-0.7 - ctl.state.d_hat_n)
    x = xr - 1e-7
    gap = gap_cycles * T
    return ctl.step(min(gap, 10 * T), x + crawl * V * gap, Reference(xr + V * gap, V, 0.0)).terms["u_dob"]


def test_the_stuck_test_is_not_blinded_by_the_dt_cap():
    """After a gap longer than the loop's dt cap the stage's speed Δx/dt came out too high (dt is capped, the
    travel is not): a stage crawling at 1/5 of the reference's speed looked like 2/5 and not stuck. The test
    now compares travels: the bound acts on it (the estimate moves towards −(δ + ε)·0.8 N)."""
    eps: list[float] = []
    off, on = _gap_case(math.inf, 0.2), _gap_case(0.2, 0.2, eps=eps)
    assert eps[0] < 0.05  # the stage followed with the exact friction level: no excess seen
    assert on > off + 0.1  # measured −0.16 against −0.67 N (before: the same −0.67 N, no action)
    # a stage that really follows (travel = the reference's) is not stuck: no action
    assert _gap_case(0.2, 1.0) == _gap_case(math.inf, 1.0)


@pytest.mark.parametrize("kind", ["qfilter", "kalman"])
def test_the_excess_goes_back_at_the_observers_own_rate_while_slowed(kind):
    """Slowed ×3, one stuck step: the estimate moves (1 − a) of the way to the bound, a = exp(−2π·f·T) with f the
    observer's bandwidth as it runs: /3 for the Q filter, which the loop slows down, unslowed for the Kalman
    form, which it does not (before: /3 for both, so a Kalman observer gave its excess back 2.5x slower)."""
    eps: list[float] = []
    off = _gap_case(math.inf, 0.0, kind, 3.0, 1)
    on = _gap_case(0.2, 0.0, kind, 3.0, 1, eps=eps)
    bound = -(0.2 + eps[0]) * 0.8
    f = 100.0 / 3.0 if kind == "qfilter" else 100.0
    assert (on - off) / (bound - off) == pytest.approx(1.0 - math.exp(-2.0 * math.pi * f * T), rel=1e-6)


@pytest.mark.parametrize("scale", [1.5, 2.0])
def test_the_limit_holds_at_other_slow_down_levels_whatever_the_first_interval(scale):
    """The same knock and move at the slow-down levels 1.5 and 2: the stage sticks less than at 3 (its feedback is
    faster), and the limit still cuts the stuck time by > 2x and the lag by > 40 % (measured at 1.5 / 2: 52 -> 6 and
    82 -> 9 cycles, 11.9 -> 3.8 and 18.8 -> 6.8 µm); a first interval of 1.001 T changes the runs by at most a
    cycle of stuck time and 0.5 µm (before: 50 -> 43 and 77 -> 60 cycles of the reproduction's stuck time)."""
    mv = slice(N1 + NR, N1 + NR + N2)

    def stuck(r):
        return int(((r["e"][mv] > 0.0) & (np.abs(r["v"][mv]) < 0.25 * V)).sum())

    def lag(r):
        return float(np.max(np.abs(r["e"][mv])))

    old = _run(True, 1.0, scale, stuck_dob_fraction=math.inf)
    new = _run(True, 1.0, scale, stuck_dob_fraction=0.2)
    old_p = _run(True, 1.001, scale, stuck_dob_fraction=math.inf)
    new_p = _run(True, 1.001, scale, stuck_dob_fraction=0.2)
    assert stuck(old) > 30
    assert stuck(new) < 0.5 * stuck(old)
    assert lag(new) < 0.6 * lag(old)
    for a, b in ((old, old_p), (new, new_p)):
        assert abs(stuck(a) - stuck(b)) <= 1
        assert abs(lag(a) - lag(b)) < 0.5e-6
