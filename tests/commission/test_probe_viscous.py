"""The sanity probe's mass on a stage with a large viscous force (analysis.probe_joint_fit).

Oracle: a plain rigid mass with viscous and Coulomb friction, ``m·ẍ = F − c·ẋ − F_c·sgn(ẋ)`` (sticking while
``|F| ≤ F_c`` at rest), integrated with 20 sub-steps per loop period, driven by the real
:class:`SanityProbe` through one period of I/O delay and read through a 1 nm sensor quantum. The two-acceleration
estimate ``(F2 − F1)/(a2 − a1)`` reads 3.6 kg for the 0.67 kg / 89 N·s/m stage (tests/commission/plant_kinds.py
k101, which then faulted in the friction passes); the joint fit must read the true mass."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stagectl.commission import analysis as an
from stagectl.commission.controllers import SanityProbe

T = 1e-3


def _probe(m: float, c: float, f_c: float, f_lim: float, delay: int = 1, q: float = 1e-9) -> SanityProbe:
    probe = SanityProbe(f_lim_n=f_lim, d_detect_m=2e-6, d_acc_m=2e-5, v_stop_m_s=0.05)
    x = v = 0.0
    pending = [0.0] * delay
    probe.reset(0.0)
    h = T / 20
    for _ in range(20000):
        pending.append(probe.step(T, round(x / q) * q))
        f = pending.pop(0)
        if probe.done:
            break
        for _ in range(20):
            if v == 0.0 and abs(f) <= f_c:
                continue
            v_new = v + h * (f - f_c * math.copysign(1.0, v if v != 0.0 else f) - c * v) / m
            if v != 0.0 and v_new * v < 0.0:
                v_new = 0.0
            x += 0.5 * h * (v + v_new)
            v = v_new
    return probe


@pytest.mark.parametrize(("m", "c", "f_c"), [(0.6713, 88.9, 0.237), (2.276, 89.0, 0.35), (30.0, 300.0, 20.0)])
def test_probe_mass_is_not_inflated_by_a_viscous_force(m: float, c: float, f_c: float) -> None:
    p = _probe(m, c, f_c, f_lim=max(2.0, 2.0 * f_c))
    res = an.evaluate_probe(p.dirs, p.f_lim, p.d_detect, None)
    assert res.mass_kg == pytest.approx(m, rel=0.05)
    assert res.mass_from == "joint"
    assert 0.0 < res.mass_std_kg < 0.1 * m
    assert min(res.quadratic_mass_kg) > 1.1 * m          # the estimate it replaces is biased by the viscous force
    for jf in res.joint:
        assert jf is not None
        assert jf["viscous_n_s_m"] == pytest.approx(c, rel=0.1)
        assert jf["friction_n"] == pytest.approx(f_c, rel=0.2)


def test_a_small_viscous_force_keeps_the_two_acceleration_mass() -> None:
    """Coulomb only: the joint fit finds no viscous force worth its extra parameter; the mass stays the
    two-acceleration estimate, exactly (the quick start's figures depend on it)."""
    p = _probe(2.0, 0.0, 0.5, f_lim=4.0)
    res = an.evaluate_probe(p.dirs, p.f_lim, p.d_detect, 2.0)
    assert res.mass_from == "quadratic"
    assert res.mass_kg == float(np.median(res.quadratic_mass_kg))
    assert res.mass_kg == pytest.approx(2.0, rel=0.05)


def test_the_frf_mass_is_judged_against_the_joint_fit() -> None:
    """A viscous force too small for the probe to replace its two-acceleration mass (under a 10 % share) still
    biases it; the FRF's mass is judged against the joint fit's (analysis.probe_reference_mass), within
    3 combined standard errors (analysis.frf_mass_consistent). Fresh plant k111 of tests/commission/plant_kinds.py:
    3.37 kg, 9.3 N s/m; its FRF read 2.26 ± 0.24 kg and was kept, then the viscous fit read +48 %."""
    m = 3.37
    p = _probe(m, 9.3, 1.63, f_lim=3.3)
    res = an.evaluate_probe(p.dirs, p.f_lim, p.d_detect, None)
    assert res.mass_from == "quadratic"
    assert res.mass_kg > 1.02 * m                       # the viscous bias the probe keeps
    ref, sd, joint = an.probe_reference_mass(res)
    assert joint
    assert ref == pytest.approx(m, rel=0.01)
    assert sd == pytest.approx(an.PROBE_MASS_MIN_REL_STD * ref)  # the floor: its own error is statistical only
    assert not an.frf_mass_consistent(2.257, 0.238, ref, sd)
    assert an.frf_mass_consistent(3.2, 0.1, ref, sd)


def test_a_not_credible_frf_mass_is_replaced_by_the_joint_fit_where_its_directions_agree() -> None:
    """Fresh plant k105 of tests/commission/plant_kinds.py (0.700 kg, 9.92 N s/m, 0.85 N Coulomb): the viscous
    share is just under 10 %, so the probe keeps its two-acceleration mass, 10 % high; its FRF mass was not
    credible and that mass replaced it (identified +10.2 %). Both directions' joint fits measure the same
    viscous force, so the replacement is the joint fit's (analysis.probe_replacement_mass)."""
    m = 0.7004
    p = _probe(m, 9.921, 0.8513, f_lim=3.5)
    res = an.evaluate_probe(p.dirs, p.f_lim, p.d_detect, None)
    assert res.mass_from == "quadratic" and res.mass_kg > 1.08 * m
    assert an.probe_viscous_agrees(res)
    rep, sd, joint = an.probe_replacement_mass(res)
    assert joint
    assert rep == pytest.approx(m, rel=0.01)
    assert sd == pytest.approx(an.PROBE_MASS_MIN_REL_STD * rep)


def test_directions_that_disagree_on_the_viscous_force_keep_the_probe_mass() -> None:
    """The joint fits k110 measured (0.93 kg, 3.6 N s/m, vs 1.9 mm/s, 0.21 N offset): 6.7 ± 0.65 and 35 ± 5.6 N s/m
    read a friction that is not linear in the speed, differently each way; the probe's mass stays."""
    fits: list[dict[str, float] | None] = [
        {"mass_kg": 0.92055, "mass_std_kg": 0.00353, "viscous_n_s_m": 6.68559, "viscous_std_n_s_m": 0.65285,
         "friction_n": 1.4903, "delay_samples": 1.0, "dv_m_s": 0.00864},
        {"mass_kg": 0.79384, "mass_std_kg": 0.03791, "viscous_n_s_m": 34.99872, "viscous_std_n_s_m": 5.58083,
         "friction_n": 1.00456, "delay_samples": 1.0, "dv_m_s": 0.00725}]
    res = an.SanityResult(0.9917, [0.9571, 1.0263], [1.38, 1.42], mass_std_kg=0.084, quadratic_mass_kg=[0.9571, 1.0263],
                          joint=fits, joint_mass_kg=0.8572, joint_mass_std_kg=0.063)
    assert not an.probe_viscous_agrees(res)
    assert an.probe_replacement_mass(res) == (0.9917, 0.084, False)
    fits[1] = dict(fits[0] or {}, viscous_n_s_m=7.9)  # 1.2 N s/m apart, within 2 combined standard errors (1.8): agree
    assert an.probe_viscous_agrees(res)
    assert an.probe_replacement_mass(res)[2]
