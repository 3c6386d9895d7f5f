"""Gain design and loop analysis (python-control) and ``stagectl tune``."""

from __future__ import annotations

import json
import math

import pytest

from stagectl.cli import main
from stagectl.control.api import Reference
from stagectl.control.controller import StageController
from stagectl.control.design import analyse_design, design_pid
from stagectl.schema import load


def test_design_pid_hits_the_target_crossover_with_margin():
    pid = design_pid(2.0, 20.0, 1e-3, delay_samples=1)
    loops = analyse_design(2.0, 1e-3, pid, 1)
    a = loops[0]
    assert a.crossover_hz == pytest.approx(20.0, rel=1e-3)
    assert a.phase_margin_deg > 45.0 and a.gain_margin_db > 10.0 and a.stable
    assert pid.ki_n_m_s == pytest.approx(pid.kp_n_m * 2 * math.pi * 20 / 10, rel=1e-9)
    with pytest.raises(ValueError, match="Nyquist"):
        design_pid(2.0, 600.0, 1e-3)


def _mass_sim(cfg_ctl, T: float, delay: int, n: int = 3000) -> float:
    """Pure mass (2 kg, exact ZOH) with ``delay`` samples of actuation delay under the real controller;
    returns max |x| after a 1 µm step command (linear: no friction)."""
    ctl = StageController(cfg_ctl, T)
    ctl.reset(0.0)
    x = v = 0.0
    hist = [0.0] * (delay + 1)
    peak = 0.0
    for k in range(n):
        cmd = ctl.step(T, x, Reference(1e-6 if k > 10 else 0.0))
        hist.append(cmd.force_n)
        u = hist[-1 - delay]
        a = u / 2.0
        x, v = x + v * T + a * T * T / 2, v + a * T
        peak = max(peak, abs(x))
        if not math.isfinite(x) or peak > 1.0:
            break
    return peak


@pytest.mark.parametrize("kind,pid_hz,dob_hz,cd,expect_stable", [
    ("qfilter", 20.0, 100.0, 1, True), ("qfilter", 80.0, 200.0, 0, False),
    ("kalman", 20.0, 60.0, 1, True), ("kalman", 60.0, 120.0, 0, False),
])
def test_analysis_predicts_time_domain_stability(kind, pid_hz, dob_hz, cd, expect_stable):
    """The discrete loop model (plant, delay, PID and Q-filter DOB as implemented) agrees with a simulation."""
    from stagectl.control.controller import ControllerConfig

    T = 1e-3
    pid = design_pid(2.0, pid_hz, T, 1)
    loops = analyse_design(2.0, T, pid, 1, dob_hz, cd, dob_kind=kind)
    assert loops[1].stable is expect_stable
    cfg = load(ControllerConfig, {
        "mass_kg": 2.0, "max_force_n": 1e9,
        "pid": {"kp_n_m": pid.kp_n_m, "ki_n_m_s": pid.ki_n_m_s, "kd_n_s_m": pid.kd_n_s_m,
                "derivative_cutoff_hz": pid.derivative_cutoff_hz, "derivative_on": "error"},
        "dob": {"kind": kind, "bandwidth_hz": dob_hz, "command_delay_samples": cd},
        "feedforward": {"kind": "none", "inertia": False}}, "controller")
    peak = _mass_sim(cfg, T, 1)
    if expect_stable:
        assert peak < 3e-6
    else:
        assert peak > 1e-3


def test_tune_cli_json_and_plot(tmp_path, capsys):
    rc = main(["tune", "--mass-kg", "2", "--period-s", "1e-3", "--bandwidth-hz", "20", "--out", str(tmp_path),
               "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0
    d = out["designed"]
    assert d["loops"]["pid"]["crossover_hz"] == pytest.approx(20.0, rel=1e-3)
    assert d["loops"]["pid+dob"]["closed_loop_stable"] is True
    assert "controller:" in d["yaml"]
    png = tmp_path / "tune_bode.png"
    assert png.exists() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_tune_cli_reads_the_app_config(repo_root, capsys):
    cfg = repo_root / "config" / "sim.yaml"
    if not cfg.exists():
        pytest.skip("config/sim.yaml not shipped yet")
    rc = main(["tune", "--config", str(cfg)])
    out = capsys.readouterr().out
    assert rc in (0, 1)
    assert "configured:" in out and "designed for a" in out and "phase margin" in out


def test_tune_cli_bad_input_is_a_clear_error(capsys):
    rc = main(["tune", "--mass-kg", "-1", "--bandwidth-hz", "900", "--period-s", "1e-3"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "--mass-kg: must be > 0 kg" in err and "Nyquist" in err
    rc = main(["tune"])
    assert rc == 2 and "--mass-kg: required" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["sim", "hil-canopen", "hil-serial", "stage-canopen"])
def test_tune_reports_margins_of_every_shipped_config(repo_root, capsys, name):
    rc = main(["tune", "--config", str(repo_root / "config" / f"{name}.yaml"), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0 and out["configured"]["stable"] is True
    loops = out["configured"]["loops"]
    assert set(loops) == {"pid", "pid+dob"}
    for s in loops.values():
        assert s["closed_loop_stable"] and s["gain_margin_db"] >= 6.0 and s["phase_margin_deg"] >= 25.0
        assert s["healthy"] == (s["phase_margin_deg"] >= 40.0 and s["gain_margin_db"] >= 6.0)
    assert 15.0 < loops["pid"]["crossover_hz"] < 70.0


def test_hil_serial_tuning_keeps_margin_with_the_interferometer_latency(repo_root):
    """The interferometer is not sampled on SYNC: two periods of loop delay. Its shipped tuning keeps a phase
    margin there that the 40 Hz tuning of sim.yaml does not."""
    from stagectl.config import load_app_config
    from stagectl.control.design import analyse_design

    def pm_at_two_periods(name):
        c = load_app_config(repo_root / "config" / name).controller
        _, d = analyse_design(2.0, 1e-3, c.pid, 2, c.dob.bandwidth_hz, c.dob.command_delay_samples)
        return d.phase_margin_deg, d.gain_margin_db

    pm, gm = pm_at_two_periods("hil-serial.yaml")
    assert pm >= 30.0 and gm >= 6.0
    assert pm_at_two_periods("sim.yaml")[0] < 10.0
