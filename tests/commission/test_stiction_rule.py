"""The gains choice on a sticky stage: a finalist whose excess stiction length (F_s - F_c)/K_p exceeds the
following-error limit is not chosen while a stiffer healthy finalist exists. k106 (1.36 kg, F_s 2.04 N,
F_c 1.70 N, 50 um limit, 1 kHz loop): on main the twin picked 10 Hz + Q-filter, which faulted the cosine."""
from __future__ import annotations

from typing import Any

import pytest

from stagectl.commission.sequence import choose_gains, stiction_excess, stiction_screen

M, T, FS, FC, FE = 1.36, 1e-3, 2.04, 1.70, 50e-6


def softest(fin: list[dict[str, Any]]) -> dict[str, Any]:
    """A ranking that prefers the lowest crossover (what the twin's near tie did on k106)."""
    return min(fin, key=lambda e: e["crossover_target_hz"])


@pytest.fixture(scope="module")
def gains() -> dict[str, Any]:
    ex = stiction_excess({"friction": {"fs_n": FS, "fc_n": FC}}, 1.76)
    assert ex == pytest.approx(FS - FC)
    return choose_gains(M, T, None, None, rank=softest, stiction=(1.76, ex, FE))


def test_sticky_stage_refuses_soft_finalists(gains: dict[str, Any]) -> None:
    g = gains
    ch = g["chosen"]
    assert (FS - FC) / ch["pid"]["kp_n_m"] <= FE
    rule = g["stiction_rule"]
    assert rule["excluded"], "the 10 Hz designs ((F_s - F_c)/K_p ~ 4 limits) must be excluded"
    assert all(e["excess_stiction_length_m"] > FE for e in rule["excluded"])
    assert min(e["crossover_target_hz"] for e in rule["excluded"]) < ch["crossover_target_hz"]
    # without the rule the ranking alone would have chosen a design that cannot hold the excess
    assert (FS - FC) / softest(g["finalists"])["pid"]["kp_n_m"] > FE


def test_small_excess_keeps_soft_finalists(gains: dict[str, Any]) -> None:
    """Little stiction over Coulomb (generated plant 34: 0.10 N): a soft design stays eligible, even with a
    large F_b/K_p; and a breakaway no finalist can hold excludes nothing and says so."""
    kept, rule = stiction_screen(gains["finalists"], 2.0, 0.01, FE)
    assert rule["excluded"] == [] and len(kept) == len(gains["finalists"])
    assert max(e["stiction_length_m"] for e in kept) > 5 * FE
    kept, rule = stiction_screen(gains["finalists"], 1e4, 1e4, FE)
    assert rule["excluded"] == [] and "none excluded" in rule["reason"] and rule["confidence"] == "low"
    assert stiction_excess({"friction": {"fc_n": 1.0}}, 0.8) == 0.0
