"""``stagectl model plot`` / ``stagectl model compare`` (in-process CLI, real files and PNGs)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from stagectl.cli import main

REPO = Path(__file__).resolve().parents[2]
GMS_FILE = REPO / "config" / "models" / "kamenar2016_gms.yaml"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_model_plot_writes_three_pngs_and_json_summary(tmp_path, capsys):
    out = tmp_path / "plots"
    assert main(["model", "plot", str(GMS_FILE), "--out", str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    names = sorted(Path(f).name for f in res["files"])
    assert names == ["hysteresis.png", "stribeck.png", "virgin.png"]
    for f in res["files"]:
        data = Path(f).read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 10_000
    s = res["summary"]
    assert s["virgin_n"]["1um"] == pytest.approx(0.524485, abs=1e-3)  # 1 µm/s ramp: + tiny viscous/damping
    assert s["virgin_n"]["10um"] == pytest.approx(0.867290, abs=1e-3)
    assert s["stribeck_n"]["0.001m_s"] == pytest.approx(0.845951, abs=1e-5)
    assert s["stribeck_n"]["-0.001m_s"] == pytest.approx(-0.845951, abs=1e-5)
    assert s["initial_stiffness_n_m"] == pytest.approx(638895.0, rel=0.01)


def test_model_compare_overlays_and_reports_difference(tmp_path, capsys):
    other = tmp_path / "maxwell.yaml"
    other.write_text("friction:\n  model: maxwell_slip\n  k_n_m: [200000.0, 20000.0]\n  w_n: [0.4, 0.5]\n")
    out = tmp_path / "cmp"
    assert main(["model", "compare", str(GMS_FILE), str(other), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    for name in ("virgin_compare.png", "hysteresis_compare.png", "stribeck_compare.png"):
        assert str(out / name) in text
        assert (out / name).read_bytes().startswith(PNG_MAGIC)
    assert "RMS difference" in text


def test_model_plot_bad_file_is_a_clean_error(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("friction:\n  model: gms\n  k_n_m: [1.0]\n  alpha: [1.0]\n  fc_n: 1.0\n  fs_n: 1.0\n  cc: 2\n")
    assert main(["model", "plot", str(bad), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "stagectl: error:" in err and "friction.cc: unknown key" in err and "Traceback" not in err
    assert main(["model", "plot", str(tmp_path / "missing.yaml"), "--out", str(tmp_path)]) == 2
    assert "cannot read" in capsys.readouterr().err


GOOD_GMS = "friction:\n  model: gms\n  k_n_m: [1.0e5, 2.0e4]\n  alpha: [0.5, 0.5]\n  fc_n: 0.8\n  fs_n: 0.9\n"


@pytest.mark.parametrize(
    "text,expected",
    [
        (None, ["cannot read configuration file"]),  # missing file
        ("friction:\n  model: gms\n  k_n_m: [1.0\n", ["YAML syntax error at line"]),
        (b"\xff\xfe\x00", ["not a UTF-8 text file"]),
        ("- 1\n- 2\n", ["expected a model file mapping"]),
        ("friction:\n  model: gmz\n", ["friction.model: unknown friction model 'gmz'", "gms"]),
        ("friction:\n  k_n_m: [1.0]\n", ["friction.model: required key missing"]),
        (GOOD_GMS + "  c_n_s: -5\n", ["friction.c_n_s: must be > 0 N/s (got -5 N/s)"]),
        (GOOD_GMS + "  viscous_n_s_m: abc\n", ["friction.viscous_n_s_m: expected a number N·s/m"]),
        (GOOD_GMS.replace("[1.0e5, 2.0e4]", "1.0e5"), ["friction.k_n_m: expected a list (values in N/m)"]),
        (GOOD_GMS.replace("fs_n: 0.9", "fs_n: .nan"), ["friction.fs_n: must be a finite number N, got NaN"]),
        (GOOD_GMS.replace("fs_n: 0.9", "fs_n: -0.7"), ["friction.fs_n: must be > 0 N (got -0.7 N)"]),
        (GOOD_GMS.replace("[0.5, 0.5]", "[1.0]") + "mass_kg: -2\neffects: {offset: {force_n: x}}\n",
         ["friction.alpha: needs 2 entries", "mass_kg: must be > 0 kg", "effects.offset.force_n: expected a number N"]),
    ],
)
def test_bad_model_files_give_one_clean_line_per_problem(tmp_path, capsys, text, expected):
    f = tmp_path / "m.yaml"
    if isinstance(text, bytes):
        f.write_bytes(text)
    elif text is not None:
        f.write_text(text, encoding="utf-8")
    assert main(["model", "plot", str(f), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert lines and all(line.startswith("stagectl: error: ") for line in lines), err
    assert len(lines) == max(1, sum(":" in e for e in expected))  # one line per problem (key: message)
    for e in expected:
        assert e in err
    assert "Traceback" not in err


def test_unwritable_out_dir_is_a_clean_error(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["model", "plot", str(GMS_FILE), "--out", str(blocker / "sub")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("stagectl: error: --out: cannot create output directory") and "Traceback" not in err
