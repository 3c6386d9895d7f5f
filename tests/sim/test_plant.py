"""StagePlant: each effect moves the stage as its equation says; sensor, actuator, integrator checks."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from stagectl.errors import ConfigError
from stagectl.friction import load_model_file
from stagectl.sim.plant import PlantConfig, StagePlant

REPO = Path(__file__).resolve().parents[2]
MODELS = REPO / "config" / "models"

K_TABLE1 = [454610.0, 111088.0, 45601.0, 16402.0, 6899.0, 4295.0]
ALPHA_TABLE1 = [0.378, 0.138, 0.148, 0.177, 0.112, 0.046]

VISCOUS_ONLY = {"model": "stribeck", "fc_n": 0.0, "fs_n": 0.0, "viscous_n_s_m": 20.0}


def make(friction=None, **kw) -> StagePlant:
    data = {"mass_kg": kw.pop("mass_kg", 1.0), "friction": friction or VISCOUS_ONLY, **kw}
    return StagePlant(PlantConfig.from_mapping(data))


def gms(sigma1=0.0, viscous=0.0, k=K_TABLE1):
    return {"model": "gms", "k_n_m": list(k), "alpha": ALPHA_TABLE1 if len(k) == 6 else [1.0 / len(k)] * len(k), "fc_n": 0.8, "fs_n": 0.9,
            "c_n_s": 1e4, "sigma1_n_s_m": sigma1, "viscous_n_s_m": viscous}


def dominant_frequency(x: np.ndarray, dt: float) -> float:
    """Frequency of the oscillation from mean-crossings (sub-sample interpolation)."""
    y = x - x.mean()
    idx = np.nonzero((y[:-1] < 0) & (y[1:] >= 0))[0]
    tc = (idx + (-y[idx]) / (y[idx + 1] - y[idx])) * dt
    return float((len(tc) - 1) / (tc[-1] - tc[0]))


# ---------------------------------------------------------------------------------------------- dynamics
@pytest.mark.parametrize("mass,f_expected", [(0.5, 179.91), (2.0, 89.95), (20.0, 28.45)])
def test_presliding_resonance_matches_tv7(mass, f_expected):
    dut = make(gms(), mass_kg=mass)
    # a small force keeps every element elastic (0.01 N / 638895 N/m = 16 nm << 0.75 µm)
    r = dut.simulate(np.full(int(0.5 / 1e-4), 0.01), 1e-4)
    f = dominant_frequency(r["x"], 1e-4)
    assert f == pytest.approx(f_expected, rel=0.01)
    assert r["x"].mean() == pytest.approx(0.01 / sum(K_TABLE1), rel=0.02)


def test_stable_at_stiff_end():
    # sum k = 2e6 N/m, m = 0.5 kg, undamped: h*omega = 1e-5 * 2000 = 0.02; amplitude must not grow
    k = [2e6 * ki / sum(K_TABLE1) for ki in K_TABLE1]
    dut = make(gms(k=k), mass_kg=0.5)
    r = dut.simulate(np.full(20000, 0.02), 1e-4)
    y = r["x"] - 0.02 / 2e6
    first = np.abs(y[:500]).max()
    last = np.abs(y[-500:]).max()
    assert np.all(np.isfinite(r["x"]))
    assert last <= first * 1.01
    assert dominant_frequency(r["x"], 1e-4) == pytest.approx(math.sqrt(2e6 / 0.5) / (2 * math.pi), rel=0.01)


def test_energy_balance_gms_with_damping():
    dut = make(gms(sigma1=30.0, viscous=10.0), mass_kg=2.0)
    rng = np.random.default_rng(1)
    u = np.repeat(rng.uniform(-1.5, 1.5, 40), 500)  # 40 random force levels, 50 ms each
    r = dut.simulate(u, 1e-4)
    w = dut.work_j()
    ke = 0.5 * 2.0 * r["v"][-1] ** 2
    assert w["friction"] > 0.0  # dissipated
    assert w["applied"] == pytest.approx(ke + w["friction"] + w["other"], abs=1e-3 * abs(w["applied"]) + 1e-9)
    # cross-check the accumulated friction work against the recorded trajectory
    wf = np.sum(r["friction"][:-1] * np.diff(r["x"]))
    assert wf == pytest.approx(w["friction"], rel=0.02)


# ---------------------------------------------------------------------------------------------- effects
def _pd_settle(dut: StagePlant, kp: float, kd: float, n: int = 30000, dt: float = 1e-4) -> float:
    x_prev = dut.measure()
    for _ in range(n):
        x = dut.measure()
        u = -kp * x - kd * (x - x_prev) / dt
        x_prev = x
        dut.step(u, dt)
    return dut.x_m


def test_offset_shifts_pd_steady_state_by_f0_over_kp():
    kp, f0 = 2000.0, 0.5
    dut = make(effects={"offset": {"force_n": f0}}, sensor={"resolution_m": 1e-12})
    x_ss = _pd_settle(dut, kp, 60.0)
    assert x_ss == pytest.approx(-f0 / kp, rel=1e-3)
    assert dut.other_n == pytest.approx(f0)


def test_spring_static_equilibrium():
    dut = make(effects={"spring": {"stiffness_n_m": 500.0, "x0_m": 1e-3}})
    dut.simulate(np.full(30000, 2.0), 1e-4)
    assert dut.x_m == pytest.approx(1e-3 + 2.0 / 500.0, rel=1e-4)
    assert dut.other_n == pytest.approx(2.0, rel=1e-4)
    assert abs(dut.v_m_s) < 1e-7


def test_cogging_force_at_rest_and_stable_detent():
    amp, lam, phase = 0.3, 1e-3, 0.4
    dut = make(effects={"cogging": {"amplitude_n": amp, "wavelength_m": lam, "phase_rad": phase}},
               x0_m=0.1e-3)
    assert dut.other_n == pytest.approx(amp * math.sin(2 * math.pi * 0.1e-3 / lam + phase))
    dut.simulate(np.zeros(30000), 1e-4)
    # settles where the conservative force vanishes with positive slope (a stable detent)
    ph = 2 * math.pi * dut.x_m / lam + phase
    assert math.sin(ph) == pytest.approx(0.0, abs=1e-4)
    assert math.cos(ph) > 0
    assert dut.other_n == pytest.approx(0.0, abs=1e-4)


def test_cogging_held_by_presliding_friction():
    # with GMS friction the stage stays put (within pre-sliding) and friction balances the cogging force
    dut = make(gms(sigma1=30.0, viscous=10.0), mass_kg=2.0, x0_m=0.1e-3,
               effects={"cogging": {"amplitude_n": 0.3, "wavelength_m": 1e-3}})
    dut.simulate(np.zeros(20000), 1e-4)
    assert abs(dut.x_m - 0.1e-3) < 2e-6
    assert dut.friction_n == pytest.approx(-dut.other_n, abs=1e-4)


@pytest.mark.parametrize("dt,tau,shift", [(5e-5, 3.5e-4, 7), (2.5e-5, 2.5e-5, 1)])
def test_delay_shifts_response_by_tau(dt, tau, shift):
    u = np.concatenate([np.zeros(20), np.full(200, 1.0), np.full(200, -0.5)])
    ref = make(substep_s=dt / 5).simulate(u, dt)["x"]
    got = make(substep_s=dt / 5, effects={"delay": {"delay_s": tau}}).simulate(u, dt)["x"]
    np.testing.assert_allclose(got[shift:], ref[:-shift], rtol=1e-9, atol=1e-15)


def test_sub_sample_delay_against_fine_reference():
    # tau = 25 µs inside 100 µs control periods == a 1-sample shift on a 25 µs grid with repeated commands
    u = np.concatenate([np.zeros(5), np.full(60, 1.0), np.full(60, -2.0), np.full(40, 0.5)])
    coarse = make(substep_s=5e-6, effects={"delay": {"delay_s": 2.5e-5}}).simulate(u, 1e-4)["x"]
    fine = make(substep_s=5e-6).simulate(np.concatenate([[0.0], np.repeat(u, 4)]), 2.5e-5)["x"]
    np.testing.assert_allclose(coarse, fine[3::4][: len(coarse)], rtol=1e-9, atol=1e-15)


def test_delay_step_and_simulate_agree_and_applied_force_is_delayed():
    u = np.sin(np.arange(300) * 0.05)
    a = make(effects={"delay": {"delay_s": 1.7e-4}})
    b = make(effects={"delay": {"delay_s": 1.7e-4}})
    xa = []
    for uk in u[:150]:
        a.step(uk, 1e-4)
        xa.append(a.x_m)
    ra = a.simulate(u[150:], 1e-4)  # continues with the step() history
    xb = b.simulate(u, 1e-4)["x"]
    np.testing.assert_allclose(np.concatenate([xa, ra["x"]]), xb, rtol=1e-12, atol=1e-18)
    c = make(effects={"delay": {"delay_s": 3e-4}}, substep_s=1e-4)
    for uk in [1.0, 2.0, 3.0, 4.0]:
        c.step(uk, 1e-4)
    assert c.applied_n == pytest.approx(1.0)  # the command of 3 periods ago


def test_asymmetry_sliding_levels():
    fric = {"model": "stribeck", "fc_n": 1.0, "fs_n": 1.0, "viscous_n_s_m": 20.0}
    r = 0.2
    fwd = make(fric, effects={"asymmetry": {"ratio": r}})
    fwd.simulate(np.full(5000, 3.0), 1e-4)
    # Fc+ = (1+r)Fc and Fv+ = (1+r)Fv: F = (1+r)(Fc + σ2 v)
    assert fwd.friction_n == pytest.approx((1 + r) * (1.0 + 20.0 * fwd.v_m_s), rel=1e-9)
    assert fwd.v_m_s == pytest.approx((3.0 / (1 + r) - 1.0) / 20.0, rel=1e-3)
    bwd = make(fric, effects={"asymmetry": {"ratio": r}})
    bwd.simulate(np.full(5000, -3.0), 1e-4)
    assert bwd.v_m_s == pytest.approx(-(3.0 / (1 - r) - 1.0) / 20.0, rel=1e-3)


def test_viscous_asymmetry_sliding_levels():
    """Fv+ = Fv + d_v, Fv− = Fv − d_v, Coulomb symmetric: the terminal speeds under ±3 N follow from
    3 = Fc + Fv±·|v| (a plain reference, not the plant's kernels)."""
    fric = {"model": "stribeck", "fc_n": 1.0, "fs_n": 1.0, "viscous_n_s_m": 20.0}
    d = 8.0
    fwd = make(fric, effects={"viscous_asymmetry": {"difference_n_s_m": d}})
    fwd.simulate(np.full(20000, 3.0), 1e-4)
    assert fwd.v_m_s == pytest.approx((3.0 - 1.0) / (20.0 + d), rel=1e-3)
    bwd = make(fric, effects={"viscous_asymmetry": {"difference_n_s_m": d}})
    bwd.simulate(np.full(20000, -3.0), 1e-4)
    assert bwd.v_m_s == pytest.approx(-(3.0 - 1.0) / (20.0 - d), rel=1e-3)


def test_position_ripple_modulates_sliding_force_and_breakaway():
    fric = {"model": "stribeck", "fc_n": 1.0, "fs_n": 1.0, "viscous_n_s_m": 5.0}
    rp = {"amplitude": 0.2, "wavelength_m": 1e-3, "phase_rad": 0.0}
    dut = make(fric, effects={"position_ripple": rp})
    r = dut.simulate(np.full(4000, 2.0), 1e-4)
    moving = r["v"] > 1e-3
    expected = (1.0 + 5.0 * r["v"]) * (1 + 0.2 * np.sin(2 * np.pi * r["x"] / 1e-3))
    np.testing.assert_allclose(r["friction"][moving], expected[moving], rtol=1e-9)
    # at x = λ/4 the break-away level is 1.2 N: 1.1 N does not move the stage, 1.3 N does
    for u, moves in [(1.1, False), (1.3, True)]:
        d = make(fric, effects={"position_ripple": rp}, x0_m=0.25e-3)
        d.simulate(np.full(100, u), 1e-4)
        assert (abs(d.x_m - 0.25e-3) > 1e-9) == moves


# ---------------------------------------------------------------------------------------------- static friction
def test_karnopp_stick_and_breakaway():
    fric = {"model": "stribeck", "fc_n": 1.0, "fs_n": 1.5, "viscous_n_s_m": 0.4}
    dut = make(fric)
    dut.simulate(np.full(1000, 1.4), 1e-4)
    assert dut.x_m == 0.0 and dut.v_m_s == 0.0
    assert dut.friction_n == pytest.approx(1.4)
    dut.simulate(np.full(1000, 1.6), 1e-4)
    assert dut.v_m_s > 0.0
    dut.simulate(np.zeros(20000), 1e-4)  # decelerates and sticks again
    assert dut.v_m_s == 0.0
    x_stop = dut.x_m
    dut.simulate(np.full(1000, -1.3), 1e-4)
    assert dut.x_m == x_stop
    assert dut.friction_n == pytest.approx(-1.3)


# ---------------------------------------------------------------------------------------------- actuator/sensor
def test_force_clamp():
    dut = make(actuator={"max_force_n": 1.0})
    dut.step(100.0, 1e-4)
    assert dut.applied_n == 1.0
    dut.step(-100.0, 1e-4)
    assert dut.applied_n == -1.0
    r = make(actuator={"max_force_n": 1.0}, friction={"model": "stribeck", "fc_n": 0.0, "fs_n": 0.0})
    out = r.simulate(np.full(10, 5.0), 1e-3)
    assert out["v"][-1] == pytest.approx(1.0 / 1.0 * 0.01, rel=1e-9)  # a = 1 N / 1 kg


def test_sensor_quantisation():
    dut = make(sensor={"resolution_m": 1e-6}, x0_m=3.4e-6)
    assert dut.measure() == pytest.approx(3e-6)
    assert dut.measure_counts() == 3
    dut.reset(x0_m=-2.6e-6)
    assert dut.measure_counts() == -3
    r = dut.simulate(np.full(2000, 0.5), 1e-4)
    np.testing.assert_allclose(r["x_meas"], np.floor(r["x"] / 1e-6 + 0.5) * 1e-6, rtol=0, atol=1e-15)


def test_sensor_delay_steps():
    dut = make(sensor={"resolution_m": 1e-12, "delay_steps": 3})
    xs, ms = [], []
    for _ in range(50):
        dut.step(1.0, 1e-4)
        xs.append(dut.x_m)
        ms.append(dut.measure())
    np.testing.assert_allclose(ms[3:], xs[:-3], atol=1e-12)
    assert ms[:3] == [0.0, 0.0, 0.0]


def test_sensor_noise_statistics_and_seed():
    cfg = {"sensor": {"resolution_m": 1e-10, "noise_std_m": 5e-8}, "seed": 7}
    a = make(**cfg)
    r = a.simulate(np.zeros(20000), 1e-4)
    err = r["x_meas"] - r["x"]
    assert np.std(err) == pytest.approx(5e-8, rel=0.05)
    assert abs(np.mean(err)) < 5e-9
    # same seed -> same readings, step() loop == simulate()
    b = make(**cfg)
    ms = []
    for _ in range(100):
        b.step(0.0, 1e-4)
        ms.append(b.measure())
    np.testing.assert_allclose(ms, r["x_meas"][:100], rtol=0, atol=1e-15)


def test_step_loop_equals_simulate_gms_with_effects():
    extra = {"effects": {"cogging": {"amplitude_n": 0.1, "wavelength_m": 5e-5}, "asymmetry": {"ratio": 0.1},
                         "delay": {"delay_s": 1.3e-4}},
             "sensor": {"resolution_m": 1e-9, "noise_std_m": 2e-9, "delay_steps": 2}, "seed": 3}
    u = 1.2 * np.sin(np.arange(3000) * 2 * np.pi * 2e-4)
    a = make(gms(sigma1=20.0, viscous=10.0), mass_kg=2.0, **extra)
    b = make(gms(sigma1=20.0, viscous=10.0), mass_kg=2.0, **extra)
    rb = b.simulate(u, 1e-4)
    xs, ms, fs = [], [], []
    for uk in u:
        a.step(uk, 1e-4)
        xs.append(a.x_m)
        ms.append(a.measure())
        fs.append(a.friction_n)
    np.testing.assert_allclose(xs, rb["x"], rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(fs, rb["friction"], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(ms, rb["x_meas"], rtol=0, atol=1e-15)
    assert np.ptp(rb["x"]) > 1e-5  # it really slid
    assert a.t_s == pytest.approx(0.3)


def test_reset_restores_initial_state():
    dut = make(gms(), mass_kg=2.0)
    dut.simulate(np.full(100, 2.0), 1e-4)
    dut.reset(x0_m=1e-3)
    assert (dut.t_s, dut.x_m, dut.v_m_s, dut.friction_n) == (0.0, 1e-3, 0.0, 0.0)
    assert not np.any(dut.friction_state)


# ---------------------------------------------------------------------------------------------- config
def test_model_file_relative_to_base_dir_and_overrides():
    gms_model = load_model_file(MODELS / "kamenar2016_gms.yaml")  # the configuration layer's job
    cfg = PlantConfig.from_mapping({"model_file": "kamenar2016_gms.yaml"}, model=gms_model)
    assert cfg.mass_kg == 2.0 and cfg.friction.tag == "gms"
    cfg2 = PlantConfig.from_mapping(
        {"model_file": "kamenar2016_gms.yaml", "mass_kg": 5.0, "friction": {"c_n_s": 2e4},
         "effects": {"offset": {"force_n": 0.1}}}, model=gms_model)
    assert cfg2.mass_kg == 5.0
    assert cfg2.friction.params.c_n_s == 2e4 and cfg2.friction.params.fs_n == 0.9
    assert cfg2.effects.offset is not None and cfg2.effects.offset.force_n == 0.1


def test_config_errors_name_every_key():
    with pytest.raises(ConfigError) as ei:
        PlantConfig.from_mapping({"mass_kg": -1.0, "friction": {"model": "gms", "k_n_m": [1.0], "alpha": [1.0],
                                                                "fc_n": 1.0, "fs_n": 1.0, "c_ns": 3},
                                  "sensor": {"resolution_m": 0.0}, "substepp_s": 1e-5})
    msg = str(ei.value)
    for key in ("plant.mass_kg", "plant.friction.c_ns", "plant.sensor.resolution_m", "plant.substepp_s"):
        assert key in msg
    with pytest.raises(ConfigError, match="plant.model_file"):
        PlantConfig.from_mapping({"model_file": "nope.yaml"})  # given, but not loaded


def test_bad_step_arguments():
    dut = make()
    with pytest.raises(ValueError, match="dt_s"):
        dut.step(0.0, 0.0)
    with pytest.raises(ValueError, match="u_n"):
        dut.step(float("nan"), 1e-4)


def test_simulate_batch_equals_individual_runs():
    from stagectl.friction import build
    from stagectl.sim.plant import simulate_batch

    base = PlantConfig.from_mapping({"mass_kg": 2.0, "friction": gms(), "effects": {"delay": {"delay_s": 1.5e-4}}})
    models = [build(gms(sigma1=s1, viscous=10.0)) for s1 in (0.0, 20.0, 80.0)]
    u = 1.2 * np.sin(np.arange(2000) * 2 * np.pi * 5e-4)
    out = simulate_batch(base, models, u, 1e-4)
    assert out["x"].shape == (3, 2000)
    for j, m in enumerate(models):
        single = StagePlant(PlantConfig.from_mapping({"mass_kg": 2.0, "friction": m,
                                                      "effects": {"delay": {"delay_s": 1.5e-4}}})).simulate(u, 1e-4)
        np.testing.assert_array_equal(out["x"][j], single["x"])
        np.testing.assert_array_equal(out["friction"][j], single["friction"])
    assert np.max(np.abs(out["x"][0] - out["x"][2])) > 1e-7
    with pytest.raises(ValueError, match="one class"):
        simulate_batch(base, [models[0], build(VISCOUS_ONLY)], u, 1e-4)


def test_substep_too_large_for_stiffness_or_damping_is_rejected():
    with pytest.raises(ConfigError, match=r"plant.substep_s: must be <= 0.0005 s for stiffness 2e\+06 N/m"):
        PlantConfig.from_mapping({"mass_kg": 0.5, "friction": gms(k=[2e6]), "substep_s": 1e-3})
    with pytest.raises(ConfigError, match="substep_s: .*damping 1e\\+04 N·s/m"):
        PlantConfig.from_mapping({"mass_kg": 0.5, "friction": {**VISCOUS_ONLY, "viscous_n_s_m": 1e4},
                                  "substep_s": 1e-4})
    PlantConfig.from_mapping({"mass_kg": 0.5, "friction": gms(k=[2e6]), "substep_s": 1e-5})  # fine


# ---------------------------------------------------------------------------------------------- every model
ALL_MODELS = {
    "stribeck": {"model": "stribeck", "fc_n": 0.8, "fs_n": 0.9, "viscous_n_s_m": 10.0},
    "maxwell_slip": {"model": "maxwell_slip", "k_n_m": K_TABLE1, "alpha": ALPHA_TABLE1, "fs_n": 0.9,
                     "viscous_n_s_m": 10.0},
    "gms": gms(sigma1=30.0, viscous=10.0),
    "lugre": {"model": "lugre", "sigma0_n_m": 1e5, "sigma1_n_s_m": 316.2, "viscous_n_s_m": 0.4, "fc_n": 0.8,
              "fs_n": 0.9},
    "dahl": {"model": "dahl", "sigma0_n_m": 1e5, "fc_n": 0.8, "viscous_n_s_m": 1.0},
    "hsieh": None,  # the shipped model file
}


@pytest.mark.parametrize("tag", sorted(ALL_MODELS))
def test_every_model_in_the_plant_balances_energy_and_dissipates(tag):
    from stagectl.friction import load_model_file, registry

    fric = ALL_MODELS[tag] or load_model_file(MODELS / "kamenar2016_hsieh.yaml").friction.spec()
    dut = make(fric, mass_kg=2.0)
    assert set(ALL_MODELS) == set(registry())  # every registered model runs in the plant
    rng = np.random.default_rng(2)
    u = 1.5 * np.sin(2 * np.pi * 2.0 * np.arange(12000) * 1e-4) + np.repeat(rng.uniform(-0.3, 0.3, 30), 400)
    r = dut.simulate(u, 1e-4)
    w = dut.work_j()
    ke = 0.5 * 2.0 * r["v"][-1] ** 2
    assert np.ptp(r["x"]) > 1e-4  # slid (both pre-sliding and gross motion were visited)
    assert w["friction"] > 0.0  # friction dissipated energy
    assert w["applied"] == pytest.approx(ke + w["friction"] + w["other"], abs=2e-3 * abs(w["applied"]) + 1e-9)


@pytest.mark.parametrize("tag", sorted(ALL_MODELS))
def test_relaxed_state_at_rest_carries_no_force_as_the_plant_assumes(tag):
    """``StagePlant.reset`` starts with friction 0 without calling the model's force kernel (so a run does not
    compile it): that holds only if every model's relaxed state at v = 0 has zero force."""
    from stagectl.friction import build, load_model_file

    model = build(ALL_MODELS[tag] or load_model_file(MODELS / "kamenar2016_hsieh.yaml").friction.spec())
    assert model.force(model.initial_state(), 0.0) == 0.0
    assert make(ALL_MODELS[tag] or model.spec(), mass_kg=2.0).friction_n == 0.0


@pytest.mark.parametrize("tag,mass", [("hsieh", 2.0), ("lugre", 1.0), ("dahl", 0.01)])
def test_substep_limit_applies_to_every_stiff_or_damped_model(tag, mass):
    from stagectl.friction import load_model_file

    fric = ALL_MODELS[tag] or load_model_file(MODELS / "kamenar2016_hsieh.yaml").friction.spec()
    with pytest.raises(ConfigError, match="plant.substep_s: must be <="):
        PlantConfig.from_mapping({"mass_kg": mass, "friction": fric, "substep_s": 5e-3})
    PlantConfig.from_mapping({"mass_kg": mass, "friction": fric, "substep_s": 1e-5})


def test_constructor_prepares_the_integration_kernel_and_leaves_the_plant_relaxed():
    """A virtual drive builds its plant before it answers its master: the first cyclic ``step`` must not compile
    (a 2 s compile inside the cyclic exchange looks like a dead drive). The constructor's warm-up step relies on
    ``reset`` undoing a step completely: a used-then-reset plant must follow a fresh one exactly."""
    from stagectl.jit import compiled_signatures

    kw = dict(friction=gms(sigma1=1.0), effects={"delay": {"delay_s": 2e-4}}, sensor={"noise_std_m": 1e-9})
    fresh = make(**kw)
    assert compiled_signatures(fresh._integrate) >= 1
    used = make(**kw)
    for _ in range(20):
        used.step(2.0, 1e-3)
    assert used.measure() != fresh.measure()
    used.reset()
    for k in range(200):
        u = 0.5 * math.sin(0.05 * k)
        fresh.step(u, 1e-3)
        used.step(u, 1e-3)
        assert used.measure() == fresh.measure()
    np.testing.assert_array_equal(used._ps, fresh._ps)
    np.testing.assert_array_equal(used._fs, fresh._fs)
