"""The gains choice on a sticky stage: a finalist whose stiction length F_b/K_p exceeds STICTION_LENGTH_X_FE
following-error limits is not chosen while a stiffer healthy finalist exists (k106: 1.36 kg, 2.04 N breakaway,
50 um limit, 1 kHz loop; on main the twin picked 10 Hz + Q-filter, which hunted and faulted the cosine)."""
from __future__ import annotations

from typing import Any

import pytest

from stagectl.commission.sequence import STICTION_LENGTH_X_FE, choose_gains, stiction_screen

M, T, FB, FE = 1.36, 1e-3, 2.04, 50e-6


def softest(fin: list[dict[str, Any]]) -> dict[str, Any]:
    """A ranking that prefers the lowest crossover (what the twin's near tie did on k106)."""
    return min(fin, key=lambda e: e["crossover_target_hz"])


@pytest.fixture(scope="module")
def gains() -> dict[str, Any]:
    return choose_gains(M, T, None, None, rank=softest, stiction=(FB, FE))


def test_sticky_stage_refuses_soft_finalists(gains: dict[str, Any]) -> None:
    g = gains
    lim = STICTION_LENGTH_X_FE * FE
    ch = g["chosen"]
    assert FB / ch["pid"]["kp_n_m"] <= lim
    rule = g["stiction_rule"]
    assert rule["excluded"], "the 10 Hz designs (stiction length ~20 limits) must be excluded"
    assert all(e["stiction_length_m"] > lim for e in rule["excluded"])
    assert min(e["crossover_target_hz"] for e in rule["excluded"]) < ch["crossover_target_hz"]
    # without the rule the ranking alone would have chosen a design that cannot hold the breakaway
    assert FB / softest(g["finalists"])["pid"]["kp_n_m"] > lim


def test_rule_keeps_all_when_none_can_hold(gains: dict[str, Any]) -> None:
    """A breakaway no finalist can hold: nothing is excluded and the record says so."""
    kept, rule = stiction_screen(gains["finalists"], 1e4, FE)
    assert rule["excluded"] == [] and "none excluded" in rule["reason"]
    assert len(kept) == len(gains["finalists"]) > 1
