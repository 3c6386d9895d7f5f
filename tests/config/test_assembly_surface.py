"""What the configuration and the assembly expose after the clean-up: no unused AppConfig helpers, the scenario
registry imported from control/ (not re-exported by the assembly), and controller terms through a typed
protocol."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import stagectl.app as app
from stagectl.clock import SimClock
from stagectl.config import AppConfig, load_app_config
from stagectl.control.api import Command, Reference
from stagectl.control.controller import TERM_NAMES
from stagectl.errors import StageError
from stagectl.runtime.protocols import NamesTerms

REPO = Path(__file__).resolve().parents[2]


def test_app_config_has_no_unused_helpers():
    assert not hasattr(AppConfig, "period_s") and not hasattr(AppConfig, "resolve")


def test_scenario_registry_is_not_re_exported_by_the_assembly():
    assert not {"get_scenario", "scenario_names", "TrajectoryReference"} & set(app.__all__)
    for path in (REPO / "stagectl").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module == "stagectl.app":
                names = {a.name for a in node.names}
                assert not names & {"get_scenario", "scenario_names", "TrajectoryReference"}, path


class _Named:
    term_names = ("u_a", "u_b")

    def reset(self, x_m: float) -> None:
        pass

    def step(self, dt: float, x_meas_m: float, ref: Reference) -> Command:
        return Command(0.0, {"u_a": 0.0, "u_b": 0.0})

    def retune(self, cfg: object) -> None:
        pass


def test_controller_terms_through_the_typed_protocol():
    assert isinstance(_Named(), NamesTerms)
    cfg = load_app_config(REPO / "config" / "sim.yaml")
    with app.build_stage(cfg, clock=SimClock(), controller=_Named()) as stage:
        assert stage.loop.term_names == ("u_a", "u_b")
    with app.build_stage(cfg, clock=SimClock()) as stage:
        assert stage.loop.term_names == tuple(TERM_NAMES)


def test_inject_fault_refused_on_a_stage_without_simulation():
    stage = object.__new__(app.Stage)
    stage.plant_io = None
    stage.world = None
    with pytest.raises(StageError, match="only available on a simulated stage"):
        stage.inject_fault("emcy")
