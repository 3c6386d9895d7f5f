"""Friction feed-forward: reference-driven model copy, jitter-immune reversals, effects, Coulomb baseline."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from control_harness import seed_model  # noqa: E402

from stagectl.control.api import Reference  # noqa: E402
from stagectl.control.friction_ff import CoulombFeedforward, DirectionLatch, FrictionFeedforward  # noqa: E402
from stagectl.friction import build  # noqa: E402
from stagectl.friction.effects import Effects  # noqa: E402
from stagectl.schema import load  # noqa: E402

DT = 1e-3


def _ramp_refs(n: int, v: float, x0: float = 0.0) -> list[Reference]:
    return [Reference(x0 + v * k * DT, v, 0.0) for k in range(n)]


def test_follows_model_along_a_clean_reference():
    """Without jitter the feed-forward equals the model's force along the same path (after the threshold)."""
    model = seed_model().friction
    dut = FrictionFeedforward(model, reversal_threshold_m=5e-9)
    dut.reset(0.0)
    refs = _ramp_refs(40, 2e-6) + [Reference(78e-9 - 2e-6 * k * DT, -2e-6, 0.0) for k in range(1, 40)]
    out = np.array([dut.step(DT, r) for r in refs])
    x = np.array([r.x_m for r in refs])
    expected = model.force_along(x, np.arange(x.size) * DT)
    # identical once the first threshold has been passed and after the reversal has been confirmed
    assert np.allclose(out[10:40], expected[10:40], rtol=0, atol=1e-12)
    assert np.allclose(out[45:], expected[45:], rtol=0, atol=1e-12)
    assert dut.state.reversals == 1


def test_reversal_detection_ignores_jitter_below_threshold():
    model = seed_model().friction
    rng = np.random.default_rng(1)
    n = 400
    base = _ramp_refs(n, 1e-6)  # 1 nm per sample
    jitter = rng.uniform(-2e-9, 2e-9, n)  # ±2 nm < 5 nm threshold, velocity jitter below 10 µm/s
    clean = FrictionFeedforward(model, reversal_threshold_m=5e-9)
    noisy = FrictionFeedforward(model, reversal_threshold_m=5e-9)
    naive = FrictionFeedforward(model, reversal_threshold_m=0.0, reversal_velocity_m_s=1e-12)
    for d in (clean, noisy, naive):
        d.reset(0.0)
    f_clean, f_noisy, f_naive = [], [], []
    n_el = len(model.params.k_n_m)
    el_noisy, el_naive = [], []  # sum of the element forces (without the rate-dependent damping terms)
    for r, j in zip(base, jitter):
        f_clean.append(clean.step(DT, r))
        rj = Reference(r.x_m + j, r.v_m_s + j / DT * 0.001, 0.0)
        f_noisy.append(noisy.step(DT, rj))
        f_naive.append(naive.step(DT, rj))
        el_noisy.append(float(np.sum(noisy.model_state[:n_el])))
        el_naive.append(float(np.sum(naive.model_state[:n_el])))
    assert noisy.state.reversals == 0 and noisy.latch.direction == 1
    assert naive.state.reversals > 50  # without the latch every back-step is a "reversal"
    # the jitter-immune copy stays within the force of a few nm of pre-sliding stiffness of the clean one
    k0 = sum(model.params.k_n_m)
    assert np.max(np.abs(np.array(f_noisy[50:]) - np.array(f_clean[50:]))) < k0 * 5e-9
    # the latched copy is monotonic in the loading direction (never unloads on jitter)
    assert np.all(np.diff(el_noisy) >= -1e-12)
    assert np.sum(np.diff(el_naive) < -1e-4) > 50


def test_direction_latch_confirms_by_velocity_or_distance():
    dut = DirectionLatch(threshold_m=5e-9, velocity_m_s=1e-5)
    dut.reset(0.0)
    assert dut.update(3e-9, 0.0) is False and dut.direction == 0
    assert dut.update(6e-9, 0.0) is True and dut.direction == 1
    assert dut.update(20e-9, 0.0) is False
    assert dut.update(16e-9, -1e-6) is False and dut.direction == 1  # 4 nm back, slow: jitter
    assert dut.update(19e-9, 0.0) is False
    assert dut.update(18.5e-9, -2e-5) is True and dut.direction == -1  # fast enough backwards
    assert dut.update(10e-9, -2e-5) is False
    assert dut.update(16e-9, 0.0) is True and dut.direction == 1  # moved back 6 nm from the minimum


def test_effects_are_compensated_and_delay_is_looked_ahead():
    model = build({"model": "stribeck", **_stribeck_params()}) if _has("stribeck") else seed_model().friction
    eff = load(Effects, {"offset": {"force_n": 0.3}, "spring": {"stiffness_n_m": 100.0, "x0_m": 0.0},
                         "cogging": {"amplitude_n": 0.05, "wavelength_m": 1e-3},
                         "delay": {"delay_s": 2e-3}}, "effects")
    dut = FrictionFeedforward(model, eff)
    dut.reset(0.0)
    ref = Reference(1e-4, 0.0, 0.0)
    u = dut.step(DT, ref)
    x = 1e-4
    assert dut.state.f_other_n == pytest.approx(0.3 + 100.0 * x + 0.05 * math.sin(2 * math.pi * x / 1e-3))
    assert u == pytest.approx(dut.state.f_friction_n + dut.state.f_other_n)
    # delay: the reference is evaluated 2 ms ahead (x + v·τ + a·τ²/2)
    dut2 = FrictionFeedforward(model, load(Effects, {"spring": {"stiffness_n_m": 1000.0}}, "e"), lookahead_s=2e-3)
    dut2.reset(0.0)
    dut2.step(DT, Reference(1e-5, 1e-3, 0.5))
    assert dut2.state.f_other_n == pytest.approx(1000.0 * (1e-5 + 1e-3 * 2e-3 + 0.5 * 0.5 * 4e-6))


def test_asymmetry_scales_friction_by_direction():
    model = seed_model().friction
    eff = load(Effects, {"asymmetry": {"ratio": 0.2}}, "effects")
    plain = FrictionFeedforward(model)
    asym = FrictionFeedforward(model, eff)
    for d in (plain, asym):
        d.reset(0.0)
    for r in _ramp_refs(100, 1e-3):  # sliding forward
        fp, fa = plain.step(DT, r), asym.step(DT, r)
    assert fa == pytest.approx(1.2 * fp)


def test_coulomb_baseline_holds_direction_through_zero_velocity():
    dut = CoulombFeedforward(0.8, viscous_n_s_m=10.0)
    dut.reset(0.0)
    assert dut.step(DT, Reference(0.0, 0.0)) == 0.0
    assert dut.step(DT, Reference(1e-6, 1e-3)) == pytest.approx(0.8 + 0.01)
    # stops at the top: direction (and Coulomb force) held, no sgn(0) = 0 chatter
    assert dut.step(DT, Reference(1e-6, 0.0)) == pytest.approx(0.8)
    assert dut.step(DT, Reference(0.998e-6, -1e-7)) == pytest.approx(0.8 - 1e-6)  # 2 nm back: jitter
    assert dut.step(DT, Reference(0.99e-6, -1e-7)) == pytest.approx(-0.8 - 1e-6)  # 10 nm back: reversal


@pytest.mark.parametrize("dt", [0.0, -1.0, math.nan])
def test_bad_dt_raises(dt):
    dut = FrictionFeedforward(seed_model().friction)
    dut.reset(0.0)
    with pytest.raises(ValueError, match="dt"):
        dut.step(dt, Reference(0.0))


def _has(tag: str) -> bool:
    from stagectl.friction import registry  # importing the package registers every model

    return tag in registry()


def _stribeck_params() -> dict:
    from stagectl.friction import registry

    cls = registry()["stribeck"]
    import dataclasses

    names = {f.name for f in dataclasses.fields(cls.Params)}
    p = {"fc_n": 0.8, "fs_n": 0.9, "vs_m_s": 1e-3}
    return {k: v for k, v in p.items() if k in names}


@pytest.mark.parametrize("name", ["kamenar2016_gms.yaml", "kamenar2016_hsieh.yaml"])
def test_any_library_model_drives_the_feedforward(name):
    from control_harness import REPO

    from stagectl.friction import load_model_file

    path = REPO / "config" / "models" / name
    if not path.exists():
        pytest.skip(f"{name} not shipped")
    model = load_model_file(path).friction
    dut = FrictionFeedforward(model)
    dut.reset(0.0)
    out = []
    for k in range(1, 1001):  # one 10 µm raised-cosine period at 1 kHz
        t = k * DT
        x = 5e-6 * (1 - math.cos(2 * math.pi * t))
        v = 5e-6 * 2 * math.pi * math.sin(2 * math.pi * t)
        out.append(dut.step(DT, Reference(x, v, 0.0)))
    f = np.array(out)
    assert np.all(np.isfinite(f))
    assert f.max() > 0.3 and f.min() < -0.3  # pre-sliding force of both signs (Fs ≈ 0.9 N)
    assert dut.state.reversals == 1


def test_the_model_kernel_is_loaded_at_construction_not_in_the_first_moving_cycle():
    """A fresh process: constructing the feed-forward loads the GMS model's compiled step (numba import and
    cache load took 0.5-0.9 s in the HIL's first moving cycle, and the drive's heartbeat consumer faulted)."""
    import subprocess

    code = ("from stagectl.control.friction_ff import FrictionFeedforward\n"
            "import stagectl.config as c, pathlib\n"
            "m = c.load_app_config(pathlib.Path('config/sim.yaml')).controller.feedforward.model.friction\n"
            "assert not type(m)._kstep.signatures\n"
            "FrictionFeedforward(m)\n"
            "print(len(type(m)._kstep.signatures))\n")
    root = Path(__file__).resolve().parents[2]
    r = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert int(r.stdout.strip()) >= 1
