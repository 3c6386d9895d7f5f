"""Bounded YAML and one-line errors for hostile configuration files (issue 16).

The loader refuses alias bombs, deep nesting, oversize files and duplicate keys before building any value, turns
every PyYAML exception into one :class:`ConfigError` line naming the line, and the schema names the field and
unit of a 401-digit integer or a non-finite value. ``check-config``, ``run``, ``simulate`` and ``daemon`` give
exit 2 with those lines, never a traceback.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tracemalloc
from pathlib import Path

import pytest
import yaml

from stagectl.commands.check_config import run as check_config_run
from stagectl.config import load_app_config
from stagectl.errors import ConfigError, short
from stagectl.schema import MAX_YAML_ALIASES, MAX_YAML_BYTES, MAX_YAML_DEPTH, MAX_YAML_NODES, load_yaml_file

from support import cli_in_process

REPO = Path(__file__).resolve().parents[2]


def laughs(levels: int, fan: int) -> str:
    """A "billion laughs" document: ``fan**levels`` strings from ``levels * fan`` aliases."""
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, levels):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * fan) + "]")
    lines.append(f"controller: *a{levels - 1}")
    return "\n".join(lines) + "\n"


def _refused(tmp_path: Path, text: str, name: str = "bad.yaml") -> str:
    p = tmp_path / name
    p.write_text(text)
    with pytest.raises(ConfigError) as ei:
        load_yaml_file(p)
    assert len(ei.value.problems) == 1, ei.value.problems
    return ei.value.problems[0]


@pytest.mark.parametrize(("levels", "fan", "why"), [
    (10, 9, f"more than {MAX_YAML_NODES} values once aliases are expanded"),   # 9^10 strings, 81 aliases
    (12, 30, f"more than {MAX_YAML_ALIASES} aliases"),                          # the 3.4 KB file of the issue
])
def test_alias_bomb_refused_with_little_memory(tmp_path: Path, levels: int, fan: int, why: str) -> None:
    text = laughs(levels, fan)
    tracemalloc.start()
    try:
        msg = _refused(tmp_path, text)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert why in msg
    assert peak < 20e6, f"{peak / 1e6:.1f} MB to refuse a {len(text)} B file"


def test_a_few_aliases_and_merge_keys_still_work(tmp_path: Path) -> None:
    p = tmp_path / "ok.yaml"
    p.write_text("base: &b {kp: 1, kd: 2}\nx:\n  <<: *b\n  kp: 3\ny: [*b, *b]\n")
    assert load_yaml_file(p) == {"base": {"kp": 1, "kd": 2}, "x": {"kp": 3, "kd": 2},
                                 "y": [{"kp": 1, "kd": 2}, {"kp": 1, "kd": 2}]}


@pytest.mark.parametrize(("text", "expected"), [
    ("[" * 5000 + "]" * 5000, f"nested deeper than {MAX_YAML_DEPTH} levels at line 1"),
    ("a:\n" + "".join("  " * i + f"k{i}:\n" for i in range(1, 40)), f"nested deeper than {MAX_YAML_DEPTH}"),
    ("a: &a [*a]\n", "recursive alias at line 1"),
    ("safety:\n  max_force_n: 1\n  max_force_n: 2\n", "line 3, column 3: duplicate key 'max_force_n' (first at line 2)"),
    ("loop: {period_s: 0.001, period_s: 0.002}\n", "duplicate key 'period_s' (first at line 1)"),
    ("controller: !!timestamp 2001-13-45x\n", "line 1, column 13: cannot read '2001-13-45x' as timestamp"),
    ("controller: !!timestamp 2001-02-30\n", "cannot read '2001-02-30' as timestamp (ValueError)"),
    ("controller: !!int " + "9" * 5000 + "\n", "cannot read '999"),
    ("controller: !!python/object:os.system x\n", "could not determine a constructor"),
    ("\x1f: 1\n", "special characters are not allowed"),
    ("a: 1\n--- \nb: 2\n", "YAML syntax error at line 2"),
    ("a: [1, 2\n", "YAML syntax error at line 2"),
])
def test_hostile_yaml_is_one_line_naming_the_line(tmp_path: Path, text: str, expected: str) -> None:
    msg = _refused(tmp_path, text)
    assert expected in msg and "\n" not in msg and len(msg) < 400, msg


def test_oversize_file_refused_without_reading_it_all(tmp_path: Path) -> None:
    p = tmp_path / "huge.yaml"
    p.write_text("a: " + "x" * (MAX_YAML_BYTES + 10))
    with pytest.raises(ConfigError, match=f"larger than {MAX_YAML_BYTES // 1024} KiB"):
        load_yaml_file(p)


def _sim() -> dict:
    return yaml.safe_load((REPO / "config" / "sim.yaml").read_text())


@pytest.mark.parametrize(("key", "value", "expected"), [
    (("controller", "pid", "kp_n_m"), 10**400, "controller.pid.kp_n_m: must be finite N/m, got <integer of 401 digits>"),
    (("safety", "stale_cycles"), 10**400, "safety.stale_cycles: out of range"),
    (("safety", "max_force_n"), float("nan"), "safety.max_force_n: must be a finite number N, got NaN"),
    (("controller", "mass_kg"), float("inf"), "controller.mass_kg: must be finite kg"),
    (("description",), "x" * 100_000, None),
    (("loop", "period_s"), ["x" * 1000] * 100, "loop.period_s: expected a number s, got list ["),
    # in range for the schema before, then an OverflowError or a hang inside `simulate`
    (("sim", "plant", "sensor", "noise_std_m"), 1e300, "sim.plant.sensor.noise_std_m: must be <= 1 m"),
    (("sim", "plant", "sensor", "resolution_m"), 1e-300, "sim.plant.sensor.resolution_m: must be >= 1e-15 m"),
    (("sim", "plant", "substep_s"), 1e-300, "sim.plant.substep_s: must be >= 1e-07 s"),
    (("sim", "drive", "resolution_m"), 1e-300, "sim.drive.resolution_m: must be >= 1e-15 m"),
], ids=["401-digit-float", "401-digit-int", "nan", "inf", "long-description", "100-KB-list", "noise-1e300",
        "resolution-1e-300", "substep-1e-300", "drive-resolution-1e-300"])
def test_extreme_values_name_field_and_unit_in_a_short_line(tmp_path: Path, key: tuple[str, ...], value: object,
                                                            expected: str | None) -> None:
    data = _sim()
    data["sim"]["plant"]["model_file"] = str(REPO / "config" / "models" / "kamenar2016_gms.yaml")
    data["controller"]["feedforward"]["model_file"] = str(REPO / "config" / "models" / "kamenar2016_gms.yaml")
    node = data
    for k in key[:-1]:
        node = node[k]
    node[key[-1]] = value
    p = tmp_path / "extreme.yaml"
    p.write_text(yaml.safe_dump(data, width=10**9))
    if expected is None:  # a long description is valid
        assert load_app_config(p).description == value
        return
    with pytest.raises(ConfigError) as ei:
        load_app_config(p)
    assert any(expected in line for line in ei.value.problems), ei.value.problems
    assert all(len(line) < 200 for line in ei.value.problems), ei.value.problems


def test_check_config_refuses_the_alias_bomb_in_process(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "laughs.yaml"
    p.write_text(laughs(12, 30))
    assert check_config_run(argparse.Namespace(file=str(p), quiet=False)) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0].endswith("1 problem") and len(err) == 2 and "aliases" in err[1], err


@pytest.mark.parametrize("command", [["check-config"], ["run", "--duration", "1", "--config"],
                                     ["simulate", "--out", "OUT", "--config"], ["daemon", "--config"]])
def test_every_command_gives_exit_2_and_no_traceback(tmp_path: Path, command: list[str]) -> None:
    p = tmp_path / "ts.yaml"
    p.write_text("loop: {period_s: 0.001}\ncontroller: !!timestamp 2001-13-45x\n")
    args = [a.replace("OUT", str(tmp_path / "out")) for a in command]
    if command[0] in ("run", "simulate"):  # in process (what they say is tested; their start is the same CLI's)
        r = cli_in_process([*args, str(p)])
    else:  # check-config's light start and the service's own start: real processes
        r = subprocess.run([sys.executable, "-m", "stagectl.cli", *args, str(p)], capture_output=True, text=True,
                           timeout=120, env={**os.environ, "RUNTIME_DIRECTORY": str(tmp_path / "rt")})
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert "Traceback" not in r.stderr and "internal error" not in r.stderr
    assert "line 2, column 13: cannot read '2001-13-45x' as timestamp" in r.stderr, r.stderr


def test_short_is_bounded_for_hostile_values() -> None:
    a: list[object] = []
    a.append(a)
    nested: object = ["lol"] * 9
    for _ in range(30):
        nested = [nested] * 9  # 9^31 elements if printed in full
    assert short(10**400) == "<integer of 401 digits>"
    assert short(-(10**400)) == "<integer of 401 digits>"
    assert "digits" in short(10**100_000)
    for v in ("x" * 10**6, a, nested, {"k": list(range(10**5))}):
        assert len(short(v)) <= 60
    assert short("abc") == "'abc'" and short(1.5) == "1.5"


def test_check_config_refuses_a_bad_file_before_the_heavy_imports(tmp_path: Path) -> None:
    """A refused YAML file costs the interpreter's start and the parse, not the validation's imports (numpy,
    numba, the controller): check-config on the alias bomb is as cheap as `stagectl --help`."""
    p = tmp_path / "laughs.yaml"
    p.write_text(laughs(12, 30))
    code = ("import sys\nfrom stagectl.cli import main\nrc = main(['check-config', sys.argv[1]])\n"
            "print(rc, sorted(m for m in ('numpy', 'stagectl.config', 'stagectl.control') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code, str(p)], capture_output=True, text=True, timeout=120)
    assert r.stdout.split("\n")[0] == "2 []", (r.stdout, r.stderr)
    assert "more than 100 aliases" in r.stderr


def test_a_thousand_unknown_keys_give_a_bounded_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "keys.yaml"
    p.write_text("".join(f"key_{i}: {i}\n" for i in range(1000)))
    assert check_config_run(argparse.Namespace(file=str(p), quiet=False)) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0].endswith(": 1003 problems"), err[0]  # 1000 unknown keys + safety, controller, sim missing
    assert len(err) == 1 + 100 + 1 and err[-1] == "stagectl: error: ... and 903 more problems", err[-3:]
