"""Every command with hostile arguments: one ``stagectl…: error:`` line, exit 2, never a traceback.

The table runs in-process through :func:`stagectl.cli.main` (the console script's entry point, so what it
prints is what a user sees); a few cases also run as real subprocesses to prove the installed script
behaves the same. Each case must fail *before* any long work: the whole table takes seconds.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stagectl import cli

REPO = Path(__file__).resolve().parents[2]
ERROR_LINE = re.compile(r"^stagectl: error: \S")  # argparse's refusals too (no usage block)


@pytest.fixture(scope="module")
def rec(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small, valid recording (a slow sine with Coulomb friction), so only the hostile option fails."""
    d = tmp_path_factory.mktemp("rec")
    t = np.arange(0, 2.0, 1e-3)
    x = 1e-4 * np.sin(2 * np.pi * 1.0 * t)
    u = 2.0 * np.sign(np.cos(2 * np.pi * 1.0 * t)) + 0.5 * np.cos(2 * np.pi * t)
    p = d / "rec.csv"
    np.savetxt(p, np.column_stack([t, x, u]), delimiter=",", header="t,x,u", comments="", fmt="%.10g")
    return p


HOSTILE = [
    # numbers out of range, not finite, not numbers: refused with the option and its unit
    "run --config config/sim.yaml --duration -1",
    "run --config config/sim.yaml --duration nan",
    "simulate --config config/sim.yaml --out {tmp}/o --tolerance -1",
    "simulate --config config/sim.yaml --out {tmp}/o --tolerance abc",
    "simulate --config config/sim.yaml --out {tmp}/o --duration 0",
    "simulate --config config/sim.yaml --out {tmp}/o --duration 1e12",  # was a MemoryError (128 PiB recording)
    "simulate --config config/sim.yaml --out {tmp}/o --scenario steps --repetitions 100000",
    "run --config config/sim.yaml --duration 1e12 --out {tmp}/o",
    "status --timeout -1 --socket {tmp}/none.sock",
    "status --timeout inf --socket {tmp}/none.sock",
    "move --to nan --socket {tmp}/none.sock",
    "move --by 1e-5 --max-velocity -1 --socket {tmp}/none.sock",
    "sim-plant --config config/hil-canopen.yaml --port 99999",
    "identify {rec} --model gms --out {tmp}/m.yaml --cutoff-hz -5",
    "identify {rec} --model gms --out {tmp}/m.yaml --cutoff-hz 0",
    "identify {rec} --model gms --out {tmp}/m.yaml --cutoff-hz 10000",
    "identify {rec} --model gms --out {tmp}/m.yaml --mass-kg -2",
    "identify {rec} --model gms --out {tmp}/m.yaml --elements 0",
    "discover {rec} --out {tmp}/d --cutoff-hz -5",
    "discover {rec} --out {tmp}/d --cutoff-hz 10000",
    "discover {rec} --out {tmp}/d --max-rounds -1",
    "tune --config config/sim.yaml --bandwidth-hz -3",
    "tune --config config/sim.yaml --period-s 1e-9",  # was a ZeroDivisionError (internal error, exit 70)
    "tune --config config/sim.yaml --delay-samples 100000",  # was a MemoryError: a 10^5-state model
    "tune --config config/sim.yaml --dob-bandwidth-hz 1e6",  # above Nyquist: was designed and refused (exit 1)
    "tune --mass-kg 2 --period-s 1",
    "tune --mass-kg 1e12 --bandwidth-hz 20 --period-s 0.001",  # was a ZeroDivisionError (exit 70; audit16)
    # benchmarks: every numeric option checked before any work; names checked against what exists
    "bench loop --duration -1",
    "bench loop --duration nan",
    "bench telemetry --duration-s -1",
    "bench telemetry --rate-hz 0 --duration-s 1",
    "bench models --steps -5 --quick",
    "bench models --models nosuch --quick",
    "bench startup --repeat -1",
    "bench startup --switch --switch-cycles 0",
    "bench startup --switch --switch-interval -1",
    "bench startup --config {tmp}/missing.yaml",
    "bench control --pid-bandwidths abc",
    "bench io --fifo 0",
    "commission --config config/sim.yaml --out {tmp}/c --inject-fault garbage",
    "commission --config config/sim.yaml --out {tmp}/c --inject-fault frf@-1",
    # paths that cannot be read or written: checked before the work
    "run --config {tmp}/missing.yaml",
    "simulate --config {tmp} --out {tmp}/o",
    "simulate --config config/sim.yaml --out /proc/stagectl-x",
    "identify {rec} --model gms --out /proc/stagectl-x.yaml",
    "identify {rec} --model dahl --out /dev/full --quiet",  # the disk fills when the model file is written
    "identify {rec} --model gms --out {tmp}",
    "identify {tmp} --model gms --out {tmp}/m.yaml",
    "identify /dev/null --model gms --out {tmp}/m.yaml",
    "identify {rec} --model gms --out {tmp}/m.yaml --columns t=zz",
    "identify {rec} --model gms --out {tmp}/m.yaml --columns garbage",
    "discover {rec} --out /proc/stagectl-x",
    "discover {rec} --out {tmp}/d --validate {tmp}/missing.csv",
    "check-config /dev/null",
    "check-config {rec}",
    "model plot {tmp}/missing.yaml --out {tmp}/p.png",
    "model plot config/models/kamenar2016_gms.yaml --out /dev/full",
    # no daemon behind the socket
    "status --socket {tmp}/none.sock",
    "gains --socket {rec}",
    "move --by -1e-5 --socket {tmp}/none.sock",
    "reset --socket {tmp}/none.sock",
    "stop --socket {tmp}/none.sock",
    "stop --json --socket {tmp}/none.sock",
    "reset --json --socket {tmp}/none.sock",
    "record start x --socket {tmp}/none.sock",
    "plot {rec} --out {tmp}/p.txt",
    "plot {tmp}/missing.csv",
    "plot {rec} --out /proc/stagectl-x.png",
    # configuration files that are not configurations
    "check-config {tmp}",
    "run --config {rec}",
    "simulate --config {rec} --out {tmp}/o",
    "daemon --config {tmp}/missing.yaml --runtime-dir {tmp}/run",
    # argparse's own refusals: one line too, naming the command
    "identify {rec} --model nosuch --out {tmp}/m.yaml",
    "identify {rec} --model gms --out {tmp}/m.yaml --cutoff-hz abc",
    "move --socket {tmp}/none.sock",
    "move --to 1 --by 1 --socket {tmp}/none.sock",
    "record",
    "bench",
    "bench models --nope",
    "scope --every 0 --socket {tmp}/none.sock",
    "scope --socket {tmp}/none.sock",
    "nosuchcommand",
]


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    try:
        rc = cli.main(argv)
    except SystemExit as exc:  # argparse exits with 2 itself
        rc = int(exc.code) if isinstance(exc.code, int) else 1
    return rc, capsys.readouterr().err


@pytest.mark.parametrize("case", HOSTILE)
def test_hostile_arguments_give_one_error_line_and_exit_2(case: str, rec: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str],
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)
    argv = shlex.split(case.format(rec=rec, tmp=tmp_path))
    dirs_before = {p for p in tmp_path.rglob("*") if p.is_dir()}
    rc, err = _run(argv, capsys)  # an uncaught exception fails the test here: that is a traceback
    lines = [line for line in err.splitlines() if line.strip()]
    # a refused command leaves no empty output directory behind (it made --out before finding the problem)
    left = [p for p in tmp_path.rglob("*") if p.is_dir() and p not in dirs_before and not any(p.iterdir())]
    assert not left, (left, err)
    if argv[0] == "daemon":  # the service logs to the journal (<3> = error priority), not as a CLI error
        lines = [line for line in lines if line.startswith("<3>")]
        assert rc == 2 and lines and "Traceback" not in err, err
        return
    errors = [line for line in lines if ERROR_LINE.match(line)]
    usage = [line for line in lines if re.search(r": \d+ problems?$", line)]  # check-config's count
    assert rc == 2, (rc, err)
    assert errors and len(errors) + len(usage) == len(lines), err  # one line per problem, nothing else
    assert len(errors) == 1 or "check-config" in case, err  # several only where the config has several
    assert "Traceback" not in err and "internal error" not in err, err


@pytest.mark.parametrize("command", ["discover {rec} --out {tmp}/d --model config/sim.yaml",
                                     "model plot config/sim.yaml --out {tmp}/p"])
def test_a_stage_config_given_for_a_model_file_says_so_in_one_line(command: str, rec: Path, tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str],
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """A stage config where a friction model file belongs: one line naming the mistake and the model file
    the config itself uses (not one "unknown key" line per section), exit 2."""
    monkeypatch.chdir(REPO)
    rc, err = _run(shlex.split(command.format(rec=rec, tmp=tmp_path)), capsys)
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc == 2, err
    assert len(lines) == 1 and "is a stage config, not a model file" in lines[0], err
    assert str(REPO / "config" / "models" / "kamenar2016_gms.yaml") in lines[0], err


def test_negative_scientific_values_are_values_not_options(capsys: pytest.CaptureFixture[str],
                                                           tmp_path: Path) -> None:
    rc, err = _run(["move", "--by", "-1e-5", "--socket", str(tmp_path / "none.sock")], capsys)
    assert rc == 2 and "no control socket" in err, err  # parsed: it got as far as connecting


def test_help_has_no_rst_markup(capsys: pytest.CaptureFixture[str]) -> None:
    """Every command's --help (descriptions come from module docstrings): no ``literal`` or :role: markup."""
    commands = [name for a in cli.build_parser(None)._actions if hasattr(a, "choices") and isinstance(a.choices, dict)
                for name in a.choices]
    assert {"identify", "discover", "simulate", "bench", "commission", "scope"} <= set(commands)
    for cmd in commands:
        with pytest.raises(SystemExit):
            cli.main([cmd, "--help"])
        out = capsys.readouterr().out
        assert "``" not in out and not re.search(r":(mod|func|class|meth|data|attr):`", out), (cmd, out)


def test_a_bug_is_one_line_with_exit_70(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
                                        tmp_path: Path) -> None:
    """A genuine bug (here: a command that raises) is reported in one line, the traceback on request."""
    from stagectl.commands import check_config

    def boom(args: object) -> int:
        raise ZeroDivisionError("division by zero")

    monkeypatch.setattr(check_config, "run", boom)
    monkeypatch.delenv("STAGECTL_TRACEBACK", raising=False)
    rc, err = _run(["check-config", str(tmp_path / "x.yaml")], capsys)
    assert rc == 70 and err.count("\n") == 1 and "internal error: ZeroDivisionError" in err, err
    monkeypatch.setenv("STAGECTL_TRACEBACK", "1")
    with pytest.raises(ZeroDivisionError):
        cli.main(["check-config", str(tmp_path / "x.yaml")])


@pytest.mark.parametrize("case", [
    "identify {tmp}/missing.csv --model gms --out {tmp}/m.yaml --cutoff-hz -5",
    "status --timeout -1 --socket {tmp}/none.sock",
])
def test_installed_script_gives_one_line_too(case: str, tmp_path: Path) -> None:
    script = Path(sys.executable).with_name("stagectl")
    argv = [str(script)] if script.exists() else [sys.executable, "-m", "stagectl.cli"]
    p = subprocess.run([*argv, *shlex.split(case.format(tmp=tmp_path))], check=False, capture_output=True,
                       text=True,
                       cwd=REPO, timeout=120, env={**os.environ, "STAGECTL_TRACEBACK": ""})
    assert p.returncode == 2, p.stderr
    assert "Traceback" not in p.stderr
    assert sum(bool(ERROR_LINE.match(line)) for line in p.stderr.splitlines()) == 1, p.stderr


def test_stdout_on_a_full_disk_is_one_error_line(tmp_path: Path) -> None:
    """``> /dev/full``: the lost output is an error (exit 2, one line), not a traceback at interpreter exit."""
    script = Path(sys.executable).with_name("stagectl")
    argv = [str(script)] if script.exists() else [sys.executable, "-m", "stagectl.cli"]
    with open("/dev/full", "w") as full:
        p = subprocess.run([*argv, "check-config", "config/sim.yaml"], check=False, stdout=full,
                           stderr=subprocess.PIPE, text=True, cwd=REPO, timeout=120)
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr
    assert [bool(ERROR_LINE.match(line)) for line in p.stderr.splitlines()] == [True], p.stderr


def test_every_command_and_subcommand_prints_its_help(capsys: pytest.CaptureFixture[str]) -> None:
    """--help of every command and of every nested subcommand (bench KIND, model plot …) exits 0 with usage text:
    argparse formats help strings with %, so a literal '%' in one (e.g. '20 %-wrong') crashes the whole help."""
    import argparse

    parser = cli.build_parser(None)

    def walk(p: argparse.ArgumentParser, path: list[str]) -> list[list[str]]:
        out = [path]
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    out += walk(sub, [*path, name])
        return out

    paths = walk(parser, [])
    assert len(paths) > 20
    for path in paths:
        with pytest.raises(SystemExit) as ex:
            cli.main([*path, "--help"])
        assert ex.value.code == 0, path
        assert "usage:" in capsys.readouterr().out, path


@pytest.mark.parametrize(("case", "flag", "unit"), [
    ("run --config config/sim.yaml --duration abc", "--duration", "in s"),
    ("simulate --config config/sim.yaml --out {tmp}/o --duration 10s", "--duration", "in s"),
    ("tune --mass-kg 2kg", "--mass-kg", "in kg"),
    ("tune --mass-kg 2 --bandwidth-hz fast", "--bandwidth-hz", "in Hz"),
    ("tune --mass-kg 2 --period-s 1ms", "--period-s", "in s"),
    ("commission --config config/sim.yaml --out {tmp}/c --max-force 1N", "--max-force", "in N"),
    ("commission --config config/sim.yaml --out {tmp}/c --max-velocity 1mm/s", "--max-velocity", "in m/s"),
])
def test_a_number_option_given_text_names_its_unit(case: str, flag: str, unit: str, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str],
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)
    rc, err = _run(shlex.split(case.format(tmp=tmp_path)), capsys)
    assert rc == 2 and err.count("\n") == 1 and unit in err and flag in err, err


def test_a_recording_in_other_units_names_the_units_not_a_fitted_parameter(tmp_path: Path,
                                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """x logged in µm (values ~100 instead of 1e-4): the fit's mass comes out negative; the line says to check
    the recording's units and shows the span it read, not only 'mass_kg: must be > 0 kg'."""
    t = np.arange(0, 2.0, 1e-3)
    x_um = 100.0 * np.sin(2 * np.pi * t)
    u = 2.0 * np.sign(np.cos(2 * np.pi * t))
    p = tmp_path / "um.csv"
    np.savetxt(p, np.column_stack([t, x_um, u]), delimiter=",", header="t,x,u", comments="", fmt="%.10g")
    rc, err = _run(["identify", str(p), "--model", "gms", "--out", str(tmp_path / "m.yaml"), "--quiet"], capsys)
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc == 2 and len(lines) == 1 and ERROR_LINE.match(lines[0]), err
    assert "um.csv" in err and "units" in err and "x in m" in err and "x spans 200 m" in err, err
    assert not (tmp_path / "m.yaml").exists()


def test_a_stale_socket_or_a_directory_is_named_as_such(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A daemon killed with SIGKILL leaves its socket file: 'no daemon listening', not '[Errno 111] Connection
    refused'; a directory given as --socket is named a directory."""
    import socket

    stale = tmp_path / "control.sock"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(stale))
    s.close()  # the file stays, nobody listens
    rc, err = _run(["status", "--socket", str(stale)], capsys)
    assert rc == 2 and err.count("\n") == 1 and "no daemon listening" in err and "Errno" not in err, err
    rc, err = _run(["stop", "--socket", str(tmp_path)], capsys)
    assert rc == 2 and err.count("\n") == 1 and "not a control socket but a directory" in err, err
