"""The recording CSV format, and the in-memory recorder for ``simulate``/``run``/benchmarks.

:class:`~stagectl.ident.recording.RecordingCsv` (next to the reader of the format) is the one writer of the
recording format (docs/recordings.md): one header row with the loop's column names, ``,`` separator, one row
per control sample, SI units. The daemon's telemetry writer (continuous files and named recordings,
``%.12g``), :meth:`Recorder.write_csv` (``simulate``, ``run``, benchmarks, ``%.10g``) and
:meth:`~stagectl.ident.recording.Recording.save_csv` (``%.17g``) all use it, so every file feeds
``stagectl identify`` unchanged.

:class:`Recorder` is a loop sink (``append(row)``) writing into a preallocated float64 array; a run longer than
announced (``stagectl run`` without ``--duration`` past 600 s) goes on in new blocks of
:attr:`Recorder.block_rows` rows, joined once when the rows are read. (It doubled the array in the loop thread:
at 600 s a 1.2 M-row copy that took 1.5 s of one cycle at load 7.) Afterwards:

* :meth:`Recorder.write_csv` — one header row, one row per control sample, SI units, columns as the
  loop's (``t`` s, ``x`` m, ``u`` N, ``x_ref`` m, ``v_ref`` m/s, ``a_ref`` m/s², ``e`` m, ``v`` m/s, terms N);
* :func:`tracking_summary` — RMS and max tracking error, settling time of each point-to-point move;
* :func:`plot_run` — PNGs of position/reference, error and force terms.

Settling time of a move: with the reference at rest after moving (v_ref = a_ref = 0 from sample i₀ on,
until it moves again at i₁), the time from i₀ until |e| enters and then stays within ±``tol_m`` for the
rest of [i₀, i₁). ``None`` when it never settles within that rest interval.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from stagectl.errors import StageError
from stagectl.ident.recording import RecordingCsv
from stagectl.plots import plot_recording

__all__ = ["Recorder", "hold_report", "plot_run", "tracking_summary", "write_outputs"]


class Recorder:
    """A telemetry sink keeping every row in memory (loop thread only while running)."""

    #: rows of each block added once the announced capacity is full (65536 × 18 columns: 9.4 MB, allocated
    #: zeroed by the OS page by page as rows are written, never copied while the loop runs)
    block_rows = 65536

    def __init__(self, columns: Sequence[str], capacity: int = 1024) -> None:
        self.columns = tuple(columns)
        self._data = np.zeros((max(16, int(capacity)), len(self.columns)))
        self._full: list[np.ndarray] = []  # filled blocks before _data, in order
        self._base = 0  # rows held in _full
        self.n = 0

    @classmethod
    def of(cls, columns: Sequence[str], rows: npt.ArrayLike) -> Recorder:
        """A recording holding ``rows`` (one row per sample, one column per name in ``columns``) at once."""
        data = np.asarray(rows, dtype=float).reshape(-1, len(columns))
        rec = cls(columns, capacity=data.shape[0])
        rec._data[: data.shape[0]] = data
        rec.n = data.shape[0]
        return rec

    def append(self, row: tuple[float, ...]) -> None:
        i = self.n - self._base
        if i >= self._data.shape[0]:  # longer than announced: a new block, the rows so far stay where they are
            self._full.append(self._data)
            self._base += self._data.shape[0]
            self._data = np.zeros((self.block_rows, len(self.columns)))
            i = 0
        self._data[i] = row
        self.n += 1

    def _rows(self) -> np.ndarray:
        """Every row in one array (the blocks joined once, after the run; not from the loop thread)."""
        if self._full:
            self._data = np.concatenate([*self._full, self._data[: self.n - self._base]])
            self._full, self._base = [], 0
        return self._data

    @property
    def data(self) -> np.ndarray:
        return self._rows()[: self.n]

    def col(self, name: str) -> np.ndarray:
        return self._rows()[: self.n, self.columns.index(name)]

    def write_csv(self, path: str | Path) -> Path:
        """The recording as CSV (:class:`RecordingCsv`); returns the path."""
        return RecordingCsv(self.columns, "%.10g").write(path, self.data)


def _rest_intervals(v_ref: np.ndarray, a_ref: np.ndarray) -> list[tuple[int, int]]:
    """[i0, i1) intervals where the reference is at rest *after having moved*."""
    moving = (v_ref != 0.0) | (a_ref != 0.0)
    out: list[tuple[int, int]] = []
    n = moving.size
    i = 0
    seen_motion = False
    while i < n:
        if moving[i]:
            seen_motion = True
            i += 1
            continue
        j = i
        while j < n and not moving[j]:
            j += 1
        if seen_motion:
            out.append((i, j))
        i = j
    return out


def tracking_summary(rec: Recorder, *, tol_m: float = 10e-9, skip_s: float = 0.0) -> dict[str, Any]:
    """Tracking-error figures of a recording (errors in m, times in s).

    ``skip_s`` excludes the first seconds from RMS/max (start-up transient).

    With a ``stale`` column (the loop's telemetry) it adds ``stale_fraction`` and ``measured_rms_error_m`` /
    ``measured_max_error_m``: the same over the rows with a fresh sample only. A stale row records the last
    sample's position held (or an old one), so on a moving stage its ``e`` grows by v·(rows since the sample)
    though nothing was measured (a HIL drive held off the CPU for 5 ms at 2 mm/s: 10 µm that the next sample
    shows was never there).

    Per move (each interval [i₀, i₁) where the reference rests after having moved), two settle figures that
    answer different questions:

    * ``settling_time_s``: t_k − t_i₀ for the first sample k from which |e| ≤ ``tol_m`` up to the end of the
      rest (the next move or the end of the recording); 0.0 if never outside; ``None`` if the last sample at
      rest is outside (it had not settled *for good*).
    * ``in_position_after_s`` (with an ``in_position`` column, the controller's detector with its own window
      ``controller.settle.tolerance_m`` and dwell ``dwell_s``): t − t_i₀ when the detector *first* declared
      in position, i.e. what a sequencer waiting for in-position would have seen, even if it withdrew it later;
      ``None`` if it never did. ``in_position_lost`` counts those withdrawals in the rest interval.

    With the same band and a stage that stays inside, in_position_after_s = settling_time_s + dwell (to one
    sample). A stage whose rest error hovers around the band gives an early in_position_after_s, in_position_lost
    ≥ 1 and a late or ``None`` settling_time_s.
    """
    t = rec.col("t")
    e = rec.col("e")
    out: dict[str, Any] = {"samples": int(rec.n), "duration_s": float(t[-1] - t[0]) if rec.n else 0.0}
    sel = t >= (t[0] + skip_s) if rec.n else np.zeros(0, bool)
    es = e[sel]
    out["rms_error_m"] = float(np.sqrt(np.mean(es * es))) if es.size else math.nan
    out["max_error_m"] = float(np.max(np.abs(es))) if es.size else math.nan
    if "stale" in rec.columns and rec.n:
        stale = rec.col("stale")[sel] > 0.5
        em = es[~stale]
        out["stale_fraction"] = float(np.mean(stale)) if stale.size else 0.0
        out["measured_rms_error_m"] = float(np.sqrt(np.mean(em * em))) if em.size else math.nan
        out["measured_max_error_m"] = float(np.max(np.abs(em))) if em.size else math.nan
    if "u" in rec.columns and rec.n:
        u = rec.col("u")
        out["rms_force_n"] = float(np.sqrt(np.mean(u[sel] ** 2)))
        out["max_force_n"] = float(np.max(np.abs(u[sel])))
    settle: list[float | None] = []
    if rec.n and "v_ref" in rec.columns and "a_ref" in rec.columns:
        for i0, i1 in _rest_intervals(rec.col("v_ref"), rec.col("a_ref")):
            outside = np.nonzero(np.abs(e[i0:i1]) > tol_m)[0]
            if outside.size == 0:
                settle.append(0.0)
            elif outside[-1] == i1 - i0 - 1:
                settle.append(None)
            else:
                k = i0 + outside[-1] + 1
                settle.append(float(t[k] - t[i0]))
    done = [s for s in settle if s is not None]
    if rec.n and "in_position" in rec.columns and "v_ref" in rec.columns and "a_ref" in rec.columns:
        ip = rec.col("in_position") > 0.5
        first: list[float | None] = []
        lost: list[int] = []
        for i0, i1 in _rest_intervals(rec.col("v_ref"), rec.col("a_ref")):
            on = np.nonzero(ip[i0:i1])[0]
            first.append(float(t[i0 + on[0]] - t[i0]) if on.size else None)
            lost.append(int(np.count_nonzero(ip[i0:i1 - 1] & ~ip[i0 + 1:i1])))
        out["in_position_after_s"] = first
        out["in_position_lost"] = lost
    out["settling_tolerance_m"] = tol_m
    out["moves"] = len(settle)
    out["moves_settled"] = len(done)
    out["settling_time_s"] = settle
    out["settling_time_max_s"] = (max(done) if len(done) == len(settle) else None) if settle else None
    out["settling_time_mean_s"] = float(np.mean(done)) if done else None
    return out


def hold_report(rec: Recorder, *, tol_m: float = 10e-9, window_s: float = 0.03) -> list[dict[str, Any]]:
    """Per point-to-point move (rest interval after motion): settling and hold behaviour.

    For the rest interval [i₀, i₁) after each move: ``settle_s`` (as in :func:`tracking_summary`: from the end of
    the commanded move until |e| enters ±``tol_m`` and stays there for the rest of the interval; None if it
    does not), ``hold_excursion_m`` (max |e| after ``window_s`` from the end of the move), ``late_excursion_m``
    (max |e| in the second half of the hold: what is left once settling is over), ``hold_s`` (length of the
    interval) and ``limit_cycle``: the error still leaves the band in the second half of the hold *and*
    changes sign there outside the band at least twice (a friction limit cycle hunts around the target; a
    slow one-sided creep does not count as one, it shows as an unsettled move with its excursion).
    """
    out: list[dict[str, Any]] = []
    if not rec.n or "v_ref" not in rec.columns or "a_ref" not in rec.columns:
        return out
    t = rec.col("t")
    e = rec.col("e")
    for i0, i1 in _rest_intervals(rec.col("v_ref"), rec.col("a_ref")):
        seg = e[i0:i1]
        outside = np.nonzero(np.abs(seg) > tol_m)[0]
        if outside.size == 0:
            settle: float | None = 0.0
        elif outside[-1] == i1 - i0 - 1:
            settle = None
        else:
            settle = float(t[i0 + outside[-1] + 1] - t[i0])
        j0 = i0 + int(np.searchsorted(t[i0:i1] - t[i0], window_s - 1e-12))
        exc = float(np.max(np.abs(e[j0:i1]))) if j0 < i1 else 0.0
        late = e[(i0 + i1) // 2:i1]
        big = late[np.abs(late) > tol_m]
        flips = int(np.count_nonzero(np.diff(np.sign(big)) != 0)) if big.size > 1 else 0
        out.append({"settle_s": settle, "hold_excursion_m": exc, "hold_s": float(t[i1 - 1] - t[i0]),
                    "late_excursion_m": float(np.max(np.abs(late))) if late.size else 0.0,
                    "limit_cycle": bool(big.size and flips >= 2)})
    return out


def plot_run(rec: Recorder, out_dir: str | Path, title: str = "") -> list[Path]:
    """Write ``tracking.png`` (position and reference, error, force and its terms, velocity; see
    :func:`stagectl.plots.plot_recording`) into ``out_dir``; returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return [plot_recording(rec.columns, rec.data, out / "tracking.png", title)]


def write_outputs(rec: Recorder, out_dir: str | Path, summary: dict[str, Any], *, plots: bool = True,
                  title: str = "") -> dict[str, str]:
    """CSV + summary.json (+ PNG) into ``out_dir``; returns the written paths by kind."""

    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
        files = {"csv": str(rec.write_csv(out / "telemetry.csv"))}
        sp = out / "summary.json"
        files["summary"] = str(sp)
        if plots and rec.n > 1:
            files["plots"] = ",".join(str(p) for p in plot_run(rec, out, title))
        summary = {**summary, "files": files}
        sp.write_text(json.dumps(summary, indent=2, default=_json_default) + "\n", encoding="utf-8")
    except OSError as exc:
        raise StageError(f"--out: writing the results to {str(out)!r} failed ({exc.strerror or exc})") from None
    return files


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    return str(o)
