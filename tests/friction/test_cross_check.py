"""Cross-checks of the compiled paths against plain-Python code, and the one interface across all models.

Every fast path (``step``, ``force_along``, ``force_along_batch``, the plant's fused loop) runs the same
compiled kernel, so agreement between them proves nothing about the equations. Here each model's kernel is
compared with an independent plain-Python implementation written from docs/friction-models.md in this file
(Stribeck with Karnopp values and frictional lag, Maxwell-slip); the GMS reference lives in
``test_gms.py::RefGms`` (``test_scalar_kernel_along_batch_and_reference_agree``). The compiled plant is
checked against the pure-Python GMS + rigid-body loop that ``stagectl bench models`` uses as its baseline.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from stagectl.friction import build, load_model_file, registry

REPO = Path(__file__).resolve().parents[2]
MODELS = REPO / "config" / "models"
UM = 1e-6
K6 = [454610.0, 111088.0, 45601.0, 16402.0, 6899.0, 4295.0]
A6 = [0.378, 0.138, 0.148, 0.177, 0.112, 0.046]

#: one parameter set per model tag (SI units)
SPECS = {
    "stribeck": {"model": "stribeck", "fc_n": 0.8, "fs_n": 0.9, "vs_m_s": 1e-3, "viscous_n_s_m": 10.0},
    "maxwell_slip": {"model": "maxwell_slip", "k_n_m": K6, "alpha": A6, "fs_n": 0.9, "viscous_n_s_m": 10.0},
    "gms": {"model": "gms", "k_n_m": K6, "alpha": A6, "fc_n": 0.8, "fs_n": 0.9, "c_n_s": 1e4,
            "sigma1_n_s_m": 20.0, "viscous_n_s_m": 10.0},
    "lugre": {"model": "lugre", "sigma0_n_m": 1e5, "sigma1_n_s_m": math.sqrt(1e5), "viscous_n_s_m": 0.4,
              "fc_n": 1.0, "fs_n": 1.5, "vs_m_s": 1e-3},
    "dahl": {"model": "dahl", "sigma0_n_m": 1e5, "fc_n": 1.0, "viscous_n_s_m": 0.5},
    "hsieh": load_model_file(MODELS / "kamenar2016_hsieh.yaml").friction.spec(),
}


def trajectory(seed: int, n: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    """Pre-sliding wiggles, sliding both ways, reversals, pauses (v = 0 exactly), varying dt."""
    rng = np.random.default_rng(seed)
    v = np.repeat(rng.choice([-4e-3, -8e-4, -3e-5, 0.0, 2e-5, 5e-4, 2e-3, 6e-3], n // 40), 40)
    v *= rng.uniform(0.5, 1.5, v.size)
    dt = rng.uniform(5e-5, 2e-4, v.size)
    return np.concatenate([[0.0], np.cumsum(v * dt)]), np.concatenate([[0.0], np.cumsum(dt)])


# ---------------------------------------------------------------------------------------------- plain Python
def ref_stribeck(fc, fs, vs, delta, sigma2, lag, x, t):
    """F = sgn(v)(Fc + e) + σ2 v with e → (Fs − Fc)exp(−|v/Vs|^δ) through an exact first-order lag."""
    e = fs - fc  # relaxed (at rest)
    out = []
    for k in range(len(x)):
        if k == 0:
            v = (x[1] - x[0]) / (t[1] - t[0])
            ee = e if lag > 0 else (fs - fc) * math.exp(-abs(v / vs) ** delta)
        else:
            v = (x[k] - x[k - 1]) / (t[k] - t[k - 1])
            ess = (fs - fc) * math.exp(-abs(v / vs) ** delta)
            if lag > 0:
                e = ess + (e - ess) * math.exp(-(t[k] - t[k - 1]) / lag)
                ee = e
            else:
                ee = ess
        sg = (v > 0) - (v < 0)
        out.append(sg * (fc + ee) + sigma2 * v)
    return out


def ref_maxwell(k, w, sigma2, x, t):
    """Jenkins elements: F_i ← min(max(F_i + k_i Δx, −W_i), W_i); F = ΣF_i + σ2 v."""
    f = [0.0] * len(k)
    out = [sigma2 * (x[1] - x[0]) / (t[1] - t[0])]
    for j in range(1, len(x)):
        dx = x[j] - x[j - 1]
        for i in range(len(k)):
            f[i] = min(max(f[i] + k[i] * dx, -w[i]), w[i])
        out.append(sum(f) + sigma2 * dx / (t[j] - t[j - 1]))
    return out


@pytest.mark.parametrize("delta,lag", [(2.0, 0.0), (1.5, 0.0), (1.0, 3e-3), (0.7, 2e-4)])
def test_stribeck_compiled_paths_equal_plain_python(delta, lag, paths):
    spec = {**SPECS["stribeck"], "delta": delta, "lag_s": lag}
    dut = build(spec)
    x, t = trajectory(11)
    f = dut.force_along(x, t)
    ref = ref_stribeck(0.8, 0.9, 1e-3, delta, 10.0, lag, x.tolist(), t.tolist())
    np.testing.assert_allclose(f, ref, rtol=1e-12, atol=1e-12)
    assert np.any(f == 0.0) and np.any(f > 0.5) and np.any(f < -0.5)  # pauses and sliding both ways
    scalar, by_kernel = paths(dut, x, t)
    np.testing.assert_array_equal(f, scalar)
    np.testing.assert_array_equal(f, by_kernel)
    kern = dut.kernel()
    assert (kern.breakaway_n, kern.stick_velocity_m_s) == (0.9, 1e-6)  # Karnopp band values for the plant


@pytest.mark.parametrize("viscous", [0.0, 10.0])
def test_maxwell_compiled_paths_equal_plain_python(viscous):
    spec = {**SPECS["maxwell_slip"], "viscous_n_s_m": viscous}
    dut = build(spec)
    x, t = trajectory(12)
    f = dut.force_along(x, t)
    ref = ref_maxwell(K6, [a * 0.9 for a in A6], viscous, x.tolist(), t.tolist())
    np.testing.assert_allclose(f, ref, rtol=1e-12, atol=1e-12)
    batch = type(dut).force_along_batch([dut.params, dut.params], x, t)
    np.testing.assert_array_equal(batch[1], f)
    assert np.ptp(x) > 30 * UM  # beyond pre-sliding: every element slipped


def test_compiled_plant_equals_plain_python_gms_plant():
    """The fused numba plant loop against the pure-Python GMS + rigid body of the benchmark baseline."""
    from stagectl.bench.models import SPECS as BENCH_SPECS
    from stagectl.bench.models import python_gms_plant
    from stagectl.sim.plant import PlantConfig, StagePlant

    spec = BENCH_SPECS["gms"]
    dt, n = 1e-5, 30_000  # 0.3 s of u = 1.5 sin(2π 5 t): slides both ways
    dut = StagePlant(PlantConfig(mass_kg=2.0, friction=build(spec), substep_s=dt))
    r = dut.simulate(1.5 * np.sin(2 * np.pi * 5.0 * np.arange(n) * dt), dt)
    x_py = python_gms_plant(n, dt, 2.0, spec)
    assert np.ptp(r["x"]) > 1e-4
    assert r["x"][-1] == pytest.approx(x_py, rel=1e-9, abs=1e-12)


# ---------------------------------------------------------------------------------------------- one interface
def test_every_model_of_issue_2_is_registered():
    build(SPECS["stribeck"])
    assert set(registry()) >= {"stribeck", "maxwell_slip", "gms", "hsieh", "lugre", "dahl"}
    assert set(SPECS) == set(registry())  # a new model must be added to these interface tests


@pytest.mark.parametrize("tag", sorted(SPECS))
def test_interface_sign_convention_relaxed_start_and_paths(tag, paths):
    dut = build(SPECS[tag])
    assert dataclass_is_frozen(dut.params)
    s0 = dut.initial_state()
    assert s0.dtype == np.float64 and s0.shape == (dut.n_states,)
    # sign convention: F opposes motion, positive while sliding with v > 0
    for v in (2e-3, -2e-3):
        x = np.linspace(0.0, math.copysign(300 * UM, v), 601)
        f = dut.force_along(x, np.abs(x) / abs(v))
        assert isinstance(f, np.ndarray) and f.dtype == np.float64 and f.shape == x.shape
        assert math.copysign(1.0, f[-1]) == math.copysign(1.0, v) and abs(f[-1]) > 0.3
    # every call starts from the relaxed state; the scalar path gives the same numbers
    x, t = trajectory(5, 800)
    f1, f2 = dut.force_along(x, t), dut.force_along(x, t)
    np.testing.assert_array_equal(f1, f2)
    f_sc, f_kern = paths(dut, x, t)
    np.testing.assert_array_equal(f1, f_sc)
    np.testing.assert_array_equal(f1, f_kern)
    np.testing.assert_array_equal(type(dut).force_along_batch([dut.params], x, t)[0], f1)
    assert build(dut.spec()).params == dut.params


@pytest.mark.parametrize("tag", sorted(SPECS))
def test_energy_dissipated_on_closed_paths_every_model(tag):
    dut = build(SPECS[tag])
    for seed in range(3):
        rng = np.random.default_rng(seed)
        pts = np.concatenate([[0.0], rng.uniform(-40, 40, 4), [0.0]]) * UM
        x = np.concatenate([np.linspace(a, b, 400, endpoint=False) for a, b in zip(pts[:-1], pts[1:])] + [[0.0]])
        speed = float(rng.choice([1e-6, 1e-4, 2e-3]))
        t = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(x)) / speed + 1e-9)])
        f = dut.force_along(x, t)
        assert float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(x))) >= -1e-9  # ∮F dx: never created


def dataclass_is_frozen(obj) -> bool:
    import dataclasses

    return dataclasses.is_dataclass(obj) and obj.__dataclass_params__.frozen
