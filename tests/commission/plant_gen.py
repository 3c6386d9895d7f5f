"""A generator of hidden plants for commissioning tests: stages the commissioning has never seen.

``hidden_plant(seed)`` draws a plant inside what the shipped test stage's limits permit (10 N force, ±5 mm,
20 mm/s): mass 0.5–20 kg; a GMS friction with Coulomb 0.3–1.8 N, static/Coulomb 1.0–1.3 (break-away within a quarter of the force limit), Stribeck velocity
0.3–3 mm/s, viscous 2–40 N s/m, 3–8 Maxwell-slip elements whose break-away displacements are log-spaced
within 0.1–20 µm (total pre-sliding stiffness from them, micro-damping ζ ≈ 0.1); optionally a cogging force
(5–25 % of Coulomb, period 0.3–1.5 mm) and an offset (±5–20 % of Coulomb). ``stage_yaml`` embeds it in a
``sim:`` section the commissioning does not read; the controller side is the seed stage's
(:func:`commission_stage.controller_and_safety_yaml`). ``exact_model`` is the plant's model as a model file
(the oracle's feed-forward). The configuration states a mass 30 % off the plant's and the seed
stage's gains scaled to it.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from commission_stage import controller_and_safety_yaml


def hidden_plant(seed: int) -> dict[str, Any]:
    """The ``sim.plant`` mapping of generated plant number ``seed`` (deterministic)."""
    rng = np.random.default_rng(seed)
    mass = float(np.exp(rng.uniform(math.log(0.5), math.log(20.0))))
    fc = float(np.exp(rng.uniform(math.log(0.3), math.log(1.8))))
    fs = fc * float(rng.uniform(1.0, 1.3))
    n = int(rng.integers(3, 9))
    d_lo = float(np.exp(rng.uniform(math.log(0.1e-6), math.log(1e-6))))
    d_hi = float(np.exp(rng.uniform(math.log(3e-6), math.log(20e-6))))
    deltas = np.geomspace(d_lo, d_hi, n)
    alpha = rng.uniform(0.5, 1.5, n)
    alpha /= alpha.sum()
    k = alpha * fs / deltas
    zeta = 0.1
    s1 = 2 * zeta * math.sqrt(float(k.sum()) * mass) * k / k.sum()
    plant: dict[str, Any] = {
        "mass_kg": round(mass, 4),
        "friction": {"model": "gms", "k_n_m": [round(float(v), 1) for v in k],
                     "alpha": [round(float(v), 4) for v in alpha], "fs_n": round(fs, 4), "fc_n": round(fc, 4),
                     "vs_m_s": round(float(np.exp(rng.uniform(math.log(3e-4), math.log(3e-3)))), 6),
                     "delta": 2.0, "c_n_s": round(10.0 * fs / 1e-3, 1),
                     "viscous_n_s_m": round(float(np.exp(rng.uniform(math.log(2.0), math.log(40.0)))), 3),
                     "sigma1_n_s_m": [round(float(v), 3) for v in s1]},
        "sensor": {"resolution_m": 1.0e-9, "noise_std_m": 0.5e-9},
        "actuator": {"max_force_n": 200.0},
        "seed": seed,
    }
    eff: dict[str, Any] = {}
    if rng.uniform() < 0.7:
        eff["cogging"] = {"amplitude_n": round(fc * float(rng.uniform(0.05, 0.25)), 4),
                          "wavelength_m": round(float(rng.uniform(0.3e-3, 1.5e-3)), 6)}
    if rng.uniform() < 0.4:
        eff["offset"] = {"force_n": round(fc * float(rng.uniform(0.05, 0.2)) * float(rng.choice([-1, 1])), 4)}
    if eff:
        plant["effects"] = eff
    return plant


def exact_model(plant: dict[str, Any]) -> dict[str, Any]:
    """The plant's own model as a model file mapping (mass, friction, effects)."""
    m: dict[str, Any] = {"mass_kg": plant["mass_kg"], "friction": dict(plant["friction"])}
    if plant.get("effects"):
        m["effects"] = plant["effects"]
    return m


def stage_yaml(path: Path, plant: dict[str, Any]) -> Path:
    """A commissioning configuration for ``plant``: embedded lock-step plant (``sim:``), the seed stage's
    controller and safety sections."""
    import yaml

    rest = yaml.safe_load(controller_and_safety_yaml())
    # the configuration states the mass the user believes (30 % off the plant's, either way; the sanity
    # probe refuses 5x) and the seed stage's 40 Hz gains scaled to it
    ctl = rest["controller"]
    m_cfg = plant["mass_kg"] * (1.3 if plant["seed"] % 2 else 1 / 1.3)
    s = m_cfg / ctl["mass_kg"]
    ctl["mass_kg"] = round(m_cfg, 4)
    for key in ("kp_n_m", "ki_n_m_s", "kd_n_s_m"):
        ctl["pid"][key] = float(ctl["pid"][key]) * s
    path.write_text(yaml.safe_dump({
        "description": "generated hidden plant", "loop": {"period_s": 0.001},
        "io": {"kind": "plant_io", "sensor": "drive", "delay_cycles": 1}, "sim": {"plant": plant}, **rest}))
    return path


def against_exact(out: Path, plant: dict[str, Any], stroke_m: float = 0.002,
                  tol_m: float = 10e-9) -> dict[str, dict[str, Any]]:
    """DIR/stage.yaml's controller and the same gains given the exact model, both on the plant, through the
    verification's protocol (settle band ``tol_m`` [m]); returns {"new": ..., "exact": ...} of the scenario
    summaries."""
    import yaml

    from stagectl.commission.sequence import simulate_verification
    from stagectl.config import load_app_config

    data = yaml.safe_load((out / "stage.yaml").read_text())
    ctl = data["controller"]
    ctl["feedforward"]["model_file"] = str(out / ctl["feedforward"]["model_file"])
    (out / "exact.yaml").write_text(yaml.safe_dump(exact_model(plant)))
    comm_delay = float((yaml.safe_load(Path(ctl["feedforward"]["model_file"]).read_text()).get("effects") or {})
                       .get("delay", {}).get("delay_s", 0.0))
    exact = dict(ctl, mass_kg=plant["mass_kg"],
                 feedforward=dict(ctl["feedforward"], model_file=str(out / "exact.yaml"),
                                  lookahead_s=float(ctl["feedforward"]["lookahead_s"]) + comm_delay))
    res = {}
    for name, c in (("new", ctl), ("exact", exact)):
        d = dict(data, controller=c, io={"kind": "plant_io", "sensor": "drive", "delay_cycles": 1},
                 sim={"plant": plant})
        p = out / f"check-{name}.yaml"
        p.write_text(yaml.safe_dump(d))
        res[name] = simulate_verification(load_app_config(p), stroke_m, tol_m)
    return res


def verification_cosine(cfg: Any) -> tuple[Any, float]:
    """As ``simulate_verification`` for the cosine alone: a fresh stage at 0, the verification lead, the
    scenario (2 mm stroke), in simulated time, without a fault. Returns the recording and the lead's duration
    [s] (the scenario starts that long after the recording's first sample)."""
    from stagectl.app import build_stage
    from stagectl.clock import SimClock
    from stagectl.commission.sequence import _verify_scenario, verification_lead
    from stagectl.control.trajectory import Scenario
    from stagectl.recorder import Recorder

    lead = verification_lead(0.0, 0.002)
    sc = _verify_scenario("cosine", 0.0, 0.002)
    assert sc is not None
    full = Scenario(name="cosine", segments=(*lead, *sc.segments), start_m=0.0)
    dur = full.duration_s(0.0) + 0.2
    with build_stage(cfg, clock=SimClock()) as st:
        rec = Recorder(st.loop.columns, capacity=int(dur / cfg.loop.period_s) + 16)
        st.loop.add_sink(rec)
        st.load_scenario(full)
        res = st.loop.run(duration_s=dur)
    assert res.fault is None
    return rec, Scenario(name="lead", segments=lead).duration_s(0.0)
