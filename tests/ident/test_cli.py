"""`stagectl discover` / `stagectl identify` end to end (real subprocess, real files)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stagectl.friction import build, load_model_file
from stagectl.ident import synth

from support import cli_in_process


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "stagectl.cli", *args], capture_output=True, text=True,
                          timeout=300)


def _save_renamed(rec, path: Path) -> None:
    data = np.column_stack([rec.t, rec.x, rec.u, rec.x_ref])
    np.savetxt(path, data, delimiter=",", header="t_s,position_m,force_N,reference_m", comments="", fmt="%.17g")


@pytest.fixture(scope="module")
def spring_stage(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict]:
    rng = np.random.default_rng(3000)
    st = synth.hide(synth.draw_stage(rng), "spring", rng)
    d = tmp_path_factory.mktemp("cli")
    motion = synth.Motion(duration_s=9.0)
    _save_renamed(synth.closed_loop(st, motion=motion, seed=3000), d / "est.csv")
    _save_renamed(synth.closed_loop(st, motion=motion, seed=3001), d / "val.csv")
    return d / "est.csv", d / "val.csv", st


def test_discover_cli_writes_report_plots_and_loadable_model(spring_stage, tmp_path: Path) -> None:
    est, val, st = spring_stage
    start = tmp_path / "start.yaml"
    start.write_text("friction: {model: stribeck, fc_n: 1.0, fs_n: 1.0, viscous_n_s_m: 10.0}\n", encoding="utf-8")
    out = tmp_path / "out"
    p = _cli("discover", str(est), "--validate", str(val), "--model", str(start), "--columns",
             "t=t_s,x=position_m,u=force_N,x_ref=reference_m", "--out", str(out), "--json")
    assert p.returncode == 0, p.stderr
    rep = json.loads(p.stdout)
    for key in ("gap_metric", "gap_before", "gap_after", "effects", "rejected", "disagreement"):
        assert key in rep
    assert "force" in rep["gap_metric"] and "validation" in rep["gap_metric"]
    assert [e["name"] for e in rep["effects"]][:1] == ["spring"]
    e = rep["effects"][0]
    assert set(e) >= {"name", "parameters", "gap_before", "gap_after", "evidence"}
    assert e["parameters"]["stiffness_n_m"] == pytest.approx(st["effects"]["spring"]["stiffness_n_m"], rel=0.05)
    assert rep["gap_after"] < 0.5 * rep["gap_before"]
    assert any(d["kind"] == "regime" for d in rep["disagreement"])
    assert (out / "report.json").exists() and (out / "report.md").exists()
    pngs = sorted(x.name for x in out.glob("*.png"))
    assert len(pngs) >= 3 and all((out / x).stat().st_size > 1000 for x in pngs)
    md = (out / "report.md").read_text(encoding="utf-8")
    assert "spring" in md and ".png" in md
    # every candidate of every round with its key parameter and verdict; the model file names its base model
    rows = [c for r in rep["rounds"] for c in r["candidates"] if "error" not in c]
    assert rows and all(c.get("verdict") for c in rows)
    assert sum(c["verdict"].startswith("accepted") for c in rows) == len(rep["effects"])
    assert any(c["verdict"].startswith("rejected: ") for c in rows)
    assert "| verdict |" in md and "λ = " in md  # periodic candidates show their wavelength
    header = (out / "model.yaml").read_text(encoding="utf-8").splitlines()[0]
    assert header.startswith("#") and "base model:" in header and "no Stribeck effect was found" in header
    # the augmented model loads as a StageModel, and the plant accepts it
    model = load_model_file(out / "model.yaml")
    assert model.effects.spring is not None
    assert model.mass_kg == pytest.approx(st["mass_kg"], rel=0.05)
    from stagectl.sim.plant import PlantConfig, StagePlant

    StagePlant(PlantConfig.from_mapping({"model_file": str(out / "model.yaml")}, model=model))


def test_identify_cli_writes_model_and_plots(spring_stage, tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    """In-process ``stagectl.cli.main`` (the discover test above covers the real subprocess)."""
    from stagectl.cli import main

    est, _, st = spring_stage
    out = tmp_path / "m.yaml"
    rc = main(["identify", str(est), "--model", "stribeck", "--columns", "t=t_s,x=position_m,u=force_N",
               "--out", str(out), "--plot", str(tmp_path / "plots"), "--json"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    q = json.loads(cap.out)
    assert q["quality"]["fit"]["force_rms_error_n"] >= 0
    model = load_model_file(out)
    assert model.friction.tag == "stribeck"
    assert model.mass_kg is not None and model.mass_kg > 0  # (biased here: a stribeck fit has no spring term)
    assert build(model.friction.spec()).params.fc_n > 0
    assert len(list((tmp_path / "plots").glob("*.png"))) >= 2


def test_cli_bad_recording_names_row_and_column(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from stagectl.cli import main

    bad = tmp_path / "bad.csv"
    bad.write_text("t,x,u\n0,0,0\n0.001,oops,0\n", encoding="utf-8")
    for cmd in (["discover", str(bad), "--out", str(tmp_path / "o")],
                ["identify", str(bad), "--model", "gms", "--out", str(tmp_path / "m.yaml")]):
        assert main(cmd) == 2
        err = capsys.readouterr().err
        assert "row 3" in err and "column 'x'" in err
        assert "Traceback" not in err


def test_cli_missing_column_suggests_mapping(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from stagectl.cli import main

    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,position_m,force_N\n0,0,0\n", encoding="utf-8")
    assert main(["discover", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "missing required column 't'" in err and "--columns" in err
    assert "Traceback" not in err


def test_cli_non_utf8_bom_and_bad_out_are_one_line_errors(tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """Audit: a latin-1/binary file and an --out that is a file gave tracebacks; a spreadsheet BOM hid 't'."""
    from stagectl.cli import main
    from stagectl.ident.recording import load_recording

    lat = tmp_path / "latin1.csv"
    lat.write_bytes(b"t,x,u\n0,0,1\n0.001,\xe9,1\n")
    assert main(["discover", str(lat), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "stagectl: error:" in err and "UTF-8" in err and "Traceback" not in err
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbft,x,u\n0,0,1\n0.001,0,1\n0.002,0,1\n")
    rec = load_recording(bom)
    assert rec.t.tolist() == [0.0, 0.001, 0.002]
    ofile = tmp_path / "ofile"
    ofile.write_text("", encoding="utf-8")
    assert main(["discover", str(bom), "--out", str(ofile)]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "not a directory" in err and "Traceback" not in err
    assert main(["identify", str(bom), "--model", "stribeck", "--out", str(tmp_path / "no" / "m.yaml")]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "existing directory" in err and "Traceback" not in err


def test_discover_accepts_a_recording_with_gaps_and_says_it_resampled(spring_stage, tmp_path: Path) -> None:
    """Skipped control cycles leave t non-uniform: the recording is resampled onto a uniform grid with a note
    (issue 15), instead of a refusal."""
    est, _, _ = spring_stage
    data = np.loadtxt(est, delimiter=",", skiprows=1)
    rng = np.random.default_rng(7)
    keep = np.ones(len(data), bool)
    keep[rng.choice(np.arange(10, len(data) - 10), size=len(data) // 25, replace=False)] = False  # 4 % skipped
    gappy = tmp_path / "gappy.csv"
    np.savetxt(gappy, data[keep], delimiter=",", header="t_s,position_m,force_N,reference_m", comments="",
               fmt="%.17g")
    out = tmp_path / "out"
    p = cli_in_process(["discover", str(gappy), "--columns", "t=t_s,x=position_m,u=force_N,x_ref=reference_m",
                        "--out", str(out), "--json", "--no-plots", "--max-rounds", "1"])  # the note, not the process
    assert p.returncode == 0, p.stderr
    rep = json.loads(p.stdout)
    assert any("resampled onto a uniform" in n for n in rep["data_notes"]), rep["data_notes"]
    assert [e["name"] for e in rep["effects"]] == ["spring"]
    assert "resampled" in (out / "report.md").read_text(encoding="utf-8")


@pytest.mark.parametrize("what", ["huge_x", "tiny_dt", "huge_x_ref"])
def test_extreme_but_valid_recordings_give_one_error_line(spring_stage, tmp_path: Path, what: str) -> None:
    """Values around 1e300 or a 1e-300 s time step are valid CSV but no physical recording: one line naming the
    row, column and unit, exit 2 (issue 16)."""
    est, _, _ = spring_stage
    data = np.loadtxt(est, delimiter=",", skiprows=1)[:600]
    if what == "huge_x":
        data[300, 1] = 1e300
    elif what == "huge_x_ref":  # an optional column, still loaded: checked like the required ones
        data[300, 3] = -1e300
    else:
        data[:, 0] = np.arange(len(data)) * 1e-300
    bad = tmp_path / "bad.csv"
    np.savetxt(bad, data, delimiter=",", header="t_s,position_m,force_N,reference_m", comments="", fmt="%.17g")
    for cmd, extra in (("discover", ()), ("identify", ("--model", "stribeck"))):
        # in process: the refusal is what is tested (the subprocess runs are the tests above and below)
        p = cli_in_process([cmd, str(bad), *extra, "--columns", "t=t_s,x=position_m,u=force_N,x_ref=reference_m",
                            "--out", str(tmp_path / f"{cmd}.yaml")])
        assert p.returncode == 2, (cmd, p.stdout, p.stderr)
        lines = p.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("stagectl: error:"), p.stderr
        assert "Traceback" not in p.stderr
        expected = {"huge_x": "column 'x': 1e+300 m ", "huge_x_ref": "column 'x_ref': -1e+300 m ",
                    "tiny_dt": "time step"}[what]
        assert expected in lines[0], lines[0]


def test_presliding_extent_finds_the_end_of_a_virgin_curve() -> None:
    """The identify plot's zoom window: where an exponential virgin curve F = Fc(1 − e^{−d/d0}) reaches 95 %
    (d = d0·ln 20), checked against that closed form; a curve that never saturates gives its whole range."""
    import numpy as np

    from stagectl.plots import presliding_extent

    d = np.linspace(0.0, 1e-3, 200001)
    d0 = 2e-6
    got = presliding_extent(d, 0.8 * (1 - np.exp(-d / d0)))
    assert got == pytest.approx(d0 * np.log(20.0), rel=1e-3)
    assert presliding_extent(d, 5.0 * d) == pytest.approx(d[int(np.argmax(d >= 0.95e-3))])
    assert presliding_extent(d, np.zeros_like(d)) == d[-1]


def test_discover_reports_progress_per_candidate_with_a_bounded_time_left(spring_stage) -> None:
    """discover(..., progress=) is told before every candidate fit, with a done value that only grows and stays
    within max_rounds; the command's line gives the time left as an upper bound ("at most")."""
    import io

    from stagectl.commands.progress import Progress
    from stagectl.ident.discover import discover
    from stagectl.ident.recording import load_recording

    est, val, _ = spring_stage
    cols = "t=t_s,x=position_m,u=force_N,x_ref=reference_m"
    seen: list[tuple[float, str]] = []
    discover(load_recording(str(est), cols, min_rows=200), validate=load_recording(str(val), cols, min_rows=200),
             max_rounds=3, progress=lambda done, what: seen.append((done, what)))
    dones = [d for d, _ in seen]
    assert len(seen) >= 5 and dones == sorted(dones) and 0.0 <= dones[0] and dones[-1] < 3.0
    assert seen[0][1].startswith("round 1, candidate 1 of ") and any(w.startswith("round 2,") for _, w in seen)
    out = io.StringIO()
    now = [0.0]
    p = Progress("discover", 3, stream=out, every_s=0.0, clock=lambda: now[0])
    p.bounded(0.0, "round 1, candidate 1 of 12 (stribeck)")
    now[0] = 30.0  # the test's clock: 1.5 rounds in 30 s, 1.5 rounds left at most
    p.bounded(1.5, "round 2, candidate 3 of 12 (cogging)")
    line = out.getvalue().splitlines()[-1]
    assert line == "discover: round 2, candidate 3 of 12 (cogging) (30 s elapsed, at most ~30 s left)"


def test_identify_accepts_a_recording_with_gaps_and_says_it_resampled(tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """identify too: skipped cycles are resampled (not refused) and the output says so."""
    from stagectl.cli import main

    t = np.arange(0.0, 2.0, 1e-3)
    x = 5e-4 * np.sin(2 * np.pi * 1.0 * t)
    u = 0.8 * np.tanh(np.gradient(x, t) / 1e-4)
    keep = np.ones(t.size, bool)
    keep[[300, 301, 302, 1200]] = False  # 4 skipped cycles
    gappy = tmp_path / "gappy.csv"
    np.savetxt(gappy, np.column_stack([t, x, u])[keep], delimiter=",", header="t,x,u", comments="", fmt="%.12g")
    rc = main(["identify", str(gappy), "--model", "dahl", "--out", str(tmp_path / "m.yaml"), "--quiet"])
    out = capsys.readouterr().out
    assert rc in (0, 3) and (tmp_path / "m.yaml").is_file()
    assert "note: irregular sampling" in out and "4 of 2000 grid samples were not measured" in out, out
