"""Constant sliding speeds the chosen loop cannot hold (stagectl.commission.sliding): a steep Stribeck drop is a
negative damping; below the loop's negative-damping limit sliding limit-cycles."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

from stagectl.commission.analysis import stribeck_curve_at
from stagectl.commission.sequence import sliding_check
from stagectl.commission.sliding import _closed_loop_poles, net_slope, sliding_line, unstable_sliding
from stagectl.control.pid import PidConfig

ROOT = Path(__file__).resolve().parents[2]
T = 1e-3
#: the gains commissioning chose for the steep stage (19 Hz PID, Q-filter 95 Hz, 1 kg, one cycle of delay)
PID = PidConfig(kp_n_m=4442.154, ki_n_m_s=53030.67, kd_n_s_m=111.63, derivative_cutoff_hz=95.0)
STEEP = {"fs_n": 3.2, "fc_n": 2.5, "vs_m_s": 2e-3, "delta": 2.0, "viscous_n_s_m": 40.0}


def test_net_slope_is_the_curves_derivative() -> None:
    # oracle: central differences of the curve the fit reports
    v = np.logspace(-5, -1, 40)
    h = 1e-4 * v
    fd = (stribeck_curve_at(STEEP, v + h) - stribeck_curve_at(STEEP, v - h)) / (2 * h)
    assert np.allclose(net_slope(STEEP, v), fd, rtol=1e-5, atol=1e-6)


def test_steep_drop_flags_the_band_the_exact_model_limit_cycles_in() -> None:
    s = unstable_sliding(STEEP, 1.0, T, PID, 1, "qfilter", 95.0)
    assert s is not None
    assert math.isclose(s["worst_net_slope_n_s_m"], -260.0, abs_tol=3.0)
    assert math.isclose(s["worst_speed_m_s"], 1.41e-3, rel_tol=0.05)
    # the loop's own limit: stable just above it, unstable just below
    lim = s["damping_limit_n_s_m"]
    assert -230.0 < lim < -170.0
    assert np.all(np.abs(_closed_loop_poles(1.0, T, PID, 1, "qfilter", 95.0, lim + 2.0)) < 1.0)
    assert np.any(np.abs(_closed_loop_poles(1.0, T, PID, 1, "qfilter", 95.0, lim - 2.0)) >= 1.0)
    assert len(s["bands_m_s"]) == 1
    lo, hi = s["bands_m_s"][0]
    # the exact model limit-cycles at 1.0-1.8 mm/s; the linearised band contains that and is not much wider
    assert 0.75e-3 < lo <= 1.0e-3 and 1.8e-3 <= hi < 2.3e-3
    # every flagged speed has a net slope below the limit, every speed outside the band one above it
    v = np.array([lo, hi])
    assert np.all(net_slope(STEEP, v) < lim + 10.0)
    assert np.all(net_slope(STEEP, np.array([0.9 * lo, 1.1 * hi])) > lim - 10.0)
    assert 25.0 < s["limit_cycle_hz"] < 50.0  # the exact model's cycle: ~40 Hz
    line = sliding_line(s)
    assert line is not None and "limit-cycle" in line and f"{1e3 * lo:.2g}" in line and f"{1e3 * hi:.2g}" in line


def test_sequence_wrapper_reads_the_chosen_design() -> None:
    pid = {"kp_n_m": PID.kp_n_m, "ki_n_m_s": PID.ki_n_m_s, "kd_n_s_m": PID.kd_n_s_m, "derivative_cutoff_hz": 95.0}
    gains = {"mass_kg": 1.0, "delay_samples": 1, "chosen": {"pid": pid, "dob_kind": "qfilter", "dob_bandwidth_hz": 95.0}}
    s = sliding_check(gains, STEEP, T)
    assert s is not None and s["bands_m_s"]
    assert sliding_check(gains, None, T) is None


def test_gentle_or_no_drop_flags_nothing() -> None:
    fr = yaml.safe_load((ROOT / "config/models/kamenar2016_gms.yaml").read_text())["friction"]
    sim = {k: float(fr[k]) for k in ("fs_n", "fc_n", "vs_m_s", "delta", "viscous_n_s_m")}
    s = unstable_sliding(sim, 1.0, T, PID, 1, "qfilter", 95.0)
    assert s is not None and s["bands_m_s"] == [] and sliding_line(s) is None
    assert s["worst_net_slope_n_s_m"] < 0.0  # negative, but well inside what the loop holds
    flat = {**STEEP, "fs_n": STEEP["fc_n"]}
    s = unstable_sliding(flat, 1.0, T, PID, 1, "qfilter", 95.0)
    assert s is not None and s["bands_m_s"] == [] and s["worst_net_slope_n_s_m"] >= 40.0 - 1e-9


def _const_speed_rms(cfg_path: Path, v: float) -> float:
    from stagectl.app import build_stage
    from stagectl.clock import SimClock
    from stagectl.commission.sequence import verification_lead
    from stagectl.config import load_app_config
    from stagectl.control.trajectory import Scenario, Triangle
    from stagectl.recorder import Recorder

    cfg = load_app_config(cfg_path)
    seg = Triangle(span_m=1e-3, velocity_m_s=v, max_acceleration_m_s2=0.02, max_jerk_m_s3=1.0, cycles=1)
    full = Scenario(name="t", segments=(*verification_lead(0.0, 0.002), seg), start_m=0.0)
    dur = full.duration_s(0.0) + 0.2
    with build_stage(cfg, clock=SimClock()) as st:
        rec = Recorder(st.loop.columns, capacity=int(dur / T) + 16)
        st.loop.add_sink(rec)
        st.load_scenario(full)
        st.loop.run(duration_s=dur)
    c = list(rec.columns)
    D = rec.data
    t = D[:, 0] - D[0, 0]
    m = (t > 0.7) & (np.abs(D[:, c.index("v_ref")]) >= 0.999 * v)
    return float(np.sqrt(np.mean(D[m, c.index("e")] ** 2)))


def test_the_exact_model_limit_cycles_inside_the_band_only(tmp_path: Path) -> None:
    # oracle: the real loop (PID + Q-filter + the exact GMS model's feed-forward) on the simulated plant with
    # the steep curve, at constant speeds inside and outside the flagged band
    from support import shipped_config_mapping

    fr = {"model": "gms", "k_n_m": [2.0e5, 5.0e4, 1.5e4, 5.0e3], "alpha": [0.4, 0.3, 0.2, 0.1],
          "sigma1_n_s_m": [74.0, 18.5, 5.6, 1.9], "c_n_s": 3.0e4, **STEEP}
    (tmp_path / "exact.yaml").write_text(yaml.safe_dump({"mass_kg": 1.0, "friction": fr}))
    data = shipped_config_mapping("sim.yaml")
    data["io"] = {"kind": "plant_io", "sensor": "drive", "delay_cycles": 1}
    data["sim"]["plant"] = {k: v for k, v in data["sim"]["plant"].items() if k != "model_file"}
    data["sim"]["plant"].update(mass_kg=1.0, friction=fr)
    data["controller"] = {
        "mass_kg": 1.0, "max_force_n": 10.0,
        "pid": {"kp_n_m": PID.kp_n_m, "ki_n_m_s": PID.ki_n_m_s, "kd_n_s_m": PID.kd_n_s_m,
                "derivative_cutoff_hz": 95.0},
        "dob": {"kind": "qfilter", "bandwidth_hz": 95.0, "command_delay_samples": 1},
        "feedforward": {"kind": "model", "model_file": str(tmp_path / "exact.yaml"), "inertia": True,
                        "lookahead_s": 0.0015}}
    data.pop("demo", None)
    (tmp_path / "stage.yaml").write_text(yaml.safe_dump(data))
    s = unstable_sliding(STEEP, 1.0, T, PID, 1, "qfilter", 95.0)
    assert s is not None
    lo, hi = s["bands_m_s"][0]
    inside = _const_speed_rms(tmp_path / "stage.yaml", math.sqrt(lo * hi))
    outside = _const_speed_rms(tmp_path / "stage.yaml", 1.25 * hi)
    assert inside > 1e-6 and outside < 0.3e-6, (inside, outside)


def test_report_md_states_the_band_in_the_gains_section_and_json_keeps_it() -> None:
    import json

    from stagectl.commission.outputs import report_markdown

    s = unstable_sliding(STEEP, 1.0, T, PID, 1, "qfilter", 95.0)
    chosen = {"crossover_target_hz": 19.0, "dob_kind": "qfilter", "dob_bandwidth_hz": 95.0,
              "pid": {"kp_n_m": PID.kp_n_m, "ki_n_m_s": PID.ki_n_m_s, "kd_n_s_m": PID.kd_n_s_m},
              "model": {"phase_margin_deg": 43.2, "gain_margin_db": 9.1, "crossover_hz": 19.0}}
    rep = {"status": "complete", "config": "x.yaml", "experiments": [],
           "gains": {"chosen": chosen, "unstable_sliding": s},
           "envelope": {"x_lo_m": -0.002, "x_hi_m": 0.002, "f_max_n": 10.0, "v_max_m_s": 0.02}}
    md = report_markdown(rep, [])
    gains = md.split("## Gains", 1)[1].split("\n## ", 1)[0]
    assert "Constant speeds between 0.81 and 2.1 mm/s will limit-cycle near 35 Hz with these gains" in gains
    assert json.loads(json.dumps(s)) == s  # plain values for report.json
    rep["gains"]["unstable_sliding"] = unstable_sliding({**STEEP, "fs_n": 2.5}, 1.0, T, PID, 1, "qfilter", 95.0)
    assert "limit-cycle" not in report_markdown(rep, [])


def test_a_band_that_reaches_the_grid_end_is_not_given_an_edge_there():
    """A net slope still below the loop's limit at the grid's end (here a fitted viscous of −400 N·s/m on a flat
    curve; likewise a δ <= 1 drop, steepest at v → 0) runs on beyond the speeds checked: the report named the
    grid's ends (v_s·10⁻³, v_s·10²) as the band's edges, "between 0.001 and 1e+02 mm/s" (review27d)."""
    from stagectl.commission.sliding import band_words
    from stagectl.control import design

    pid = design.design_pid(2.0, 20.0, 1e-3, 1)
    flat = {"fc_n": 1.0, "fs_n": 1.0, "vs_m_s": 1e-3, "delta": 2.0, "viscous_n_s_m": -400.0}
    s = unstable_sliding(flat, 2.0, 1e-3, pid, 1, "qfilter", 20.0)
    assert s is not None and s["bands_m_s"] == [[1e-6, 0.1]]  # the whole grid
    line = sliding_line(s)
    assert line is not None and "between" not in line and "whole range checked" in line
    grid = [1e-4, 1.0, 3]
    assert band_words([1e-4, 2e-3], grid).startswith("up to 2 mm/s")
    assert band_words([2e-3, 1.0], grid).startswith("from 2 mm/s")
    assert band_words([1e-3, 2e-3], grid, "-") == "1-2 mm/s"


def test_confidence_is_not_high_where_the_curve_was_not_measured():
    """The check said "confidence high" on any curve: a flat one (no drop identified, the band from a fitted
    viscous slope alone) or one whose band lies below the slowest sliding pass (the drop there extrapolated,
    the stick-slipping passes left out) is no measured linearisation (review27d)."""
    from stagectl.control import design

    pid = design.design_pid(2.0, 20.0, 1e-3, 1)
    flat = {"fc_n": 1.0, "fs_n": 1.0, "vs_m_s": 1e-3, "delta": 2.0, "viscous_n_s_m": -400.0,
            "stribeck_identified": False, "v_min_m_s": 1e-3}
    s = unstable_sliding(flat, 2.0, 1e-3, pid, 1, "qfilter", 20.0)
    assert s is not None and s["bands_m_s"] and s["confidence"] == "low"
    assert "confidence low: no Stribeck drop" in str(sliding_line(s))
    base = unstable_sliding(STEEP, 1.0, T, PID, 1, "qfilter", 95.0)
    assert base is not None and base["confidence"] == "high"
    lo = base["bands_m_s"][0][0]
    below = unstable_sliding({**STEEP, "stribeck_identified": True, "v_min_m_s": 2 * lo}, 1.0, T, PID, 1,
                             "qfilter", 95.0)
    assert below is not None and below["confidence"] == "medium" and "extrapolated" in str(sliding_line(below))
    above = unstable_sliding({**STEEP, "v_min_m_s": 0.5 * lo}, 1.0, T, PID, 1, "qfilter", 95.0)
    assert above is not None and above["confidence"] == "high"


def test_the_check_reads_the_models_refitted_curve_and_keeps_the_passes_facts() -> None:
    """sequence.sliding_curve: the model's sliding curve (after the Stribeck refit) when it has one, with the
    passes' slowest sliding speed and identification flag kept for the confidence; else the passes' curve."""
    from stagectl.commission.sequence import sliding_curve

    passes = {"fc_n": 2.5, "fs_n": 3.0, "vs_m_s": 1.5e-3, "delta": 2.0, "viscous_n_s_m": 40.0, "v_min_m_s": 1e-3,
              "stribeck_identified": True}
    model = {"friction": {"model": "gms", "fc_n": 2.5, "fs_n": 3.2, "vs_m_s": 2e-3, "delta": 2.0,
                          "viscous_n_s_m": 40.0, "k_n_m": [1e5]}}
    c = sliding_curve(model, passes)
    assert c is not None and c["fs_n"] == 3.2 and c["vs_m_s"] == 2e-3
    assert c["v_min_m_s"] == 1e-3 and c["stribeck_identified"] is True
    assert sliding_curve({"friction": {"model": "coulomb", "fc_n": 2.5}}, passes) is passes
    assert sliding_curve(None, None) is None


def test_damping_limit_of_a_loop_unstable_without_damping_is_zero() -> None:
    """A loop that is unstable on the damping-free plant tolerates no negative damping: the limit is 0, not a
    bisection's value that assumed stability at 0 (the 1 kg stage's gains ×20: far past the gain margin)."""
    from stagectl.commission.sliding import damping_limit

    hot = PidConfig(kp_n_m=20 * PID.kp_n_m, ki_n_m_s=20 * PID.ki_n_m_s, kd_n_s_m=20 * PID.kd_n_s_m,
                    derivative_cutoff_hz=95.0)
    assert np.any(np.abs(_closed_loop_poles(1.0, T, hot, 1, "qfilter", 95.0, 0.0)) >= 1.0)
    assert damping_limit(1.0, T, hot, 1, "qfilter", 95.0, -300.0) == 0.0
    # the healthy design keeps its measured limit
    lim = damping_limit(1.0, T, PID, 1, "qfilter", 95.0, -300.0)
    assert lim is not None and -230.0 < lim < -170.0
