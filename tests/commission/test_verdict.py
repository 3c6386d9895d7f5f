"""The commissioning's verdict on hand-built before/after figures (outputs.verdict)."""

from __future__ import annotations

from typing import Any

from stagectl.commission.outputs import VERDICT_RMS_TOL, margin_standing, verdict


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


# the outside stage's figures (PM 13.5 deg / GM 1.9 dB given, on the measured FRF): the commissioned controller
# lost on triangle RMS (+17 %) and steps settled (2/4 vs 4/4), and won cosine 16 nm vs 1.37 um, steps 103 vs 974 nm
_OUTSIDE = {"cosine": {"before": _run(1370.0, 1, 1), "after": _run(16.0, 1, 1)},
            "triangle": {"before": _run(2970.0, 1, 1), "after": _run(2970.0 * 1.17, 1, 1)},
            "steps": {"before": _run(974.0, 4, 4), "after": _run(103.0, 2, 4)}}


def _gains(given_pm: float, given_gm: float, healthy: bool = True, pm: float = 53.2, gm: float = 8.2) -> dict[str, Any]:
    mm = {"phase_margin_deg": pm, "gain_margin_db": gm}
    return {"given": {"measured": {"phase_margin_deg": given_pm, "gain_margin_db": given_gm,
                                   "healthy": given_pm >= 40.0 and given_gm >= 8.0}},
            "chosen": {"healthy": healthy, "model": dict(mm, phase_margin_deg=pm - 10.0, gain_margin_db=gm + 1.0),
                       "measured": mm}}


def test_a_given_controller_below_the_margin_floor_is_not_kept_over_a_healthy_one() -> None:
    assert verdict(_OUTSIDE)["recommend"] == "given"     # on tracking figures alone (main's rule)
    ms = margin_standing(_gains(13.5, 1.87))
    assert ms is not None and ms["floor_pm_deg"] == 40.0 and ms["commissioned"]["phase_margin_deg"] == 43.2
    v = verdict(_OUTSIDE, ms)
    assert v["recommend"] == "new", v["text"]
    assert v["text"].startswith("use stage.yaml: the given controller has PM 14 deg / GM 1.9 dB on the measured FRF, "
                                "below the PM 40 deg / GM 8 dB floor the commissioned one meets (PM 43 deg / GM 8.2 dB)")
    assert "triangle: RMS" in v["text"] and "steps: settled 2/4 after vs 4/4 before" in v["text"]
    # a given controller that meets the floor, or a commissioned one that misses it: tracking decides, as before
    assert margin_standing(_gains(45.0, 9.0)) is None
    assert margin_standing(_gains(13.5, 1.87, pm=38.0)) is None
    # the fallback tier: its lower floor (25 deg / 3 dB) both ways
    fb = margin_standing(_gains(13.5, 1.87, healthy=False, pm=36.0, gm=4.0))
    assert fb is not None and fb["tier"] == "fallback" and verdict(_OUTSIDE, fb)["recommend"] == "new"
    assert "(the fallback tier's)" in verdict(_OUTSIDE, fb)["text"]
    assert margin_standing(_gains(30.0, 4.0, healthy=False, pm=36.0, gm=4.0)) is None


def test_a_commissioned_controller_worse_by_a_wide_margin_everywhere_is_not_recommended_for_its_margins() -> None:
    ms = margin_standing(_gains(13.5, 1.87))
    wide = {k: {"before": d["before"], "after": _run(2.5e9 * d["before"]["rms_error_m"], 0, d["before"]["moves"])}
            for k, d in _OUTSIDE.items()}
    v = verdict(wide, ms)
    assert v["recommend"] == "given", v["text"]
    assert v["text"].startswith("keep the given controller, though the given controller has PM 14 deg")
    assert "worse by a wide margin on every figure" in v["text"]
    # one scenario within the wide ratio is enough for the margins to decide
    wide["cosine"]["after"] = _run(1.5 * 1370.0, 1, 1)
    assert verdict(wide, ms)["recommend"] == "new"
