"""Recording I/O: the CSV convention and its errors (row and column named)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stagectl.errors import DataError
from stagectl.ident.recording import Recording, load_recording, parse_columns


def _write(tmp_path: Path, text: str, name: str = "rec.csv") -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


GOOD = "t,x,u\n0.000,0.0,1.0\n0.001,1e-6,1.5\n0.002,3e-6,2.0\n0.003,6e-6,2.5\n"


def test_loads_canonical_columns(tmp_path: Path) -> None:
    dut = load_recording(_write(tmp_path, GOOD))
    assert len(dut) == 4
    np.testing.assert_allclose(dut.x, [0.0, 1e-6, 3e-6, 6e-6])
    np.testing.assert_allclose(dut.u, [1.0, 1.5, 2.0, 2.5])
    assert dut.dt_s == pytest.approx(1e-3)
    assert dut.x_ref is None


def test_columns_mapping_and_extra_columns(tmp_path: Path) -> None:
    text = "t_s,position_m,force_N,reference_m,u_V\n0,0,1,0,0.1\n0.001,1e-6,2,1e-6,0.2\n0.002,2e-6,3,2e-6,0.3\n"
    dut = load_recording(_write(tmp_path, text), "t=t_s,x=position_m,u=force_N,x_ref=reference_m")
    np.testing.assert_allclose(dut.u, [1, 2, 3])
    np.testing.assert_allclose(dut.x_ref, [0, 1e-6, 2e-6])
    np.testing.assert_allclose(dut.extra["u_V"], [0.1, 0.2, 0.3])


def test_round_trip_save_csv(tmp_path: Path) -> None:
    rec = Recording(t=np.arange(5) * 1e-3, x=np.linspace(0, 1e-5, 5), u=np.ones(5), x_ref=np.zeros(5))
    rec.save_csv(tmp_path / "r.csv")
    back = load_recording(tmp_path / "r.csv")
    np.testing.assert_array_equal(back.x, rec.x)
    np.testing.assert_array_equal(back.x_ref, rec.x_ref)


@pytest.mark.parametrize(
    ("text", "columns", "fragments"),
    [
        ("t,x\n0,0\n0.001,0\n0.002,0\n", None, ["missing required column 'u'", "--columns u=NAME"]),
        ("t_s,x,u\n0,0,0\n0.001,0,0\n0.002,0,0\n", "t=time", ["missing required column 'time'"]),
        ("t,x,u\n0,0,0\n0.001,abc,0\n0.002,0,0\n", None, ["row 3", "column 'x'", "non-numeric", "'abc'"]),
        ("t,x,u\n0,0,0\n0.001,0,nan\n0.002,0,0\n", None, ["row 3", "column 'u'", "not a finite number", "in N"]),
        ("t,x,u\n0,0,0\n0.001,inf,0\n0.002,0,0\n", None, ["row 3", "column 'x'", "not a finite"]),
        ("t,x,u\n0,0,0\n0.001,0,0\n0.001,0,0\n", None, ["row 4", "column 't'", "not strictly increasing"]),
        ("t,x,u\n0,0,0\n0.002,0,0\n0.001,0,0\n", None, ["row 4", "column 't'", "not strictly increasing"]),
        ("t,x,u\n0,0,0\n", None, ["1 data rows", "at least 3"]),
        ("t,x,u\n0,0,0\n0.001,0\n0.002,0,0\n", None, ["row 3", "column 'u'", "row too short"]),
        # a decimal comma (or a stray field) shifts the columns: refused, not read from the wrong places
        ("t,x,u\n0,0,0\n0.001,0,0,5\n0.002,0,0\n", None, ["row 3", "4 values", "header has 3 columns"]),
        ("", None, ["empty file"]),
        # a spreadsheet export separated by ';' (decimal-comma locales) or tabs: said so, not "map --columns"
        ("t;x;u\n0;0;0\n0,001;0;0\n0,002;0;0\n", None, ["line 1", "one column", "';'", "by ','"]),
        ("t\tx\tu\n0\t0\t0\n0.001\t0\t0\n0.002\t0\t0\n", None, ["one column", "'\\t'", "by ','"]),
    ],
)
def test_bad_files_name_row_and_column(tmp_path: Path, text: str, columns: str | None, fragments: list[str]) -> None:
    p = _write(tmp_path, text)
    with pytest.raises(DataError) as exc:
        load_recording(p, columns)
    msg = str(exc.value)
    assert str(p) in msg
    for frag in fragments:
        assert frag in msg, msg


def test_trailing_empty_fields_are_accepted(tmp_path: Path) -> None:
    # spreadsheet exports often end rows with a separator: empty cells beyond the header are not values
    dut = load_recording(_write(tmp_path, "t,x,u\n0,0,1,\n0.001,0,2,\n0.002,0,3,,\n"))
    np.testing.assert_allclose(dut.u, [1, 2, 3])


def test_missing_file_is_a_data_error(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="cannot open"):
        load_recording(tmp_path / "nope.csv")


@pytest.mark.parametrize("spec", ["t", "q=x", "t="])
def test_bad_columns_spec(spec: str) -> None:
    with pytest.raises(DataError, match="--columns"):
        parse_columns(spec)


def test_a_yaml_file_given_as_a_recording_is_named_as_such(tmp_path, repo_root) -> None:
    """A config or model file given where a recording belongs (the audit: `identify config/sim.yaml`) gets one
    line saying it is not a recording, not "missing required column 't'" over the YAML's first line."""
    import pytest

    from stagectl.errors import DataError
    from stagectl.ident.recording import load_recording

    for src in (repo_root / "config" / "sim.yaml", repo_root / "config" / "models" / "seed_gms.yaml"):
        if not src.exists():
            continue
        with pytest.raises(DataError) as ei:
            load_recording(src)
        assert "not a recording but YAML-like text" in str(ei.value) and "missing" not in str(ei.value)
    odd = tmp_path / "notes.txt"
    odd.write_text("# stagectl: a model\nfriction:\n  model: gms\n")
    with pytest.raises(DataError, match="not a recording"):
        load_recording(odd)


@pytest.mark.parametrize(("header", "columns", "fragments"), [
    # a column whose name gives a unit other than the canonical column's SI unit would be read 1000x off
    ("t,x_mm,u", "x=x_mm", ["'x_mm'", "mm", "x must be in m"]),
    ("t_ms,x,u", "t=t_ms", ["'t_ms'", "ms", "t must be in s"]),
    ("t,x,u_kN", "u=u_kN", ["'u_kN'", "kN", "u must be in N"]),
    ("t,x,current_A", "u=current_A", ["'current_A'", "A", "u must be in N"]),
    ("t,x [um],u", "x=x [um]", ["'x [um]'", "um", "x must be in m"]),
    ("t,x,u,v_mm_s", "v=v_mm_s", ["'v_mm_s'", "mm/s", "v must be in m/s"]),
])
def test_a_column_named_in_another_unit_is_refused(tmp_path: Path, header: str, columns: str,
                                                   fragments: list[str]) -> None:
    n = len(header.split(","))
    rows = "".join(",".join([f"{k * 1e-3:g}"] + ["0"] * (n - 1)) + "\n" for k in range(4))
    with pytest.raises(DataError) as err:
        load_recording(_write(tmp_path, header + "\n" + rows), columns)
    msg = str(err.value)
    assert "\n" not in msg
    for f in fragments:
        assert f in msg, (f, msg)


@pytest.mark.parametrize("header", ["t_s,position_m,force_N,reference_m", "time_s,x_m,u_n,x_ref_m"])
def test_si_unit_suffixes_are_accepted(tmp_path: Path, header: str) -> None:
    names = header.split(",")
    spec = ",".join(f"{k}={v}" for k, v in zip(("t", "x", "u", "x_ref"), names))
    dut = load_recording(_write(tmp_path, header + "\n0,0,1,0\n0.001,1e-6,2,0\n0.002,2e-6,3,0\n"), spec)
    np.testing.assert_allclose(dut.u, [1, 2, 3])


def test_a_duplicated_column_name_is_refused(tmp_path: Path) -> None:
    # which of the two 'u' columns is the force is ambiguous: never pick one silently
    with pytest.raises(DataError, match=r"column 'u' appears 2 times \(columns 3, 4\)"):
        load_recording(_write(tmp_path, "t,x,u,u\n0,0,1,9\n0.001,0,1,9\n0.002,0,1,9\n"))


def test_a_non_utf8_byte_is_named_by_its_line_and_file_offset(tmp_path: Path) -> None:
    p = tmp_path / "rec.csv"
    good = "".join(f"{k * 1e-3:.3f},0,0\n" for k in range(5000))
    p.write_bytes(("t,x,u\n" + good).encode() + b"0.5,\xff,0\n")
    with pytest.raises(DataError) as err:
        load_recording(p)
    offset = len(("t,x,u\n" + good).encode()) + 4
    assert f"line 5002: not UTF-8 text (invalid start byte at byte {offset})" in str(err.value)
    p.write_bytes(b"t,x,u\n0,0,0\n\xff\xfe\n")
    with pytest.raises(DataError, match=r"line 3: not UTF-8 text \(invalid start byte at byte 12\)"):
        load_recording(p)


def test_one_file_column_read_as_two_columns_is_refused(tmp_path: Path) -> None:
    # `--columns x=u`: the force read as the position too; the fit ran on it and wrote a model file
    with pytest.raises(DataError, match=r"column 'u' would be read as both x and u"):
        load_recording(_write(tmp_path, GOOD), "x=u")
