"""Test helpers shared by several test areas (on sys.path via pytest's ``pythonpath``)."""

from __future__ import annotations

import math

from stagectl.control.api import Reference


class RampReference:
    """Constant-velocity moves; implements the loop's ReferenceSource protocol."""

    def __init__(self, v_default: float = 1e-3):
        self.v_default = v_default
        self._x0 = 0.0
        self._t0 = 0.0
        self._target = 0.0
        self._v = 0.0

    def hold(self, t_s: float, x_m: float) -> None:
        self._x0, self._t0, self._target, self._v = x_m, t_s, x_m, 0.0

    def sample(self, t_s: float) -> Reference:
        if self._v == 0.0:
            return Reference(self._target)
        x = self._x0 + self._v * (t_s - self._t0)
        if (self._v > 0 and x >= self._target) or (self._v < 0 and x <= self._target):
            self._x0, self._v = self._target, 0.0
            return Reference(self._target)
        return Reference(x, self._v)

    def move(self, t_s: float, target_m: float, max_velocity_m_s: float | None) -> float:
        x = self.sample(t_s).x_m
        v = max_velocity_m_s or self.v_default
        self._x0, self._t0, self._target = x, t_s, target_m
        self._v = math.copysign(v, target_m - x) if target_m != x else 0.0
        return abs(target_m - x) / v

    def stop(self, t_s: float) -> float:
        x = self.sample(t_s).x_m
        self.hold(t_s, x)
        return x

    @property
    def target_m(self) -> float:
        return self._target

    @property
    def target_m(self) -> float:
        return self._target


def stop_process(proc, timeout_s: float) -> None:
    """Stop a test subprocess: SIGTERM, wait up to ``timeout_s``, then SIGKILL; close its pipes."""
    import signal
    import subprocess

    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(10)
    for stream in (proc.stdout, proc.stderr):
        if stream is not None:
            stream.close()


# ------------------------------------------------------------------------------------------ subprocesses
def stagectl_cmd() -> list[str]:
    """The ``stagectl`` entry point of this interpreter's environment (``python -m stagectl.cli`` without one)."""
    import sys
    from pathlib import Path

    exe = Path(sys.executable).parent / "stagectl"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "stagectl.cli"]


def run_on_pty(argv: list[str], *, interrupt_on: str | None = None, cwd=None, stdout=None,
               timeout_s: float = 180.0) -> tuple[int, str]:
    """Run ``stagectl argv`` with its stderr on a pty (a terminal: progress lines are redrawn in place) and
    return (exit status, what it wrote there). ``interrupt_on``: send a real SIGINT (Ctrl-C) as soon as that
    text has appeared (the process's own progress line: no wall-clock sleep). ``stdout``: a file object for
    its standard output (default: discarded)."""
    import os
    import pty
    import select
    import signal
    import subprocess

    m, s = pty.openpty()
    # preexec_fn: a test run in the background (no job control) ignores SIGINT and a child inherits SIG_IGN,
    # in which case Python never raises KeyboardInterrupt; with SIG_DFL at exec it installs its handler
    p = subprocess.Popen([*stagectl_cmd(), *argv], cwd=cwd, stdout=stdout or subprocess.DEVNULL, stderr=s,
                         env={**os.environ, "STAGECTL_TRACEBACK": ""},
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    os.close(s)
    buf = b""
    try:
        while True:
            r, _, _ = select.select([m], [], [], timeout_s)
            if not r:
                raise AssertionError(f"stagectl {' '.join(argv)}: no output for {timeout_s} s: {buf[-500:]!r}")
            try:
                chunk = os.read(m, 4096)
            except OSError:  # EIO: the child closed its end
                break
            if not chunk:
                break
            buf += chunk
            if interrupt_on is not None and interrupt_on.encode() in buf:
                p.send_signal(signal.SIGINT)
                interrupt_on = None
        p.wait(timeout_s)
    finally:
        os.close(m)
        if p.poll() is None:
            p.kill()
            p.wait(10)
    return p.returncode, buf.decode(errors="replace")


def absolutize_paths(node, base):
    """A configuration mapping with its relative file paths made absolute against ``base``, so that it still loads
    from a temporary directory (:func:`stagectl.schema.absolute_paths`)."""
    from stagectl.schema import absolute_paths

    return absolute_paths(node, base)


# ------------------------------------------------------------------------------------------ shipped configs
def shipped_config_mapping(name: str) -> dict:
    """A shipped ``config/<name>`` as a mapping, its model-file paths made absolute (so it validates anywhere)."""
    from pathlib import Path

    import yaml

    repo = Path(__file__).resolve().parents[1]
    model = str(repo / "config" / "models" / "kamenar2016_gms.yaml")
    data = yaml.safe_load((repo / "config" / name).read_text())
    if "sim" in data:
        data["sim"]["plant"]["model_file"] = model
    data["controller"]["feedforward"]["model_file"] = model
    return data


def embedded_hil_mapping(name: str) -> dict:
    """A shipped HIL config (``hil-canopen.yaml``, ``hil-serial.yaml``) with its ``sim:`` section run in-process:
    io.kind ``embedded_canopen`` (the real CiA 402 driver on a virtual bus), the interferometer without its TCP
    transport, and the loop without sim-plant pacing (``device_time``, ``pace_cycles``)."""
    data = shipped_config_mapping(name)
    io = data["io"]
    drive = {k: v for k, v in io["drive"].items()
             if k in ("node_id", "resolution_m", "force_per_unit_n", "max_force_n")}
    data["io"] = {"kind": "embedded_canopen", "sensor": io["sensor"], "drive": drive}
    data["sim"]["transport"] = {"kind": "virtual"}
    if "interferometer" in data["sim"]:
        data["sim"]["interferometer"] = {k: v for k, v in data["sim"]["interferometer"].items()
                                         if k not in ("transport", "host", "port")}
    for k in ("device_time", "pace_cycles"):
        data["loop"].pop(k, None)
    return data


def config_problems(data: dict) -> list[str]:
    """The problems :func:`stagectl.config.parse_app_config` reports for ``data`` (it must report some)."""
    from pathlib import Path

    import pytest

    from stagectl.config import parse_app_config
    from stagectl.errors import ConfigError

    with pytest.raises(ConfigError) as ei:
        parse_app_config(data, Path(__file__).resolve().parents[1] / "config" / "x.yaml")
    return ei.value.problems


def cli_in_process(argv: list[str]):
    """``stagectl ARGV`` run in this process (:func:`stagectl.cli.main`), returned like ``subprocess.run``
    (``returncode``, ``stdout``, ``stderr``). For tests of what a command says and returns, not of the process
    itself: it saves a new interpreter's imports (0.5–1.4 s of CPU each). An uncaught exception (what a
    subprocess would print as a traceback) fails the calling test."""
    import contextlib
    import io
    import subprocess

    from stagectl.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main([str(a) for a in argv])
        except SystemExit as exc:  # argparse's refusals
            rc = exc.code if isinstance(exc.code, int) else 1
    return subprocess.CompletedProcess(argv, rc, out.getvalue(), err.getvalue())


def cycle_drive(dut, n: int, force_n: float):
    """``n`` bus cycles of a driver (SYNC, read, write ``force_n``) or until a read reports a fault; returns the
    last measurement."""
    m = None
    for _ in range(n):
        dut.sync()
        m = dut.read()
        if m.fault is not None:
            return m
        dut.write(force_n)
    return m


def friction_moves(seed: int, n: int):
    """A random velocity history for stepping friction kernels: pre-sliding wiggles, sliding both ways,
    reversals, pauses (v = 0), tiny and large steps. Returns ``(v [m/s], dt [s])``, 40 samples per level."""
    import numpy as np

    rng = np.random.default_rng(seed)
    v = np.repeat(rng.choice([-5e-3, -1e-3, -2e-4, -1e-5, 0.0, 1e-5, 3e-4, 1e-3, 8e-3], n // 40), 40)
    v *= rng.uniform(0.5, 1.5, v.size)
    dt = rng.uniform(5e-5, 1e-3, v.size)
    return v, dt


def drive_limit_config(move_force_fraction: float = 0.0, **drive):
    """config/sim.yaml through the embedded CiA 402 drive, with ``sim.drive`` keys overridden (e.g. its
    ``max_force_n``, the drive's max torque 0x6072) and the tracking window widened to 1 mm (a saturated move
    lags by ~0.12 mm before it catches up: the window, not the force limits). Moves run as given
    (``safety.move_force_fraction`` 0: these tests saturate the drive on purpose) unless
    ``move_force_fraction`` is given."""
    from pathlib import Path

    import yaml

    from stagectl.config import parse_app_config

    sim_yaml = Path(__file__).resolve().parents[1] / "config" / "sim.yaml"
    data = yaml.safe_load(sim_yaml.read_text())
    data["io"]["kind"] = "embedded_canopen"
    data["sim"]["drive"].update(drive)
    data["safety"]["following_error_m"] = 1e-3
    data["safety"]["stale_travel_m"] = 1e-3
    data["safety"]["move_force_fraction"] = move_force_fraction
    return parse_app_config(data, sim_yaml)
