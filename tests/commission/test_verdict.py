"""The commissioning's verdict on hand-built before/after figures (outputs.verdict)."""

from __future__ import annotations

from typing import Any

from stagectl.commission.outputs import VERDICT_RMS_TOL, verdict


def _run(rms_nm: float, settled: int, moves: int) -> dict[str, Any]:
    return {"rms_error_m": rms_nm * 1e-9, "max_error_m": 3 * rms_nm * 1e-9, "moves_settled": settled, "moves": moves}


def _ver(cos_after_nm: float, steps_after_settled: int = 4) -> dict[str, dict[str, Any]]:
    """The HIL commissioning's figures: cosine 17.2 nm before, triangle 0/1 -> 1/1, steps 3/4 -> 4/4."""
    return {"cosine": {"before": _run(17.2, 1, 1), "after": _run(cos_after_nm, 1, 1)},
            "triangle": {"before": _run(90.0, 0, 1), "after": _run(71.0, 1, 1)},
            "steps": {"before": _run(66.0, 3, 4), "after": _run(60.0, steps_after_settled, 4)}}


def test_a_difference_within_the_noise_does_not_keep_the_given_controller() -> None:
    v = verdict(_ver(17.4))   # +1.2 %: keep the given controller on main
    assert v["recommend"] == "new", v["text"]
    assert v["text"].startswith("use stage.yaml")
    assert f"{100 * VERDICT_RMS_TOL:.0f} %" in v["text"] and "no fewer moves settled" in v["text"]
    assert "moves settled 6/6 after vs 4/6 before" in v["text"]
    assert "cosine: RMS 17.4 nm after vs 17.2 nm before (+1.2 %)" in v["text"]


def test_a_difference_beyond_the_tolerance_or_fewer_settled_moves_keep_it() -> None:
    v = verdict(_ver(17.2 * (1 + VERDICT_RMS_TOL) * 1.01))
    assert v["recommend"] == "given" and v["worse"][0].startswith("cosine: RMS"), v
    assert "rule: " in v["text"]
    v = verdict(_ver(10.0, steps_after_settled=2))   # lower RMS everywhere, but steps settle 2/4 (was 3/4)
    assert v["recommend"] == "given"
    assert v["worse"] == ["steps: settled 2/4 after vs 3/4 before, though its RMS is within the 5 % tolerance: 60 vs 66 nm"]


def test_no_runs_no_verdict() -> None:
    assert verdict({})["recommend"] == "unverified"
