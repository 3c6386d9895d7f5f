"""The sanity probe and the drive's own force limit (found by an outside-in check of a user-made stage).

* A stage whose breakaway lies between the probe's gentle search (F_max/2) and F_max is probed once more up to
  F_max at the same ramp rate, instead of being called a stuck axis.
* A CiA 402 drive whose max torque 0x6072 is 3000 units, 3 N with the shipped 1 mN units (the virtual drive
  with ``sim.drive.max_force_n: 3``), under the configured 10 N: the driver clamps every command there. The experiments now clamp at that limit too, so
  a recording's ``u`` is the force the stage got (before, the probe recorded 4 N while the drive applied 3 N).

Each run stops with an injected fault early in the FRF, right after the probe (simulated time).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from commission_stage import write_stage  # noqa: E402
from support import shipped_config_mapping  # noqa: E402

from stagectl.cli import main  # noqa: E402
from stagectl.commission.envelope import make_envelope, within_drive_limit  # noqa: E402
from stagectl.ident.recording import load_recording  # noqa: E402


def _commission_to_frf(cfg: Path, out: Path) -> dict:
    rc = main(["commission", "--config", str(cfg), "--out", str(out), "--no-plots", "--quiet",
               "--inject-fault", "frf@0.05"])
    rep = json.loads((out / "report.json").read_text())
    assert rc == 1 and rep["aborted"]["experiment"] == "frf", rep["aborted"]
    return rep


def test_breakaway_above_half_the_force_is_probed_again_up_to_f_max(tmp_path: Path) -> None:
    # 2.6 kg plant, Coulomb 4.2 N, static 4.35 N: above F_max/2 = 3.5 N, below F_max = 7 N (plant_io: no drive)
    cfg = write_stage(tmp_path / "stiff.yaml", fc_n=4.2)
    rep = _commission_to_frf(cfg, tmp_path / "o")
    names = [e["name"] for e in rep["experiments"]]
    assert names[:3] == ["sanity", "sanity_full_force", "frf"], names
    brk = rep["sanity"]["breakaway_n"]
    assert all(3.5 < b <= 7.0 for b in brk), brk  # above the first search's F_max/2, below F_max
    assert abs(rep["sanity"]["mass_kg"] / 2.6 - 1) < 0.2, rep["sanity"]


def test_experiments_stay_within_the_drives_max_torque(tmp_path: Path) -> None:
    data = shipped_config_mapping("sim.yaml")
    data["sim"]["drive"]["max_force_n"] = 3.0  # the drive's 0x6072: 3000 x 1 mN
    data["sim"]["plant"]["friction"] = {"fc_n": 1.5, "fs_n": 1.6}  # probe levels 1.5x and 2.5x breakaway: 4 N
    cfg = tmp_path / "sim3n.yaml"
    cfg.write_text(yaml.safe_dump(data))
    rep = _commission_to_frf(cfg, tmp_path / "o")
    assert rep["envelope"]["drive_limit_n"] == pytest.approx(3.0)
    u = load_recording(tmp_path / "o" / "recordings" / "sanity.csv", min_rows=100).u
    assert np.max(np.abs(u)) <= 3.0 + 1e-9
    assert np.max(np.abs(u)) >= 2.9  # the probe did reach the drive's limit (it asked for 4 N)


def test_drive_limit_only_lowers_what_is_commanded() -> None:
    env = make_envelope(min_position_m=-0.005, max_position_m=0.005, safety_force_n=10.0, controller_force_n=10.0,
                        max_velocity_m_s=0.02, period_s=1e-3, following_error_m=5e-5)
    assert within_drive_limit(env, None) is env and within_drive_limit(env, 30.0) is env
    low = within_drive_limit(env, 3.0)
    assert low.f_max_n == env.f_max_n == pytest.approx(7.0)  # amplitudes keep scaling with F_max
    assert low.f_cmd_n == 3.0 and env.f_cmd_n == pytest.approx(7.0)
    assert "drive_limit_n" not in env.as_dict() and low.as_dict()["drive_limit_n"] == 3.0


def test_no_motion_says_the_drive_limit_is_a_cap_not_scaled_by_the_fraction() -> None:
    """The probe's force is min(0.7 x min(safety, controller, --max-force), drive limit): the drive's own limit is a
    cap, not one of the forces the 0.7 applies to (the line read "0.7 x the lowest of ... and the drive's limit")."""
    from stagectl.commission.analysis import SanityError, evaluate_probe
    from stagectl.commission.controllers import ProbeDirection

    with pytest.raises(SanityError) as ei:
        evaluate_probe([ProbeDirection(1, "no_motion"), ProbeDirection(-1, "no_motion")], 3.0, 2e-5, 1.0)
    msg = str(ei.value)
    assert "\n" not in msg and "with up to 3 N" in msg, msg
    assert "0.7 x the lowest of safety.max_force_n, controller.max_force_n and --max-force" in msg, msg
    assert "never above the drive's limit" in msg, msg
