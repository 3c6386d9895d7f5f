"""The plant's fast paths give the same numbers as the plain ones: selected/decimated/preallocated outputs of
``simulate``, the per-model fused loop against a plain-Python rigid-body loop, and batch runs (the branch-free
many-sets GMS kernel and the generic interleaved loop) against one run per parameter set."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from stagectl.sim.plant import PlantConfig, StagePlant, simulate_batch

from stagectl.friction import build

K = [454610.0, 111088.0, 45601.0, 16402.0, 6899.0, 4295.0]
A = [0.378, 0.138, 0.148, 0.177, 0.112, 0.046]
GMS = {"model": "gms", "k_n_m": K, "alpha": A, "fc_n": 0.8, "fs_n": 0.9, "c_n_s": 1e4,
       "sigma1_n_s_m": [160.88, 39.31, 16.14, 5.80, 2.44, 1.52], "viscous_n_s_m": 10.0}
DAHL = {"model": "dahl", "sigma0_n_m": 1e5, "fc_n": 1.0}
DT = 1e-4
U = 1.5 * np.sin(2 * np.pi * 5.0 * np.arange(3000) * DT)  # slides both ways, passes through pre-sliding


def plant(spec=GMS, **kw) -> StagePlant:
    return StagePlant(PlantConfig(mass_kg=2.0, friction=build(spec), substep_s=2e-5, **kw))


def test_selected_decimated_and_preallocated_outputs_equal_the_full_run():
    full = plant().simulate(U, DT)
    assert set(full) == {"t", "x", "v", "friction", "x_meas"}
    only_x = plant().simulate(U, DT, outputs=("x",))
    assert set(only_x) == {"x"} and np.array_equal(only_x["x"], full["x"])
    dec = plant().simulate(U, DT, outputs=("t", "v", "friction"), every=7)
    n = len(U) // 7
    for name in ("t", "v", "friction"):
        assert np.array_equal(dec[name], full[name][6::7][:n]), name
    buf = np.empty(len(U))
    got = plant().simulate(U, DT, outputs=("x",), out={"x": buf})
    assert got["x"] is buf and np.array_equal(buf, full["x"])


def test_simulate_options_refuse_bad_values():
    p = plant()
    with pytest.raises(ValueError, match="outputs"):
        p.simulate(U, DT, outputs=("position",))
    with pytest.raises(ValueError, match="x_meas needs every=1"):
        p.simulate(U, DT, every=2)
    with pytest.raises(ValueError, match="every"):
        p.simulate(U, DT, outputs=("x",), every=0)
    with pytest.raises(ValueError, match=r"out\['x'\]"):
        p.simulate(U, DT, outputs=("x",), out={"x": np.empty(3)})
    with pytest.raises(ValueError, match="finite"):
        p.simulate(np.array([0.0, math.nan]), DT)


def test_after_an_x_only_run_the_sensor_reads_the_end_position():
    p = plant()
    r = p.simulate(U, DT, outputs=("x",))
    assert p.measure() == pytest.approx(r["x"][-1], abs=1e-9)


@pytest.mark.parametrize("spec", [GMS, DAHL])
def test_fused_loop_equals_a_plain_python_rigid_body_loop(spec):
    """Semi-implicit Euler written out in Python around the model's own scalar step (same sub-step)."""
    p = plant(spec)
    got = p.simulate(U[:400], DT, outputs=("x", "friction"))
    model = build(spec)
    st = model.initial_state()
    h, nsub, m = 2e-5, 5, 2.0
    x = v = 0.0
    ff = model.force(st, 0.0)
    xs, fs = [], []
    for u in U[:400]:
        for _ in range(nsub):
            v = v + h * (u - ff) / m
            dx = h * v
            x += dx
            ff = model.step(st, dx, v, h)
        xs.append(x)
        fs.append(ff)
    np.testing.assert_allclose(got["x"], xs, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(got["friction"], fs, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("spec", [GMS, DAHL])
def test_the_per_cycle_step_equals_the_simulate_loop_bit_for_bit(spec):
    """``step`` of a plain plant runs its own kernel (the model's step called), ``simulate`` the
    fully optimised loop with the step pasted in: the same arithmetic in the same order, so the same bits in
    every state variable, with a constant F_other (offset) and 1-, 5- and 7-sub-step cycles."""
    from stagectl.friction import parse_effects

    problems: list[str] = []
    eff = parse_effects({"offset": {"force_n": 0.2}}, "effects", problems)
    a, b = (plant(spec, effects=eff) for _ in range(2))
    assert a._cycle is not None and not problems
    for dt in (2e-5, DT, 1.4e-4):
        want = b.simulate(U[:300], dt, outputs=("x", "v", "friction"))
        got = {"x": [], "v": [], "friction": []}
        for u in U[:300]:
            a.step(u, dt)
            got["x"].append(a.x_m)
            got["v"].append(a.v_m_s)
            got["friction"].append(a.friction_n)
        for k, seq in got.items():
            np.testing.assert_array_equal(seq, want[k])
        np.testing.assert_array_equal(a._ps, b._ps)  # time, F_other, applied force, work totals too
        np.testing.assert_array_equal(a._fs, b._fs)
    assert abs(a.x_m) > 5e-6 and a.work_j()["friction"] > 0.0  # it moved beyond pre-sliding


@pytest.mark.parametrize("spec", [GMS, DAHL])
def test_batch_equals_one_run_per_parameter_set(spec):
    base = build(spec)
    rng = np.random.default_rng(1)
    sets = []
    for _ in range(5):
        kw = {k: v * float(rng.uniform(0.8, 1.2)) for k, v in base.spec().items()
              if isinstance(v, float) and k in ("fc_n", "sigma0_n_m", "c_n_s", "viscous_n_s_m")}
        if "fc_n" in kw and "fs_n" in base.spec():
            kw["fs_n"] = max(kw["fc_n"], base.spec()["fs_n"])
        sets.append(base.replace(**kw))
    cfg = PlantConfig(mass_kg=2.0, friction=base, substep_s=2e-5)
    got = simulate_batch(cfg, sets, U[:500], DT)
    for j, s in enumerate(sets):
        one = StagePlant(dataclasses.replace(cfg, friction=s)).simulate(U[:500], DT)
        for name in ("x", "v", "friction"):
            assert np.array_equal(got[name][j], one[name]), (j, name)


def test_batch_outputs_subset_equals_the_full_run():
    base = build(GMS)
    sets = [base, base.replace(fc_n=0.85)]
    cfg = PlantConfig(mass_kg=2.0, friction=base, substep_s=2e-5)
    full = simulate_batch(cfg, sets, U[:200], DT)
    only_x = simulate_batch(cfg, sets, U[:200], DT, outputs=("x",))
    assert list(only_x) == ["x"] and np.array_equal(only_x["x"], full["x"])
    with pytest.raises(ValueError, match="outputs: unknown"):
        simulate_batch(cfg, sets, U[:10], DT, outputs=("x_meas",))


def test_batch_with_effects_takes_the_general_path_and_still_matches():
    cfg = PlantConfig.from_mapping({"mass_kg": 2.0, "friction": GMS, "substep_s": 2e-5,
                                    "effects": {"cogging": {"amplitude_n": 0.05, "wavelength_m": 1e-4}}})
    sets = [cfg.friction, cfg.friction.replace(fc_n=0.85)]
    got = simulate_batch(cfg, sets, U[:300], DT)
    for j, s in enumerate(sets):
        one = StagePlant(dataclasses.replace(cfg, friction=s)).simulate(U[:300], DT)
        assert np.array_equal(got["x"][j], one["x"])
