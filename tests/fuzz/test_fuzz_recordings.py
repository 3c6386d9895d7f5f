"""Fuzz the recordings reader of ``identify``/``discover`` (:func:`stagectl.ident.recording.load_recording`) and
the physical range check that runs before any fit (:func:`stagectl.ident.signals.check_ranges`).

Invariant: a :class:`~stagectl.ident.recording.Recording` with finite, strictly increasing time, or one
:class:`~stagectl.errors.DataError` line (no newline, bounded length, naming the file); nothing else escapes.
Inputs: CSV text built from hostile cells (huge, tiny, NaN, inf, text, quotes, empty, 1e300, 1e-300 time
steps) under a valid or damaged header, and raw bytes (BOM, non-UTF-8, NUL, over-long fields).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from stagectl.errors import DataError
from stagectl.ident.recording import load_recording
from stagectl.ident.signals import check_ranges

sys.path.insert(0, str(Path(__file__).parent))
from fuzzing import fuzz  # noqa: E402

CELLS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["1e300", "-1e300", "1e-300", "0", "-0", "nan", "inf", "-inf", "", " ", "abc", '"1"', '"',
                     "1,2", "0x10", "1e999", "9" * 400, "1_000", "١", "\x00", "1.0\r", "+.5"]),
    st.integers(-(10**20), 10**20).map(str),
    st.text(max_size=8),
)
HEADERS = st.sampled_from([
    ["t", "x", "u"], ["t", "x", "u", "x_ref", "v"], ["t_s", "position_m", "force_N"], ["t", "x"], ["t", "t", "x", "u"],
    ["\ufefft", "x", "u"], [" t ", "x ", " u"], [], ["t", "x", "u", ""],
])


def _check(path: Path, columns: str | None) -> None:
    try:
        rec = load_recording(path, columns, min_rows=2)
    except DataError as exc:
        msg = str(exc)
        assert "\n" not in msg and len(msg) < 1500 and str(path) in msg, msg[:300]
        return
    assert rec.t.size >= 2 and np.all(np.isfinite(rec.t)) and np.all(np.diff(rec.t) > 0)
    assert np.all(np.isfinite(rec.x)) and np.all(np.isfinite(rec.u))
    try:
        check_ranges(rec)
    except DataError as exc:
        assert "\n" not in str(exc) and "outside" in str(exc)


@fuzz(150)
@given(HEADERS, st.lists(st.lists(CELLS, min_size=0, max_size=6), min_size=0, max_size=8),
       st.sampled_from([None, "t=t_s,x=position_m,u=force_N"]))
def test_csv_from_hostile_cells(header: list[str], rows: list[list[str]], columns: str | None) -> None:
    text = "\n".join([",".join(header), *(",".join(r) for r in rows)]) + "\n"
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "rec.csv"
        p.write_bytes(text.encode("utf-8", "replace"))  # lone surrogates from st.text() become '?'
        _check(p, columns)


@fuzz(150)
@given(st.lists(st.floats(1e-300, 1e300) | st.sampled_from([1e-300, 1e300, 5e-324, 1.7e308]), min_size=3,
                max_size=12),
       st.sampled_from([0.0, 1e300, -1e300, 1e-300, 1e12, 1e9]))
def test_extreme_but_valid_numbers(steps: list[float], level: float) -> None:
    """Valid CSV, strictly increasing time, finite values at the edges of float64: the reader takes it or names
    the problem; the range check then refuses what no stage can have produced."""
    with np.errstate(over="ignore"):
        t = np.cumsum(steps)  # may reach inf: then the reader must name the non-finite time
    n = t.size
    x = np.full(n, level) + np.arange(n) * 1e-9
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "rec.csv"
        np.savetxt(p, np.column_stack([t, x, np.full(n, level)]), delimiter=",", header="t,x,u", comments="",
                   fmt="%.17g")
        _check(p, None)


@fuzz(100)
@given(st.binary(max_size=400), st.sampled_from([b"", b"\xef\xbb\xbf", b"t,x,u\n", b"t,x,u\r\n0,0,0\r\n"]))
def test_raw_bytes(data: bytes, lead: bytes) -> None:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "rec.csv"
        p.write_bytes(lead + data)
        _check(p, None)


def test_over_long_field_is_one_line() -> None:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "rec.csv"
        p.write_text("t,x,u\n0,0,0\n1," + "7" * 300_000 + ",0\n2,0,0\n")
        _check(p, None)
