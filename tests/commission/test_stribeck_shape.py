"""The constant-velocity fit where the passes do not separate the Stribeck tail from the viscous term
(analysis._stribeck_shape): the pairs' odd parts of generated plants 72 and 75 (tests/commission/plant_gen.py)
as their passes measured them, built from the plants' own curves. On main the free five-parameter curve
traded its tail against the viscous term (72: Fc −14 %, Fv +18 %; 75: Fv +17 %) and reported ±0.01 %."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from stagectl.commission import analysis as an

sys.path.insert(0, str(Path(__file__).parent))
from plant_gen import hidden_plant


def _segments(fr: dict[str, float], speeds: np.ndarray, se: list[float], wobble: list[float],
              delta: float = 2.0) -> list[an.CvSegment]:
    """Both directions of each speed [m/s]: the curve's force plus an odd ``wobble`` [N] (the means'
    measurement error), each mean with its standard error ``se`` [N]."""
    out = []
    for v, s, w in zip(speeds.tolist(), se, wobble):
        for sg in (1.0, -1.0):
            e = np.exp(-abs(v / fr["vs_m_s"]) ** delta)
            f = sg * (fr["fc_n"] + (fr["fs_n"] - fr["fc_n"]) * e + w) + fr["viscous_n_s_m"] * sg * v
            out.append(an.CvSegment(sg * v, float(f), s, 200))
    return out


def _errors(cv: an.CvFriction, fr: dict[str, float]) -> tuple[float, float]:
    return cv.coulomb_n / fr["fc_n"] - 1.0, cv.viscous_n_s_m / fr["viscous_n_s_m"] - 1.0


def test_heavy_stage_without_its_fastest_pair() -> None:
    # plant 72 (11 kg, vs 2.7 mm/s): its 16 mm/s passes were too short to settle, five pairs 0.16-6.4 mm/s
    # are left; their standard errors as measured, the means within 0.1 mN of the curve
    fr = hidden_plant(72)["friction"]
    speeds = np.geomspace(0.16e-3, 16e-3, 6)[:5]
    cv = an.cv_friction(_segments(fr, speeds, [5e-4, 1.6e-3, 7e-4, 1.2e-3, 2e-3], [0.0, 1e-4, 0.0, -1e-4, 1e-4]))
    efc, efv = _errors(cv, fr)
    assert abs(efc) < 0.1 and abs(efv) < 0.1, (efc, efv)  # main: −5.6 %, +8.0 %
    # the uncertainty says what the data leave open: the truth within two standard errors, and not ±0.01 %
    assert abs(cv.coulomb_n - fr["fc_n"]) <= 2 * cv.coulomb_std_n
    assert abs(cv.viscous_n_s_m - fr["viscous_n_s_m"]) <= 2 * cv.viscous_std_n_s_m
    assert cv.viscous_std_n_s_m > 0.03 * cv.viscous_n_s_m  # main: 0.04 %
    sh = cv.shape
    assert sh is not None and sh["delta_held"] and cv.stribeck is not None and cv.stribeck["delta_held"] == 1.0
    assert sh["viscous_range_n_s_m"][1] > 1.1 * fr["viscous_n_s_m"]
    line = an.shape_line(cv)
    assert line is not None and "do not separate" in line


def test_one_noisy_pair_beyond_the_dip() -> None:
    # plant 75 (1.1 kg, vs 2.0 mm/s): six pairs, only the 16 mm/s one well beyond the dip, read over a
    # 15-sample cogging-centred window: 3 mN high with a 5.5 mN standard error
    fr = hidden_plant(75)["friction"]
    speeds = np.geomspace(0.16e-3, 16e-3, 6)
    cv = an.cv_friction(_segments(fr, speeds, [5e-5, 5e-5, 9e-5, 1.6e-4, 4e-4, 5.5e-3],
                                  [0.0, 0.0, 0.0, 0.0, 1.4e-4, 3e-3]))
    efc, efv = _errors(cv, fr)
    assert abs(efc) < 0.02 and abs(efv) < 0.1, (efc, efv)  # main: −0.4 %, +13.9 %
    assert abs(cv.viscous_n_s_m - fr["viscous_n_s_m"]) <= 2 * cv.viscous_std_n_s_m


def test_a_resolved_curve_keeps_its_shape() -> None:
    # passes from 0.4 to 40 vs: the curve's shape (δ = 1, not the default 2) is measured and stays free,
    # Fc and Fv tight and no warning
    fr = {"fc_n": 0.5, "fs_n": 0.7, "vs_m_s": 0.4e-3, "viscous_n_s_m": 8.0}
    speeds = np.geomspace(0.16e-3, 16e-3, 6)
    cv = an.cv_friction(_segments(fr, speeds, [3e-4] * 6, [1e-4, -1e-4] * 3, delta=1.0))
    efc, efv = _errors(cv, fr)
    assert abs(efc) < 0.005 and abs(efv) < 0.01, (efc, efv)
    assert cv.stribeck is not None and abs(cv.stribeck["delta"] - 1.0) < 0.05
    assert cv.shape is not None and not cv.shape["delta_held"] and "delta_held" not in cv.stribeck
    assert cv.viscous_std_n_s_m < 0.02 * fr["viscous_n_s_m"]
    assert an.shape_line(cv) is None
