"""``--scenario FILE.yaml`` (simulate, run): a scenario written as YAML. A ``sine`` ending moving, then a ``dwell``
and ``settle_s``, runs to the end without a fault, the reference holding the position the sine reached (on main
the generator raised ``dwell must start at rest``); a segment that cannot run or a bad value is one line naming
the segment's index, exit 2."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest
from support import cli_in_process

REPO = Path(__file__).resolve().parents[2]
SIM = REPO / "config" / "sim.yaml"


def test_sine_then_dwell_from_a_file_simulates_and_holds_where_the_sine_ended(tmp_path: Path) -> None:
    f = tmp_path / "sine_dwell.yaml"
    f.write_text("segments:\n"
                 "  - {kind: sine, amplitude_m: 1.0e-6, frequency_hz: 4.0, cycles: 1.125}\n"
                 "  - {kind: dwell, duration_s: 0.05}\n"
                 "settle_s: 0.05\n")
    out = tmp_path / "out"
    r = cli_in_process(["simulate", "--config", SIM, "--scenario", f, "--out", out, "-q", "--no-plots"])
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["fault"] is None and summary["loop"]["ended_by"] == "duration"
    with (out / "telemetry.csv").open() as fh:
        rows = [{k: float(v) for k, v in row.items()} for row in csv.DictReader(fh)]
    t_end = 1.125 / 4.0  # the sine ends at x = A·sin(2.25π) moving at 2πfA·cos(2.25π) = +18 µm/s
    moving = [r for r in rows if r["t"] <= t_end]
    assert moving[-1]["v_ref"] > 15e-6
    after = [r for r in rows if r["t"] > t_end + 0.002]
    assert len(after) > 90
    assert all(r["x_ref"] == after[0]["x_ref"] and r["v_ref"] == 0.0 and r["a_ref"] == 0.0 for r in after)
    assert after[0]["x_ref"] == pytest.approx(1e-6 * math.sin(2.25 * math.pi), rel=1e-9)
    assert max(abs(r["x_ref"] - r["x"]) for r in after[-20:]) < 50e-9  # and the stage holds there


@pytest.mark.parametrize("text, line", [
    ("segments:\n  - {kind: move, by_m: 1.0e-6}\n  - {kind: triangle, span_m: 1.0e-6, velocity_m_s: 1.0e-3}\n",
     "segments[1] (triangle): triangle: span 1e-06 m too short"),
    ("segments:\n  - {kind: sine, amplitude_m: 1.0e-6, frequency_hz: 4.0}\n  - {kind: dwell, duration_s: -1}\n",
     "segments[1].duration_s: must be > 0 s (got -1 s)"),
])
def test_a_bad_scenario_file_is_one_line_naming_the_segment(tmp_path: Path, text: str, line: str) -> None:
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    for cmd in ("simulate", "run"):
        r = cli_in_process([cmd, "--config", SIM, "--scenario", f, "--out", tmp_path / cmd, "-q", "--no-plots",
                            "--duration", "1"])
        assert r.returncode == 2
        err = r.stderr.strip().splitlines()
        assert len(err) == 1 and err[0] == f"stagectl: error: --scenario: {f}: {line}" + err[0].split(line, 1)[1]
        assert not (tmp_path / cmd / "telemetry.csv").exists()


def test_a_missing_scenario_file_is_one_line_naming_the_scenario_file(tmp_path: Path) -> None:
    """``--scenario`` naming a file that is not there (or a directory) says it cannot read the *scenario* file
    (on main: "cannot read configuration file", as if ``--config`` were wrong), one line, exit 2, through
    the real command (a subprocess)."""
    import subprocess

    from support import stagectl_cmd

    (tmp_path / "dir.yaml").mkdir()
    for cmd, name, why in (("simulate", "missing.yaml", "No such file or directory"),
                           ("run", "dir.yaml", "Is a directory")):
        f = tmp_path / name
        r = subprocess.run([*stagectl_cmd(), cmd, "--config", str(SIM), "--scenario", str(f),
                            "--out", str(tmp_path / cmd), "-q", "--no-plots"],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 2, r.stderr
        assert r.stderr.strip().splitlines() == [
            f"stagectl: error: --scenario: {f}: cannot read scenario file ({why})"]
        assert not (tmp_path / cmd / "telemetry.csv").exists()
