"""Commissioning evaluation on hidden plants (the README's *Known limits* table; docs/commissioning.md).

Run from the repository root::

    .venv/bin/python tests/commission/eval_hidden_plants.py TAG PLANT [PLANT ...]

A plant ``kN`` is :func:`plant_kinds.fresh_plant` (N) with its own config scale, a plain ``N`` is
:func:`plant_gen.hidden_plant` (N). Each is commissioned lock-step in-process with ``--max-stroke 0.002
--no-verify`` (0.01 m for a heavy axis) from a config without the plant's parameters, then ``stage.yaml`` and
the same gains given the exact hidden model run the verification scenarios (``simulate_verification``, settle
band max(10 nm, 2 sensor quanta)). One JSON row per plant goes to stdout and to ``runs/eval-hidden/TAG/
rows.jsonl``: identified vs true mass, Coulomb and viscous (``m_err``, ``fc_err``, ``fv_err``), the named
effects, the largest following error of the experiments, and the cosine / triangle / steps RMS ratios new /
exact with the steps settled. Not a test (pytest does not collect it): ~15–40 s of CPU per plant.
"""

from __future__ import annotations

import csv
import json
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from plant_gen import against_exact, hidden_plant, stage_yaml

from stagectl.cli import main


def _peak_error(out: Path, row: dict[str, Any]) -> None:
    peak = 0.0
    for f in sorted((out / "recordings").glob("*.csv")):
        with open(f) as fh:
            rd = csv.reader(line for line in fh if not line.startswith("#"))
            ie = next(rd).index("e")
            e = max((abs(float(r[ie])) for r in rd if len(r) > ie), default=0.0)
        if e > peak:
            peak, row["peak_in"] = e, f.stem
    row["peak_um"] = round(peak * 1e6, 2)


def evaluate(root: Path, s: str) -> dict[str, Any]:
    if s.startswith("k"):
        from plant_kinds import fresh_plant, fresh_stage_yaml

        plant, kind = fresh_plant(int(s[1:]))
        cfg = fresh_stage_yaml(root / f"p{s}.yaml", plant, kind)
    else:
        plant, kind = hidden_plant(int(s)), "gen"
        cfg = stage_yaml(root / f"p{s}.yaml", plant)
    stroke = 0.01 if kind == "heavy" else 0.002
    out = root / f"out{s}"
    t0 = time.process_time()
    rc = main(["commission", "--config", str(cfg), "--out", str(out), "--no-plots", "--no-verify", "--quiet",
               "--max-stroke", str(stroke)])
    fr = plant["friction"]
    row: dict[str, Any] = {"plant": s, "kind": kind, "rc": rc, "cpu_s": round(time.process_time() - t0, 1),
                           "mass": plant["mass_kg"], "fc": fr["fc_n"], "fv": fr["viscous_n_s_m"],
                           "eff": sorted(plant.get("effects") or {})}
    if not (out / "report.json").is_file():
        return row
    rep = json.loads((out / "report.json").read_text())
    row["status"] = rep.get("status")
    if rep.get("aborted"):
        row["aborted"] = {k: rep["aborted"].get(k) for k in ("experiment", "reason")}
    _peak_error(out, row)
    if rc != 0:
        return row
    fit = rep["fitted"]
    row["found"] = fit["effects"]
    row["m_err"] = round(fit["mass_kg"]["value"] / plant["mass_kg"] - 1, 4)
    row["fc_err"] = round(fit["coulomb_n"]["value"] / fr["fc_n"] - 1, 4)
    row["fv_err"] = round(fit["viscous_n_s_m"]["value"] / fr["viscous_n_s_m"] - 1, 4)
    r = against_exact(out, plant, stroke, max(10e-9, 2 * plant["sensor"]["resolution_m"]))
    for sc in ("cosine", "triangle", "steps"):
        if sc in r["new"]:
            row[sc] = (r["new"][sc]["rms_error_m"], r["exact"][sc]["rms_error_m"])
            row[sc + "_ratio"] = round(r["new"][sc]["rms_error_m"] / r["exact"][sc]["rms_error_m"], 3)
    st, se = r["new"]["steps"], r["exact"]["steps"]
    row["settled"] = f'{st["moves_settled"]}/{st["moves"]}'
    row["settled_exact"] = f'{se["moves_settled"]}/{se["moves"]}'
    return row


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit("usage: eval_hidden_plants.py TAG PLANT [PLANT ...]   (PLANT: kN fresh, N generated)")
    root = (Path("runs") / "eval-hidden" / sys.argv[1]).resolve()
    root.mkdir(parents=True, exist_ok=True)
    for s in sys.argv[2:]:
        row = evaluate(root, s)
        print(json.dumps(row, default=str), flush=True)
        with open(root / "rows.jsonl", "a") as f:
            f.write(json.dumps(row, default=str) + "\n")
