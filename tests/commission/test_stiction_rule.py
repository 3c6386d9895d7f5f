"""The gains choice on a sticky stage (k106: 1.36 kg, F_s 2.04 N, F_c 1.70 N, 50 um following-error limit, 1 kHz).
On main the twin ranked a soft design ~10 % ahead of a stiff one (a near tie) and the soft one faulted the cosine
on the stage: a finalist whose excess stiction length (F_s - F_c)/K_p exceeds the limit wins only by a clear
margin (STICKY_NEAR_TIE)."""
from __future__ import annotations

import math
from typing import Any

import pytest

from stagectl.commission.sequence import (STICKY_NEAR_TIE, choose_gains, pick_finalist, stiction_excess,
                                          stiction_screen)

M, T, FS, FC, FE = 1.36, 1e-3, 2.04, 1.70, 50e-6


def twin_keys(fin: list[dict[str, Any]], soft_gain: float) -> list[tuple[float, float]]:
    """Rank keys as the twin gives them: the softest design ahead of every other by ``soft_gain``."""
    soft = min(fin, key=lambda e: e["crossover_target_hz"])
    return [(math.log(271e-9 * (1 - soft_gain)) if e is soft else math.log(271e-9 + 1e-9 * i), -2.0)
            for i, e in enumerate(fin)]


@pytest.fixture(scope="module")
def fin() -> list[dict[str, Any]]:
    g = choose_gains(M, T, None, None)
    stiction_screen(g["finalists"], 1.76, stiction_excess({"friction": {"fs_n": FS, "fc_n": FC}}, 1.76), FE)
    return list(g["finalists"])


def test_near_tie_goes_to_the_design_that_holds_the_stiction(fin: list[dict[str, Any]]) -> None:
    soft = min(fin, key=lambda e: e["crossover_target_hz"])
    assert soft["sticky"] and soft["excess_stiction_length_m"] > FE
    assert any(not e["sticky"] for e in fin)
    i, dec = pick_finalist(fin, twin_keys(fin, 0.10))  # k106 on main: 243 against 271 nm
    assert not fin[i]["sticky"] and (FS - FC) / fin[i]["pid"]["kp_n_m"] <= FE
    assert "sticky" in dec["decision"] and dec["confidence"] == "medium"


def test_clear_win_keeps_the_sticky_design(fin: list[dict[str, Any]]) -> None:
    """Generated plant 36: its soft design was 30 % ahead on the twin and ran without a fault."""
    i, dec = pick_finalist(fin, twin_keys(fin, 0.30))
    assert fin[i] is min(fin, key=lambda e: e["crossover_target_hz"]) and 0.30 > STICKY_NEAR_TIE
    assert "although sticky" in dec["decision"]


def test_small_excess_marks_nothing(fin: list[dict[str, Any]]) -> None:
    """Little stiction over Coulomb (plant 34: 0.10 N; k100: 0.04 N): the twin alone decides."""
    rec = stiction_screen([dict(e) for e in fin], 1.2, 0.04, FE)
    assert rec["sticky"] == []
    assert stiction_excess({"friction": {"fc_n": 1.0}}, 0.8) == 0.0
