"""Commissioning names no effect the stage does not have (issue 11: "the hidden effect is named", and only it).

* A cogging the slow passes' period scan finds must recur in a second experiment over the same positions, the
  constant-velocity passes (:func:`stagectl.commission.fit.cogging_confirmation`). Oracle: the plain simulation
  of ``test_cogging_edge`` (a rigid mass with smooth Coulomb + viscous friction and a position force under a
  PID, independent of stagectl's plant and controller), run at the slow passes' speed and at 2 mm/s.
* End to end on fresh plant k109 (``plant_kinds.fresh_plant(109)``: a 30 kg ball-screw-scale axis, GMS friction,
  an offset; no cogging, no play). Main named a backlash (its pre-sliding fit put 1.6e5 N s/m of micro-damping
  on an element, failed validation, and the backlash took the reversals) and a cogging (the slow passes'
  scan peaked at 68 mN, 6.97 mm, ratio 48; the constant-velocity passes show 0.00 of it).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from plant_kinds import fresh_plant, fresh_stage_yaml
from test_cogging_edge import T, _slow_passes

from stagectl.cli import main
from stagectl.commission.fit import cogging_confirmation, cogging_evidence


def test_cogging_is_named_only_when_the_constant_velocity_passes_show_it() -> None:
    amp, lam = 0.1, 0.68e-3

    def cog(x: float) -> float:
        return amp * math.sin(2 * math.pi * x / lam + 0.4)

    ev = cogging_evidence(_slow_passes(cog), 0.79, T)
    assert ev["present"], ev
    held_out = cogging_confirmation(_slow_passes(cog, v_m_s=2e-3), 0.79, T, ev)
    assert held_out["confirmed"] and abs(held_out["fraction"] - 1) < 0.1, held_out
    # the same scan result, but the other experiment over the same positions has no such force
    none = cogging_confirmation(_slow_passes(lambda x: 0.0, v_m_s=2e-3), 0.79, T, ev)
    assert not none["confirmed"] and abs(none["fraction"]) < 0.1, none
    assert none["amplitude_std_n"] < 0.1 * amp and "not a force of position" in none["reason"]


@pytest.mark.slow  # a whole commissioning of a 30 kg axis: ~13 s of CPU (pytest -m slow)
def test_heavy_axis_without_cogging_or_play_names_neither(tmp_path: Path) -> None:
    plant, kind = fresh_plant(109)
    assert kind == "heavy" and set(plant["effects"]) == {"offset"} and plant["friction"]["model"] == "gms"
    cfg = fresh_stage_yaml(tmp_path / "stage.yaml", plant, kind)
    out = tmp_path / "out"
    assert main(["commission", "--config", str(cfg), "--out", str(out), "--no-plots", "--no-verify", "--quiet",
                 "--max-stroke", "0.01"]) == 0
    rep = json.loads((out / "report.json").read_text())
    found = set(rep["fitted"]["effects"])
    assert {"offset", "presliding"} <= found, found  # what the plant has (GMS: pre-sliding)
    assert not {"backlash", "cogging", "position_ripple", "spring"} & found, found
    cog = rep["discovery"]["evidence"]["cogging"]
    assert not cog["present"], cog  # main: the slow passes' ratio 48, named
    assert "held_out" not in cog or cog["held_out"]["fraction"] < 0.1, cog
