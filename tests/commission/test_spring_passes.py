"""A spring ``k·(x − x0)`` that discover named takes its stiffness and rest position from the slow passes
(:func:`stagectl.commission.fit.slow_pass_spring`, docs/commissioning.md §4).

Fresh plant k111 of tests/commission/plant_kinds.py (444.74 N/m, x0 = −198.0 µm): discover, reading the
spring jointly with the pre-sliding elements on the nested reversals near the stroke's centre, fitted 453.0 N/m
and x0 = −208.8 µm, 4.8 mN of spring force off everywhere; main kept it, and the commissioned cosine was 3.97×
the exact model's. The slow passes over the stroke read both directions at the same positions: their slope is
``k`` and their even part at their mean position ``x̄`` is ``k·(x̄ − x0)`` plus the other named effects' even
parts (443.8 N/m, −198.0 µm on k111; cosine 2.06×).

Oracles: the closed-loop slow passes of ``test_cogging_edge._slow_passes`` (a plain rigid mass with Coulomb and
viscous friction under a PID, the position force given), and slow passes written from the friction laws
(``test_analysis._slow_passes``) for an asymmetry beside the spring. A fraction of a second each.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_analysis import _slow_passes as _hand_passes
from test_cogging_edge import T, _slow_passes

from stagectl.commission import fit

K, X0 = 444.74, -198.0e-6
DISCOVERED = {"stiffness_n_m": 453.04, "x0_m": -208.83e-6}  # what discover fitted on k111


def test_a_discovered_spring_gets_the_slow_passes_rest_position() -> None:
    slow = _slow_passes(lambda x: K * (x - X0))
    sp = fit.slow_pass_spring(slow, 0.79, T, DISCOVERED, {"spring": DISCOVERED})
    assert sp["used"], sp
    assert sp["stiffness_n_m"] == pytest.approx(K, rel=0.01)
    assert abs(sp["x0_m"] - X0) < 1e-6, sp  # discover's was 10.8 µm off


def test_an_offset_named_beside_the_spring_is_not_counted_twice() -> None:
    f0 = 0.03
    slow = _slow_passes(lambda x: K * (x - X0) + f0)
    eff = {"spring": DISCOVERED, "offset": {"force_n": f0}}
    sp = fit.slow_pass_spring(slow, 0.79, T, DISCOVERED, eff)
    assert sp["used"] and abs(sp["x0_m"] - X0) < 1e-6, sp
    # without the offset named, the spring's constant part carries it: the same force along the stroke
    alone = fit.slow_pass_spring(slow, 0.79, T, DISCOVERED, {"spring": DISCOVERED})
    assert alone["x0_m"] == pytest.approx(X0 - f0 / alone["stiffness_n_m"], abs=1e-6)


def test_an_asymmetry_named_beside_the_spring_keeps_its_even_part() -> None:
    """Friction ``F·(1 + r·sgn F)`` has the even part ``r·F`` at the passes' level: it is no spring force."""
    r, fc = 0.05, 0.5
    slow = _hand_passes(lambda x, d: fc * d * (1.0 + r * d) + K * (x - X0))
    sp = fit.slow_pass_spring(slow, 1.0, 1e-3, DISCOVERED, {"spring": DISCOVERED, "asymmetry": {"ratio": r}})
    assert sp["used"] and abs(sp["x0_m"] - X0) < 1e-6, sp
    naive = fit.slow_pass_spring(slow, 1.0, 1e-3, DISCOVERED, {"spring": DISCOVERED})
    assert abs(naive["x0_m"] - X0) > 40e-6  # r·Fc = 25 mN read as spring force: 56 µm


def test_slow_passes_without_the_slope_leave_discovers_spring() -> None:
    slow = _slow_passes(lambda x: 0.02 + 0.0 * x)
    sp = fit.slow_pass_spring(slow, 0.79, T, DISCOVERED, {"spring": DISCOVERED})
    assert not sp["used"] and "does not confirm" in sp["reason"], sp
    assert np.isfinite(sp["slope_n_m"])
