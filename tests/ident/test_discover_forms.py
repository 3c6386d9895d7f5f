"""Held-out generator for issue 13: asymmetry in its three physical forms and pre-sliding on long-stroke axes
with rare reversals, each hidden in a closed-loop recording of the simulated plant (docs/discovery.md §1, §7).

Stages are drawn by ``synth.draw_stage`` from consecutive seeds (not picked to pass); the hidden effect's size
is drawn over a plausible range from the same generator. The forms, in the plant's terms:

* viscous only: ``viscous_asymmetry`` d_v (Fv± = Fv ± d_v, Coulomb symmetric);
* Coulomb only: ``asymmetry`` ratio r on the whole friction, with ``viscous_asymmetry`` −r·Fv cancelling its
  viscous part (Fc± = (1 ± r)·Fc, Fv symmetric); sliding data cannot tell this from an offset (§1), so
  discovery must name ``offset`` and say so;
* mixed: ``asymmetry`` ratio r alone (Fc± and Fv± both scaled by 1 ± r).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from stagectl.ident import synth
from stagectl.ident.discover import DiscoveryResult, discover
from stagectl.ident.results import CandidateFit

MOTION = synth.Motion(duration_s=12.0)
#: a long-stroke axis: long cruises at up to 60 mm/s, a reversal every stroke only (no micro oscillation,
#: a small sweep): about 0.5 % of the samples lie within the pre-sliding distance of a reversal
LONG_STROKE = synth.Motion(duration_s=12.0, v_min_m_s=5e-3, v_max_m_s=60e-3, a_max_m_s2=1.0, cruise_s=1.2,
                           micro_amplitude_m=0.0, sweep_amplitude_m=20e-6)


def _stage(seed: int) -> tuple[dict[str, Any], np.random.Generator]:
    rng = np.random.default_rng(seed)
    return synth.draw_stage(rng), rng


def _run(st: dict[str, Any], seed: int, motion: synth.Motion = MOTION) -> DiscoveryResult:
    rec = synth.closed_loop(st, motion=motion, seed=seed)
    return discover(rec, max_rounds=3)


def test_viscous_only_asymmetry_is_named_with_both_coefficients() -> None:
    st, rng = _stage(1300)
    fv = st["friction"]["viscous_n_s_m"]
    dv = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.25, 0.5) * fv)
    st["effects"] = {"viscous_asymmetry": {"difference_n_s_m": dv}}
    res = _run(st, 1300)
    assert [e.name for e in res.effects][:1] == ["viscous_asymmetry"], res.rounds[0].candidates
    p = res.effects[0].parameters
    assert p.fv_plus_n_s_m == pytest.approx(fv + dv, rel=0.1)
    assert p.fv_minus_n_s_m == pytest.approx(fv - dv, rel=0.1)
    assert "offset" not in [e.name for e in res.effects]  # no Coulomb offset injected


def test_coulomb_only_asymmetry_is_named_as_the_offset_it_is_while_sliding() -> None:
    st, rng = _stage(1301)
    fc, fv = st["friction"]["fc_n"], st["friction"]["viscous_n_s_m"]
    r = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 0.4))
    st["effects"] = {"asymmetry": {"ratio": r}, "viscous_asymmetry": {"difference_n_s_m": -r * fv}}
    res = _run(st, 1301)
    names = [e.name for e in res.effects]
    assert names[:1] == ["offset"], res.rounds[0].candidates
    # Fc+ − Fc− = 2·r·Fc shows up as F_0 = r·Fc (sign: the force the stage feels moving either way)
    assert res.effects[0].parameters.force_n == pytest.approx(r * fc, rel=0.15)
    assert "Coulomb asymmetry" in res.effects[0].evidence and "break-away" in res.effects[0].evidence
    assert "viscous_asymmetry" not in names


def test_mixed_asymmetry_is_named_in_its_proportional_form() -> None:
    st, rng = _stage(1302)
    r = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 0.4))
    st["effects"] = {"asymmetry": {"ratio": r}}
    res = _run(st, 1302)
    names = [e.name for e in res.effects]
    assert names[:1] == ["asymmetry"], res.rounds[0].candidates
    assert res.effects[0].parameters.ratio == pytest.approx(r, abs=0.05)
    assert res.gap_after <= 0.5 * res.gap_before


def test_independent_coulomb_and_viscous_asymmetry_are_named_as_offset_and_viscous_asymmetry() -> None:
    """Coulomb and viscous levels asymmetric with different ratios: the pair offset + viscous_asymmetry is
    tried as one candidate and wins on parsimony over asymmetry+offset, the same force while sliding."""
    st, rng = _stage(1306)
    fc, fv = st["friction"]["fc_n"], st["friction"]["viscous_n_s_m"]
    rc = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 0.35))
    rv = -float(np.sign(rc)) * float(rng.uniform(0.2, 0.35))  # the viscous part the other way
    # asymmetry r scales both parts; the viscous_asymmetry term sets the viscous difference to rv·Fv
    st["effects"] = {"asymmetry": {"ratio": rc}, "viscous_asymmetry": {"difference_n_s_m": (rv - rc) * fv}}
    res = _run(st, 1306)
    got = {e.name: e.parameters for e in res.effects}
    assert set(got) == {"offset", "viscous_asymmetry"}, res.rounds[0].candidates
    assert got["offset"].force_n == pytest.approx(rc * fc, rel=0.2)
    assert got["viscous_asymmetry"].difference_n_s_m == pytest.approx(rv * fv, rel=0.2)


def test_presliding_on_a_long_stroke_axis_is_named_from_its_regime() -> None:
    """Reversals are rare, so pre-sliding cannot cut the global residual by 20 %: it is judged near reversals,
    and the global gap must not get worse (docs/discovery.md §7)."""
    st, rng = _stage(1303)
    st = synth.hide(st, "presliding", rng)
    res = _run(st, 1303, LONG_STROKE)
    acc = {e.name: e for e in res.effects}
    assert "presliding" in acc, [c for r in res.rounds for c in r.candidates if c.name == "presliding"]
    row = next(c for r in res.rounds for c in r.candidates if c.name == "presliding" and isinstance(c, CandidateFit))
    assert row.regime == "near_reversal" and row.regime_rel_gain is not None and row.regime_rel_gain >= 0.2
    assert row.gap_after <= row.gap_before
    assert set(acc) <= {"presliding", "stribeck"}, list(acc)  # nothing else invented


def test_long_stroke_null_recording_names_nothing_in_any_regime() -> None:
    """The regime-aware rule stays below its margin on a recording with nothing hidden."""
    st, _ = _stage(1304)
    res = _run(st, 1304, LONG_STROKE)
    assert res.effects == []
    gains = [c.regime_rel_gain for c in res.rounds[0].candidates
             if isinstance(c, CandidateFit) and c.regime_rel_gain is not None]
    assert gains and max(gains) < 0.2, gains


def test_hidden_backlash_on_a_ball_screw_axis_is_told_apart_from_presliding(tmp_path: Path) -> None:
    """A ball-screw-scale axis (load 4 kg, motor side 0.8 kg, stiff nut contact 1e7 N/m, encoder on the motor)
    with a hidden play of 15-30 µm: discovery names backlash, not pre-sliding, with the play and the load mass
    it loses at each reversal (docs/discovery.md §10)."""
    st, rng = _stage(1305)
    st["mass_kg"] = 4.0
    gap = float(rng.uniform(15e-6, 30e-6))
    bl = {"gap_m": gap, "other_mass_kg": 0.8, "contact_stiffness_n_m": 1e7, "coupling_step_s": 2e-5}
    rec = synth.closed_loop(st, motion=MOTION, seed=1305, backlash=bl)
    res = discover(rec, max_rounds=2)
    names = [e.name for e in res.effects]
    assert names[:1] == ["backlash"], res.rounds[0].candidates
    p = res.effects[0].parameters
    assert p.gap_m == pytest.approx(gap, rel=0.15)
    assert p.mass_lost_kg == pytest.approx(4.0, rel=0.3)  # the load's mass is not carried inside the play
    assert "lost motion" in res.effects[0].evidence
    # round trip: discover -> model.yaml (backlash: section) -> plant and feed-forward -> discover's start model
    from stagectl.sim.backlash import BacklashPlant, plant_from_model

    from stagectl.control.friction_ff import FrictionFeedforward
    from stagectl.friction import load_model_file, save_model_file
    from stagectl.ident import effects as fx
    from stagectl.ident.modelio import hyp_to_model, model_to_hyp
    save_model_file(hyp_to_model(res.final.hyp), tmp_path / "model.yaml")
    model = load_model_file(tmp_path / "model.yaml")
    assert model.backlash is not None and model.mass_kg is not None
    assert model.backlash.gap_m == pytest.approx(gap, rel=0.15)
    assert model.backlash.friction_side == "load" and model.backlash.sensor_side == "motor"
    assert model.backlash.other_mass_kg == pytest.approx(0.8, abs=0.6)  # the motor side: total − load
    assert model.mass_kg == pytest.approx(4.8, rel=0.05)
    plant = plant_from_model(model, sensor={"resolution_m": 1e-9})
    assert isinstance(plant, BacklashPlant) and plant.bl.gap_m == model.backlash.gap_m
    assert plant.cfg.mass_kg == pytest.approx(model.mass_kg - model.backlash.other_mass_kg)
    for _ in range(200):  # push, then reverse: the motor crosses the play before the load follows
        plant.step(5.0, 1e-3)
    x_load = plant.x_load_m
    while plant.contact_force_n >= 0.0 and abs(plant.x_load_m - x_load) < 1e-3:
        plant.step(-5.0, 1e-4)
    assert plant.x_motor_m - plant.x_load_m == pytest.approx(-0.5 * model.backlash.gap_m, abs=0.2 * gap)
    FrictionFeedforward(model.friction, model.effects)  # the feed-forward reads the same file
    h = model_to_hyp(model)
    assert h.has("backlash") and fx.BACKLASH.shape(h).gap_m == model.backlash.gap_m


def test_a_fit_beyond_a_physical_bound_is_reported_not_clipped() -> None:
    """A ripple amplitude >= 1 (friction would reverse sign) is named as a bound violation and the model file
    refuses it instead of silently clipping it to 0.99."""
    from stagectl.errors import ConfigError
    from stagectl.friction.effects import PositionRipple
    from stagectl.ident import effects as fx
    from stagectl.ident.hypothesis import Hyp
    from stagectl.ident.modelio import hyp_to_model

    p = PositionRipple(amplitude=1.3, wavelength_m=1e-3, phase_rad=0.0)
    assert fx.RIPPLE.bounds is not None and "reverse sign" in fx.RIPPLE.bounds(p)[0]
    h = fx.RIPPLE.reshaped(Hyp(effects=("position_ripple",), theta={"m": 1.0, "fc": 1.0, "fv": 1.0, "rs": 1.3}),
                           wavelength_m=1e-3)
    with pytest.raises((ConfigError, ValueError)):
        hyp_to_model(h)


def test_one_directional_motion_reports_the_cogging_ripple_tie_with_the_separating_experiment() -> None:
    """Moving in one direction at nearly constant speed, a ripple of the friction force (a·F·sin) and a
    cogging force (A·sin) at the same wavelength are the same force: the report must say the data cannot
    separate them and name the experiment that would (move over the same positions in both directions)."""
    rng = np.random.default_rng(1310)
    st = synth.draw_stage(rng)
    fc = st["friction"]["fc_n"]
    st["sensor"] = {"resolution_m": 1e-9, "noise_std_m": 60e-9}
    st["effects"] = {"cogging": {"amplitude_n": 0.4 * fc, "wavelength_m": 1e-3, "phase_rad": 0.7}}
    dt, n = 1e-3, 8000
    t = np.arange(n) * dt
    v = 8e-3 * 0.5 * (1.0 - np.cos(np.pi * np.minimum(t / 0.5, 1.0)))  # ramp to 8 mm/s, then one direction
    rec = synth.closed_loop(st, x_ref=np.cumsum(v) * dt, seed=1310)
    assert np.all(np.diff(rec.x[200:]) > -1e-7)  # one-directional indeed (up to noise)
    res = discover(rec, max_rounds=2)
    names = [e.name for e in res.effects]
    assert names[:1] in (["cogging"], ["position_ripple"]), res.rounds[0].candidates
    other = "position_ripple" if names[0] == "cogging" else "cogging"
    row = next(c for c in res.rounds[0].candidates if c.name == names[0] and isinstance(c, CandidateFit))
    assert row.note is not None and f"tie with {other}" in row.note, row.note
    assert "cannot separate" in row.note and "both directions" in row.note
    # the note reaches the written report
    from stagectl.ident.report import _markdown, build_report
    assert f"tie with {other}" in _markdown(build_report(res, {"estimation": "synth"}), [])


def test_friction_rising_with_speed_is_named_with_fs_below_fc(tmp_path: Path) -> None:
    """Rolling contacts (ball screws, rolling guides) show no Stribeck dip: the friction rises from a lower
    break-away level to the Coulomb level over tens of mm/s (the EMPS axis does, docs/discovery.md §11). The
    Stribeck candidate takes that form (Fs < Fc), and the model file holds it."""
    from stagectl.friction import load_model_file
    from stagectl.ident.report import write_outputs

    st, rng = _stage(1306)
    fc = float(st["friction"]["fc_n"])
    fs = fc * float(rng.uniform(0.4, 0.7))
    st["friction"].update(fs_n=fs, vs_m_s=float(rng.uniform(4e-3, 10e-3)), delta=float(rng.uniform(1.0, 2.0)))
    res = _run(st, 1306, LONG_STROKE)
    acc = {e.name: e for e in res.effects}
    assert list(acc)[:1] == ["stribeck"], res.rounds[0].candidates
    p = acc["stribeck"].parameters
    assert p.fs_n < p.fc_n and p.fs_n == pytest.approx(fs, rel=0.25) and p.fc_n == pytest.approx(fc, rel=0.1)
    assert "rises with speed" in acc["stribeck"].evidence
    write_outputs(res, tmp_path, {"estimation": "synth"}, plots=False)
    model = load_model_file(tmp_path / "model.yaml")
    assert model.friction.params.fs_n < model.friction.params.fc_n  # type: ignore[attr-defined]
    assert "rising with speed" in (tmp_path / "model.yaml").read_text().splitlines()[0]
