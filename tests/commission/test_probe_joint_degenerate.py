"""review17: the probe's joint mass + viscous fit (analysis.probe_joint_fit) on degenerate data returns None (no
estimate) instead of raising or returning a mass with a fake-small standard error that passes the gates.

Oracle: a rigid mass with viscous and Coulomb friction stepped in plain Python (semi-implicit Euler)."""

from __future__ import annotations

import math

import pytest

from stagectl.commission.analysis import probe_joint_fit

DT = 1e-3


def _sim(m: float, c: float, f_c: float, f1: float, f2: float, n: int = 60) -> tuple[list[float], list[float]]:
    x = v = 0.0
    xs = []
    for i in range(2 * n):
        f = f1 if i < n else f2
        a = (f - f_c - c * v) / m if (f > f_c or v > 0.0) else 0.0
        v += a * DT
        x += v * DT
        xs.append(x)
    return xs[:n], xs[n:]


def test_two_levels_still_fit() -> None:
    x1, x2 = _sim(0.67, 89.0, 1.0, 3.0, 6.0)
    jf = probe_joint_fit(x1, x2, 3.0, 6.0, DT)
    assert jf is not None and jf["mass_kg"] > 0.0 and jf["viscous_n_s_m"] > 0.0


@pytest.mark.parametrize("c", [0.0, 5.0])
def test_one_force_level_gives_no_mass(c: float) -> None:
    # one level: m·x + c·∫x + (F_f − F)·t²/2 − p − q·t = 0 is a column dependency; before the fix the fit returned
    # 0.50 kg (true 0.67) with a 2e-9 kg standard error, or a 0.0 one (a negative variance clamped to 0)
    x1, x2 = _sim(0.67, c, 1.0, 3.0, 3.0)
    assert probe_joint_fit(x1, x2, 3.0, 3.0, DT) is None


@pytest.mark.parametrize("where", ["x1", "x2", "f1", "dt"])
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_data_gives_no_mass(where: str, bad: float) -> None:
    # before the fix a nan/inf sample raised LinAlgError out of lstsq
    x1, x2 = _sim(0.67, 89.0, 1.0, 3.0, 6.0)
    f1, dt = 3.0, DT
    if where == "x1":
        x1[-1] = bad
    elif where == "x2":
        x2[3] = bad
    elif where == "f1":
        f1 = bad
    else:
        dt = bad
    assert probe_joint_fit(x1, x2, f1, 6.0, dt) is None


def test_no_motion_gives_no_mass() -> None:
    assert probe_joint_fit([0.0] * 60, [0.0] * 60, 3.0, 6.0, DT) is None
    assert probe_joint_fit([1e-3] * 60, [1e-3] * 60, 3.0, 6.0, DT) is None
