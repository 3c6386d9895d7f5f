"""Recordings: the one CSV format of stagectl (``docs/recordings.md``).

A recording is a CSV file with one header row, one row per control sample, SI units. Canonical columns:

==========  ====  ==========================================================
``t``       s     sample time, strictly increasing
``x``       m     measured position, sampled at ``t[k]``
``u``       N     force commanded to the drive; acts over ``[t[k], t[k+1])`` (zero-order hold)
``x_ref``   m     optional position reference
``v``       m/s   optional velocity estimate
==========  ====  ==========================================================

Other column names are mapped with ``columns={"t": "t_s", "x": "position_m", "u": "force_N"}`` (the CLI's
``--columns t=t_s,x=position_m,u=force_N``). Every problem raises :class:`~stagectl.errors.DataError`
naming the file, the row (1-based line number in the file, header = line 1) and the column.
"""

from __future__ import annotations

import csv
import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from stagectl.errors import DataError, cut, short

FloatArray = npt.NDArray[np.float64]

#: canonical column -> unit (for messages)
UNITS = {"t": "s", "x": "m", "u": "N", "x_ref": "m", "v": "m/s", "v_ref": "m/s", "a_ref": "m/s^2", "e": "m"}
#: canonical column -> the dimension its SI unit measures
_DIMENSION = {"t": "time", "x": "length", "u": "force", "x_ref": "length", "v": "velocity", "v_ref": "velocity",
              "a_ref": "acceleration", "e": "length"}
#: a unit a column name may end in (``x_mm``, ``x [mm]``, ``v_mm_s``), lower case -> (dimension, is SI); what is
#: not listed here is not taken for a unit (``position``, ``ref``)
_NAMED_UNITS = {
    **{u: ("length", u == "m") for u in ("m", "mm", "um", "µm", "nm", "cm", "in", "mil", "deg", "rad", "counts")},
    **{u: ("time", u == "s") for u in ("s", "ms", "us", "µs", "ns", "min")},
    **{u: ("force", u == "n") for u in ("n", "kn", "mn", "un", "kgf", "lbf", "a", "ma", "pct", "percent",
                                         "permille")},
    **{f"{u}/s": ("velocity", u == "m") for u in ("m", "mm", "um", "µm", "nm", "deg", "rad", "counts")},
    **{f"{u}/{s}": ("acceleration", u == "m") for u in ("m", "mm", "um") for s in ("s^2", "s2")},
}


def _named_unit(name: str) -> str | None:
    """The unit a column name ends in, as written (``x_mm`` -> ``mm``, ``v_mm_s`` -> ``mm/s``, ``x [um]`` ->
    ``um``), or None when its end is not a unit of :data:`_NAMED_UNITS`."""
    n = name.strip()
    if n.endswith(("]", ")")) and ("[" in n or "(" in n):
        unit = n[max(n.rfind("["), n.rfind("(")) + 1:-1].strip()
        return unit if unit.lower() in _NAMED_UNITS else None
    parts = n.replace(" ", "_").split("_")
    if len(parts) >= 3 and f"{parts[-2]}/{parts[-1]}".lower() in _NAMED_UNITS:
        return f"{parts[-2]}/{parts[-1]}"
    if len(parts) >= 2 and parts[-1].lower() in _NAMED_UNITS:
        return parts[-1]
    return None


def _unit_problem(p: Path, key: str, name: str) -> str | None:
    """A column read as ``key`` whose name says it is in another unit than ``key``'s SI unit: the values would
    be read 10^3 or 10^6 off (or as another quantity) without any other sign of it."""
    unit = _named_unit(name)
    if unit is None:
        return None
    dim, si = _NAMED_UNITS[unit.lower()]
    if dim == _DIMENSION.get(key) and si:
        return None
    what = f"in {unit} by its name" if dim == _DIMENSION.get(key) else f"a {dim} in {unit} by its name"
    return (f"{p}: column {short(name)} read as {key} is {what}; {key} must be in {UNITS[key]} "
            "(docs/recordings.md): convert the column to SI units, or rename it if its name is wrong")


def _utf8_problem(p: Path) -> str:
    """Where the first byte that is not UTF-8 sits: the file's line and byte offset (the text reader decodes in
    blocks, so its own error names neither)."""
    try:
        raw = p.read_bytes()
    except OSError as exc:
        return f"{p}: cannot read recording ({exc.strerror or exc})"
    start = 3 if raw.startswith(b"\xef\xbb\xbf") else 0
    try:
        raw[start:].decode("utf-8")
    except UnicodeDecodeError as exc:
        at = start + exc.start
        line = raw.count(b"\n", 0, at) + 1
        return (f"{p}: line {line}: not UTF-8 text ({exc.reason} at byte {at}); save the "
                "recording as UTF-8 CSV")
    return f"{p}: not UTF-8 text; save the recording as UTF-8 CSV"


REQUIRED = ("t", "x", "u")
OPTIONAL = ("x_ref", "v")


class RecordingCsv:
    """Header and rows of the recording CSV for ``columns`` (see the module docstring).

    Not real-time: formatting runs in the writer thread or after the run, never in the loop.
    """

    def __init__(self, columns: Sequence[str], float_format: str = "%.12g") -> None:
        """``float_format``: printf format of every value (``%.12g`` telemetry, ``%.10g`` run outputs)."""
        self.columns = tuple(columns)
        self.header = ",".join(self.columns) + "\n"
        self._row = ",".join([float_format] * len(self.columns)) + "\n"

    def rows(self, data: npt.NDArray[np.float64]) -> str:
        """``data`` (one row per sample, one column per name) as CSV lines."""
        fmt = self._row
        return "".join([fmt % tuple(r) for r in data.tolist()])

    def write(self, path: str | Path, data: npt.NDArray[np.float64]) -> Path:
        """Write a whole file (header + rows); returns its path."""
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        with open(p, "w", encoding="ascii", newline="") as fh:
            fh.write(self.header)
            fh.write(self.rows(data))
        return p


@dataclass
class Recording:
    """A loaded recording (arrays of equal length, SI units).

    Attributes
    ----------
    t, x, u : ndarray
        Time [s], measured position [m], commanded force [N] (zero-order hold over ``[t[k], t[k+1])``).
    x_ref, v : ndarray or None
        Optional reference position [m] and velocity estimate [m/s].
    source : str
        File name (or a description) for reports.
    extra : dict
        Any other numeric columns found (by their file name).
    """

    t: FloatArray
    x: FloatArray
    u: FloatArray
    x_ref: FloatArray | None = None
    v: FloatArray | None = None
    source: str = "<memory>"
    extra: dict[str, FloatArray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def dt_s(self) -> float:
        """Median sample period [s]."""
        return float(np.median(np.diff(self.t)))

    def slice(self, start: int, stop: int) -> Recording:
        """Samples ``start:stop`` as a new recording."""
        return Recording(
            self.t[start:stop].copy(),
            self.x[start:stop].copy(),
            self.u[start:stop].copy(),
            None if self.x_ref is None else self.x_ref[start:stop].copy(),
            None if self.v is None else self.v[start:stop].copy(),
            f"{self.source}[{start}:{stop}]",
            {k: v[start:stop].copy() for k, v in self.extra.items()},
        )

    def save_csv(self, path: str | Path) -> None:
        """Write the recording with canonical column names (full float precision)."""
        cols: dict[str, FloatArray] = {"t": self.t, "x": self.x, "u": self.u}
        if self.x_ref is not None:
            cols["x_ref"] = self.x_ref
        if self.v is not None:
            cols["v"] = self.v
        cols.update(self.extra)
        RecordingCsv(list(cols), "%.17g").write(path, np.column_stack(list(cols.values())))


def parse_columns(spec: str | None) -> dict[str, str]:
    """Parse ``"t=t_s,x=position_m,u=force_N"`` into ``{"t": "t_s", ...}``.

    Raises
    ------
    DataError
        Malformed entry or an unknown canonical name.
    """
    out: dict[str, str] = {}
    if not spec:
        return out
    for item in spec.split(","):
        item = item.strip()
        if not item:
            continue
        if "=" not in item:
            raise DataError(f"--columns: entry {short(item)} is not of the form canonical=file_column "
                            "(e.g. t=t_s)")
        key, _, name = item.partition("=")
        key, name = key.strip(), name.strip()
        if key not in UNITS:
            raise DataError(f"--columns: unknown canonical column {short(key)} (known: {', '.join(UNITS)})")
        if not name:
            raise DataError(f"--columns: empty file column name for {short(key)}")
        out[key] = name
    return out


def load_recording(
    path: str | Path,
    columns: Mapping[str, str] | str | None = None,
    min_rows: int = 3,
    required: Sequence[str] = REQUIRED,
) -> Recording:
    """Load and validate a recording CSV.

    Parameters
    ----------
    path : path
        CSV file with a header row.
    columns : mapping or str, optional
        Canonical name -> column name in the file (or the ``--columns`` string).
    min_rows : int
        Fewest data rows the calling analysis needs.
    required : sequence of str
        Canonical columns that must be present.

    Raises
    ------
    DataError
        Unreadable file, missing column, non-numeric cell, NaN/inf, time not strictly increasing, too few
        rows; the message names the file, the row (file line number) and the column.
    """
    p = Path(path)
    cmap = parse_columns(columns) if isinstance(columns, str) or columns is None else dict(columns)
    try:
        # utf-8-sig: spreadsheet exports start with a byte-order mark, which would otherwise become part of
        # the first column name
        fh = p.open(newline="", encoding="utf-8-sig")
    except OSError as exc:
        raise DataError(f"{p}: cannot open recording ({exc.strerror or exc})") from None
    with fh:
        reader = csv.reader(fh)
        try:
            header = next(reader)
        except StopIteration:
            raise DataError(f"{p}: empty file (expected a header row with columns {', '.join(required)})") from None
        except csv.Error as exc:
            raise DataError(f"{p}: line 1: malformed CSV ({exc})") from None
        except UnicodeDecodeError:
            raise DataError(_utf8_problem(p)) from None
        header = [h.strip() for h in header]
        first = header[0] if header else ""
        if (p.suffix.lower() in (".yaml", ".yml") or first.startswith("#")  # recordings have no comments
                or (len(header) == 1 and first.endswith(":"))):
            raise DataError(f"{p}: not a recording but YAML-like text (a config or model file?); a recording is a "
                            f"CSV whose header row names the columns {', '.join(required)} (docs/recordings.md)")
        if len(header) == 1:
            sep = next((c for c in (";", "\t", "|") if c in first), None)
            if sep is not None:  # a spreadsheet export with another separator: one column named 't;x;u'
                raise DataError(f"{p}: line 1: the header is one column, {cut(first, 60)!r}, split by "
                                f"{sep!r}: a recording separates its columns by ',' (docs/recordings.md); "
                                "export it as comma-separated, with '.' for decimals")
        index = {name: i for i, name in enumerate(header)}
        wanted: dict[str, str] = {}
        for key in (*required, *OPTIONAL):
            name = cmap.get(key, key)
            if name in index:
                wanted[key] = name
            elif key in required:
                hint = f" (mapped from {short(key)} by --columns)" if key in cmap else ""
                raise DataError(
                    f"{p}: missing required column {short(name)}{hint} [{UNITS.get(key, '')}]; "
                    f"header has: {cut(', '.join(header), 200)}"
                    + ("" if key in cmap else f"; map another name with --columns {key}=NAME")
                )
        for key, name in cmap.items():
            if key not in wanted and name not in index:
                raise DataError(f"{p}: column {short(name)} given for {short(key)} by --columns "
                                "is not in the header")
        for key, name in wanted.items():
            both = [k for k, n in wanted.items() if n == name]
            if len(both) > 1:
                raise DataError(f"{p}: column {short(name)} would be read as both {' and '.join(both)}; map each "
                                "canonical column to its own file column with --columns")
            at = [i + 1 for i, h in enumerate(header) if h == name]
            if len(at) > 1:  # csv would take the last: which one is meant cannot be known
                raise DataError(f"{p}: line 1: column {short(name)} appears {len(at)} times (columns "
                                f"{', '.join(map(str, at))}); each column of the header needs its own name")
            problem = _unit_problem(p, key, name)
            if problem is not None:
                raise DataError(problem)
        used = set(wanted.values())
        extra_names = [h for h in header if h and h not in used]
        fast = _read_fast(p, len(header))
        if fast is not None:  # all numeric and finite: the checks below on t still apply
            data = {k: np.ascontiguousarray(fast[:, index[wanted[k]]]) for k in wanted}
            extra_fast = {h: np.ascontiguousarray(fast[:, index[h]]) for h in extra_names}
            return _finish(p, data, wanted, extra_fast, fast.shape[0], min_rows)
        rows: list[list[float]] = []
        extra_rows: list[list[float]] = []
        extra_ok = {h: True for h in extra_names}
        order = list(wanted)
        cols_idx = [index[wanted[k]] for k in order]
        extra_idx = [index[h] for h in extra_names]
        line = 1
        try:
            for row in reader:
                line += 1
                if not row or all(not c.strip() for c in row):
                    continue
                if len(row) > len(header) and any(c.strip() for c in row[len(header):]):
                    # a decimal comma or a stray field shifts every later column: refuse, never misread
                    raise DataError(f"{p}: row {line}: {len(row)} values, the header has {len(header)} columns "
                                    "(a decimal comma? use '.' for decimals)")
                vals: list[float] = []
                for key, ci in zip(order, cols_idx):
                    if ci >= len(row):
                        raise DataError(f"{p}: row {line}, column {short(wanted[key])}: missing value "
                                        "(row too short)")
                    cell = row[ci].strip()
                    try:
                        val = float(cell)
                    except ValueError:
                        raise DataError(
                            f"{p}: row {line}, column {short(wanted[key])}: non-numeric value {short(cell)} "
                            f"(expected a number in {UNITS.get(key, 'SI units')})"
                        ) from None
                    if not math.isfinite(val):
                        raise DataError(f"{p}: row {line}, column {short(wanted[key])}: "
                                        f"{short(cell, 30)} is not a finite number "
                                        f"(expected a number in {UNITS.get(key, 'SI units')})")
                    vals.append(val)
                rows.append(vals)
                ev: list[float] = []
                for h, ci in zip(extra_names, extra_idx):
                    try:
                        ev.append(float(row[ci]) if ci < len(row) else math.nan)
                    except ValueError:
                        extra_ok[h] = False
                        ev.append(math.nan)
                extra_rows.append(ev)
        except csv.Error as exc:
            raise DataError(f"{p}: row {line + 1}: malformed CSV ({exc})") from None
        except UnicodeDecodeError:
            raise DataError(_utf8_problem(p)) from None
    n = len(rows)
    arr = np.asarray(rows, dtype=np.float64).reshape(n, len(order))
    data = {k: np.ascontiguousarray(arr[:, i]) for i, k in enumerate(order)}
    extra: dict[str, FloatArray] = {}
    if extra_rows:
        earr = np.asarray(extra_rows, dtype=np.float64)
        for j, h in enumerate(extra_names):
            if extra_ok[h] and np.all(np.isfinite(earr[:, j])):
                extra[h] = np.ascontiguousarray(earr[:, j])
    return _finish(p, data, wanted, extra, n, min_rows)


def _read_fast(p: Path, ncols: int) -> FloatArray | None:
    """The data rows as one float array when every cell is a finite number (numpy's C parser, several times
    faster than the row-by-row reader); None otherwise, and the careful reader then names the bad cell."""
    try:
        with warnings.catch_warnings():  # "input contained no data": the careful reader says it in one line
            warnings.simplefilter("ignore")
            arr = np.loadtxt(p, delimiter=",", dtype=np.float64, ndmin=2, skiprows=1, encoding="utf-8-sig")
    except (ValueError, IndexError, OSError, UnicodeDecodeError):
        return None
    if arr.ndim != 2 or arr.shape[1] != ncols or not np.all(np.isfinite(arr)):
        return None
    return np.asarray(arr, dtype=np.float64)


def _finish(p: Path, data: dict[str, FloatArray], wanted: dict[str, str], extra: dict[str, FloatArray], n: int,
            min_rows: int) -> Recording:
    if n < min_rows:
        raise DataError(f"{p}: {n} data rows, this analysis needs at least {min_rows}")
    t = data["t"]
    dt = np.diff(t)
    bad = np.flatnonzero(~(dt > 0))
    if bad.size:
        k = int(bad[0]) + 1
        # line numbers: data row k is on line k + 2 when no blank lines were skipped (header = line 1)
        raise DataError(
            f"{p}: row {k + 2}, column {short(wanted['t'])}: time not strictly increasing "
            f"({t[k]:.9g} s after {t[k - 1]:.9g} s)"
        )
    return Recording(
        t=t,
        x=data["x"],
        u=data["u"],
        x_ref=data.get("x_ref"),
        v=data.get("v"),
        source=str(p),
        extra=extra,
    )
