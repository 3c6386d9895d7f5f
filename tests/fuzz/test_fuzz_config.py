"""Fuzz the configuration loader: YAML text and mutated real configurations.

Invariant: :func:`stagectl.schema.parse_yaml_text` and :func:`stagectl.config.parse_app_config` either return
or raise :class:`~stagectl.errors.ConfigError` whose lines are short and name a key path or the file; no other
exception escapes (the CLI would turn it into exit 1 and systemd into a restart loop).
"""

from __future__ import annotations

import copy
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from stagectl.config import parse_app_config
from stagectl.errors import MAX_PROBLEM_CHARS, MAX_PROBLEMS, ConfigError
from stagectl.schema import parse_yaml_text

sys.path.insert(0, str(Path(__file__).parent))
from fuzzing import fuzz  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
CONFIGS = ["sim.yaml", "stage-canopen.yaml", "hil-serial.yaml", "hil-canopen.yaml"]

#: YAML fragments that have broken PyYAML or the loader before (issue 16) plus plain syntax
YAML_ATOMS = ["!!timestamp 2001-13-45x", "!!timestamp 2001-02-30", "9" * 401, "-" + "9" * 5000, ".nan", ".inf",
              "-.inf", "1e400", "!!binary '@@'", "!!float abc", "!!int 0x", "&a [*a]", "*undefined", "{a: 1, a: 2}",
              "[[[[[[[[", "'unterminated", "!!python/object:os.system x", "~", "yes", "0o777", "0b101",
              "!!set {a, b}", "!!omap [a: 1]", "? [a]\n: b", "<<: {a: 1}", "\t", "%YAML 1.1\n---", "--- a\n--- b"]

HOSTILE = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([1e308, -1e308, 5e-324, -0.0, 0.0, 1e-300, 2.0**63, 10**401, -(10**30), 2**63, -1]),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.booleans(), st.none(),
    st.text(max_size=30),
    st.sampled_from(["fast", "1e-3", "nan", "inf", "1e999", "embedded_canopen", "plant_io", "serial", "gms",
                     "models/kamenar2016_gms.yaml", "/dev/zero", "..", "socketcand", "virtual", "qfilter", "none"]),
    st.lists(st.floats(allow_nan=True) | st.integers(), max_size=4),
    st.dictionaries(st.text(max_size=8), st.integers() | st.floats(), max_size=3),
)


def _paths(node: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every key path of a nested mapping/list (containers included, so whole sections get replaced too)."""
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, (*prefix, i))
    return out


BASE = {name: yaml.safe_load((REPO / "config" / name).read_text()) for name in CONFIGS}
PATHS = {name: _paths(data) for name, data in BASE.items()}


def _check_error(exc: ConfigError) -> None:
    assert exc.problems, "a ConfigError names its problems"
    assert len(exc.problems) <= MAX_PROBLEMS + 1
    for line in exc.problems:
        assert line.strip() and len(line) <= MAX_PROBLEM_CHARS + 40, line[:200]
        assert "Traceback" not in line


@fuzz(200)
@given(st.lists(st.sampled_from(YAML_ATOMS) | st.text(max_size=20), min_size=1, max_size=6),
       st.sampled_from(["", "  ", "key: ", "- ", "a:\n  b: "]))
def test_yaml_text_gives_a_value_or_one_config_error(atoms: list[str], lead: str) -> None:
    text = lead + "\n".join(atoms)
    try:
        parse_yaml_text(text, "fuzz.yaml")
    except ConfigError as exc:
        _check_error(exc)
        assert len(exc.problems) == 1 and exc.problems[0].startswith("fuzz.yaml: ")


@fuzz(150)
@given(st.sampled_from(CONFIGS), st.data())
def test_mutated_configuration_is_valid_or_one_config_error(name: str, data: st.DataObject) -> None:
    cfg = copy.deepcopy(BASE[name])
    for _ in range(data.draw(st.integers(1, 3), label="mutations")):
        path = data.draw(st.sampled_from(PATHS[name]), label="path")
        node = cfg
        try:
            for k in path[:-1]:
                node = node[k]
            if data.draw(st.booleans(), label="delete") and isinstance(node, dict):
                node.pop(path[-1], None)
            else:
                node[path[-1]] = data.draw(HOSTILE, label="value")
        except (KeyError, IndexError, TypeError):
            continue  # an earlier mutation replaced a parent
    try:
        parse_app_config(cfg, REPO / "config" / name)
    except ConfigError as exc:
        _check_error(exc)


@pytest.mark.parametrize("name", CONFIGS)
def test_unmutated_configurations_load(name: str) -> None:
    """The fuzz base is valid: a mutation that breaks nothing must load."""
    assert parse_app_config(copy.deepcopy(BASE[name]), REPO / "config" / name) is not None
