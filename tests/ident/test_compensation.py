"""A discovered effect improves compensation (issue 6): discover's augmented ``model.yaml`` used as the
controller's feed-forward ``model_file`` in ``stagectl simulate`` reduces the tracking error on the stage
with that (hidden) effect, compared with the same model without the effect."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from stagectl.friction import load_model_file
from stagectl.ident import synth
from stagectl.ident.discover import discover
from stagectl.ident.report import write_outputs

REPO = Path(__file__).resolve().parents[2]


def test_discovered_cogging_in_feedforward_reduces_tracking_error(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    from stagectl.cli import main

    rng = np.random.default_rng(606)
    cog = {"amplitude_n": float(rng.uniform(0.3, 0.6)), "wavelength_m": float(rng.uniform(0.15e-3, 0.3e-3)),
           "phase_rad": float(rng.uniform(0, 2 * np.pi))}
    stage = {"mass_kg": 2.0, "friction": {"model": "stribeck", "fc_n": 0.5, "fs_n": 0.5, "viscous_n_s_m": 20.0},
             "effects": {"cogging": cog}, "sensor": {"resolution_m": 1e-9, "noise_std_m": 0.5e-9}}
    rec = synth.closed_loop(stage, motion=synth.Motion(duration_s=8.0, v_max_m_s=5e-3), seed=606)
    res = discover(rec)
    assert [e.name for e in res.effects] == ["cogging"]
    write_outputs(res, tmp_path / "disc", {"estimation": "synth"}, plots=False)
    augmented = tmp_path / "disc" / "model.yaml"
    model = load_model_file(augmented)
    assert model.effects.cogging is not None
    plain_spec = yaml.safe_load(augmented.read_text(encoding="utf-8"))
    plain_spec.pop("effects")
    plain_spec.pop("meta", None)
    plain = tmp_path / "plain.yaml"
    plain.write_text(yaml.safe_dump(plain_spec), encoding="utf-8")

    cfg = yaml.safe_load((REPO / "config" / "sim.yaml").read_text(encoding="utf-8"))
    cfg["sim"]["plant"] = {**{k: v for k, v in cfg["sim"]["plant"].items() if k != "model_file"}, **stage}
    rms = {}
    for name, mf in (("plain", plain), ("augmented", augmented)):
        cfg["controller"]["feedforward"]["model_file"] = str(mf)
        path = tmp_path / f"cfg_{name}.yaml"
        path.write_text(yaml.safe_dump(cfg), encoding="utf-8")
        assert main(["simulate", "--config", str(path), "--scenario", "triangle", "--out",
                     str(tmp_path / f"run_{name}"), "--no-plots"]) == 0
        summary = json.loads((tmp_path / f"run_{name}" / "summary.json").read_text(encoding="utf-8"))
        assert summary["fault"] is None
        rms[name] = summary["rms_error_m"]
    capsys.readouterr()
    print(rms)
    assert rms["augmented"] < 0.7 * rms["plain"], rms
