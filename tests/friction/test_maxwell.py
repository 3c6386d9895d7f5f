"""Maxwell-slip model (tag ``maxwell_slip``): TV2 virgin curve, Masing loops, energy per cycle, wipe-out."""

from __future__ import annotations

import numpy as np
import pytest

from stagectl.errors import ConfigError
from stagectl.friction import build

K = [454610.0, 111088.0, 45601.0, 16402.0, 6899.0, 4295.0]
ALPHA = [0.378, 0.138, 0.148, 0.177, 0.112, 0.046]
SPEC = {"model": "maxwell_slip", "k_n_m": K, "alpha": ALPHA, "fs_n": 0.9}
UM = 1e-6

VIRGIN_TV2 = [(0.5, 0.319447), (1, 0.524485), (2, 0.610794), (5, 0.735580), (10, 0.867290), (14.611, 0.899100),
              (30, 0.899100)]
ENERGY_TV2 = [(0.5, 0.0), (1, 0.342467), (2, 2.141429), (5, 8.821926), (10, 21.017056), (15, 37.139976),
              (30, 91.085976)]


def along(dut, x):
    x = np.asarray(x, dtype=float)
    return dut.force_along(x, np.arange(x.size) * 1e-3)


@pytest.mark.parametrize("spec", [SPEC, {"model": "maxwell_slip", "k_n_m": K, "w_n": [a * 0.9 for a in ALPHA]}])
def test_tv2_virgin_curve(spec):
    dut = build(spec)
    xs = np.array([0.0] + [x for x, _ in VIRGIN_TV2]) * UM
    f = along(dut, xs)
    np.testing.assert_allclose(f[1:], [fv for _, fv in VIRGIN_TV2], atol=1e-6)
    np.testing.assert_allclose(dut.virgin(xs)[1:], [fv for _, fv in VIRGIN_TV2], atol=1e-6)
    # the slip displacements of TV2
    w = np.array(dut.params.slip_forces_n)
    np.testing.assert_allclose(w / np.array(K) / UM, [0.74833, 1.11803, 2.92099, 9.71223, 14.61081, 9.63912],
                               atol=1e-5)


def test_virgin_curve_is_odd_and_rate_independent():
    dut = build(SPEC)
    x = np.linspace(0, -20 * UM, 50)
    f_slow = dut.force_along(x, np.linspace(0, 100.0, 50))
    f_fast = dut.force_along(x, np.linspace(0, 1e-3, 50))
    np.testing.assert_allclose(f_slow, f_fast, rtol=0, atol=1e-15)
    np.testing.assert_allclose(f_slow, -dut.virgin(-x), atol=1e-12)


def cycle(amplitude: float, n: int = 4000) -> np.ndarray:
    """0 → +A (virgin), then A → −A → +A; +A at index n, 0 (descending) at 2n, −A at 3n."""
    up = np.linspace(0, amplitude, n + 1)
    down = np.linspace(amplitude, -amplitude, 2 * n + 1)[1:]
    up2 = np.linspace(-amplitude, amplitude, 2 * n + 1)[1:]
    return np.concatenate([up, down, up2])


@pytest.mark.parametrize("amp,f_a,f_zero", [(2.0, 0.610794, -0.438176), (10.0, 0.867290, -0.603870)])
def test_masing_loop_values(amp, f_a, f_zero):
    dut = build(SPEC)
    n = 4000
    x = cycle(amp * UM, n)
    f = along(dut, x)
    assert f[n] == pytest.approx(f_a, abs=1e-6)  # +A
    assert f[3 * n] == pytest.approx(-f_a, abs=1e-6)  # -A
    i0 = 2 * n  # x = 0 on the descending branch
    assert x[i0] == pytest.approx(0.0, abs=1e-15)
    assert f[i0] == pytest.approx(f_zero, abs=1e-6)
    assert f[-1] == pytest.approx(f_a, abs=1e-9)  # the loop closes at the reversal force
    # descending branch is the Masing image of the virgin curve: F = F_r − 2·F_v((x_r − x)/2)
    desc = slice(n, 3 * n + 1)
    np.testing.assert_allclose(f[desc], f_a - 2 * dut.virgin((amp * UM - x[desc]) / 2), atol=1e-9)


@pytest.mark.parametrize("amp,energy_uj", ENERGY_TV2)
def test_tv2_energy_per_cycle(amp, energy_uj):
    dut = build(SPEC)
    n = 20000
    x = cycle(amp * UM, n)
    f = along(dut, x)
    loop = slice(n, None)
    xl, fl = x[loop], f[loop]
    area = float(np.sum(0.5 * (fl[1:] + fl[:-1]) * np.diff(xl)))  # ∮F dx, trapezoid
    assert dut.cycle_energy(amp * UM) / 1e-6 == pytest.approx(energy_uj, abs=1e-6)
    if energy_uj == 0.0:
        assert abs(area) < 1e-15
    else:
        assert area / 1e-6 == pytest.approx(energy_uj, rel=1e-5)


def test_wipe_out_returns_to_the_outer_branch():
    dut = build(SPEC)
    # outer: 0 -> 8 µm -> 2 µm; inner loop 2 -> 5 -> 3 -> 5 ; continuing down must follow the old branch
    path_plain = np.concatenate([np.linspace(0, 8, 81), np.linspace(8, -4, 121)[1:]]) * UM
    path_inner = np.concatenate([np.linspace(0, 8, 81), np.linspace(8, 2, 61)[1:], np.linspace(2, 5, 31)[1:],
                                 np.linspace(5, 3, 21)[1:], np.linspace(3, 5, 21)[1:], np.linspace(5, -4, 91)[1:]]) * UM
    fp = along(dut, path_plain)
    fi = along(dut, path_inner)
    # after the inner loop closes and x passes its start (2 µm), forces coincide with the plain path
    sel_p = path_plain[81:] < 1.95 * UM
    sel_i = np.zeros(path_inner.size, bool)
    sel_i[-90:] = path_inner[-90:] < 1.95 * UM
    np.testing.assert_allclose(fi[sel_i], fp[81:][sel_p][-sel_i.sum():], atol=1e-12)


def test_viscous_term_and_kernel_paths_agree(paths):
    dut = build({**SPEC, "viscous_n_s_m": 10.0})
    rng = np.random.default_rng(4)
    x = np.cumsum(rng.normal(0, 0.5 * UM, 500))
    t = np.cumsum(rng.uniform(1e-4, 2e-3, 500))
    f = dut.force_along(x, t)
    f_scalar, f_kern = paths(dut, x, t)
    np.testing.assert_array_equal(f, f_scalar)
    np.testing.assert_array_equal(f, f_kern)
    batch = type(dut).force_along_batch([dut.params, build(SPEC).params], x, t)
    np.testing.assert_array_equal(batch[0], f)
    np.testing.assert_allclose(batch[0] - batch[1], 10.0 * np.r_[(x[1] - x[0]) / (t[1] - t[0]),
                                                               np.diff(x) / np.diff(t)], rtol=1e-9, atol=1e-12)
    # independent reference: clip update
    z = np.zeros(len(K))
    w = np.array(ALPHA) * 0.9
    ref = []
    for i in range(1, x.size):
        z = np.clip(z + np.array(K) * (x[i] - x[i - 1]), -w, w)
        ref.append(z.sum() + 10.0 * (x[i] - x[i - 1]) / (t[i] - t[i - 1]))
    np.testing.assert_allclose(f[1:], ref, atol=1e-12)


@pytest.mark.parametrize(
    "bad,key",
    [({"k_n_m": [1.0, -2.0, 3.0, 4.0, 5.0, 6.0]}, "friction.k_n_m[1]"), ({"alpha": [0.5]}, "alpha"),
     ({"fs_n": None}, "w_n"), ({"w_n": [1.0] * 6}, "w_n"), ({"viscous_n_s_m": -1.0}, "friction.viscous_n_s_m"),
     ({"kk_n_m": [1.0]}, "friction.kk_n_m")],
)
def test_build_errors_name_the_key(bad, key):
    spec = {**SPEC, **bad}
    spec = {k: v for k, v in spec.items() if v is not None}
    with pytest.raises(ConfigError) as ei:
        build(spec)
    assert key in str(ei.value)
