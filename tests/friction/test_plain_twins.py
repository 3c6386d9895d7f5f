"""Plain-Python twins of the compiled kernels (``stagectl.jit.plain``; what a real stage's feed-forward runs without
numba) against the compiled kernels, step by step, for every friction model and every branch of its step: equal
within 1e-12 of the force scale (the same source in the same order; bit for bit in practice). No time asserted."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from support import friction_moves

from stagectl.friction import build, load_model_file
from stagectl.jit import LazyKernel, plain
from stagectl.resources import config_dir

#: the stated tolerance, relative to the model's force scale
RTOL = 1e-12

MODELS = {
    "gms_table1": load_model_file(config_dir() / "models" / "kamenar2016_gms.yaml").friction,
    # every GMS branch: delta neither 1 nor 2, micro-damping, viscous, two elements
    "gms_damped": build({"model": "gms", "k_n_m": [3e5, 8e4], "alpha": [0.7, 0.3], "fc_n": 1.0, "fs_n": 1.4,
                         "vs_m_s": 2e-3, "delta": 1.4, "c_n_s": 3e3, "sigma1_n_s_m": [20.0, 5.0],
                         "viscous_n_s_m": 0.7}),
    "hsieh_table1": load_model_file(config_dir() / "models" / "kamenar2016_hsieh.yaml").friction,
    "lugre": build({"model": "lugre", "sigma0_n_m": 1e5, "sigma1_n_s_m": 30.0, "fc_n": 1.0, "fs_n": 1.5,
                    "vs_m_s": 1e-3, "delta": 1.3, "viscous_n_s_m": 0.4, "sigma1_decay_m_s": 2e-3}),
    "dahl_classic": build({"model": "dahl", "sigma0_n_m": 2e5, "fc_n": 1.0, "viscous_n_s_m": 0.3}),
    "dahl_stiff": build({"model": "dahl", "sigma0_n_m": 2e5, "fc_n": 1.0, "exponent": 1.7}),
    "dahl_soft": build({"model": "dahl", "sigma0_n_m": 2e5, "fc_n": 1.0, "exponent": 0.6}),
    "maxwell_slip": build({"model": "maxwell_slip", "k_n_m": [1e5, 4e4, 1e4], "w_n": [0.3, 0.4, 0.5],
                           "viscous_n_s_m": 0.2}),
    "stribeck_lag": build({"model": "stribeck", "fc_n": 1.0, "fs_n": 1.5, "vs_m_s": 1e-3, "delta": 2.0,
                           "viscous_n_s_m": 0.5, "lag_s": 3e-3}),
    "stribeck_delta1": build({"model": "stribeck", "fc_n": 1.0, "fs_n": 1.2, "vs_m_s": 1e-3, "delta": 1.0}),
}



@pytest.mark.parametrize("name", sorted(MODELS))
def test_the_plain_step_equals_the_compiled_step(name: str) -> None:
    model = MODELS[name]
    step = model.plain_stepper()
    assert step is not None
    s_c = model.initial_state()
    s_p = s_c.tolist()
    scale = max(1.0, float(np.max(np.abs([model.step(model.initial_state(), 1e-3, 1e-2, 0.1)]))))
    v, dt = friction_moves(3, 4000)
    worst = 0.0
    forces = []
    for vk, dtk in zip(v, dt):
        fc = model.step(s_c, vk * dtk, vk, dtk)
        fp = step(s_p, vk * dtk, vk, dtk)
        assert isinstance(fp, float)
        worst = max(worst, abs(fc - fp))
        forces.append(fc)
    assert np.ptp(forces) > 0.1 * scale  # it went through pre-sliding and sliding, both ways
    assert worst <= RTOL * scale, worst
    np.testing.assert_allclose(s_p, s_c, rtol=RTOL, atol=RTOL * scale)


def test_the_plain_twin_calls_the_twins_of_the_kernels_it_calls() -> None:
    from stagectl.friction import _numba, gms

    assert isinstance(gms._kstep, LazyKernel)
    twin = plain(gms._kstep)
    assert twin.__globals__["stribeck_excess"] is plain(_numba.stribeck_excess)  # not the compiled kernel
    assert twin.__globals__["np"].int64 is int  # numpy's integer cast as Python's int (the same value)
    assert twin.__globals__["np"].zeros is np.zeros


def test_importing_the_models_and_stepping_plain_imports_no_numba() -> None:
    code = (
        "import sys\n"
        "from stagectl.friction import build\n"
        "m = build({'model': 'gms', 'k_n_m': [1e5, 2e5], 'alpha': [0.5, 0.5], 'fc_n': 1.0, 'fs_n': 1.2})\n"
        "s = m.initial_state().tolist(); f = m.plain_stepper()\n"
        "print(f(s, 1e-6, 1e-3, 1e-3), 'numba' in sys.modules)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    force, loaded = r.stdout.split()
    assert float(force) > 0.0 and loaded == "False"
