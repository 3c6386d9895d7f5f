"""The additional effects' three paths agree: scalar methods, numpy-vectorised methods and compiled kernels.

One agreement test over every effect of :class:`stagectl.friction.effects.Effects` (each alone and all
together), on random parameters and random positions/forces from a fixed seed.
"""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from stagectl.friction.effects import (
    Asymmetry,
    Cogging,
    Delay,
    Effects,
    Offset,
    PositionRipple,
    Spring,
    ViscousAsymmetry,
    modify_friction_kernel,
    other_force_kernel,
    pack_layout,
    velocity_force_kernel,
)


def _draw(rng: np.random.Generator) -> dict[str, object]:
    return {
        "asymmetry": Asymmetry(ratio=float(rng.uniform(-0.9, 0.9))),
        "position_ripple": PositionRipple(amplitude=float(rng.uniform(0.0, 0.9)),
                                          wavelength_m=float(rng.uniform(1e-4, 1e-2)),
                                          phase_rad=float(rng.uniform(-np.pi, np.pi))),
        "cogging": Cogging(amplitude_n=float(rng.uniform(0.0, 3.0)), wavelength_m=float(rng.uniform(1e-4, 1e-2)),
                           phase_rad=float(rng.uniform(-np.pi, np.pi))),
        "offset": Offset(force_n=float(rng.uniform(-2.0, 2.0))),
        "spring": Spring(stiffness_n_m=float(rng.uniform(-200.0, 200.0)), x0_m=float(rng.uniform(-0.01, 0.01))),
        "delay": Delay(delay_s=float(rng.uniform(0.0, 0.01))),
        "viscous_asymmetry": ViscousAsymmetry(difference_n_s_m=float(rng.uniform(-50.0, 50.0))),
    }


NAMES = [f.name for f in fields(Effects)]


def test_every_effect_is_drawn() -> None:
    assert sorted(_draw(np.random.default_rng(0))) == sorted(NAMES)


@pytest.mark.parametrize("active", [(n,) for n in NAMES] + [tuple(NAMES)], ids=lambda a: "+".join(a))
def test_compiled_kernels_agree_with_scalar_and_array_paths(active: tuple[str, ...]) -> None:
    rng = np.random.default_rng(1234)
    for _trial in range(20):
        drawn = _draw(rng)
        dut = Effects(**{n: drawn[n] for n in active})  # type: ignore[arg-type]
        ep = np.ascontiguousarray(dut.packed())
        assert ep.shape == (len(pack_layout()),)
        x = rng.uniform(-0.05, 0.05, 64)
        f = rng.normal(0.0, 2.0, 64)
        f[:4] = 0.0  # exact zero friction (asymmetry keeps it zero)
        v = rng.normal(0.0, 0.05, 64)
        v[:2] = 0.0
        mod_arr = dut.modify_friction_array(f, x)
        oth_arr = dut.other_force_array(x)
        vel_arr = dut.velocity_force_array(v)
        for k in range(x.size):
            mod_s = dut.modify_friction(float(f[k]), float(x[k]))
            oth_s = dut.other_force(float(x[k]))
            assert modify_friction_kernel(ep, float(f[k]), float(x[k])) == pytest.approx(mod_s, rel=1e-12, abs=1e-15)
            assert other_force_kernel(ep, float(x[k])) == pytest.approx(oth_s, rel=1e-12, abs=1e-12)
            assert mod_arr[k] == pytest.approx(mod_s, rel=1e-12, abs=1e-15)
            assert oth_arr[k] == pytest.approx(oth_s, rel=1e-12, abs=1e-12)
            vel_s = dut.velocity_force(float(v[k]))
            assert velocity_force_kernel(ep, float(v[k])) == pytest.approx(vel_s, rel=1e-12, abs=1e-15)
            assert vel_arr[k] == pytest.approx(vel_s, rel=1e-12, abs=1e-15)
        if "delay" in active:
            assert ep[pack_layout().index("delay_s")] == dut.delay.delay_s  # type: ignore[union-attr]


def test_no_effects_is_identity() -> None:
    dut = Effects()
    ep = np.ascontiguousarray(dut.packed())
    for x, f in ((0.0, 1.5), (0.013, -0.7), (-0.02, 0.0)):
        assert modify_friction_kernel(ep, f, x) == f == dut.modify_friction(f, x)
        assert other_force_kernel(ep, x) == 0.0 == dut.other_force(x)
        assert velocity_force_kernel(ep, 0.3) == 0.0 == dut.velocity_force(0.3)
