"""``stagectl bench models [--json] [--quick]``: friction model + plant throughput.

Measured in one run (figures are never copied from elsewhere):

* **single**: one open-loop plant trajectory (``StagePlant.simulate``) with each registered model,
  control period = sub-step = 10 µs, so one step = one plant+friction integration step;
* **batch**: the same plant with 1000 perturbed parameter sets (``stagectl.sim.plant.simulate_batch``);
* **baseline**: a straightforward pure-Python GMS (N = 6) + plant loop with the same equations;
* **C reference** (``stagectl.bench.cref``): a minimal C implementation of the same GMS + plant recurrence,
  compiled with the system C compiler at ``-O2`` in this run (skipped with a note when there is none), single
  trajectory and a batch that interleaves the sets per time step; the GMS rates are reported as ratios to it
  and the C and compiled trajectories are compared (``c_max_abs_dx_m``); these runs are timed in the process's
  CPU time (``timer``), so that other load on a shared machine does not enter the ratios;
* **first call**: a new plant's first ``simulate(u, outputs=("x",))`` of ``--first-steps`` steps (fresh
  output memory, kernel already loaded), against the C reference writing into fresh memory too;
* **per-sample**: ``model.step(state, dx, v, dt)`` called from Python, as the control loop's
  feed-forward does, and ``StagePlant.step(u, dt)`` (10 sub-steps), in µs per call.

JIT compile / cache-load time is excluded from every rate (each path is warmed up first) and reported
separately as ``warmup_s`` (wall clock). Rates are the best of ``--repeat`` runs in process CPU time (least
disturbed by other load on a shared machine).
"""

from __future__ import annotations

import argparse
import math
import time
from typing import Any

from stagectl.bench import tell

import numpy as np

from stagectl.resources import config_dir

TARGET_SINGLE_STEPS_S = 2_000_000.0
TARGET_RATIO = 20.0
TARGET_PER_SAMPLE_US = 10.0
TARGET_VS_C_SINGLE = 0.9
TARGET_VS_C_FIRST = 0.7
TARGET_VS_C_BATCH = 1.0

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
    parser.add_argument("--first-steps", type=int, default=None,
                        help="steps of the first-call run (default 1e7, --quick 2e6)")
    parser.add_argument("--no-c", action="store_true", help="skip the C reference")


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
    """Best of ``repeat`` runs in this process's CPU time (every run here is single-threaded in this process)."""
    best = math.inf
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
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


# ---------------------------------------------------------------------------------------------- C reference
def _c_reference(spec: dict[str, Any], mass: float, dt: float, u_single: Any, u_batch: Any, n_sets: int,
                 rng: np.random.Generator, repeat: int, gms_entry: dict[str, Any] | None,
                 n_first: int) -> dict[str, Any]:
    """The C GMS reference against the compiled plant, measured here, interleaved (C, compiled, C, …) so
    that both see the same load; the best of each is kept. Timed in this process's CPU time (both run in
    this thread): time the process spends descheduled by other load on a shared machine does not count."""
    from stagectl.bench import cref
    from stagectl.friction import build
    from stagectl.sim.plant import PlantConfig, StagePlant, simulate_batch

    lib, why = cref.load()
    if lib is None:
        return {"skipped": why}
    model = build(spec)
    par = cref.pack(spec)
    n = u_single.shape[0]
    cfg = PlantConfig(mass_kg=mass, friction=model, substep_s=dt)
    plant = StagePlant(cfg)
    plant.simulate(u_single[:10], dt, outputs=("x",))
    xc = np.empty(n)
    xn = np.empty(n)
    cref.single(lib, u_single[:10], dt, mass, par, xc[:10])
    t_c = t_n = math.inf
    for _ in range(max(3, repeat)):
        t0 = time.process_time()
        cref.single(lib, u_single, dt, mass, par, xc)
        t_c = min(t_c, time.process_time() - t0)
        plant.reset()
        t0 = time.process_time()
        plant.simulate(u_single, dt, outputs=("x",), out={"x": xn})
        t_n = min(t_n, time.process_time() - t0)
    out: dict[str, Any] = {
        "compiler": cref.compiler(), "flags": "-O2", "timer": "process CPU time",
        "c_single_steps_per_s": n / t_c, "compiled_single_steps_per_s": n / t_n, "single_vs_c": t_c / t_n,
        "c_max_abs_dx_m": float(np.max(np.abs(xc - xn))),
    }
    # first call: fresh plant, fresh output memory (the kernel is loaded: compile time is warmup_s)
    u_first = 1.5 * np.sin(2 * np.pi * 5.0 * np.arange(n_first) * dt)
    t0 = time.process_time()
    cref.single(lib, u_first, dt, mass, par, np.empty(n_first))
    t_cf = time.process_time() - t0
    fresh = StagePlant(cfg)
    t0 = time.process_time()
    fresh.simulate(u_first, dt, outputs=("x",))
    t_nf = time.process_time() - t0
    out.update({"first_call_steps": n_first, "c_first_call_steps_per_s": n_first / t_cf,
                "compiled_first_call_steps_per_s": n_first / t_nf, "first_call_vs_c": t_c / n * n_first / t_nf,
                "first_call_vs_c_first_call": t_cf / t_nf})
    # batch: the same perturbed sets for both (parameters packed per set)
    sets = _perturbed(model, n_sets, rng)
    P = np.ascontiguousarray(np.stack([cref.pack(s.spec()) for s in sets]))
    nb = u_batch.shape[0]
    xcb = np.empty((n_sets, nb))
    cref.batch(lib, u_batch[:10], dt, mass, P[:2], np.empty((2, 10)))
    simulate_batch(cfg, sets[:2], u_batch[:10], dt, outputs=("x",))
    t_cb = t_nb = math.inf
    res: dict[str, Any] = {}
    for _ in range(max(2, repeat - 1)):
        t0 = time.process_time()
        cref.batch(lib, u_batch, dt, mass, P, xcb)
        t_cb = min(t_cb, time.process_time() - t0)
        t0 = time.process_time()
        res = simulate_batch(cfg, sets, u_batch, dt, outputs=("x",))  # x only, as the C batch
        t_nb = min(t_nb, time.process_time() - t0)
    out.update({"c_batch_set_steps_per_s": n_sets * nb / t_cb, "compiled_batch_set_steps_per_s": n_sets * nb / t_nb,
                "batch_vs_c": t_cb / t_nb, "c_batch_max_abs_dx_m": float(np.max(np.abs(res["x"] - xcb)))})
    if gms_entry is not None:
        gms_entry["single_vs_c"] = out["single_vs_c"]
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
    unknown = [t for t in tags if t not in registry()]
    if unknown or not tags:
        from stagectl.errors import ConfigError

        raise ConfigError(f"--models: unknown model {', '.join(unknown) or '(none given)'} "
                          f"(known: {', '.join(sorted(registry()))})")
    t_axis = np.arange(n_single) * dt
    u_single = 1.5 * np.sin(2 * np.pi * 5.0 * t_axis)  # slides both ways and passes through pre-sliding
    u_batch = u_single[:n_batch_steps]

    results: dict[str, Any] = {}
    for i, tag in enumerate(tags):
        tell(args, i, len(tags) + 1, f"model {i + 1} of {len(tags)}, {tag}")
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

        x_buf = np.empty(n_single)

        def single() -> None:
            plant.reset()
            plant.simulate(u_single, dt, outputs=("x",), out={"x": x_buf})

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
    tell(args, len(tags), len(tags) + 1, "the C reference and the pure-Python baseline")
    c_ref = None if getattr(args, "no_c", False) else _c_reference(
        gms_spec, mass, dt, u_single, u_batch, n_sets, rng, repeat, results.get("gms"),
        int(args.first_steps or (2_000_000 if quick else 10_000_000)))
    python_gms_plant(100, dt, mass, gms_spec)
    t_py = _best(lambda: python_gms_plant(n_py, dt, mass, gms_spec), max(1, repeat - 1))
    baseline = n_py / t_py
    out: dict[str, Any] = {
        "setup": {"plant_mass_kg": mass, "dt_s": dt, "substeps_per_step": 1, "single_steps": n_single,
                  "batch_sets": n_sets, "batch_steps_per_set": n_batch_steps, "baseline_steps": n_py,
                  "repeat": repeat, "input": "u = 1.5 N sin(2π·5 Hz·t), GMS N = 6 (Table 1)"},
        "baseline_python_gms_steps_per_s": baseline,
        "models": results,
        "c_reference": c_ref,
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
        if c_ref and "single_vs_c" in c_ref:
            for key, target in (("single_vs_c", TARGET_VS_C_SINGLE), ("first_call_vs_c", TARGET_VS_C_FIRST),
                                ("batch_vs_c", TARGET_VS_C_BATCH)):
                out["targets"][f"gms_{key}"] = {"value": c_ref[key], "target": target,
                                                "met": c_ref[key] >= target}
    return out
