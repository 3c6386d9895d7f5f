"""`stagectl scope` against the daemon on the simulated stage: the ``subscribe`` request through the real
control socket, and the Textual view driven headless by Textual's own test driver (``App.run_test``)."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from stagectl.commands.scope import ScopeData, make_app, socket_poller
from stagectl.daemon.control import ControlClient
from stagectl.daemon.stream import LoopTap

sys.path.insert(0, str(Path(__file__).parent))
from support import stagectl_cmd  # noqa: E402
from test_end_to_end import _config  # noqa: E402


def test_loop_tap_hands_over_every_row_once_and_drops_what_was_overwritten():
    tap = LoopTap(["t", "x"], capacity=64)
    for k in range(10):
        tap.append((k * 1e-3, float(k)))
    first, rows = tap.take()
    assert first == 0 and [r[1] for r in rows] == list(range(10))
    assert tap.take()[1].shape[0] == 0  # nothing new
    for k in range(10, 300):  # the consumer falls behind by more than the tap holds
        tap.append((k * 1e-3, float(k)))
    first, rows = tap.take()
    assert first > 10 and rows[0][1] == first and rows[-1][1] == 299  # the newest rows, contiguous
    tap.append(("bad",))  # a malformed row is skipped, never raised into the loop
    assert tap.take()[1].shape[0] == 0


@pytest.fixture
def daemon_socket(tmp_path, notify_socket):
    cfg = _config(tmp_path)
    # the stream is fed from the telemetry writer's drains, every flush_interval_s: the default 0.2 s here, not
    # the end-to-end tests' 10 s (the move waited up to 10 s of wall clock for the writer, the daemon cycling)
    doc = yaml.safe_load(cfg.read_text())
    doc["daemon"]["telemetry"]["flush_interval_s"] = 0.2
    cfg.write_text(yaml.safe_dump(doc))
    run = tmp_path / "run"
    env = {**os.environ, "NOTIFY_SOCKET": str(notify_socket.path), "PYTHONUNBUFFERED": "1"}
    env.pop("WATCHDOG_PID", None)
    env.pop("WATCHDOG_USEC", None)
    proc = subprocess.Popen([*stagectl_cmd(), "daemon", "--config", str(cfg), "--runtime-dir", str(run)],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        notify_socket.wait_for("READY", "1", timeout=120, alive=lambda: proc.poll() is None)
        yield str(run / "control.sock")
    finally:
        proc.terminate()
        proc.wait(30)


def test_scope_shows_a_move_of_the_simulated_stage(daemon_socket):
    with ControlClient(daemon_socket, timeout_s=10) as c:
        bad = c.request({"request": "subscribe", "signals": ["nope"]})
        assert not bad["ok"] and bad["error"].startswith("signals: unknown 'nope'")
        bad = c.request({"request": "subscribe", "every": 0})
        assert not bad["ok"] and bad["error"].startswith("every:")
        bad = c.request({"request": "subscribe", "extra": 1})
        assert not bad["ok"] and bad["error"].startswith("extra:")
        first = c.request({"request": "subscribe", "signals": ["t", "x", "u_ff"], "every": 2})
        assert first["ok"] and first["columns"] == ["t", "x", "u_ff"]

    data = ScopeData(window_s=5.0)
    with ControlClient(daemon_socket, timeout_s=10) as client:
        poll = socket_poller(client, data, every=5)

        async def drive() -> tuple[str, str]:
            app = make_app(data, poll, rate_hz=20.0)
            async with app.run_test(size=(120, 40)) as pilot:
                with ControlClient(daemon_socket, timeout_s=10) as mover:  # the scope's client is its worker's
                    assert mover.request({"request": "move", "relative_m": 1e-5})["ok"]
                # wait on the stream itself (simulated stage, real socket), not on a fixed time
                for _ in range(3000):
                    await pilot.pause(0.02)
                    x = data.series("x")
                    if x and max(x) > 9e-6:
                        break
                await pilot.press("space")
                assert app.paused  # type: ignore[attr-defined]
                await pilot.press("space")
                values = str(app.query_one("#values").render())
                header = str(app.query_one("#header").render())
                await pilot.press("q")
            return values, header

        values, header = asyncio.run(drive())
    assert max(data.series("x")) > 9e-6, "the move never reached the scope"
    assert "NO DATA" not in header and "cycle" in header, header
    assert "µm" in values or "nm" in values, values
    ts = data.series("t")
    assert all(b > a for a, b in zip(ts, ts[1:])), "rows arrive in order, without repeats"
    # the command a user types (README quick start): `stagectl scope --once`, one text frame, as a real process
    p = subprocess.run([*stagectl_cmd(), "scope", "--once", "--socket", daemon_socket], capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    frame = p.stdout
    assert frame.startswith("daemon active") and "drive enabled" in frame, frame[:300]
    for panel in ("position [", "tracking error [", "force [", "velocity ["):
        assert panel in frame, (panel, frame[:2000])
    assert "faults: none" in frame and "Traceback" not in p.stderr
    # `stagectl scope --once | head -1`: the reader of stdout went away, not the daemon; it said
    # "control.sock: [Errno 32] Broken pipe" and exit 2
    q = subprocess.Popen([*stagectl_cmd(), "scope", "--once", "--socket", daemon_socket], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    assert q.stdout is not None
    q.stdout.close()  # no reader: every write to stdout fails with EPIPE
    _, err = q.communicate(timeout=120)
    assert q.returncode == 0 and err == "", (q.returncode, err)
