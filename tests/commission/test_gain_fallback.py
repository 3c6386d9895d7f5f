"""The gains' fallback tier (stagectl.commission.sequence): on a stiction-heavy stage (hidden plant k112: 0.89 kg,
F_s - F_c 0.43 N, 50 um following-error limit, so K_p >= 8.5 kN/m) every design that meets the floor (PM 40 deg,
GM 8 dB on the model and the measured FRF) was sticky (19 Hz + Q 38 Hz: the twin's cosine 18 um) or faulted on
the twin (35 Hz PID); the tier takes the best design on the twin among the stiffer ones that keep reduced margins,
with confidence low and the margins it gives up named. Synthetic candidates with k112's margins (report.json of
the commissioning on main)."""
from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from stagectl.commission.sequence import (
    FALLBACK_MIN_GAIN_MARGIN_DB,
    FALLBACK_MIN_PHASE_MARGIN_DEG,
    MIN_GAIN_MARGIN_DB,
    MIN_PHASE_MARGIN_DEG,
    _design_name,
    choose_gains,
    controller_mapping,
    fallback_candidates,
    fallback_needed,
    pick_fallback,
    pick_finalist,
    stiction_screen,
)

sys.path.insert(0, str(Path(__file__).parent))
from plant_gen import exact_model
from plant_kinds import fresh_plant, fresh_stage_yaml

ch_name = _design_name

T, FE, DF = 1e-3, 50e-6, 0.427
KP_MIN = DF / FE  # 8.54 kN/m
INF = math.inf


def design(fc: float, dob: str, dbw: float, kp: float, pm: float, gm: float, mpm: float, mgm: float,
           healthy: bool = False) -> dict[str, Any]:
    """A design as choose_gains records it: model margins (crossover 1.6 f_c, phase crossover 145 Hz) and
    measured-FRF margins (phase crossover 216 Hz, the pre-sliding mode)."""
    return {"crossover_target_hz": fc, "dob_kind": dob, "dob_bandwidth_hz": dbw,
            "pid": {"kp_n_m": kp, "ki_n_m_s": 0.0, "kd_n_s_m": 0.0, "derivative_cutoff_hz": 200.0},
            "model": {"phase_margin_deg": pm, "gain_margin_db": gm, "crossover_hz": 1.6 * fc,
                      "phase_crossover_hz": 145.0, "closed_loop_stable": True},
            "measured": {"phase_margin_deg": mpm, "gain_margin_db": mgm, "crossover_hz": math.nan,
                         "phase_crossover_hz": 216.0},
            "healthy": healthy}


def k112_tried() -> list[dict[str, Any]]:
    return [design(40, "qfilter", 200, 17491, 27.3, 6.33, 140.3, 2.54),   # measured GM below 3 dB
            design(40, "qfilter", 130, 17491, 26.3, 6.44, 107.7, 3.43),
            design(40, "none", 100, 17491, 37.4, 8.76, INF, 10.6),
            design(35, "qfilter", 175, 13408, 30.5, 6.79, 113.3, 3.04),
            design(35, "qfilter", 130, 13408, 29.7, 6.98, 113.5, 3.77),    # a lower crossover of 0.13/T
            design(35, "qfilter", 70, 13408, 28.5, 7.47, 18.8, 3.46),      # measured PM below 25 deg
            design(35, "none", 100, 13408, 40.4, 9.86, INF, 12.4, healthy=True),
            design(26, "qfilter", 52, 7414, 34.6, 9.26, INF, 5.78),        # K_p below dF/e_max
            design(19, "qfilter", 38, 3964, 40.4, 11.5, INF, 8.42, healthy=True),
            design(8, "qfilter", 40, 704, 57.2, 13.5, INF, 9.28, healthy=True)]


def twin(rms: float) -> dict[str, dict[str, Any]]:
    return {nm: {"rms_error_m": rms, "moves_settled": 0, "moves": 4} for nm in ("cosine", "triangle", "steps")}


def key(rms: float) -> tuple[float, float]:
    return math.log(rms), 0.0


def test_candidates_are_stiff_enough_and_keep_the_reduced_margins() -> None:
    tried = k112_tried()
    cands = fallback_candidates(tried, KP_MIN, T)
    names = [(e["crossover_target_hz"], e["dob_kind"], e["dob_bandwidth_hz"]) for e in cands]
    # per observer option the highest crossover; 40 Hz + Q 200 (GM 2.5 dB), 35 + Q 70 (measured PM 19 deg),
    # 26 Hz (K_p 7.4 kN/m) and the designs that meet the floor are not candidates
    assert names == [(40, "none", 100), (40, "qfilter", 130), (35, "qfilter", 175)]  # then the most measured GM
    for e in cands:
        assert e["pid"]["kp_n_m"] >= KP_MIN and not e["healthy"]
        for d in (e["model"], e["measured"]):
            assert d["phase_margin_deg"] >= FALLBACK_MIN_PHASE_MARGIN_DEG
            assert d["gain_margin_db"] >= FALLBACK_MIN_GAIN_MARGIN_DB


def finalists_k112() -> tuple[list[dict[str, Any]], list[tuple[float, float]]]:
    tried = k112_tried()
    fin = [e for e in tried if e["healthy"]]
    stiction_screen(fin, 1.53, DF, FE)
    fin[0]["twin"] = twin(INF)  # 35 Hz PID: faulted on the twin
    fin[1]["twin"] = twin(10.9e-6)  # 19 Hz + Q 38 Hz: sticky, 10.9 um
    fin[2]["twin"] = twin(INF)  # 8 Hz: sticky and faulted
    return fin, [key(float(f["twin"]["cosine"]["rms_error_m"])) if math.isfinite(f["twin"]["cosine"]["rms_error_m"])
                 else (INF, 0.0) for f in fin]


def test_sticky_and_faulting_finalists_go_to_the_fallback() -> None:
    fin, keys = finalists_k112()
    assert [f["sticky"] for f in fin] == [False, True, True]
    i, dec = pick_finalist(fin, keys)
    # the sticky 19 Hz design is the floor's pick; the only design within the limit faulted: said so, no ratio
    assert fin[i]["crossover_target_hz"] == 19 and "faulted" in dec["decision"] and "%" not in dec["decision"]
    assert "35 Hz PID (cosine, triangle, steps) faulted" in dec["decision"]
    assert fallback_needed(fin, keys)
    cands = fallback_candidates(k112_tried(), KP_MIN, T)
    ck = [(INF, 0.0), key(1.35e-6), key(1.50e-6)]  # 40 Hz PID (faults), 40 Hz + Q 130, 35 Hz + Q 175
    j, rec = pick_fallback(fin, keys, i, cands, ck, key(2.34e-6), KP_MIN)
    assert j == 1 and rec["confidence"] == "low" and rec["chosen"] == "40 Hz PID + Q-filter 130 Hz"
    # the margins it gives up, with numbers: PM on the model, GM on the model and on the measured FRF
    assert f"PM 26.3 deg < {MIN_PHASE_MARGIN_DEG:g} deg on the model" in rec["gives_up"]
    assert f"GM 3.4 dB < {MIN_GAIN_MARGIN_DB:g} dB on the measured FRF" in rec["gives_up"]
    assert "1.1 ms more delay at its 64 Hz crossover" in rec["gives_up"]  # 26.3 / (360 * 64 Hz)
    assert "48 %" in rec["gives_up"] and "216 Hz" in rec["gives_up"]  # 10^(3.43/20) - 1
    assert "PM" not in rec["gives_up"].split("on the measured FRF")[0].split(";")[-1]  # measured PM kept
    assert "8.54 kN/m" in rec["why"] and "35 Hz PID" in rec["why"] and "19 Hz" in rec["why"]


def test_the_fallback_never_loses_to_the_given_controller_or_the_floor() -> None:
    fin, keys = finalists_k112()
    i, _ = pick_finalist(fin, keys)
    cands = fallback_candidates(k112_tried(), KP_MIN, T)
    # the given controller better on the twin than every candidate: the floor's pick stays, keep the given one
    j, rec = pick_fallback(fin, keys, i, cands, [(INF, 0.0), key(3e-6), key(4e-6)], key(2.34e-6), KP_MIN)
    assert j is None and "keep the given one" in rec["decision"] and rec["keep_given"] and rec["confidence"] == "low"
    # worse than the floor's pick (the given one could not run)
    j, rec = pick_fallback(fin, keys, i, cands, [(INF, 0.0), key(20e-6), key(30e-6)], None, KP_MIN)
    assert j is None and "not better" in rec["decision"] and not rec["keep_given"]
    # worse than the floor's pick, and the given controller better than both: the advice says so too
    j, rec = pick_fallback(fin, keys, i, cands, [(INF, 0.0), key(20e-6), key(30e-6)], key(2.34e-6), KP_MIN)
    assert j is None and "not better" in rec["decision"] and rec["keep_given"] and "keep the given" in rec["decision"]
    # ... but not when the floor's pick beats the given controller
    j, rec = pick_fallback(fin, keys, i, cands, [(INF, 0.0), key(20e-6), key(30e-6)], key(15e-6), KP_MIN)
    assert j is None and not rec["keep_given"] and "keep" not in rec["decision"]
    # every candidate faults, or there is none: the figures and the advice are still given
    for ck, cs in (([(INF, 0.0)] * 3, cands), ([], [])):
        j, rec = pick_fallback(fin, keys, i, cs, ck, key(2.34e-6), KP_MIN)
        assert j is None and "without a fault" in rec["decision"] and f"({len(cs)} kept" in rec["decision"]
        assert "the given controller 2.34 um" in rec["decision"] and rec["keep_given"]


def test_every_finalist_faulting_is_not_a_confident_choice() -> None:
    """All finalists faulted on the twin: on main the non-sticky one with the most settled moves came out as "best
    on the twin" with confidence high, and a sticky one as "chosen although sticky: 35 Hz PID faulted" (as if it
    had not faulted itself)."""
    fin, _ = finalists_k112()
    for settled_first in (2.0, 0.0):  # the 35 Hz PID (not sticky) or the 19 Hz design (sticky) settles most
        keys = [(INF, -settled_first), (INF, -1.0), (INF, 0.0)]
        i, dec = pick_finalist(fin, keys)
        assert i == (0 if settled_first else 1) and dec["confidence"] == "low"
        assert "kept (the most moves settled)" in dec["decision"] and "each faulted on the twin" in dec["decision"]
        assert all(ch_name(e) in dec["decision"] for e in fin) and fallback_needed(fin, keys)


def test_a_healthy_design_within_the_limit_keeps_the_normal_choice() -> None:
    """A finalist that meets the floor, is not sticky and runs the twin: no fallback (k100, 3, 61)."""
    fin, keys = finalists_k112()
    keys[0] = key(3e-6)  # 35 Hz PID now runs the twin
    fin[0]["twin"] = twin(3e-6)
    assert not fallback_needed(fin, keys)
    # nothing sticky (small stiction excess): only faults call the fallback
    g = choose_gains(0.89, T, None, None, stiction=(1.2, 0.04, FE))
    f2 = g["finalists"]
    assert not any(e["sticky"] for e in f2)
    assert fallback_candidates(g["tried"], 0.04 / FE, T)  # there would be candidates: the tier is what decides
    assert not fallback_needed(f2, [key(1e-6)] * len(f2))
    assert fallback_needed(f2, [(INF, 0.0)] * len(f2))


def test_k112_twin_chooses_a_stiff_design_that_tracks_the_hidden_plant(tmp_path: Path) -> None:
    """Through the sequence's own twin ranking (``Commissioning._rank_on_twin``, lock-step), on fresh plant k112
    with its exact model as the identified one and margins on the model only (no FRF): every finalist is sticky
    or faults on the twin; the fallback's design keeps K_p >= (F_s - F_c)/e_max, beats the given controller and
    the floor's pick on the twin, and on the hidden plant itself tracks better than the floor's pick."""
    import yaml

    from stagectl.commission.analysis import PlantFit
    from stagectl.commission.sequence import Commissioning, Options, simulate_verification, stiction_excess
    from stagectl.config import load_app_config

    plant, kind = fresh_plant(112)
    cfg = load_app_config(fresh_stage_yaml(tmp_path / "k112.yaml", plant, kind))
    lines: list[str] = []
    comm = Commissioning(cfg, tmp_path / "out", Options(max_stroke_m=0.002, verify=False, plots=False,
                                                        progress=lines.append), write_config=lambda res: cfg)
    m, T = float(plant["mass_kg"]), cfg.loop.period_s
    comm.res.model_spec = exact_model(plant)
    comm.res.plant = PlantFit(m, 0.0, 0.0, 0.0, 0.0, T, 0.0, 0.0, [], 0.0)
    fb = float(plant["friction"]["fs_n"])
    stiction = (fb, stiction_excess(comm.res.model_spec, fb), cfg.safety.following_error_m)
    g = choose_gains(m, T, comm.res.plant, None, stiction=stiction,
                     rank=lambda fin, spare, kp: comm._rank_on_twin(fin, m, spare, kp))
    rec, ch = g["fallback"], g["chosen"]
    kp_min = stiction[1] / stiction[2]
    assert rec["chosen"] == ch_name(ch) and rec["confidence"] == "low" and g["stiction_rule"]["confidence"] == "low"
    assert "fallback tier chose" in g["stiction_rule"]["decision"] and "candidates" not in g["stiction_rule"]
    assert "below the margin floor, confidence low" in lines[-1]  # the progress line says so too
    # report.md: the gains' headline says the design is below the floor; the tier's line, on what it checked
    from stagectl.commission.outputs import report_dict, report_markdown

    comm.res.gains = g
    md = report_markdown(report_dict(comm.res), [])
    assert f"Below the PM {MIN_PHASE_MARGIN_DEG:g} deg / GM {MIN_GAIN_MARGIN_DB:g} dB floor" in md
    assert (f"GM >= {FALLBACK_MIN_GAIN_MARGIN_DB:g} dB on the model (no measured FRF): " in md
            and "Fallback tier (confidence low): every design that meets the floor is sticky" in md)
    gains_md = md[md.index("## Gains"):md.index("## Verdict")]
    assert gains_md.count(rec["gives_up"]) == 1 and f"Decision: {rec['decision']}." in gains_md  # once there
    assert ch["pid"]["kp_n_m"] >= kp_min and not ch["healthy"] and "PM" in rec["gives_up"]
    assert isinstance(rec["given_twin"], dict) and rec["given_twin_note"].startswith("ran")  # the reference
    fin = g["finalists"]
    keys = [(float(np.mean([math.log(max(float(sc["rms_error_m"]), 1e-15)) for sc in e["twin"].values()])),
             -float(sum(int(sc["moves_settled"]) for sc in e["twin"].values()))) for e in fin]
    assert fallback_needed(fin, keys)
    soft = fin[pick_finalist(fin, keys)[0]]  # the floor's pick (sticky)
    assert soft["sticky"] and soft["pid"]["kp_n_m"] < kp_min

    def on_plant(entry: dict[str, Any]) -> dict[str, Any]:
        """``entry`` on the hidden plant with its exact model as the feed-forward (plant_gen.against_exact)."""
        (tmp_path / "exact.yaml").write_text(yaml.safe_dump(exact_model(plant)))
        ctl = controller_mapping(entry, m, 1, T, T, None, cfg.controller.max_force_n, str(tmp_path / "exact.yaml"))
        d = {"loop": {"period_s": T}, "io": {"kind": "plant_io", "sensor": "drive", "delay_cycles": 1},
             "sim": {"plant": plant}, "controller": ctl,
             "safety": yaml.safe_load((tmp_path / "k112.yaml").read_text())["safety"]}
        (tmp_path / "check.yaml").write_text(yaml.safe_dump(d))
        return simulate_verification(load_app_config(tmp_path / "check.yaml"), 0.002, 10e-9)

    new, old = on_plant(ch), on_plant(soft)
    assert new["cosine"]["rms_error_m"] < 0.5 * old["cosine"]["rms_error_m"]
    assert math.isfinite(new["steps"]["rms_error_m"])


def test_the_verdict_note_does_not_claim_the_floor_for_a_fallback_design() -> None:
    """k112 with verification: the given controller (PM 11 deg / GM 4.0 dB measured) was kept on settled steps;
    on main the note said the commissioned one keeps 40 deg / 8 dB, which a fallback design does not. Below the
    fallback tier's floor the commissioned design meets, the given controller is no longer kept (fe27)."""
    from stagectl.commission.envelope import make_envelope
    from stagectl.commission.outputs import report_dict
    from stagectl.commission.sequence import Results
    from stagectl.config import load_app_config

    cfg = load_app_config(Path(__file__).resolve().parents[2] / "config" / "sim.yaml")
    s = cfg.safety
    env = make_envelope(min_position_m=s.min_position_m, max_position_m=s.max_position_m,
                        safety_force_n=s.max_force_n, controller_force_n=cfg.controller.max_force_n,
                        max_velocity_m_s=s.max_velocity_m_s, period_s=cfg.loop.period_s,
                        following_error_m=s.following_error_m, max_stroke_m=None, max_force_n=None,
                        max_speed_m_s=None)
    chosen = design(40, "qfilter", 130, 17491, 26.3, 6.44, 107.7, 3.43)
    given = {"measured": {"phase_margin_deg": 11.2, "gain_margin_db": 3.97, "healthy": False}}
    run = lambda rms, n: {"rms_error_m": rms, "max_error_m": 3 * rms, "moves_settled": n, "moves": 4}
    ver = {"steps": {"before": run(3.59e-6, 2), "after": run(1.92e-6, 0)}}
    res = Results(cfg, env, gains={"chosen": chosen, "given": given, "mass_kg": 0.89, "delay_samples": 1},
                  verification=ver)
    # k112's given controller misses even the fallback tier's floor the commissioned one meets: the margins
    # decide (outputs.margin_standing), the fallback floor named
    v = report_dict(res)["verdict"]
    assert v["recommend"] == "new" and ("below the PM 25 deg / GM 3 dB floor (the fallback tier's) the commissioned "
                                        "one meets (PM 26 deg / GM 3.4 dB)") in v["text"], v["text"]
    # a given controller above the fallback floor but below 40 deg / 8 dB is kept on settled steps; the note
    # does not claim the floor for the fallback design
    given["measured"] = {"phase_margin_deg": 30.0, "gain_margin_db": 3.97, "healthy": False}
    text = report_dict(res)["verdict"]["text"]
    assert "keeps" not in text and "the commissioned one (fallback tier) PM 26 deg / GM 3.4 dB" in text
    given["measured"] = {"phase_margin_deg": 11.2, "gain_margin_db": 3.97, "healthy": False}
    chosen["healthy"] = True  # a design that meets the floor: the note as before
    assert "below the 40 deg / 8 dB the commissioned one keeps" in report_dict(res)["verdict"]["text"]


def test_the_twin_slots_go_to_distinct_designs() -> None:
    """Two observer options by name can be one design: 35 Hz + Q 160 Hz next to 35 Hz + Q 175 Hz (crossover equal,
    observers 9 % apart) took two of the four twin slots on k112 (on main: 40 PID, 40 + Q 130, 35 + Q 160,
    35 + Q 175). Only the first of near twins (same observer kind, crossover and observer bandwidth each within
    15 %) takes a slot; the next distinct design (30 Hz + Q 100 Hz) gets the freed one. Designs that differ in the
    observer kind (40 Hz PID, 40 Hz + Q 130) or by more than 15 % in the observer (40 + Q 130, 35 + Q 160: same
    crossover band) stay apart."""
    tried = k112_tried() + [design(35, "qfilter", 160, 13408, 30.1, 6.9, 110.0, 3.2),
                            design(30, "qfilter", 100, 9851, 32.0, 7.8, 90.0, 4.1)]
    cands = fallback_candidates(tried, KP_MIN, T)
    names = [(e["crossover_target_hz"], e["dob_kind"], e["dob_bandwidth_hz"]) for e in cands]
    assert names == [(40, "none", 100), (40, "qfilter", 130), (35, "qfilter", 160), (30, "qfilter", 100)]
    # a near twin at a neighbouring crossover is one too (32 Hz + Q 170 after 35 Hz + Q 160) ...
    near = fallback_candidates(tried[:-1] + [design(32, "qfilter", 170, 11200, 31.0, 7.1, 100.0, 3.6)], KP_MIN, T)
    assert [(e["crossover_target_hz"], e["dob_bandwidth_hz"]) for e in near] == [(40, 100), (40, 130), (35, 160)]
    # ... and a fifth distinct design still finds no slot beyond the four
    many = fallback_candidates(tried + [design(26, "qfilter", 80, 8600, 33.0, 8.0, 95.0, 4.5)], KP_MIN, T)
    assert len(many) == 4 and (26, "qfilter", 80) not in [
        (e["crossover_target_hz"], e["dob_kind"], e["dob_bandwidth_hz"]) for e in many]


def test_a_near_tie_between_fallback_candidates_is_named_not_ranked() -> None:
    """Two candidates within the twin's scatter (FALLBACK_NEAR_TIE, 11 %: 1.35 and 1.50 um): the record names the
    tie and the decision says the twin does not rank them; 1.35 against 2.0 um is no tie."""
    from stagectl.commission.sequence import FALLBACK_NEAR_TIE

    fin, keys = finalists_k112()
    i, _ = pick_finalist(fin, keys)
    cands = fallback_candidates(k112_tried(), KP_MIN, T)
    assert 1.50 / 1.35 - 1 < FALLBACK_NEAR_TIE < 2.0 / 1.35 - 1
    j, rec = pick_fallback(fin, keys, i, cands, [(INF, 0.0), key(1.35e-6), key(1.50e-6)], key(2.34e-6), KP_MIN)
    assert j == 1 and rec["near_tie"] == [ch_name(cands[2])]
    assert f"a near tie with {ch_name(cands[2])} 1.5 um" in rec["decision"] and "not ranked by it" in rec["decision"]
    j, rec = pick_fallback(fin, keys, i, cands, [(INF, 0.0), key(1.35e-6), key(2.0e-6)], key(2.34e-6), KP_MIN)
    assert j == 1 and rec["near_tie"] == [] and "near tie" not in rec["decision"]
