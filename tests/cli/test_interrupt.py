"""Ctrl-C: a real SIGINT to a real `stagectl` process. It says so in one line and exits 130. simulate keeps
what it had simulated (telemetry and a summary marked interrupted); identify, discover and bench leave no
output (no model file, no empty output directory, no partial result). No wall-clock sleep: the test waits
for the process's own progress line before it sends the signal."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from support import run_on_pty

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(("sig", "code", "name"), [(signal.SIGINT, 130, "Ctrl-C"), (signal.SIGTERM, 143, "SIGTERM")],
                         ids=["ctrl-c", "sigterm"])
def test_an_interrupt_in_simulate_keeps_what_was_simulated(tmp_path: Path, sig, code, name) -> None:
    """Ctrl-C exits 130, SIGTERM (audit16) 143; both keep every simulated row, marked interrupted."""
    out = tmp_path / "run"
    script = Path(sys.executable).with_name("stagectl")
    p = subprocess.Popen([str(script), "simulate", "--config", "config/sim.yaml", "--scenario", "cosine",
                          "--duration", "600", "--out", str(out), "--no-plots"], cwd=REPO, text=True,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**os.environ, "STAGECTL_TRACEBACK": ""},
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # see run_on_pty
    try:
        assert p.stderr is not None
        first = p.stderr.readline()  # the first progress line: the loop is running
        assert first.startswith("simulate: "), first
        p.send_signal(sig)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == code, err
    assert f"stagectl: interrupted ({name})" in err and "Traceback" not in err, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] is True and summary["samples"] > 100
    rows = (out / "telemetry.csv").read_text().splitlines()
    assert len(rows) == summary["samples"] + 1  # header + every simulated row


def _long_recording(tmp: Path) -> Path:
    """30 s of a 0.5 Hz, ±1 mm sine (1 nm encoder) against Coulomb + viscous friction: a hsieh fit or a
    discovery on it runs for many seconds, so the SIGINT lands mid-work."""
    t = np.arange(0.0, 30.0, 1e-3)
    x = np.round(1e-3 * np.sin(2 * np.pi * 0.5 * t) / 1e-9) * 1e-9
    v = np.gradient(x, t)
    u = 0.8 * np.tanh(v / 2e-4) + 50.0 * v + 2.0 * np.gradient(v, t)
    p = tmp / "long.csv"
    np.savetxt(p, np.column_stack([t, x, u, x]), delimiter=",", header="t,x,u,x_ref", comments="", fmt="%.10g")
    return p


def test_ctrl_c_in_identify_says_so_and_writes_nothing(tmp_path: Path) -> None:
    """On a terminal the fit's line names the stage; Ctrl-C during it: one line, exit 130, no model file and
    no plot directory left behind (it was created up front, to check it is writable)."""
    rec = _long_recording(tmp_path)
    rc, err = run_on_pty(["identify", str(rec), "--model", "hsieh", "--out", str(tmp_path / "m.yaml"),
                          "--plot", str(tmp_path / "plots")], interrupt_on="joint least squares by simulation")
    assert "identify: hsieh: fit 1 of " in err and "\r\x1b[K" in err, err
    assert rc == 130, err
    assert err.rstrip().endswith("stagectl: interrupted (Ctrl-C); no output was written") and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["long.csv"]


def test_ctrl_c_in_discover_says_so_and_leaves_no_empty_report_dir(tmp_path: Path) -> None:
    rec = _long_recording(tmp_path)
    rc, err = run_on_pty(["discover", str(rec), "--out", str(tmp_path / "d" / "report")],
                         interrupt_on="round 1, candidate")
    assert rc == 130, err
    assert err.rstrip().endswith("stagectl: interrupted (Ctrl-C); no output was written") and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["long.csv"]  # d/ was created by the run: gone too


def test_ctrl_c_in_bench_says_so_and_prints_no_partial_result(tmp_path: Path) -> None:
    with open(tmp_path / "stdout", "w") as out:
        rc, err = run_on_pty(["bench", "timing"], interrupt_on="case 1 of ", cwd=REPO, stdout=out)
    assert rc == 130, err
    assert re.search(r"bench timing: case 1 of \d+, canopen/cosine clean \(", err), err  # its plan, on the terminal line
    assert err.rstrip().endswith("stagectl: interrupted (Ctrl-C)") and "Traceback" not in err, err
    assert (tmp_path / "stdout").read_text() == ""


@pytest.mark.parametrize("raised", ["ImportError('cannot import name Stage from partially initialized module')",
                                    "DriverInitError('drive: SDO 0x6041 timed out')",
                                    "OSError(5, 'Input/output error')"])
def test_ctrl_c_that_surfaces_as_another_exception_still_ends_as_an_interrupt(tmp_path: Path, raised: str) -> None:
    """A SIGINT can land where Python turns its KeyboardInterrupt into another exception on the way out (half
    way through a module import or a class creation: the next use of the half-made module fails with an
    ImportError/AttributeError; or in code that catches BaseException and raises its own). Deterministic
    stand-in: a real SIGINT to a real process, inside a command whose code turns it into another exception
    (ImportError: exit 70 before; a driver error or OSError: exit 2 before).
    Exit 130 with the one interrupt line, not exit 70 "internal error"."""
    code = (
        "import os, signal, sys\n"
        "from stagectl.errors import DriverInitError\n"
        "import stagectl.commands.model as m\n"
        "def boom(args):\n"
        "    try:\n"
        "        os.kill(os.getpid(), signal.SIGINT)\n"
        "        signal.pause()  # the KeyboardInterrupt is raised here, after the handler ran\n"
        "    except BaseException:\n"
        f"        raise {raised} from None\n"
        "    return 0\n"
        "m.run_plot = boom\n"
        "from stagectl.cli import main\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    p = subprocess.run([sys.executable, "-c", code, "model", "plot", "x.yaml", "--out", "d"], cwd=tmp_path, text=True,
                       capture_output=True, timeout=60, env={**os.environ, "STAGECTL_TRACEBACK": ""},
                       preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert p.returncode == 130, p.stderr
    assert p.stderr.strip().splitlines() == ["stagectl: interrupted (Ctrl-C); no output was written"], p.stderr


def test_a_ctrl_c_swallowed_by_a_c_callback_reaches_the_command_silently(capsys) -> None:
    """A Ctrl-C landing in a ctypes callback (llvmlite's, while numba compiles on a cold cache) used to be
    printed as "Exception ignored on calling ctypes callback function ... Traceback" and lost: the command
    went on. With the CLI's handlers in place it is delivered to the main thread, and nothing is printed."""
    import ctypes

    from stagectl import cli

    @ctypes.CFUNCTYPE(None)
    def callback() -> None:  # what a SIGINT during a C callback leaves: KeyboardInterrupt inside it
        raise KeyboardInterrupt

    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a fresh `stagectl` process
    restore = cli._catch_sigint()
    try:
        assert sys.unraisablehook is cli._unraisable
        with pytest.raises(KeyboardInterrupt):
            callback()  # swallowed by ctypes, handed to sys.unraisablehook
            import time

            time.sleep(10)  # a command going on; the re-delivered interrupt ends the wait (not a timed wait)
    finally:
        restore()
        signal.signal(signal.SIGINT, before)
    assert cli._interrupted
    err = capsys.readouterr().err
    assert "Traceback" not in err and "Exception ignored" not in err, err


def test_a_sigterm_after_a_ctrl_c_does_not_cut_the_clean_stop_short() -> None:
    """Ctrl-C, then SIGTERM (a supervisor, `timeout`) while the command is stopping: the SIGTERM raised a second
    KeyboardInterrupt into that stop (run waiting for its loop, writing its recording); only a second SIGTERM
    was ignored. Any interrupt being handled now makes a SIGTERM wait for the stop it started."""
    from stagectl import cli

    before_int = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a fresh `stagectl` process
    before_term = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    restore = cli._catch_sigint()
    try:
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
        signal.raise_signal(signal.SIGTERM)  # the clean stop goes on
        assert cli._interrupted and not cli._terminated  # still reported as the Ctrl-C it was (exit 130)
    finally:
        restore()
        signal.signal(signal.SIGINT, before_int)
        signal.signal(signal.SIGTERM, before_term)


def test_an_interrupt_right_after_run_started_its_loop_still_stops_it_cleanly(tmp_path: Path, capsys) -> None:
    """`run` started its loop thread, then entered the `try` that turns Ctrl-C / SIGTERM into the clean stop; an
    interrupt in between (here raised by a line trace at the first statement after `host.start`, not by timing)
    left `with build_stage(...)` with the loop thread still running: the devices were disabled and closed under
    it, nothing was recorded, exit 130. The stop covers everything from the loop's start on."""
    from stagectl import cli
    from stagectl.commands import run as run_mod

    src = Path(run_mod.__file__).read_text().splitlines()
    start = next(i for i, ln in enumerate(src, 1) if "host.start(duration_s=args.duration)" in ln)
    code = run_mod.run.__code__

    def tracer(frame, event, arg):
        if frame.f_code is not code:
            return None

        def local(frame, event, arg):
            if event == "line" and frame.f_lineno > start:
                frame.f_trace = None
                sys.settrace(None)
                raise KeyboardInterrupt
            return local
        return local

    out = tmp_path / "run"
    sys.settrace(tracer)
    try:
        rc = cli.main(["run", "--config", str(REPO / "config" / "sim.yaml"), "--duration", "30", "--out", str(out),
                       "--no-plots", "-q"])
    finally:
        sys.settrace(None)
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    summary = json.loads(captured.out)
    assert summary["loop"]["ended_by"] == "stop" and summary["fault"] is None
    assert (out / "telemetry.csv").is_file()


def test_sigterm_in_run_stops_the_loop_and_keeps_the_recording(tmp_path: Path) -> None:
    """SIGTERM (kill, timeout, a supervisor) to `stagectl run`: the same clean stop as Ctrl-C (loop ended, zero
    force, drive disabled) and every recorded row written. Before, SIGTERM's default action killed the process
    at once: no telemetry, no summary, an empty output directory (audit16)."""
    out = tmp_path / "run"
    script = Path(sys.executable).with_name("stagectl")
    p = subprocess.Popen([str(script), "run", "--config", "config/sim.yaml", "--duration", "600", "--out", str(out),
                          "--no-plots"], cwd=REPO, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         env={**os.environ, "STAGECTL_TRACEBACK": ""})
    try:
        assert p.stderr is not None
        line = p.stderr.readline()
        while line and not line.startswith("t="):  # the first progress line: the loop is running
            line = p.stderr.readline()
        assert line.startswith("t="), line
        p.send_signal(signal.SIGTERM)
        stdout, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, err
    assert "stopping (interrupted)" in err and "Traceback" not in err, err
    summary = json.loads(stdout)
    assert summary["loop"]["cycles"] > 100 and summary["fault"] is None
    rows = (out / "telemetry.csv").read_text().splitlines()
    assert len(rows) == summary["samples"] + 1 and summary["samples"] > 100
