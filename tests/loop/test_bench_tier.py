"""The tiered-start experiment of ``stagectl bench startup --switch`` (``stagectl.bench.tier``): its plain-Python
kernels must compute what the compiled ones compute (else the bench would time the wrong thing), and a switch from
the plain to the compiled kernels with the state carried over must not change the trajectory (bumpless). No time
is asserted."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest
from stagectl.sim import plant as plant_mod
from support import friction_moves

from stagectl.bench import tier
from stagectl.config import load_app_config
from stagectl.friction import build
from stagectl.jit import cache_dir
from stagectl.resources import config_dir

#: the stated tolerance between the plain and the compiled kernels (relative to the force/position scale); the
#: same operations in the same order, so in practice they agree bit for bit
RTOL = 1e-12

SIM = load_app_config(str(config_dir() / "sim.yaml"))
GMS = SIM.sim.plant.friction  # Table 1 GMS, N = 6, delta 2, no micro-damping
# every branch: delta neither 1 nor 2, micro-damping, viscous, two elements
OTHER = build({"model": "gms", "k_n_m": [3e5, 8e4], "alpha": [0.7, 0.3], "fc_n": 1.0, "fs_n": 1.4, "vs_m_s": 2e-3,
               "delta": 1.4, "c_n_s": 3e3, "sigma1_n_s_m": [20.0, 5.0], "viscous_n_s_m": 0.7})



@pytest.mark.parametrize("model", [GMS, OTHER], ids=["table1", "damped"])
def test_plain_gms_step_equals_the_compiled_step(model) -> None:
    p = model.kernel().p
    s_c = model.initial_state()
    s_p = s_c.tolist()
    v, dt = friction_moves(3, 4000)
    n = model.n_states // 2
    worst = 0.0
    modes: set[float] = set()
    for vk, dtk in zip(v, dt):
        fc = type(model)._kstep(p, s_c, vk * dtk, vk, dtk)
        fp = tier.gms_step_plain(p.tolist(), s_p, vk * dtk, vk, dtk)
        worst = max(worst, abs(fc - fp))
        modes.update(s_c[n:].tolist())
    assert modes == {-1.0, 0.0, 1.0}  # stick and slip both ways were visited
    assert worst <= RTOL * model.params.fs_n
    np.testing.assert_allclose(s_p, s_c, rtol=0.0, atol=RTOL * model.params.fs_n)


def test_plain_plant_cycle_equals_the_compiled_cycle_and_the_layout_is_the_plants() -> None:
    assert (tier.PS_T, tier.PS_X, tier.PS_V, tier.PS_FF, tier.PS_FO, tier.PS_UA, tier.PS_STUCK, tier.PS_WIN,
            tier.PS_WF, tier.PS_WO) == (plant_mod._T, plant_mod._X, plant_mod._V, plant_mod._FF, plant_mod._FO,
                                        plant_mod._UA, plant_mod._STUCK, plant_mod._WIN, plant_mod._WF, plant_mod._WO)
    p = GMS.kernel().p
    cyc = plant_mod.cycle_for(type(GMS)._kstep)
    fs_c, ps_c = GMS.initial_state(), np.zeros(10)
    fs_p, ps_p = fs_c.tolist(), ps_c.tolist()
    for k in range(300):
        u = 3.0 * math.sin(2 * math.pi * k / 150.0)  # beyond break-away (Fs 1.5 N): slips both ways
        cyc(p, fs_c, ps_c, 0.5, 0.0, u, 1e-3, 100)
        tier.plant_cycle_plain(p.tolist(), fs_p, ps_p, 0.5, 0.0, u, 1e-3, 100)
    assert abs(ps_c[plant_mod._X]) > 1e-4  # it moved
    np.testing.assert_allclose(ps_p, ps_c, rtol=RTOL, atol=0.0)
    np.testing.assert_allclose(fs_p, fs_c, rtol=0.0, atol=RTOL * GMS.params.fs_n)


def test_a_config_without_a_simulated_gms_plant_is_skipped_with_a_reason() -> None:
    stage = load_app_config(str(config_dir() / "stage-canopen.yaml"))
    assert tier.job_for(stage, cycles=10) is None
    assert "GMS" in tier.run_switch(stage, 10, None, lambda *a: None)["skipped"]


@pytest.mark.slow  # a real 1 kHz loop in a child until numba is loaded: seconds of wall clock under load
def test_the_switch_to_the_compiled_kernels_is_bumpless_in_a_real_child() -> None:
    """The bench's child on the plant path: plain kernels until the background thread has loaded numba's, then
    the compiled ones with the state carried over. The trajectory (a function of the cycle count, not of time)
    equals the all-plain run's cycle for cycle, across the switch."""
    job = tier.job_for(SIM, cycles=3)
    sw = tier._case(sys.executable, dict(job, path="plant", tier="switch"), cache_dir())
    assert sw["switch_cycle"] is not None and sw["cycles"] >= sw["switch_cycle"] + 100
    plain = tier._case(sys.executable, dict(job, path="plant", tier="plain", cycles=sw["cycles"]), cache_dir())
    x_sw, x_pl = np.array(sw["_out"]), np.array(plain["_out"])
    assert x_sw.shape == x_pl.shape and np.abs(x_pl).max() > 1e-6
    np.testing.assert_allclose(x_sw, x_pl, rtol=RTOL, atol=0.0)
