"""More hidden plants for commissioning evaluations: kinds ``plant_gen`` does not draw.

``fresh_plant(seed)`` returns ``(plant, kind)``; the kind cycles with the seed over :data:`KINDS`:

* ``light``: a ``plant_gen``-like stage (0.5–20 kg, GMS, optional cogging and offset);
* ``heavy``: a 20–100 kg ball-screw axis, friction and force limit scaled with the mass
  (Coulomb 0.3–1.0 N/kg, viscous 2–10 N s/(m kg), break-aways 0.5–50 µm, 5 nm encoder) with a cogging
  or an offset (an inclined axis);
* ``offset``: a light stage whose only position effect is a constant force (10–30 % of Coulomb);
* ``spring``: a light stage with a spring (10–30 % of Coulomb at 1 mm from its rest position);
* ``coulomb``: Coulomb-dominated (1.0–1.8 N, viscous 1–4 N s/m), with a cogging;
* ``viscous``: viscous-dominated (Coulomb 0.2–0.5 N, viscous 40–100 N s/m), with a cogging.

``fresh_stage_yaml`` writes the commissioning configuration: the plant in ``sim:`` (not read by the
commissioning), a controller whose mass is 30 % off, whose gains are the seed stage's 40 Hz ones scaled to
that mass, and whose feed-forward model file has every friction level 30–50 % away from the plant's.
The heavy kind gets a matching scale: force limit 15 N/kg, ±0.1 m travel, 100 µm following error, 50 mm/s.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from commission_stage import controller_and_safety_yaml

KINDS = ("light", "heavy", "offset", "spring", "coulomb", "viscous")


def _logu(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(math.log(lo), math.log(hi))))


def fresh_plant(seed: int) -> tuple[dict[str, Any], str]:
    """The ``sim.plant`` mapping of fresh plant ``seed`` and its kind (deterministic)."""
    kind = KINDS[seed % len(KINDS)]
    rng = np.random.default_rng(10_000 + seed)
    if kind == "heavy":
        mass = _logu(rng, 20.0, 100.0)
        fc = mass * float(rng.uniform(0.3, 1.0))
        visc = mass * float(rng.uniform(2.0, 10.0))
        d_lo, d_hi = _logu(rng, 0.5e-6, 3e-6), _logu(rng, 10e-6, 50e-6)
        vs = _logu(rng, 1e-3, 1e-2)
    else:
        mass = _logu(rng, 0.5, 5.0 if kind in ("coulomb", "viscous") else 20.0)
        fc = _logu(rng, 0.3, 1.8)
        visc = _logu(rng, 2.0, 40.0)
        if kind == "coulomb":
            fc, visc = _logu(rng, 1.0, 1.8), _logu(rng, 1.0, 4.0)
        elif kind == "viscous":
            fc, visc = _logu(rng, 0.2, 0.5), _logu(rng, 40.0, 100.0)
        d_lo, d_hi = _logu(rng, 0.1e-6, 1e-6), _logu(rng, 3e-6, 20e-6)
        vs = _logu(rng, 3e-4, 3e-3)
    fs = fc * float(rng.uniform(1.0, 1.3))
    n = int(rng.integers(3, 9 if kind != "heavy" else 7))
    deltas = np.geomspace(d_lo, d_hi, n)
    alpha = rng.uniform(0.5, 1.5, n)
    alpha /= alpha.sum()
    k = alpha * fs / deltas
    s1 = 2 * 0.1 * math.sqrt(float(k.sum()) * mass) * k / k.sum()
    q = 5e-9 if kind == "heavy" else 1e-9
    plant: dict[str, Any] = {
        "mass_kg": round(mass, 4),
        "friction": {"model": "gms", "k_n_m": [round(float(v), 1) for v in k],
                     "alpha": [round(float(v), 4) for v in alpha], "fs_n": round(fs, 4), "fc_n": round(fc, 4),
                     "vs_m_s": round(vs, 6), "delta": 2.0, "c_n_s": round(10.0 * fs / 1e-3, 1),
                     "viscous_n_s_m": round(visc, 3), "sigma1_n_s_m": [round(float(v), 3) for v in s1]},
        "sensor": {"resolution_m": q, "noise_std_m": q / 2},
        "actuator": {"max_force_n": 200.0 if kind != "heavy" else round(40.0 * mass, 0)},
        "seed": seed,
    }
    eff: dict[str, Any] = {}
    cog = {"amplitude_n": round(fc * float(rng.uniform(0.05, 0.25)), 4),
           "wavelength_m": round(float(rng.uniform(0.3e-3, 1.5e-3) * (3.0 if kind == "heavy" else 1.0)), 6),
           "phase_rad": round(float(rng.uniform(-math.pi, math.pi)), 3)}
    off = {"force_n": round(fc * float(rng.uniform(0.1, 0.3)) * float(rng.choice([-1, 1])), 4)}
    if kind == "light":
        if rng.uniform() < 0.7:
            eff["cogging"] = cog
        if rng.uniform() < 0.4 or not eff:
            eff["offset"] = off
    elif kind == "heavy":
        if rng.uniform() < 0.5:
            eff["cogging"] = cog
        else:
            eff["offset"] = off
    elif kind == "offset":
        eff["offset"] = off
    elif kind == "spring":
        eff["spring"] = {"stiffness_n_m": round(fc * float(rng.uniform(0.1, 0.3)) / 1e-3, 2),
                         "x0_m": round(float(rng.uniform(-0.5e-3, 0.5e-3)), 6)}
    else:
        eff["cogging"] = cog
    plant["effects"] = eff
    return plant, kind


def _config_model(plant: dict[str, Any], rng: np.random.Generator, m_cfg: float) -> dict[str, Any]:
    """What the user believes: the plant's friction with every level 30–50 % off (either way)."""
    fr = dict(plant["friction"])
    for key in ("fc_n", "viscous_n_s_m", "vs_m_s"):
        fr[key] = round(fr[key] * (1 + float(rng.uniform(0.3, 0.5)) * float(rng.choice([-1, 1]))), 6)
    fr["fs_n"] = round(fr["fc_n"] * plant["friction"]["fs_n"] / plant["friction"]["fc_n"], 6)
    s = float(rng.uniform(0.5, 0.7)) if rng.uniform() < 0.5 else float(rng.uniform(1.3, 1.5))
    fr["k_n_m"] = [round(v * s, 1) for v in fr["k_n_m"]]
    fr["c_n_s"] = round(10.0 * fr["fs_n"] / 1e-3, 1)
    return {"mass_kg": round(m_cfg, 4), "friction": fr}


def fresh_stage_yaml(path: Path, plant: dict[str, Any], kind: str) -> Path:
    """The commissioning configuration of ``plant`` (see the module docstring); the model file is written
    beside it."""
    import yaml

    rng = np.random.default_rng(20_000 + int(plant["seed"]))
    rest = yaml.safe_load(controller_and_safety_yaml())
    ctl, saf = rest["controller"], rest["safety"]
    m_cfg = plant["mass_kg"] * (1.3 if plant["seed"] % 2 else 1 / 1.3)
    s = m_cfg / ctl["mass_kg"]
    ctl["mass_kg"] = round(m_cfg, 4)
    for key in ("kp_n_m", "ki_n_m_s", "kd_n_s_m"):
        ctl["pid"][key] = float(ctl["pid"][key]) * s
    model = path.with_suffix(".model.yaml")
    model.write_text(yaml.safe_dump(_config_model(plant, rng, m_cfg)))
    ctl["feedforward"]["model_file"] = str(model)
    if kind == "heavy":
        f = float(round(15.0 * plant["mass_kg"], -1))
        ctl["max_force_n"] = f
        saf.update(max_force_n=f, min_position_m=-0.1, max_position_m=0.1, following_error_m=1e-4,
                   max_velocity_m_s=0.05)
    path.write_text(yaml.safe_dump({
        "description": f"fresh hidden plant ({kind})", "loop": {"period_s": 0.001},
        "io": {"kind": "plant_io", "sensor": "drive", "delay_cycles": 1}, "sim": {"plant": plant}, **rest}))
    return path
