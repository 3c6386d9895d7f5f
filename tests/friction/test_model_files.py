"""The shipped model files: Table 1 values, every value documented (from the paper or chosen), usable."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stagectl.friction import load_model_file
from stagectl.resources import config_dir

MODELS = Path(__file__).resolve().parents[2] / "config" / "models"
FILES = sorted(MODELS.glob("*.yaml"))

TABLE1 = {
    "kamenar2016_gms.yaml": {"k_n_m": (454610.0, 111088.0, 45601.0, 16402.0, 6899.0, 4295.0),
                             "alpha": (0.378, 0.138, 0.148, 0.177, 0.112, 0.046), "fs_n": 0.9},
    "kamenar2016_hsieh.yaml": {"k1s_n_m": 51540.0, "k2s_n_m": 2026400.0, "beta_1_m": 3216500.0,
                               "cv_n_s_m": 5000.0, "rho_1_s": 500.0, "psi": 31200.0, "a": 3.22},
}


def test_both_seed_model_files_are_shipped_where_resources_finds_them():
    assert {f.name for f in FILES} >= set(TABLE1)
    assert (config_dir() / "models").resolve() == MODELS.resolve()


@pytest.mark.parametrize("name", sorted(TABLE1))
def test_table1_values(name):
    params = load_model_file(MODELS / name).friction.params
    for key, value in TABLE1[name].items():
        assert getattr(params, key) == value, key


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_every_value_is_documented_in_the_header(path):
    """Each friction key and mass_kg is named in the header comments (from the paper, or chosen and why)."""
    text = path.read_text(encoding="utf-8")
    header = "\n".join(line for line in text.splitlines() if line.startswith("#"))
    assert "NOT given by the paper" in header
    model = load_model_file(path)
    keys = [k for k in model.friction.spec() if k != "model"] + (["mass_kg"] if model.mass_kg else [])
    undocumented = [k for k in keys if k not in header and k in text.split("friction:")[1]]
    assert not undocumented, f"{path.name}: values not documented in the header: {undocumented}"


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_model_file_runs_in_the_plant_and_slides_both_ways(path):
    from stagectl.sim.plant import plant_from_model

    dut = plant_from_model(load_model_file(path))
    t = np.arange(20000) * 1e-4
    r = dut.simulate(1.5 * np.sin(2 * np.pi * 2.0 * t), 1e-4)
    assert np.all(np.isfinite(r["x"])) and np.ptp(r["x"]) > 1e-3
    sliding = np.abs(r["v"]) > 2e-3
    assert np.all(np.sign(r["friction"][sliding]) == np.sign(r["v"][sliding]))  # friction opposes motion


def test_an_interrupt_while_a_model_file_is_written_keeps_the_old_file(tmp_path):
    """`stagectl identify --out models/stage.yaml` over the model a config uses: a Ctrl-C or SIGTERM (now a
    KeyboardInterrupt anywhere in the main thread) landing after the file was opened for writing and before
    its text was written left it empty, and the config no longer loaded. The new file replaces the old one
    whole, or not at all. The interrupt is raised at the write itself (a profile hook on the C call), not by
    timing."""
    import io
    import os
    import sys

    from stagectl.friction import save_model_file

    src = MODELS / "kamenar2016_gms.yaml"
    model = load_model_file(src)
    out = tmp_path / "stage.yaml"
    save_model_file(model, out, header="the good one")
    before = out.read_text()

    def interrupt_at_write(frame, event, arg):
        if event == "c_call" and getattr(arg, "__name__", "") == "write" and isinstance(
                getattr(arg, "__self__", None), io.TextIOWrapper):  # a write into a file (not yaml's StringIO)
            sys.setprofile(None)
            raise KeyboardInterrupt

    sys.setprofile(interrupt_at_write)
    try:
        with pytest.raises(KeyboardInterrupt):
            save_model_file(model, out, header="the new one")
    finally:
        sys.setprofile(None)
    assert out.read_text() == before
    assert load_model_file(out).friction.params == model.friction.params
    assert os.listdir(tmp_path) == ["stage.yaml"]  # no temporary file left behind
