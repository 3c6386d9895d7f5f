"""Adding a discovery effect touches one file: an ``EffectSpec`` registered in a test-local copy of the
registry is picked up by the synthetic stages, the regression, the workflow, the report and the model-file
conversion with no other edit (the toy effect is a constant force under a new name and column, written to model files as
``effects.offset``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from stagectl.friction import load_model_file
from stagectl.friction.effects import Offset
from stagectl.ident import effects as fx
from stagectl.ident import regress as rg
from stagectl.ident import synth
from stagectl.ident.discover import discover
from stagectl.ident.hypothesis import (
    Column,
    EffectSpec,
    FitResult,
    Fitter,
    HiddenStage,
    Hyp,
    NoShape,
    Registry,
)
from stagectl.ident.localise import ResidualView
from stagectl.ident.modelio import hyp_to_spec, model_to_hyp
from stagectl.ident.report import write_outputs
from stagectl.ident.signals import Signals, prepare


def _columns(sig: Signals, h: Hyp, f_est: np.ndarray) -> list[Column]:
    return [Column("toy_f0", np.ones(sig.n), "toy_f0")]


def _params(h: Hyp) -> Offset:
    return Offset(force_n=h.theta.get("toy_f0", 0.0))


def _evidence(ev: ResidualView, p: Offset) -> str:
    return f"toy: mean residual {ev.mean_positive_n:+.3g} N / {ev.mean_negative_n:+.3g} N; F = {p.force_n:.4g} N"


def _search(fitter: Fitter, cur: FitResult, h: Hyp) -> FitResult:
    return fitter.fit(h)


def _hide(st: HiddenStage) -> None:
    st.effects["offset"] = {"force_n": st.sign * float(st.rng.uniform(0.2, 0.6)) * st.coulomb_n}


TOY: EffectSpec[NoShape, Offset] = EffectSpec(
    "constant_force", NoShape, _params, _evidence, _search, column_rank=45, columns=_columns, twin="offset",
    to_twin=lambda p: p, from_twin=lambda h, e: h.adding("constant_force"), hide=_hide)


@pytest.fixture
def toy_registry(monkeypatch: pytest.MonkeyPatch) -> Registry:
    reg = Registry((TOY,))
    monkeypatch.setattr(fx, "REGISTRY", reg)
    return reg


def test_a_registered_effect_is_discovered_reported_and_written(toy_registry: Registry, tmp_path: Path) -> None:
    rng = np.random.default_rng(2006)
    st = synth.hide(synth.draw_stage(rng), "constant_force", rng)  # synth picks up the toy's hide hook
    rec = synth.closed_loop(st, motion=synth.Motion(duration_s=12.0), seed=2006)
    res = discover(rec)
    # regress and discover: the toy column is fitted, the effect is named with its typed parameters
    assert [e.name for e in res.effects] == ["constant_force"]
    truth = st["effects"]["offset"]["force_n"]
    assert res.effects[0].parameters == Offset(force_n=pytest.approx(truth, rel=0.15))
    assert res.effects[0].evidence.startswith("toy: ")
    assert "toy_f0" in res.final.hyp.theta
    assert res.gap_after <= 0.5 * res.gap_before
    # report and modelio: report.json lists it, the model file carries it as its twin
    rep = write_outputs(res, tmp_path, {"estimation": "synthetic"}, plots=False)
    on_disk = json.loads((tmp_path / "report.json").read_text(encoding="utf-8"))
    assert on_disk["effects"][0]["name"] == rep["effects"][0]["name"] == "constant_force"
    assert on_disk["effects"][0]["parameters"]["force_n"] == pytest.approx(truth, rel=0.15)
    assert [c["name"] for c in on_disk["rounds"][0]["candidates"]] == ["constant_force"]
    model = load_model_file(tmp_path / "model.yaml")
    assert model.effects.offset is not None
    assert model.effects.offset.force_n == pytest.approx(truth, rel=0.15)
    # and back: a model file's offset starts a hypothesis with the toy effect
    assert model_to_hyp(model).effects == ("constant_force",)
    assert hyp_to_spec(res.final.hyp)["effects"] == {"offset": {"force_n": pytest.approx(truth, rel=0.15)}}


def test_design_iterates_the_registry(toy_registry: Registry) -> None:
    rng = np.random.default_rng(5)
    st = synth.draw_stage(rng)
    rec = synth.closed_loop(st, motion=synth.Motion(duration_s=4.0), seed=5)
    sig = prepare(rec)
    cols, _ = rg.design(sig, toy_registry.with_effect(Hyp(), "constant_force"))
    assert [c.name for c in cols] == ["fc", "fv", "toy_f0", "m"]


def test_registry_rejects_inconsistent_specs() -> None:
    with pytest.raises(ValueError, match="duplicate"):
        Registry((TOY, TOY))
    bad = EffectSpec("x", NoShape, _params, _evidence, _search, column_rank=1, contains=("nothing",))
    with pytest.raises(ValueError, match="unknown effect 'nothing'"):
        Registry((bad,))
    with pytest.raises(ValueError, match="same model-file effect"):
        Registry((TOY, fx.OFFSET))


def test_shipped_registry_holds_the_catalogue() -> None:
    # the effects README and docs/discovery.md name, in this order (a new effect may follow them)
    shipped = ("stribeck", "presliding", "frictional_lag", "asymmetry", "position_ripple", "cogging", "offset",
               "spring", "delay")
    assert fx.REGISTRY.names[:len(shipped)] == shipped
    nested = fx.REGISTRY.nested()
    assert {k: nested[k] for k in ("spring", "asymmetry", "frictional_lag")} == {
        "spring": ("offset",), "asymmetry": ("offset",), "frictional_lag": ("stribeck",)}


def test_registry_rejects_a_twin_that_is_no_model_file_effect_and_two_delays() -> None:
    bad = EffectSpec("x", NoShape, _params, _evidence, _search, column_rank=1, twin="no_such_effect")
    with pytest.raises(ValueError, match="twin 'no_such_effect' is not a model-file effect"):
        Registry((bad,))
    delayed = [EffectSpec(f"d{i}", NoShape, _params, _evidence, _search, column_rank=1,
                          target_delay=lambda h: 0.0) for i in range(2)]
    with pytest.raises(ValueError, match="more than one effect delaying the force"):
        Registry(delayed)


def test_two_effects_producing_one_column_name_fail_loudly(monkeypatch: pytest.MonkeyPatch) -> None:
    """Coefficients are keyed by column name: a second effect reusing ``toy_f0`` is a registry bug, raised as
    such (not a ValueError, which discovery would take for a candidate that cannot be fitted)."""
    twin = EffectSpec("constant_force_2", NoShape, _params, _evidence, _search, column_rank=46, columns=_columns)
    reg = Registry((TOY, twin))
    monkeypatch.setattr(fx, "REGISTRY", reg)
    st = synth.draw_stage(np.random.default_rng(5))
    sig = prepare(synth.closed_loop(st, motion=synth.Motion(duration_s=4.0), seed=5))
    h = reg.with_effect(reg.with_effect(Hyp(), "constant_force"), "constant_force_2")
    with pytest.raises(RuntimeError, match="toy_f0 produced twice"):
        rg.design(sig, h)
