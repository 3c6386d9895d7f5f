"""``stagectl bench models [--json] [--quick]``: friction model + plant throughput.

Measured in one run (figures are never copied from elsewhere):

* **single**: one open-loop plant trajectory (``StagePlant.simulate``) with each registered model,
  control period = sub-step = 10 µs, so one step = one plant+friction integration step;
* **batch**: the same plant with 1000 perturbed parameter sets (``stagectl.sim.plant.simulate_batch``);
* **baseline**: a straightforward pure-Python GMS (N = 6) + plant loop with the same equations;
* **per-sample**: ``model.step(state, dx, v, dt)`` called from Python, as the control loop's
  feed-forward does, and ``StagePlant.step(u, dt)`` (10 sub-steps), in µs per call.

JIT compile / cache-load time is excluded from every rate (each path is warmed up first) and reported
separately as ``warmup_s``. Rates are the best of ``--repeat`` runs (least disturbed by other load).
"""

from __future__ import annotations

import argparse
import math
import time
from typing import Any

import numpy as np

from stagectl.resources import config_dir

TARGET_SINGLE_STEPS_S = 2_000_000.0
TARGET_RATIO = 20.0
TARGET_PER_SAMPLE_US = 10.0

_MODELS_DIR = config_dir() / "models"  # repo checkout or the wheel's share/stagectl/config

K6 = [454610.0, 111088.0, 45601.0, 16402.0, 6899.0, 4295.0]
A6 = [0.378, 0.138, 0.148, 0.177, 0.112, 0.046]

#: benchmark parameter sets per tag (SI units); a model file is used instead where one is shipped
SPECS: dict[str, dict[str, Any]] = {
    "gms": {"model": "gms", "k_n_m": K6, "alpha": A6, "fc_n": 0.8, "fs_n": 0.9, "vs_m_s": 1e-3, "delta": 2.0,
            "c_n_s": 1e4, "viscous_n_s_m": 10.0, "sigma1_n_s_m": [160.88, 39.31, 16.14, 5.80, 2.44, 1.52]},
    "maxwell_slip": {"model": "maxwell_slip", "k_n_m": K6, "alpha": A6, "fs_n": 0.9, "viscous_n_s_m": 10.0},
    "stribeck": {"model": "stribeck", "fc_n": 0.8, "fs_n": 0.9, "vs_m_s": 1e-3, "viscous_n_s_m": 10.0},
    "lugre": {"model": "lugre", "sigma0_n_m": 1e5, "sigma1_n_s_m": math.sqrt(1e5), "viscous_n_s_m": 0.4,
              "fc_n": 1.0, "fs_n": 1.5, "vs_m_s": 1e-3},
    "dahl": {"model": "dahl", "sigma0_n_m": 1e5, "fc_n": 1.0},
}
MODEL_FILES = {"hsieh": "kamenar2016_hsieh.yaml", "gms": "kamenar2016_gms.yaml"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="short run (~10 s): fewer steps and sets")
    parser.add_argument("--steps", type=int, default=None, help="steps of the single trajectory (default 2e6)")
    parser.add_argument("--sets", type=int, default=1000, help="parameter sets in the batch run (default 1000)")
    parser.add_argument("--repeat", type=int, default=None, help="repetitions; the best is reported (default 3)")
    parser.add_argument("--models", default=None, help="comma-separated tags (default: every registered model)")


# ---------------------------------------------------------------------------------------------- baseline
def python_gms_plant(n_steps: int, dt: float, mass: float, spec: dict[str, Any]) -> float:
    """Pure-Python GMS + rigid-body loop (symplectic Euler), the straightforward way. Returns final x."""
    k = list(spec["k_n_m"])
    a = list(spec["alpha"])
    fc, fs, vs, c = spec["fc_n"], spec["fs_n"], spec["vs_m_s"], spec["c_n_s"]
    s1 = list(spec["sigma1_n_s_m"])
    s2 = spec["viscous_n_s_m"]
    n = len(k)
    f = [0.0] * n
    mode = [0.0] * n
    x = v = ff = 0.0
    for step in range(n_steps):
        u = 1.5 * math.sin(2.0 * math.pi * 5.0 * step * dt)
        v += dt * (u - ff) / mass
        dx = dt * v
        x += dx
        if v == 0.0:
            ff = sum(f)
            continue
        sg = 1.0 if v > 0 else -1.0
        g = fc + (fs - fc) * math.exp(-((v / vs) ** 2))
        decay = math.exp(-c * dt / g)
        tot = s2 * v
        for i in range(n):
            lim = a[i] * g
            if mode[i] != 0.0 and mode[i] != sg:
                mode[i] = 0.0
            if mode[i] == 0.0:
                if sg * f[i] >= lim:
                    mode[i] = sg
                    f[i] = sg * lim + (f[i] - sg * lim) * decay
                else:
                    f[i] += k[i] * dx
                    if sg * f[i] >= lim:
                        f[i] = sg * lim
                        mode[i] = sg
            else:
                f[i] = sg * lim + (f[i] - sg * lim) * decay
            rate = v if mode[i] == 0.0 else c * (sg * a[i] - f[i] / g) / k[i]
            tot += f[i] + s1[i] * rate
        ff = tot
    return x


# ---------------------------------------------------------------------------------------------- helpers
def _best(fn: Any, repeat: int) -> float:
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _spec_for(tag: str) -> dict[str, Any] | None:
    from stagectl.friction import load_model_file

    fname = MODEL_FILES.get(tag)
    if fname and (_MODELS_DIR / fname).exists():
        return load_model_file(_MODELS_DIR / fname).friction.spec()
    return SPECS.get(tag)


def _perturbed(model: Any, n_sets: int, rng: np.random.Generator) -> list[Any]:
    """``n_sets`` models with every positive float parameter scaled by U(0.8, 1.2) (fs >= fc kept)."""
    spec = model.spec()
    out = []
    for _ in range(n_sets):
        s: dict[str, Any] = {}
        for key, val in spec.items():
            if isinstance(val, float) and val > 0 and key not in ("delta",):
                s[key] = val * float(rng.uniform(0.8, 1.2))
            elif isinstance(val, list) and val and all(isinstance(e, float) for e in val) and key != "alpha":
                s[key] = [e * float(rng.uniform(0.8, 1.2)) for e in val]
            else:
                s[key] = val
        if "fs_n" in s and "fc_n" in s:
            s["fs_n"] = max(s["fs_n"], s["fc_n"])
        try:
            out.append(model.replace(**{k: v for k, v in s.items() if k != "model"}))
        except ValueError:
            out.append(model)  # keep the set count; a perturbation out of bounds falls back to nominal
    return out


# ---------------------------------------------------------------------------------------------- run
def run(args: argparse.Namespace) -> dict[str, Any]:
    from stagectl.friction import build, registry
    from stagectl.sim.plant import PlantConfig, StagePlant, simulate_batch

    quick = bool(getattr(args, "quick", False))
    n_single = int(args.steps or (300_000 if quick else 2_000_000))
    n_sets = int(args.sets if not quick else min(args.sets, 200))
    n_batch_steps = 1000 if quick else 2000
    repeat = int(args.repeat or (2 if quick else 3))
    n_py = 40_000 if quick else 200_000  # whole 0.2 s periods of the same input as the compiled runs
    dt = 1e-5
    mass = 2.0
    rng = np.random.default_rng(0)

    build(SPECS["stribeck"])  # imports every model module
    tags = sorted(registry()) if not args.models else [t.strip() for t in args.models.split(",") if t.strip()]
    t_axis = np.arange(n_single) * dt
    u_single = 1.5 * np.sin(2 * np.pi * 5.0 * t_axis)  # slides both ways and passes through pre-sliding
    u_batch = u_single[:n_batch_steps]

    results: dict[str, Any] = {}
    for tag in tags:
        entry: dict[str, Any] = {}
        results[tag] = entry
        spec = _spec_for(tag)
        if spec is None:
            entry["skipped"] = "no benchmark parameter set for this model"
            continue
        try:
            model = build(spec)
        except Exception as exc:  # report, don't abort the whole benchmark
            entry["skipped"] = f"cannot build benchmark parameters: {exc}"
            continue
        cfg = PlantConfig(mass_kg=mass, friction=model, substep_s=dt)
        plant = StagePlant(cfg)
        t0 = time.perf_counter()
        plant.simulate(u_single[:100], dt)
        sets = _perturbed(model, n_sets, rng)
        simulate_batch(cfg, sets[:2], u_batch[:10], dt)
        state = model.initial_state()
        model.step(state, 1e-9, 1e-4, 1e-4)
        entry["warmup_s"] = time.perf_counter() - t0

        def single() -> None:
            plant.reset()
            plant.simulate(u_single, dt)

        t_single = _best(single, repeat)
        entry["single_steps_per_s"] = n_single / t_single
        t_batch = _best(lambda: simulate_batch(cfg, sets, u_batch, dt), max(1, repeat - 1))
        entry["batch_steps_per_s"] = n_sets * n_batch_steps / t_batch
        entry["batch_sets"] = n_sets

        # per-sample scalar step (feed-forward path) and per-sample plant step (HIL path)
        n_ps = 20_000
        xs = 1e-6 * np.sin(np.arange(n_ps) * 0.01)
        dxs = np.diff(xs, prepend=0.0).tolist()

        def scalar() -> None:
            st = model.initial_state()
            step = model.step
            for d in dxs:
                step(st, d, d / 1e-4, 1e-4)

        entry["per_sample_step_us"] = _best(scalar, repeat) / n_ps * 1e6

        def plant_steps() -> None:
            plant.reset()
            for k in range(5000):
                plant.step(0.5, 1e-4)

        entry["plant_step_100us_us"] = _best(plant_steps, repeat) / 5000 * 1e6

    # baseline: pure-Python GMS + plant, same equations and input
    gms_spec = SPECS["gms"]
    python_gms_plant(100, dt, mass, gms_spec)
    t_py = _best(lambda: python_gms_plant(n_py, dt, mass, gms_spec), max(1, repeat - 1))
    baseline = n_py / t_py
    out: dict[str, Any] = {
        "setup": {"plant_mass_kg": mass, "dt_s": dt, "substeps_per_step": 1, "single_steps": n_single,
                  "batch_sets": n_sets, "batch_steps_per_set": n_batch_steps, "baseline_steps": n_py,
                  "repeat": repeat, "input": "u = 1.5 N sin(2π·5 Hz·t), GMS N = 6 (Table 1)"},
        "baseline_python_gms_steps_per_s": baseline,
        "models": results,
    }
    for entry in results.values():
        if "single_steps_per_s" in entry:
            entry["single_vs_baseline"] = entry["single_steps_per_s"] / baseline
            entry["batch_vs_baseline"] = entry["batch_steps_per_s"] / baseline
    g = results.get("gms", {})
    if "single_steps_per_s" in g:
        out["targets"] = {
            "gms_single_steps_per_s": {"value": g["single_steps_per_s"], "target": TARGET_SINGLE_STEPS_S,
                                       "met": g["single_steps_per_s"] >= TARGET_SINGLE_STEPS_S},
            "gms_single_vs_baseline": {"value": g["single_vs_baseline"], "target": TARGET_RATIO,
                                       "met": g["single_vs_baseline"] >= TARGET_RATIO},
            "gms_per_sample_step_us": {"value": g["per_sample_step_us"], "target": TARGET_PER_SAMPLE_US,
                                       "met": g["per_sample_step_us"] <= TARGET_PER_SAMPLE_US},
        }
    return out
