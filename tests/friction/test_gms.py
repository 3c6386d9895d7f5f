"""GMS model (tag ``gms``): Table 1 virgin curve, TV2/TV3/TV8, transition rules, path agreement, energy."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stagectl.errors import ConfigError
from stagectl.friction import build, load_model_file, registry

REPO = Path(__file__).resolve().parents[2]
MODEL_FILE = REPO / "config" / "models" / "kamenar2016_gms.yaml"
UM = 1e-6
K = [454610.0, 111088.0, 45601.0, 16402.0, 6899.0, 4295.0]
ALPHA = [0.378, 0.138, 0.148, 0.177, 0.112, 0.046]
TV3 = {"model": "gms", "k_n_m": K, "alpha": ALPHA, "fc_n": 0.8, "fs_n": 0.9, "vs_m_s": 1e-3, "delta": 2.0,
       "c_n_s": 1e4, "viscous_n_s_m": 10.0}


# ---------------------------------------------------------------------------------------------- reference
class RefGms:
    """Independent plain-Python GMS (TAC 2005 force form), written from docs/friction-models.md §3.1/§3.3."""

    def __init__(self, k, alpha, fc, fs, vs, delta, c, sigma1, sigma2):
        self.k, self.alpha = list(k), list(alpha)
        self.fc, self.fs, self.vs, self.delta, self.c = fc, fs, vs, delta, c
        self.sigma1 = list(sigma1) if isinstance(sigma1, (list, tuple)) else [sigma1] * len(self.k)
        self.sigma2 = sigma2
        self.f = [0.0] * len(self.k)
        self.slip_dir = [0] * len(self.k)  # 0 = stick

    def step(self, dx, v, dt):
        if v == 0:
            return sum(self.f)
        d = 1 if v > 0 else -1
        g = self.fc + (self.fs - self.fc) * math.exp(-abs(v / self.vs) ** self.delta)
        total = self.sigma2 * v
        for i, (k, a) in enumerate(zip(self.k, self.alpha)):
            target = d * a * g  # α_i·s(v)
            if self.slip_dir[i] == -d:
                self.slip_dir[i] = 0  # reversal: stick
            if self.slip_dir[i] == 0 and d * self.f[i] >= a * g:
                self.slip_dir[i] = d  # loaded beyond the (lowered) limit in the direction of motion
            elif self.slip_dir[i] == 0:
                trial = self.f[i] + k * dx
                if d * trial < a * g:
                    self.f[i] = trial
                    total += self.f[i] + self.sigma1[i] * v  # stick: dz/dt = v
                    continue
                self.f[i], self.slip_dir[i] = target, d  # break-away, clamped; slipping at the end
            self.f[i] = target + (self.f[i] - target) * math.exp(-self.c * dt / g)
            rate = self.c * (d * a - self.f[i] / g) / k
            total += self.f[i] + self.sigma1[i] * rate
        return total


def ref_along(spec, x, t):
    r = RefGms(spec["k_n_m"], spec["alpha"], spec["fc_n"], spec["fs_n"], spec.get("vs_m_s", 1e-3),
               spec.get("delta", 2.0), spec.get("c_n_s", 1e4), spec.get("sigma1_n_s_m", 0.0),
               spec.get("viscous_n_s_m", 0.0))
    v0 = (x[1] - x[0]) / (t[1] - t[0])
    out = [(sum(r.sigma1) + r.sigma2) * v0]  # relaxed state: all elements stick, dz/dt = v
    for i in range(1, len(x)):
        dx, dt = x[i] - x[i - 1], t[i] - t[i - 1]
        out.append(r.step(dx, dx / dt, dt))
    return np.array(out)


def random_trajectory(seed: int, n: int = 3000):
    """Pre-sliding wiggles, sliding both ways, reversals, pauses (v = 0), varying dt."""
    rng = np.random.default_rng(seed)
    v = np.repeat(rng.choice([-5e-3, -1e-3, -2e-4, -1e-5, 0.0, 1e-5, 3e-4, 1e-3, 8e-3], n // 50), 50)
    v *= rng.uniform(0.5, 1.5, v.size)
    dt = rng.uniform(5e-5, 2e-4, v.size)
    x = np.concatenate([[0.0], np.cumsum(v * dt)])
    t = np.concatenate([[0.0], np.cumsum(dt)])
    return x, t


# ---------------------------------------------------------------------------------------------- virgin curve
def test_issue2_virgin_curve_from_model_file():
    model = load_model_file(MODEL_FILE)
    assert model.friction.tag == "gms" and model.mass_kg == 2.0
    x = np.array([0.0, 1.0, 2.0, 5.0, 10.0]) * UM
    t = np.arange(x.size) * 1e3  # quasi-static: 1 µm per 1000 s
    f = model.friction.force_along(x, t)
    np.testing.assert_allclose(f[1:], [0.524485, 0.610794, 0.735580, 0.867290], atol=1e-6)


def test_tv2_virgin_curve_and_closed_form():
    dut = build(TV3)
    xs = np.array([0.0, 0.5, 1, 2, 5, 10, 14.611, 30]) * UM
    f = dut.force_along(xs, np.arange(xs.size) * 1e4)
    expected = [0.319447, 0.524485, 0.610794, 0.735580, 0.867290, 0.899100, 0.899100]
    np.testing.assert_allclose(f[1:], expected, atol=1e-6)
    np.testing.assert_allclose(dut.virgin(xs)[1:], expected, atol=1e-6)
    assert dut.stiffness_n_m == pytest.approx(638895.0)


def test_tv3_slow_ramp_equals_virgin_plus_viscous():
    dut = build(TV3)
    v = 1e-6
    x = np.linspace(0.0, 30 * UM, 3001)
    f = dut.force_along(x, x / v)
    for x_um, fv in [(5.0, 0.735590), (30.0, 0.899110)]:
        i = int(round(x_um * 100))
        assert f[i] == pytest.approx(fv, abs=1e-5)
    np.testing.assert_allclose(f[1:], dut.virgin(x[1:]) + 10.0 * v, atol=1e-5)


# ---------------------------------------------------------------------------------------------- sliding
@pytest.mark.parametrize("v,f_ss", [(1e-4, 0.899106), (1e-3, 0.845951), (3e-3, 0.829212), (1e-2, 0.899200),
                                    (-1e-3, -0.845951), (-3e-3, -0.829212)])
def test_tv3_steady_sliding_is_stribeck_with_sign(v, f_ss):
    dut = build(TV3)
    travel = 200 * UM + abs(v) * 0.05  # beyond pre-sliding, and many slip time constants
    n = 4000
    x = np.linspace(0.0, math.copysign(travel, v), n)
    f = dut.force_along(x, np.linspace(0.0, travel / abs(v), n))
    assert f[-1] == pytest.approx(f_ss, abs=2e-6)
    assert f[-1] == pytest.approx(float(dut.stribeck(v)), abs=1e-9)


def test_tv3_reversal_slope_is_sum_k():
    dut = build(TV3)
    s = dut.initial_state()
    dt = 1e-4
    for _ in range(2000):  # slide at +1 mm/s
        dut.step(s, 1e-3 * dt, 1e-3, dt)
    f0 = dut.force(s, -1e-3)
    dx = -1e-10
    f1 = dut.step(s, dx, dx / 1e-7, 1e-7)
    slope = (f1 - f0 - 10.0 * (dx / 1e-7 - (-1e-3))) / dx
    assert slope == pytest.approx(638895.0, rel=1e-9)
    assert np.all(s[6:] == 0.0)  # every element sticks after the reversal


def test_unloading_element_keeps_sticking_even_if_g_drops():
    # slide slowly forward (elements at +α·g(1e-4) ≈ +α·0.8999), then reverse FAST (g(−10 mm/s) = 0.8):
    # |F_i| > α·g(v) but sgn(F_i) ≠ sgn(v): the elements are unloaded elastically, with slope Σk.
    dut = build(TV3)
    s = dut.initial_state()
    for _ in range(3000):
        dut.step(s, 1e-4 * 1e-3, 1e-4, 1e-3)
    f_before = s[:6].copy()
    dx = -1e-9
    dut.step(s, dx, -1e-2, 1e-7)
    np.testing.assert_allclose(s[:6], f_before + np.array(K) * dx, rtol=1e-12)
    assert np.all(s[6:] == 0.0)


def test_hold_at_zero_velocity():
    dut = build({**TV3, "sigma1_n_s_m": 50.0})
    x = np.concatenate([np.linspace(0, 3 * UM, 31), np.full(50, 3 * UM)])
    t = np.arange(x.size) * 1.0  # 0.1 µm/s: quasi-static
    f = dut.force_along(x, t)
    assert np.all(f[31:] == f[31])  # v = 0 exactly: no relaxation, no damping force
    assert f[31] == pytest.approx(dut.virgin(np.array([3 * UM]))[0], abs=1e-6)
    # damping of the 3 still-sticking elements and the viscous term vanish at rest (3 elements slip)
    assert f[30] - f[31] == pytest.approx(50.0 * 3 * 1e-7 + 10.0 * 1e-7, rel=1e-3)


def test_frictional_lag_time_constant_g_over_c():
    # after a velocity jump from 1 to 3 mm/s in sliding, the force relaxes with tau = g(v)/C
    dut = build(TV3)
    s = dut.initial_state()
    dt = 1e-5
    for _ in range(20000):
        dut.step(s, 1e-3 * dt, 1e-3, dt)
    g3 = 0.8 + 0.1 * math.exp(-9.0)
    f = np.array([dut.step(s, 3e-3 * dt, 3e-3, dt) for _ in range(100)]) - 10.0 * 3e-3
    expected = 0.999 * g3 + (0.999 * (0.8 + 0.1 * math.exp(-1.0)) - 0.999 * g3) * np.exp(
        -1e4 * dt * np.arange(1, 101) / g3)
    np.testing.assert_allclose(f, expected, atol=1e-12)


# ---------------------------------------------------------------------------------------------- paths agree
@pytest.mark.parametrize("seed", [0, 1])
def test_scalar_kernel_along_batch_and_reference_agree(seed, paths):
    spec = {**TV3, "sigma1_n_s_m": [40.0, 10.0, 5.0, 2.0, 1.0, 1.0]}
    dut = build(spec)
    x, t = random_trajectory(seed)
    f_along = dut.force_along(x, t)
    f_scalar, f_kern = paths(dut, x, t)
    np.testing.assert_array_equal(f_along, f_scalar)
    np.testing.assert_array_equal(f_along, f_kern)
    other = build({**spec, "c_n_s": 3e3}).params
    batch = type(dut).force_along_batch([other, dut.params, other], x, t)
    assert batch.shape == (3, x.size)
    np.testing.assert_array_equal(batch[1], f_along)
    np.testing.assert_array_equal(batch[0], batch[2])
    assert np.max(np.abs(batch[0] - f_along)) > 1e-3  # a different C really changes the force
    np.testing.assert_allclose(f_along, ref_along(spec, x, t), rtol=1e-9, atol=1e-9)
    assert np.ptp(x) > 100 * UM  # the trajectory really slid


def test_batch_with_different_element_counts():
    a = build(TV3)
    b = build({**TV3, "k_n_m": [5e5], "alpha": [1.0]})
    x, t = random_trajectory(3, 500)
    out = type(a).force_along_batch([a.params, b.params], x, t)
    np.testing.assert_array_equal(out[0], a.force_along(x, t))
    np.testing.assert_array_equal(out[1], b.force_along(x, t))


def test_derivative_matches_step():
    dut = build(TV3)
    s = dut.initial_state()
    for _ in range(100):
        dut.step(s, 1e-3 * 1e-4, 1e-3, 1e-4)  # some elements slip now
    for v in (1e-3, -1e-3):
        s2 = s.copy()
        d = dut.derivative(s2, v)
        dut.step(s2, v * 1e-9, v, 1e-9)
        np.testing.assert_allclose((s2[:6] - s[:6]) / 1e-9, d[:6], rtol=1e-4, atol=1e-6)


# ---------------------------------------------------------------------------------------------- energy
def closed_path(waypoints_um, speeds):
    pts = np.array([0.0, *waypoints_um, 0.0]) * UM
    xs, ts = [0.0], [0.0]
    for j in range(1, pts.size):
        d = pts[j] - pts[j - 1]
        v = speeds[(j - 1) % len(speeds)]
        n = max(2, int(abs(d) / (0.05 * UM)))
        seg = np.linspace(pts[j - 1], pts[j], n + 1)[1:]
        xs.extend(seg)
        step_t = max(abs(d) / n / v, 1e-7)
        ts.extend(ts[-1] + step_t * np.arange(1, n + 1))
    return np.array(xs), np.array(ts)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    waypoints=st.lists(st.floats(-60.0, 60.0, allow_nan=False), min_size=1, max_size=6),
    speeds=st.lists(st.sampled_from([1e-6, 1e-4, 1e-3, 3e-3, 2e-2]), min_size=1, max_size=3),
    model=st.sampled_from(["gms", "gms_damped", "maxwell"]),
)
def test_energy_is_dissipated_never_created(waypoints, speeds, model):
    spec = {"gms": TV3, "gms_damped": {**TV3, "sigma1_n_s_m": 50.0, "c_n_s": 2e3},
            "maxwell": {"model": "maxwell_slip", "k_n_m": K, "alpha": ALPHA, "fs_n": 0.9}}[model]
    dut = build(spec)
    x, t = closed_path(waypoints, speeds)
    f = dut.force_along(x, t)
    work = float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(x)))  # ∮F dx over a closed path
    assert work >= -1e-9


# ---------------------------------------------------------------------------------------------- TV8 drift
def _drift_per_cycle(friction_spec, mean_n, amp_n, cycles=6):
    from stagectl.sim.plant import PlantConfig, StagePlant

    dut = StagePlant(PlantConfig.from_mapping({"mass_kg": 1.0, "friction": friction_spec}))
    dt = 1e-4
    n = int(round(1.0 / dt))
    t = np.arange(cycles * n) * dt
    r = dut.simulate(mean_n + amp_n * np.sin(2 * np.pi * t), dt)
    per_cycle = r["x"].reshape(cycles, n).mean(axis=1)
    return float(np.mean(np.diff(per_cycle[2:]))), r["x"]


def test_tv8_gms_does_not_drift():
    spec = load_model_file(MODEL_FILE).friction.spec()
    drift, x = _drift_per_cycle(spec, 0.35, 0.3)
    assert abs(drift) < 1e-3 * UM
    assert 1.5 * UM < x[-1] < 2.5 * UM  # settles near 2.07 µm inside pre-sliding


def test_tv8_lugre_drifts():
    if "lugre" not in registry():
        build(TV3)  # imports every model module
    if "lugre" not in registry():
        pytest.skip("LuGre model (stagectl.friction.lugre, engineer H2) is not available in this build")
    spec = {"model": "lugre", "sigma0_n_m": 1e5, "sigma1_n_s_m": math.sqrt(1e5), "viscous_n_s_m": 0.4,
            "fc_n": 1.0, "fs_n": 1.5, "vs_m_s": 1e-3}
    drift, _ = _drift_per_cycle(spec, 0.6, 0.35)
    assert drift > 1.0 * UM  # TV8: ≈ 7.28 µm per cycle


# ---------------------------------------------------------------------------------------------- config
@pytest.mark.parametrize(
    "bad,key",
    [({"alpha": [0.5, 0.5]}, "alpha"), ({"alpha": [0.1] * 6}, "alpha"), ({"c_n_s": 0.0}, "friction.c_n_s"),
     ({"k_n_m": [1.0, 2.0, 3.0, 4.0, 5.0, -6.0]}, "friction.k_n_m[5]"), ({"fs_n": -0.5}, "fs_n"),
     ({"sigma1_n_s_m": [1.0, 2.0]}, "sigma1_n_s_m"), ({"sigma1_n_s_m": -1.0}, "friction.sigma1_n_s_m"),
     ({"c_ns": 1.0}, "friction.c_ns"), ({"delta": 0.0}, "friction.delta")],
)
def test_build_errors_name_the_key(bad, key):
    with pytest.raises(ConfigError) as ei:
        build({**TV3, **bad})
    assert key in str(ei.value)


def test_scalar_sigma1_broadcasts_and_spec_round_trips():
    dut = build({**TV3, "sigma1_n_s_m": 3.0})
    assert dut.params.sigma1_n_s_m == (3.0,) * 6
    assert build(dut.spec()).params == dut.params
    model = load_model_file(MODEL_FILE)
    assert build(model.friction.spec()).params == model.friction.params


# ---------------------------------------------------------------------------------------------- Masing / energy
@pytest.mark.parametrize("amp,f_a,f_zero,energy_uj", [(2.0, 0.610794, -0.438176, 2.141429),
                                                       (10.0, 0.867290, -0.603870, 21.017056)])
def test_gms_quasi_static_masing_loop_and_energy_per_cycle(amp, f_a, f_zero, energy_uj):
    # at v -> 0 the GMS is the Maxwell-slip model with W_i = α_i·Fs (TV2): Masing branches, E(A) per cycle
    dut = build({**TV3, "viscous_n_s_m": 0.0})
    n = 20000
    a = amp * UM
    x = np.concatenate([np.linspace(0, a, n + 1), np.linspace(a, -a, 2 * n + 1)[1:], np.linspace(-a, a, 2 * n + 1)[1:]])
    t = np.arange(x.size) * (a / n) / 1e-8  # 10 nm/s: g(v) = Fs within 1e-10 N
    f = dut.force_along(x, t)
    assert f[n] == pytest.approx(f_a, abs=1e-6)
    assert f[2 * n] == pytest.approx(f_zero, abs=1e-6)  # x = 0 descending: F_v(A) − 2·F_v(A/2)
    assert f[3 * n] == pytest.approx(-f_a, abs=1e-6)
    assert f[-1] == pytest.approx(f_a, abs=1e-6)  # the loop closes at the reversal force
    desc = slice(n, 3 * n + 1)
    np.testing.assert_allclose(f[desc], f_a - 2 * dut.virgin((a - x[desc]) / 2), atol=1e-6)
    xl, fl = x[n:], f[n:]
    area = float(np.sum(0.5 * (fl[1:] + fl[:-1]) * np.diff(xl)))
    assert area / 1e-6 == pytest.approx(energy_uj, rel=1e-4)


@pytest.mark.parametrize("c_n_s,dt", [(1e9, 1e-2), (1e3, 1e-2), (1e9, 1e-8)])
def test_slip_update_is_unconditionally_stable(c_n_s, dt):
    # C·dt/g up to 1e7 (explicit Euler would need C·dt/g < 2): no overshoot, monotone approach to α·s(v)
    dut = build({**TV3, "c_n_s": c_n_s, "viscous_n_s_m": 0.0})
    s = dut.initial_state()
    for _ in range(200):  # slide forward at 1 mm/s into slip
        dut.step(s, 1e-3 * 1e-4, 1e-3, 1e-4)
    g = 0.8 + 0.1 * math.exp(-((5e-3 / 1e-3) ** 2))
    prev = dut.force(s, 5e-3)
    for _ in range(50):  # jump to 5 mm/s: g drops, elements relax towards α_i·g(5 mm/s)
        f = dut.step(s, 5e-3 * dt, 5e-3, dt)
        assert np.all(np.abs(s[:6]) <= np.array(ALPHA) * 0.9 + 1e-12)
        assert g * 0.999 - 1e-12 <= f <= prev + 1e-12
        prev = f
    if c_n_s * dt / g > 50:
        assert f == pytest.approx(0.999 * g, abs=1e-9)
