"""The rest additions the twins advise are checked on the stage itself (``Commissioning._rest_on_stage``): the
twins are built from the identified model and cannot see where it is wrong (seed k111: its twins advised the rest
integral and the sync, and on the stage the cosine went from 0.73 to 3.15 µm RMS). One run each with and without
them (steps and cosine, each after a friction-memory wipe, as the verification runs them); they stay only if more
steps settle and the cosine is not worse beyond the run-to-run scatter, and stage.yaml is written accordingly.

Lock-step (simulated time) on config/sim.yaml's seed stage, its controller without the rest spring and the settle
move: with cogging and an offset the model does not have, steps stop 100-200 nm off and the rest integral brings
them in (kept); on a stage whose pre-sliding stiffness is 0.3 of the model's no more steps settle with it than
without (dropped). On main (no check on the stage) stage.yaml kept whatever the twins advised."""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path
from typing import Any

import pytest


def _ab(cfg: Any, base: Any) -> tuple[dict[str, Any], list[bool], dict[str, Any], list[str]]:
    from stagectl.app import build_stage, make_controller
    from stagectl.clock import SimClock
    from stagectl.commission import sequence as sq
    from stagectl.commission.controllers import CommissionController

    with_cfg = dataclasses.replace(cfg, controller=dataclasses.replace(base, rest_integral_hz=3.0))
    without_cfg = dataclasses.replace(cfg, controller=base)
    written: list[bool] = []

    def write_config(res: Any) -> Any:  # what stage.yaml would hold: the chosen entry's rest integral on or off
        on = bool(res.gains["chosen"]["rest_integral"]["enabled"])
        written.append(on)
        return with_cfg if on else without_cfg

    with tempfile.TemporaryDirectory() as d:
        com = sq.Commissioning(cfg, Path(d), sq.Options(plots=False, verify=False), write_config)
        com.res.gains = {"chosen": {"rest": {"enabled": False}, "rest_integral": {"enabled": True, **sq.REST_INTEGRAL,
                                                                                  "reason": "on the twin"}}}
        with build_stage(cfg, clock=SimClock(), controller=CommissionController(make_controller(cfg))) as st:
            final = com._rest_on_stage(st, with_cfg, com.env.x_c_m)
        names = [e.name for e in com.res.experiments]
        planned = [n for n, _ in com._planned]
    assert final is (with_cfg if written[-1] else without_cfg)
    # every run is in the progress plan ("[i/n] name", time left): none counted past its end
    assert set(names) <= set(planned), (names, planned)
    return com.res.gains["rest_on_stage"], written, com.res.gains["chosen"], names


@pytest.fixture(scope="module")
def stage(repo_root):
    from stagectl.config import load_app_config

    cfg = load_app_config(repo_root / "config" / "sim.yaml")
    c = cfg.controller
    base = dataclasses.replace(c, rest_stiffness_fraction=0.0, rest_kd_fraction=1.0, rest_dob_bandwidth_fraction=1.0,
                               rest_spring_section_count=1,
                               settle=dataclasses.replace(c.settle, move_s=0.0, ahead_stiffness_fraction=0.0))
    return cfg, base


def test_kept_where_on_the_stage_more_steps_settle(stage):
    from stagectl.friction.effects import Cogging, Effects, Offset

    cfg, base = stage
    eff = Effects(cogging=Cogging(amplitude_n=0.1, wavelength_m=1e-3, phase_rad=0.3), offset=Offset(force_n=0.05))
    cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, plant=dataclasses.replace(cfg.sim.plant,
                                                                                              effects=eff)))
    out, written, chosen, names = _ab(cfg, base)
    f = out["figures"]
    assert names == [f"{k}_rest_{w}_{n}" for n in ("steps", "cosine") for w in ("with", "without")
                     for k in ("wipe", "verify")]
    assert f["cosine"]["with"]["rms_error_m"] <= (1 + 2 ** 0.5 * out["scatter"]) * f["cosine"]["without"]["rms_error_m"]
    assert f["steps"]["with"]["moves_settled"] > f["steps"]["without"]["moves_settled"], out
    assert out["keep"] and out["confidence"] in ("high", "medium") and out["decision"].startswith("kept")
    assert written == [False, True] and chosen["rest_integral"]["enabled"]


def test_undecided_pairs_run_again_with_the_order_swapped(stage):
    """A stage whose pre-sliding stiffness is 0.3 of the model's (a model far from the plant, as seed k111's): with
    the integral the same steps settle as without (3/4 on both), a tie with moves left to settle, which one pair
    cannot decide: a second and a third pair run, each with the arms in the other order, the steps only (no
    pooled gain, so no cosine), and the pooled result drops it with low confidence. On the sequence before this
    change one pair ran and the drop was reported with medium confidence."""
    from stagectl.commission.sequence import REST_STAGE_MAX_PAIRS
    from stagectl.friction.gms import GmsFriction

    cfg, base = stage
    q = cfg.sim.plant.friction.params
    soft = GmsFriction(dataclasses.replace(q, k_n_m=tuple(0.3 * k for k in q.k_n_m)))
    cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, plant=dataclasses.replace(cfg.sim.plant,
                                                                                              friction=soft)))
    out, written, chosen, names = _ab(cfg, base)
    pf = out["pair_figures"]
    assert "cosine" not in out["figures"]  # the steps decide there is no gain: no cosine runs
    assert all(f["steps"]["with"]["moves_settled"] == f["steps"]["without"]["moves_settled"] < 4 for f in pf), pf
    assert out["pairs"] == len(pf) == REST_STAGE_MAX_PAIRS
    assert names == [f"{k}_rest{p}_{w}_steps" for p, ws in (("", ("with", "without")), ("_p2", ("without", "with")),
                                                            ("_p3", ("with", "without"))) for w in ws
                     for k in ("wipe", "verify")]
    assert not out["keep"] and "no more steps settle" in out["decision"] and "over 3 pairs" in out["decision"]
    assert not out["decided"] and "tied" in out["undecided"] and out["confidence"] == "low"
    assert 20.0 < out["stage_s"] < 30.0  # three pairs of steps runs (wipe + steps: ~7.8 s a pair)
    # stage.yaml stays without it, and the report says why
    assert written == [False] and not chosen["rest_integral"]["enabled"]
    assert "on the stage" in chosen["rest_integral"]["reason"]


def _figs(n_w: int, n_o: int, c_ratio: float | None, c_o: float = 4e-9) -> dict[str, dict[str, dict[str, float]]]:
    f: dict[str, dict[str, dict[str, float]]] = {
        "steps": {"with": {"moves": 4, "moves_settled": n_w, "rms_error_m": 1e-7, "max_error_m": 1e-6},
                  "without": {"moves": 4, "moves_settled": n_o, "rms_error_m": 1e-7, "max_error_m": 1e-6}}}
    if c_ratio is not None:
        f["cosine"] = {"with": {"rms_error_m": c_o * c_ratio, "max_error_m": 1e-8, "moves": 1, "moves_settled": 1},
                       "without": {"rms_error_m": c_o, "max_error_m": 1e-8, "moves": 1, "moves_settled": 1}}
    return f


def test_one_pair_decides_only_far_outside_the_noise_band():
    """One pair, the assumed scatter (8 %: the ratio's σ = √2·8 % = 11.3 %). Decided at once (high): two moves more
    settle and the cosine no worse (kept), or worse by more than 4σ = 45 % (dropped); fewer steps settle by two or
    more, or every move settles without (dropped). Undecided (another pair; low if it were the last): one move
    apart, a tie with moves left, or a cosine cost within (0, 4σ] (still kept or dropped by the 2σ limit)."""
    from stagectl.commission.sequence import rest_stage_decision

    cases = {(4, 2, 0.95): (True, True), (4, 2, 1.5): (False, True), (1, 4, None): (False, True),
             (4, 4, None): (False, True), (4, 2, 1.2): (True, False), (4, 2, 1.3): (False, False),
             (3, 2, 0.95): (True, False), (2, 2, None): (False, False), (2, 3, None): (False, False)}
    for args, (keep, decided) in cases.items():
        d = rest_stage_decision([_figs(*args)])
        assert (d["keep"], d["decided"], d["confidence"], d["pairs"]) == (keep, decided, "high" if decided else "low",
                                                                          1), (args, d)
        assert (d["undecided"] is None) == decided
    assert "cosine is worse" in rest_stage_decision([_figs(4, 2, 1.5)])["decision"]
    assert rest_stage_decision(_figs(4, 2, 0.95))["keep"]  # a single pair's dict is one pair


def test_the_pooled_decision_uses_the_scatter_measured_from_the_repeats():
    """Over pairs the settled moves add up and the cosine ratio is that of the arms' means, with σ = √2·s/√k, s the
    scatter of ln(RMS) within each arm (checked against numpy's), floored at 8 %. A tie then a two-move gain decides
    (kept, medium: after more than one pair); a scatter measured above 8 % widens the limit."""
    import math

    import numpy as np

    from stagectl.commission.sequence import rest_stage_decision, rest_stage_scatter

    d = rest_stage_decision([_figs(2, 2, None), _figs(4, 2, 0.9)])
    assert (d["keep"], d["decided"], d["confidence"], d["pairs"]) == (True, True, "medium", 2), d
    assert "6/8 with, 4/8 without over 2 pairs" in d["decision"] and d["scatter_measured"] is None
    # three pairs: the cosine with them 4, 5.2, 6.4 nm, without 4, 5, 3 nm
    pairs = [_figs(4, 2, w / o, o * 1e-9) for w, o in ((4.0, 4.0), (5.2, 5.0), (6.4, 3.0))]
    lw, lo = np.log([4.0, 5.2, 6.4]), np.log([4.0, 5.0, 3.0])
    s = math.sqrt((np.var(lw, ddof=1) + np.var(lo, ddof=1)) / 2)
    assert rest_stage_scatter(pairs) == pytest.approx(s, rel=1e-9) and s > 0.08
    d = rest_stage_decision(pairs)
    rho = (4.0 + 5.2 + 6.4) / (4.0 + 5.0 + 3.0)
    assert d["scatter_used"] == pytest.approx(s) and d["cosine_z"] == pytest.approx((rho - 1) / (s * math.sqrt(2 / 3)))
    # 1.30 is 2.6σ at the assumed 8 % (dropped), within 2σ at the measured scatter (kept); undecided either way
    assert d["keep"] and not d["decided"] and d["confidence"] == "low"
    assert not rest_stage_decision([_figs(4, 2, 1.3)] * 3)["keep"]  # (identical repeats: s floored at 8 %)


@pytest.mark.parametrize("name", ["wipe_rest_with_steps", "verify_rest_with_steps", "verify_rest_without_cosine",
                                  "verify_after_steps"])
def test_a_fault_of_the_commissioned_controller_in_its_rest_check_keeps_the_given_one(repo_root, tmp_path, name):
    """A fault in the rest additions' check on the stage is a fault of the commissioned controller (with or without
    them; stage.yaml then holds it without them), as one in its verification is: report.json recommends the given
    controller and says why, instead of 'not verified'."""
    from stagectl.commission import sequence as sq
    from stagectl.commission.outputs import report_dict
    from stagectl.config import load_app_config

    cfg = load_app_config(repo_root / "config" / "sim.yaml")
    com = sq.Commissioning(cfg, tmp_path, sq.Options(plots=False), lambda res: cfg)
    com.res.aborted = sq.CommissionAborted(name, "fault following_error: 5.1e-05 m")
    v = report_dict(com.res)["verdict"]
    assert v["recommend"] == "given" and name in v["text"] and "faulted" in v["text"]


def test_a_zero_cosine_figure_is_decided_without_a_division_by_zero():
    """A cosine run at zero RMS (no error above the sensor's quantum): without the rest additions and with them,
    ρ = 1 (no cost: kept on the steps' gain); without them only, an infinite cost (dropped, decided, no z); with
    them only, ρ = 0 (kept). No ZeroDivisionError, no nan in the result."""
    import json

    from stagectl.commission.sequence import rest_stage_decision

    both = rest_stage_decision([_figs(4, 2, 0.0, c_o=0.0)])
    assert both["keep"] and both["decided"] and both["cosine_z"] == 0.0
    worse = _figs(4, 2, 1.0, c_o=0.0)
    worse["cosine"]["with"]["rms_error_m"] = 3e-9
    d = rest_stage_decision([worse])
    assert not d["keep"] and d["decided"] and d["cosine_z"] is None and "cosine is worse" in d["decision"]
    better = rest_stage_decision([_figs(4, 2, 0.0)])
    assert better["keep"] and better["decided"] and better["cosine_z"] < 0.0
    for r in (both, d, better):
        json.dumps(r, allow_nan=False)


def _hunt_figs(n_w: int, n_o: int, r_w: float, r_o: float, c_ratio: float | None = None) -> dict[str, Any]:
    f = _figs(n_w, n_o, c_ratio)
    f["steps"]["with"].update(rms_error_m=r_w, max_error_m=3 * r_w)
    f["steps"]["without"].update(rms_error_m=r_o, max_error_m=3 * r_o)
    return f


def test_a_hunting_arm_loses_the_steps_whatever_it_settles():
    """The settled count is judged at the end of a 0.25 s dwell (±10 nm): a stage that hunts can end a dwell inside
    it. Generated plant 71 (tests/commission/eval_hidden_plants.py T 71): without the rest integral its 10 um steps
    overshot by up to 16 um and crept back (5.46 um RMS, 2/8 settled over two pairs), with it they stopped 0.1-0.8
    um off (0.30 um RMS, 0/8); main dropped the integral ("no more steps settle") and stage.yaml hunted, 22.6x the
    exact model's steps RMS. Where the steps' RMS lie more than REST_STAGE_STEPS_RMS_CLEAR apart the error decides
    (then the cosine runs and is judged as before); within it the settled count decides as before."""
    from stagectl.commission.sequence import REST_STAGE_STEPS_RMS_CLEAR, _steps_favour, rest_stage_decision

    p71 = [_hunt_figs(0, 1, 3.02e-7, 5.46e-6), _hunt_figs(0, 1, 3.03e-7, 5.46e-6)]
    assert _steps_favour(p71)  # (so the cosine runs)
    d = rest_stage_decision([_hunt_figs(0, 1, 3.02e-7, 5.46e-6, 0.9), _hunt_figs(0, 1, 3.03e-7, 5.46e-6, 0.9)])
    assert d["keep"] and d["decided"] and "the error decides" in d["decision"], d
    assert d["steps_rms_m"]["without"] == pytest.approx(5.46e-6)
    # ... and a clear cosine cost still drops it
    assert not rest_stage_decision([_hunt_figs(0, 1, 3e-7, 5.46e-6, 1.6)])["keep"]
    # the other way round: the additions make the steps hunt though one more settles with them
    d = rest_stage_decision([_hunt_figs(3, 2, 5.46e-6, 3e-7)])
    assert not d["keep"] and d["decided"] and "error is larger with them" in d["decision"], d
    # a fault (infinite RMS) without them is the larger error
    assert rest_stage_decision([_hunt_figs(0, 2, 3e-7, float("inf"), 1.0)])["keep"]
    # within the factor the settled moves decide, as before
    r = 0.9 * REST_STAGE_STEPS_RMS_CLEAR
    assert not rest_stage_decision([_hunt_figs(0, 2, 1e-7, r * 1e-7)])["keep"]
    assert rest_stage_decision([_hunt_figs(4, 2, r * 1e-7, 1e-7, 1.0)])["keep"]


def test_a_stage_far_worse_than_its_twin_is_said_so():
    """stage.yaml's arm of the rest check more than REST_STAGE_STEPS_RMS_CLEAR x its twin's steps RMS gets a note
    with both figures (plant 71 on main: 5.46 um on the stage, 98.6 nm predicted); within it, none."""
    from stagectl.commission.sequence import chosen_twin_steps, steps_twin_gap

    p71 = [_hunt_figs(0, 1, 3.02e-7, 5.46e-6), _hunt_figs(0, 1, 3.03e-7, 5.46e-6)]
    gap = steps_twin_gap(p71, "without", {"rms_error_m": 9.86e-8, "moves": 4, "moves_settled": 2})
    assert gap is not None and gap["settled"] == "2/8" and gap["stage_rms_m"] == pytest.approx(5.46e-6)
    assert "5.46 um RMS" in gap["note"] and "98.6 nm its twin predicted" in gap["note"], gap["note"]
    assert steps_twin_gap(p71, "with", {"rms_error_m": 1.47e-7}) is None
    assert steps_twin_gap(p71, "without", None) is None
    # the twin figure is the one of what stage.yaml holds: the enabled addition's own twin run, else the design's
    design, ri = {"rms_error_m": 9.86e-8}, {"rms_error_m": 1.47e-7}
    chosen = {"twin": {"steps": design}, "rest": {"enabled": False},
              "rest_integral": {"enabled": True, "twin": {"steps": ri}}}
    assert chosen_twin_steps(chosen) is ri
    assert chosen_twin_steps({**chosen, "rest_integral": {"enabled": False, "twin": {"steps": ri}}}) is design
