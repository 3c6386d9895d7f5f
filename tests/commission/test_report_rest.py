"""report.md names the rest spring stage.yaml carries, with its confidence and its stuck-stage rest loop's margins
(the audit found it only in report.json), or that it is not used."""

from __future__ import annotations

from typing import Any

from stagectl.commission.outputs import report_markdown


def _rep(rest: dict[str, Any]) -> dict[str, Any]:
    chosen = {"crossover_target_hz": 22.0, "dob_kind": "qfilter", "dob_bandwidth_hz": 110.0,
              "pid": {"kp_n_m": 1.2e4, "ki_n_m_s": 1.6e5, "kd_n_s_m": 250.0},
              "model": {"phase_margin_deg": 40.4, "gain_margin_db": 8.5, "crossover_hz": 50.9}, "rest": rest}
    return {"status": "complete", "config": "x.yaml", "experiments": [], "gains": {"chosen": chosen},
            "envelope": {"x_lo_m": -0.002, "x_hi_m": 0.002, "f_max_n": 10.0, "v_max_m_s": 0.02}}


def test_the_report_names_the_advised_rest_spring_and_its_thin_margins() -> None:
    md = report_markdown(_rep({
        "enabled": True, "rest_stiffness_fraction": 0.5, "rest_spring_n_m": 3.19e5, "stiffness_n_m": 6.38e5,
        "confidence": "medium", "reason": "on the twin: settled moves 6 (without: 5)",
        "relies_on": "the stage being stuck in pre-sliding at standstill",
        "loops": {"rest/stuck": {"phase_margin_deg": 28.2, "gain_margin_db": 5.7, "healthy": False}}}), [])
    assert "Rest spring: on in stage.yaml (`rest_stiffness_fraction` 0.5, 3.19e+05 N/m" in md
    assert "confidence medium: on the twin: settled moves 6 (without: 5)" in md
    assert "phase margin 28.2 deg, gain margin 5.7 dB (below the 40 deg / 8 dB floor)" in md
    assert "It relies on the stage being stuck" in md


def test_the_report_says_when_no_rest_spring_is_used() -> None:
    md = report_markdown(_rep({"enabled": False, "reason": "its rest loop is unstable on the stuck stage"}), [])
    assert "Rest spring: not used (its rest loop is unstable on the stuck stage)." in md


def test_the_report_names_the_chosen_rest_gains_or_that_none_meets_the_floor() -> None:
    base = {"enabled": True, "rest_stiffness_fraction": 0.5, "rest_spring_n_m": 3.19e5, "stiffness_n_m": 6.38e5,
            "confidence": "medium", "reason": "on the twin: settled moves 6 (without: 5)",
            "rest_kd_fraction": 0.1, "rest_dob_bandwidth_fraction": 0.45, "rest_spring_section_count": 2,
            "loops": {"rest/stuck": {"phase_margin_deg": 89.5, "gain_margin_db": 10.1, "healthy": True}}}
    md = report_markdown(_rep({**base, "rest_gains": {"grid_points": 24, "meeting_floor": 10, "chosen": "grid"}}), [])
    assert "phase margin 89.5 deg, gain margin 10.1 dB." in md
    assert ("Its rest gains (`rest_kd_fraction` 0.1, `rest_dob_bandwidth_fraction` 0.45, `rest_spring_section_count`"
            " 2): of 24 grid points, 10 meet the floor on the stuck stage; of those tried on the twins") in md
    md = report_markdown(_rep({**base, "rest_gains": {
        "grid_points": 24, "meeting_floor": 0, "chosen": "default: no grid point meets the floor",
        "best_stuck": {"phase_margin_deg": 35.0, "gain_margin_db": 6.0}}}), [])
    assert "None of the 24 rest-gain grid points meets the floor on the stuck stage (best: phase margin 35.0 deg" in md
    md = report_markdown(_rep({**base, "rest_kd_fraction": 1.0, "rest_dob_bandwidth_fraction": 1.0,
                               "rest_spring_section_count": 1, "rest_gains": {
        "grid_points": 24, "meeting_floor": 10, "chosen": "default: the grid points that meet the floor failed on the twin",
        "twin_trials": [{"rest_kd_fraction": 0.5, "rest_dob_bandwidth_fraction": 0.45, "rest_spring_section_count": 2,
                         "phase_margin_deg": 47.4, "gain_margin_db": 8.6,
                         "twin": "on the twin: settled moves 6 (without: 5); cosine (matched twin) RMS more than 1.25x"}]}}), [])
    assert "Of 24 rest-gain grid points 10 meet the floor on the stuck stage, but those tried failed on the twin" in md
    assert ("Tried on the twins: `rest_kd_fraction` 0.5, `rest_dob_bandwidth_fraction` 0.45, `rest_spring_section_count` 2 (phase"
            " margin 47.4 deg, gain margin 8.6 dB): on the twin: settled moves 6 (without: 5); cosine (matched twin)") in md
