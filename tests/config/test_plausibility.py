"""Implausible but in-range values: one line each, naming the field, the value and the unit."""

from __future__ import annotations

import pytest
from support import config_problems, shipped_config_mapping

from stagectl.config import parse_app_config


def _set(data: dict, path: str, value: object) -> dict:
    node = data
    *parents, leaf = path.split(".")
    for key in parents:
        node = node.setdefault(key, {})
    node[leaf] = value
    return data


@pytest.mark.parametrize(("path", "value", "expect"), [
    ("safety.following_error_m", 50.0, "safety.following_error_m: 50 m is not smaller than the stroke"),
    ("sim.plant.sensor.resolution_m", 1.0, "sim.plant.sensor.resolution_m: 1 m per count is coarser"),
    ("controller.dob.bandwidth_hz", 1000.0, ("controller.dob.bandwidth_hz: 1000 Hz is at or above the Nyquist "
                                             "frequency 500 Hz")),
    ("controller.pid.derivative_cutoff_hz", 600.0, "controller.pid.derivative_cutoff_hz: 600 Hz"),
    ("safety.velocity_filter_hz", 500.0, "safety.velocity_filter_hz: 500 Hz is at or above"),
    ("safety.quick_stop_deceleration_m_s2", 0.001, ("safety.quick_stop_deceleration_m_s2: 0.001 m/s^2 stops the "
                                                    "stage from max_velocity_m_s 0.02 m/s in 0.2 m, more than the "
                                                    "stroke 0.01 m")),
    ("controller.settle.move_s", 0.0001, ("controller.settle.move_s: 0.0001 s is shorter than two loop periods "
                                          "(0.002 s)")),
])
def test_implausible_value_is_one_line(path: str, value: object, expect: str) -> None:
    problems = config_problems(_set(shipped_config_mapping("sim.yaml"), path, value))
    assert len(problems) == 1 and problems[0].startswith("x.yaml: " + expect), problems


def test_shipped_configs_are_plausible(repo_root) -> None:
    for name in ("sim.yaml", "hil-canopen.yaml", "hil-serial.yaml", "stage-canopen.yaml"):
        parse_app_config(shipped_config_mapping(name), repo_root / "config" / name)


@pytest.mark.parametrize(("path", "value", "expect"), [
    ("loop.period_s", None, "loop.period_s: expected a number s, got null"),
    ("controller.pid.kp_n_m", True, "controller.pid.kp_n_m: expected a number N/m, got true"),
    ("controller.pid.kp_n_m", {"a": 1}, "controller.pid.kp_n_m: expected a number N/m, got a mapping {'a': 1}"),
    ("loop", 5, "loop: expected a mapping, got the number 5"),
])
def test_wrong_kind_is_said_in_yaml_words(path: str, value: object, expect: str) -> None:
    """null, true, a mapping: what the user wrote, not Python's NoneType/bool/dict."""
    problems = config_problems(_set(shipped_config_mapping("sim.yaml"), path, value))
    assert problems == ["x.yaml: " + expect], problems


@pytest.mark.parametrize("path", ["sim.plant.seed", "sim.interferometer.seed"])
def test_a_negative_seed_is_refused_in_one_line(path: str) -> None:
    """numpy refuses a negative seed: check-config said OK and simulate ended in 'internal error: ValueError:
    expected non-negative integer' (exit 70); audit16."""
    data = shipped_config_mapping("hil-serial.yaml")
    problems = config_problems(_set(data, path, -1))
    assert problems == [f"x.yaml: {path}: must be >= 0 (got -1)"], problems
