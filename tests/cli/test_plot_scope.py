"""`stagectl plot`, the unit helpers, the telemetry stream behind `stagectl scope`, and the scope's views."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stagectl.cli import main
from stagectl.commands.scope import ScopeData, make_app
from stagectl.daemon.stream import TelemetryStream, parse_subscribe
from stagectl.outputs import prefix_for, si
from stagectl.runtime.requests import RequestError

COLUMNS = ("t", "x", "u", "x_ref", "v_ref", "a_ref", "e", "v", "u_pid", "u_dob", "u_ff", "u_inertia")


def _rows(first: int, n: int) -> np.ndarray:
    i = np.arange(first, first + n, dtype=np.float64)
    rows = np.zeros((n, len(COLUMNS)))
    rows[:, 0] = i * 1e-3
    rows[:, 1] = 5e-6 * np.sin(i * 1e-2)
    rows[:, 6] = 3e-9 * np.cos(i * 1e-2)
    rows[:, 2] = 0.5
    return rows


@pytest.mark.parametrize(("value", "unit", "text"), [
    (1.2345e-6, "m", "1.2345 µm"), (-2e-9, "m", "-2.0000 nm"), (0.012, "m", "12.0000 mm"), (3.0, "m", "3.0000 m"),
    (0.5, "N", "0.5000 N"), (2e-4, "N", "200.0000 µN"), (0.0, "m", "0.0000 nm"),
])
def test_si_prefix_suits_the_value(value: float, unit: str, text: str) -> None:
    assert si(value, unit) == text
    assert prefix_for(5e-7, "m") == (pytest.approx(1e9), "nm")


def test_plot_draws_any_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    csv = tmp_path / "rec.csv"
    data = np.column_stack([np.arange(200) * 1e-3, np.linspace(0, 1e-6, 200), np.ones(200), np.zeros(200)])
    np.savetxt(csv, data, delimiter=",", header="t,x,u,temperature_c", comments="", fmt="%.10g")
    assert main(["plot", str(csv)]) == 0
    png = tmp_path / "rec.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    assert main(["plot", str(csv), "--out", str(tmp_path / "missing" / "x.png")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_stream_cursor_decimation_and_loss() -> None:
    s = TelemetryStream(COLUMNS, capacity=1000)
    s(0, _rows(0, 600))
    first = s.read(None, every=10, signals=["t", "x"], max_rows=20)
    assert first["columns"] == ["t", "x"] and len(first["rows"]) == 20 and first["lost"] == 0
    assert first["rows"][-1][0] == pytest.approx(0.590)  # the newest multiple of 10 below 600
    assert first["next"] == 600
    s(600, _rows(600, 100))
    nxt = s.read(first["next"], every=10, signals=["t"])
    assert [r[0] for r in nxt["rows"]] == pytest.approx([i * 1e-3 for i in range(600, 700, 10)])
    # a client that falls behind by more than the capacity is told how much it lost, never given stale rows
    s(700, _rows(700, 1500))
    late = s.read(nxt["next"], every=1, signals=["t"], max_rows=2000)
    assert late["lost"] == 2200 - 700 - 1000 and late["rows"][0][0] == pytest.approx(1.2)
    # a gap in the writer's indices shows as lost rows too
    s(2300, _rows(2300, 10))
    gap = s.read(2195, every=1, signals=["t"])
    assert gap["lost"] == 100 and len(gap["rows"]) == 15


def test_subscribe_request_fields_are_checked() -> None:
    assert parse_subscribe({"request": "subscribe"}, COLUMNS) == (None, 1, list(COLUMNS))
    for bad, field in (({"since": -1}, "since"), ({"since": True}, "since"), ({"every": 0}, "every"),
                       ({"signals": ["nope"]}, "signals"), ({"signals": "x"}, "signals")):
        with pytest.raises(RequestError) as exc:
            parse_subscribe({"request": "subscribe", **bad}, COLUMNS)
        assert exc.value.field == field


def _filled() -> ScopeData:
    data = ScopeData(window_s=0.5)
    s = TelemetryStream(COLUMNS)
    s(0, _rows(0, 1000))
    data.add(s.read(None, every=5))
    data.set_status({"state": "active", "drive_enabled": True,
                     "loop": {"state": "active", "cycle": 1000, "overruns": 3, "lateness_us": {"p99": 42.0},
                              "fault": {"name": "following_error", "cause": "e 2 µm > 1 µm", "t_s": 0.9}}})
    return data


def test_scope_text_frame_units_window_and_faults() -> None:
    data = _filled()
    t = data.series("t")
    assert t[-1] - t[0] <= 0.5 + 1e-9  # the window
    frame = data.text_frame(width=80, height=32)
    assert "[µm]" in frame and "[nm]" in frame and "[N]" in frame  # each axis in its own unit
    assert "following_error" in frame and "lateness p99 42 µs" in frame and "drive enabled" in frame


def test_scope_app_headless() -> None:
    """Textual's own headless driver: the app mounts, polls, draws and quits on 'q'."""
    import asyncio

    data = _filled()
    polls: list[int] = []

    async def drive() -> None:
        app = make_app(data, lambda: polls.append(1), rate_hz=50.0)
        async with app.run_test(size=(120, 40)) as pilot:
            for _ in range(500):  # the poll runs in a worker thread: wait for it, not for a fixed time
                await pilot.pause(0.01)
                if polls:
                    break
            header = str(app.query_one("#header").render())
            assert "cycle 1000" in header and "FAULT following_error" in header
            assert "following_error" in str(app.query_one("#faults").render())
            await pilot.press("space")
            assert app.paused  # type: ignore[attr-defined]
            await pilot.press("q")
        assert polls

    asyncio.run(drive())


def test_scope_keys_work_while_a_poll_hangs() -> None:
    """A daemon that does not answer (a poll blocked until its socket timeout) must not freeze the view: the
    poll runs in a worker thread, so 'space' and 'q' are handled while it hangs."""
    import asyncio
    import threading

    data = _filled()
    entered, release = threading.Event(), threading.Event()
    timed_out: list[bool] = []

    def hanging_poll() -> None:
        entered.set()
        if not release.is_set():
            timed_out.append(not release.wait(10.0))  # released by the test only if its keys got through

    async def drive() -> bool:
        app = make_app(data, hanging_poll, rate_hz=50.0)
        try:
            async with app.run_test(size=(120, 40)) as pilot:
                for _ in range(500):
                    await pilot.pause(0.01)
                    if entered.is_set():
                        break
                assert entered.is_set()
                await pilot.press("space")
                paused = bool(app.paused)  # type: ignore[attr-defined]
                release.set()
                await pilot.press("q")
            return paused
        finally:
            release.set()

    assert asyncio.run(drive())
    assert timed_out == [False]


def test_an_all_nan_column_is_drawn_without_a_warning(tmp_path: Path) -> None:
    """`simulate --ilc` on a motion that never completes a repetition records ilc_rms_m as nan throughout; its
    plot printed numpy's 'RuntimeWarning: All-NaN slice encountered' under the command's output (audit16)."""
    import warnings

    from stagectl.plots import plot_recording

    n = 100
    data = np.column_stack([np.arange(n) * 1e-3, np.zeros(n), np.zeros(n), np.full(n, np.nan)])
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        png = plot_recording(("t", "x", "u", "ilc_rms_m"), data, tmp_path / "rec.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not [w for w in seen if issubclass(w.category, RuntimeWarning)], [str(w.message) for w in seen]
