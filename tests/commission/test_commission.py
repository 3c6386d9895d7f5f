"""``stagectl commission`` end to end on a lock-step simulated plant that is NOT the configured model.

The plant (tests/commission/conftest.py) has a mass, Coulomb and viscous friction 30–44 % away from the
controller's model and a hidden cogging force; the commissioning reads loop/io/safety/controller only and
must find the plant's values. Simulated time (SimClock, PlantIO lock-step): no wall-clock sleeps.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from commission_stage import HIDDEN, assert_identified, write_stage

from stagectl.cli import main
from stagectl.commission.outputs import VERDICT_RMS_TOL, VERDICT_WIDE_RATIO, margin_standing
from stagectl.config import load_app_config
from stagectl.ident.recording import load_recording


@pytest.fixture
def hidden_stage(tmp_path: Path) -> Path:
    return write_stage(tmp_path / "stage.yaml")


@pytest.fixture(scope="module")
def commissioned(tmp_path_factory: pytest.TempPathFactory) -> tuple[int, Path]:
    d = tmp_path_factory.mktemp("commission")
    cfg = write_stage(d / "stage.yaml")
    out = d / "out"
    rc = main(["commission", "--config", str(cfg), "--out", str(out), "--max-stroke", "0.002"])
    return rc, out


def test_identifies_the_hidden_plant_within_10_percent(commissioned: tuple[int, Path]) -> None:
    rc, out = commissioned
    assert rc == 0
    rep = json.loads((out / "report.json").read_text())
    assert_identified(rep, HIDDEN)
    f = rep["fitted"]
    for key, true in (("mass_kg", HIDDEN["mass_kg"]), ("coulomb_n", HIDDEN["fc_n"]),
                      ("viscous_n_s_m", HIDDEN["viscous_n_s_m"])):
        assert 0 < f[key]["std"] < 0.1 * true, (key, f[key])
    # the hidden effect's period
    cog = next(e for e in rep["discovery"]["effects"] if e["name"] == "cogging")
    assert abs(cog["parameters"]["wavelength_m"] / HIDDEN["cogging_wavelength_m"] - 1) < 0.05
    # one I/O cycle of delay (the plant's delay_cycles: 1) besides the zero-order hold
    assert abs(f["delay_s"]["value"] - 1e-3) < 0.25e-3
    # nothing named that the plant does not have (its structure: no backlash, no offset, no ripple)
    assert not {"backlash", "offset", "position_ripple"} & set(f["effects"]), f["effects"]


def test_friction_fit_reads_the_designed_passes_both_ways_on_the_plant_curve(commissioned: tuple[int, Path]) -> None:
    """The constant-velocity fit's segments are the designed passes, each speed both ways (no one-way
    repositioning cruise: on main they were in), and the odd part of each pair, ``(F(v) − F(−v))/2``, in which
    the cogging over the pass cancels, lies on the hidden plant's own sliding curve
    ``Fc + (Fs − Fc)·exp(−(v/vs)^δ) + Fv·v`` (plain formula, the plant's values) within 3 mN, the fastest
    pass within 1 %."""
    import math

    import yaml

    from commission_stage import SHIPPED

    _rc, out = commissioned
    rep = json.loads((out / "report.json").read_text())
    speeds = next(e for e in rep["experiments"] if e["name"] == "friction_cv")["params"]["speeds_m_s"]
    segs = rep["friction_cv"]["segments"]
    shipped = yaml.safe_load(Path(SHIPPED).read_text())["friction"]
    fc, fv = HIDDEN["fc_n"], HIDDEN["viscous_n_s_m"]
    fs, vs, dl = fc + 0.15, float(shipped["vs_m_s"]), float(shipped["delta"])
    pairs: dict[int, dict[bool, tuple[float, float]]] = {}
    for sg in segs:
        k = min(range(len(speeds)), key=lambda i: abs(math.log(abs(sg["v_m_s"]) / speeds[i])))
        assert abs(abs(sg["v_m_s"]) / speeds[k] - 1) < 0.05, (sg, speeds)
        assert (sg["v_m_s"] > 0) not in pairs.get(k, {}), ("two segments of one pass", sg)
        pairs.setdefault(k, {})[sg["v_m_s"] > 0] = (abs(sg["v_m_s"]), sg["f_n"])
    assert len(pairs) >= 4 and all(len(p) == 2 for p in pairs.values()), pairs
    for k, p in pairs.items():
        v = 0.5 * (p[True][0] + p[False][0])
        curve = fc + (fs - fc) * math.exp(-((v / vs) ** dl)) + fv * v
        odd = 0.5 * (p[True][1] - p[False][1])
        # the fastest pass (57 samples at 16 mm/s) reads 8 mN low; the repositioning cruises were 30-100 mN off
        assert abs(odd - curve) < (3e-3 if k < len(speeds) - 1 else 0.01 * curve), (v, p, curve)


def test_outputs_are_complete_and_valid(commissioned: tuple[int, Path]) -> None:
    _rc, out = commissioned
    cfg = load_app_config(out / "stage.yaml")  # what check-config runs
    assert main(["check-config", "-q", str(out / "stage.yaml")]) == 0
    assert cfg.controller.feedforward.model is not None
    assert cfg.controller.feedforward.model.effects.cogging is not None
    assert abs(cfg.controller.mass_kg / HIDDEN["mass_kg"] - 1) < 0.10
    rep = json.loads((out / "report.json").read_text())
    names = {e["name"] for e in rep["experiments"]}
    assert {"sanity", "frf", "friction_cv", "reversals", "presliding", "slow_passes"} <= names
    for e in rep["experiments"]:
        rec = load_recording(out / e["csv"], min_rows=50)
        assert len(rec) == e["rows"]
    # gains: the margins the report claims hold on the model and on the measured FRF
    ch = rep["gains"]["chosen"]
    assert ch["model"]["phase_margin_deg"] >= 40 and ch["model"]["gain_margin_db"] >= 8
    assert ch["measured"]["phase_margin_deg"] >= 40 and ch["measured"]["gain_margin_db"] >= 8
    # before/after side by side, for each scenario
    for name in ("cosine", "triangle", "steps"):
        assert set(rep["verification"][name]) == {"before", "after"}
    # the verdict is checked against the before/after figures, not assumed
    worse = [n for n, d in rep["verification"].items()
             if d["after"]["rms_error_m"] > (1 + VERDICT_RMS_TOL) * d["before"]["rms_error_m"]
             or d["after"]["moves_settled"] < d["before"]["moves_settled"]]
    ms = margin_standing(rep["gains"])
    if ms is None or not worse:
        assert rep["verdict"]["recommend"] == ("given" if worse else "new")
    else:  # the given controller misses the margin floor the commissioned one meets: the margins weigh in,
        # and the given one is kept only if the new one is worse by a wide margin on every figure
        wide = all(d["after"]["rms_error_m"] > VERDICT_WIDE_RATIO * d["before"]["rms_error_m"]
                   and d["after"]["moves_settled"] <= d["before"]["moves_settled"]
                   for d in rep["verification"].values())
        assert rep["verdict"]["recommend"] == ("given" if wide else "new")
        assert "floor" in rep["verdict"]["text"]
    md = (out / "report.md").read_text()
    assert "RMS before" in md and "frf.png" in md and "pre-sliding elements" in md
    assert (out / "frf.png").stat().st_size > 1000


def test_rest_spring_is_checked_before_it_is_advised(commissioned: tuple[int, Path]) -> None:
    """The new stage.yaml gets the rest spring only with its checks in the report: the rest loop on the
    identified stuck stage stable, what it relies on stated when its margins are thin, more steps settled on
    the twin; and on the stage itself the verification's 10 um steps then all settle (2 of 4 without it)."""
    import yaml

    _, out = commissioned
    rep = json.loads((out / "report.json").read_text())
    rest = rep["gains"]["chosen"]["rest"]
    assert rest["enabled"], rest["reason"]
    assert rest["loops"]["rest/stuck"]["closed_loop_stable"]
    if not (rest["loops"]["rest/stuck"]["healthy"] and rest["loops"]["rest/free"]["healthy"]):
        assert "stuck in pre-sliding" in rest["relies_on"] and rest["confidence"] == "medium"
    def settled(twin: dict) -> int:
        return sum(v["moves_settled"] for v in twin.values())

    assert settled(rest["twin"]) > settled(rep["gains"]["chosen"]["twin"])
    ctl = yaml.safe_load((out / "stage.yaml").read_text())["controller"]
    assert ctl["rest_stiffness_fraction"] == rest["rest_stiffness_fraction"] > 0
    assert ctl["feedforward"]["rest_sync_hz"] == rest["rest_sync_hz"] > 0
    # rest gains that differ from the controller's own are written only when they meet the floor on the stuck stage
    if rest["rest_gains"]["chosen"] == "grid":
        assert rest["loops"]["rest/stuck"]["healthy"]
        assert ctl.get("rest_kd_fraction", 1.0) == rest["rest_kd_fraction"] < 1.0
    steps = rep["verification"]["steps"]["after"]
    assert steps["moves_settled"] == steps["moves"], steps
    # ... and checked on the stage itself before stage.yaml kept it (Commissioning._rest_on_stage)
    ros = rep["gains"]["rest_on_stage"]
    assert ros["keep"] and ros["additions"] == ["rest spring"]
    # (this stage: 4/4 settled against 2/4 on each pair, the cosine ~9 % worse with the spring, within the limit at
    # the 8 % floor but inside its noise band: three pairs run, and the confidence says it is undecided)
    assert ros["confidence"] == ("high" if ros["pairs"] == 1 else "medium" if ros["decided"] else "low"), ros
    assert 1 <= ros["pairs"] == len(ros["pair_figures"]) <= 3
    assert ros["figures"]["steps"]["with"]["moves_settled"] > ros["figures"]["steps"]["without"]["moves_settled"]


def test_experiments_stay_inside_the_envelope(commissioned: tuple[int, Path]) -> None:
    _, out = commissioned
    rep = json.loads((out / "report.json").read_text())
    env = rep["envelope"]
    for e in rep["experiments"]:
        rec = load_recording(out / e["csv"], min_rows=10)
        assert rec.x.min() >= -0.005 and rec.x.max() <= 0.005
        assert abs(rec.u).max() <= 10.0 + 1e-9
        if not e["name"].startswith("verify"):
            assert abs(rec.u).max() <= env["f_max_n"] * 1.0 + 1e-9, e["name"]
            # experiments keep to the (lowered) stroke, with room for the controller's following error
            assert rec.x.min() >= env["x_lo_m"] - 1e-4 and rec.x.max() <= env["x_hi_m"] + 1e-4, e["name"]


def test_injected_fault_aborts_with_drive_disabled_and_recordings_kept(hidden_stage: Path, tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    rc = main(["commission", "--config", str(hidden_stage), "--out", str(out), "--no-plots",
               "--inject-fault", "friction_cv@1.0", "--quiet"])
    assert rc == 1
    err = capsys.readouterr().err  # --quiet: no progress lines, the abort still said
    assert "commission:" not in err and err.startswith("stagectl: error: "), err
    rep = json.loads((out / "report.json").read_text())
    assert rep["status"] == "aborted"
    assert rep["aborted"]["experiment"] == "friction_cv"
    assert rep["aborted"]["drive_state_after"] != "enabled"
    last = rep["experiments"][-1]
    assert last["name"] == "friction_cv" and last["fault"] is not None
    for name in ("sanity", "frf", "friction_cv"):
        rec = load_recording(out / "recordings" / f"{name}.csv", min_rows=100)
        assert rec.t[-1] > rec.t[0]
    assert not (out / "stage.yaml").exists()


def test_stuck_axis_is_one_clear_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = write_stage(tmp_path / "stuck.yaml", fc_n=50.0)  # breakaway far above the probe's force
    rc = main(["commission", "--config", str(cfg), "--out", str(tmp_path / "o"), "--no-plots"])
    assert rc == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("stagectl: error:")]
    assert len(err) == 1 and "no motion" in err[0] and "um" in err[0]
    assert (tmp_path / "o" / "recordings" / "sanity.csv").exists()


def test_command_line_can_only_lower_limits(hidden_stage: Path, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["commission", "--config", str(hidden_stage), "--out", str(tmp_path / "o"), "--max-force", "50"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "--max-force" in err and "N" in err and "Traceback" not in err


def test_refuses_while_the_daemon_holds_the_same_config(hidden_stage: Path, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    # the daemon's run marker, naming a live process (this one) and the same configuration
    (run_dir / "stagectl.running").write_text(json.dumps({"pid": os.getpid(), "config": str(hidden_stage)}))
    rc = main(["commission", "--config", str(hidden_stage), "--out", str(tmp_path / "o"), "--runtime-dir",
               str(run_dir)])
    assert rc == 2
    assert "daemon" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(("signame", "code"), [("SIGINT", 130), ("SIGTERM", 143)])
def test_ctrl_c_stops_with_the_drive_disabled_and_keeps_the_recordings(hidden_stage: Path, tmp_path: Path,
                                                                       signame: str, code: int) -> None:
    """A real process and a real SIGINT, sent when the progress line says the FRF is under way; SIGTERM
    (kill, timeout) the same, exit 143 (before audit16 it killed the process: no report, no recordings)."""
    import signal
    import subprocess

    out = tmp_path / "out"
    # a test run started in the background (`cmd &` without job control) ignores SIGINT, and a child
    # inherits SIG_IGN (Python then never raises KeyboardInterrupt): the child restores Python's handler
    boot = ("import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
            "from stagectl.cli import main; sys.exit(main(sys.argv[1:]))")
    proc = subprocess.Popen([sys.executable, "-c", boot, "commission", "--config", str(hidden_stage),
                             "--out", str(out), "--no-plots"], stderr=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True)
    assert proc.stderr is not None
    for line in proc.stderr:
        if "[2/" in line and "frf" in line:
            proc.send_signal(getattr(signal, signame))
            break
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code, err
    rep = json.loads((out / "report.json").read_text())
    assert rep["status"] == "aborted" and rep["aborted"]["interrupted"]
    assert rep["aborted"]["reason"] == f"interrupted ({'SIGTERM' if signame == 'SIGTERM' else 'Ctrl-C'})"
    assert rep["aborted"]["drive_state_after"] != "enabled"
    assert load_recording(out / "recordings" / "sanity.csv", min_rows=100).t[-1] > 1.0


@pytest.mark.slow  # ~30 s: a whole commissioning of a 60 kg axis (pytest -m slow)
def test_heavy_ball_screw_axis_scales_and_is_improved(tmp_path: Path) -> None:
    """A 60 kg axis configured as 50 kg with a weak tuning: Stribeck friction 40/48 N, 400 N s/m, an 8 N
    offset, 0.1 µm encoder, ±0.2 m travel. The standing FRF sees a stage held by its friction; the
    inverse-dynamics mass of the passes is used instead, and the verdict recommends the new tuning only
    because the before/after runs show it."""
    cfg = tmp_path / "axis.yaml"
    cfg.write_text("""
loop: {period_s: 0.001}
io: {kind: plant_io, sensor: drive, delay_cycles: 1}
sim:
  plant:
    mass_kg: 60.0
    friction: {model: stribeck, fc_n: 40.0, fs_n: 48.0, vs_m_s: 0.005, delta: 2.0, viscous_n_s_m: 400.0}
    effects: {offset: {force_n: 8.0}}
    sensor: {resolution_m: 1.0e-7, noise_std_m: 5.0e-8}
    actuator: {max_force_n: 2000.0}
controller:
  mass_kg: 50.0
  max_force_n: 1000.0
  pid: {kp_n_m: 2.46e5, ki_n_m_s: 3.1e6, kd_n_s_m: 5880.0, derivative_cutoff_hz: 100.0}
  dob: {kind: qfilter, bandwidth_hz: 100.0}
  feedforward: {kind: coulomb, coulomb_n: 30.0, viscous_n_s_m: 300.0, inertia: true}
safety: {min_position_m: -0.2, max_position_m: 0.2, following_error_m: 1.0e-3, following_error_time_s: 0.02,
         max_force_n: 1000.0, max_velocity_m_s: 0.2}
""")
    out = tmp_path / "out"
    assert main(["commission", "--config", str(cfg), "--out", str(out), "--no-plots", "--max-stroke", "0.36"]) == 0
    rep = json.loads((out / "report.json").read_text())
    f = rep["fitted"]
    assert abs(f["mass_kg"]["value"] / 60.0 - 1) < 0.10
    assert abs(f["coulomb_n"]["value"] / 40.0 - 1) < 0.05 and abs(f["viscous_n_s_m"]["value"] / 400.0 - 1) < 0.05
    assert "offset" in f["effects"] and abs(f["offset_n"]["value"] / 8.0 - 1) < 0.1
    assert rep["envelope"]["f_max_n"] == pytest.approx(700.0)
    for name, d in rep["verification"].items():
        assert d["after"]["rms_error_m"] < d["before"]["rms_error_m"], name
    assert rep["verdict"]["recommend"] == "new"


def test_experiment_tuning_is_the_one_the_identification_was_validated_with(hidden_stage: Path,
                                                                            tmp_path: Path) -> None:
    """The experiments' own controller keeps the integrator running at rest (the FRF's linear-loop model) and
    the plain inertia feed-forward m·a_ref: with the look-ahead m·(a_ref + j_ref·T/2), the controller's
    default, the commissioning of config/sim.yaml identified the pre-sliding stiffness 19 % high instead of
    10 % and its cosine error was 253 nm RMS instead of 12.8 nm. Checked on the force the controller
    commands along a jerk-limited move."""
    from stagectl.commission.sequence import Commissioning, Options
    from stagectl.control.api import Reference
    from stagectl.control.controller import StageController
    from stagectl.control.reference import TrajectoryReference
    from stagectl.control.trajectory import Move, Scenario

    cfg = load_app_config(hidden_stage)
    tuning = Commissioning(cfg, tmp_path / "o", Options(), lambda r: cfg)._commission_tuning(2.0)
    assert not tuning.hold_integrator_at_rest
    ctl = StageController(tuning, 1e-3)
    ref = TrajectoryReference()
    ref.set_scenario(Scenario(name="m", segments=(Move(by_m=1e-3, max_velocity_m_s=0.01, max_acceleration_m_s2=0.5,
                                                       max_jerk_m_s3=50.0),)))
    ref.hold(0.0, 0.0)
    worst, jerk_steps = 0.0, 0
    for k in range(1, 200):
        r = ref.sample(k * 1e-3)
        cmd = ctl.step(1e-3, r.x_m, Reference(r.x_m, r.v_m_s, r.a_m_s2))
        worst = max(worst, abs(cmd.terms["u_inertia"] - 2.0 * r.a_m_s2))
        jerk_steps += r.a_m_s2 != 0.0
    assert jerk_steps > 20 and worst == 0.0


def test_every_planned_experiment_can_take_an_injected_fault() -> None:
    """--inject-fault accepts each experiment the sequence runs (the hand-written list once missed
    ``presliding``) and refuses anything else."""
    from stagectl.commands.commission import _parse_fault
    from stagectl.commission.sequence import EXPERIMENTS
    from stagectl.errors import ConfigError

    assert "presliding" in EXPERIMENTS
    for name in (*EXPERIMENTS, "wipe_rest_with_steps", "verify_rest_without_cosine"):  # (the rest check's runs)
        assert _parse_fault(f"{name}@0.5") == (name, 0.5)
    with pytest.raises(ConfigError, match="unknown experiment"):
        _parse_fault("warp_drive@1")


@pytest.mark.slow  # the README's quick start: a full commissioning, ~15 s of CPU
def test_the_quick_start_names_only_what_the_seed_stage_has(tmp_path: Path) -> None:
    """README's commissioning of config/sim.yaml (the seed stage: GMS friction, i.e. Stribeck and pre-sliding;
    no backlash, offset, ripple or cogging). The experiments run a linear loop: with the observer anti-wind-up
    on in them, the force at every reversal was bent and discover named a false 24 µm backlash."""
    cfg = Path(__file__).resolve().parents[2] / "config" / "sim.yaml"
    out = tmp_path / "out"
    assert main(["commission", "--config", str(cfg), "--out", str(out), "--no-plots", "-q"]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert set(rep["fitted"]["effects"]) == {"stribeck", "presliding"}, rep["fitted"]["effects"]
