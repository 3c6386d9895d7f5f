"""Conversion between fitted hypotheses (:class:`stagectl.ident.hypothesis.Hyp`) and model files.

A hypothesis becomes a :class:`stagectl.friction.StageModel` (``mass_kg`` + ``friction`` + ``effects``):

* no pre-sliding: ``model: stribeck`` with ``fc_n``, ``fs_n`` (= fc_n without a Stribeck effect), ``vs_m_s``,
  ``delta``, ``viscous_n_s_m``, ``lag_s`` (frictional lag);
* with pre-sliding: ``model: gms`` whose elements are the fitted Maxwell-slip elements: ``k_i = W_i/Δ_i``,
  ``α_i = W_i/ΣW``; the Coulomb column (a jump at reversal) becomes one stiff element with
  ``Δ = COULOMB_ELEMENT_FRACTION·min Δ``; ``c_n_s`` from the frictional lag (τ = Fs/C) or fast (τ = 10 µs);
* every registered effect with a model-file twin (:data:`stagectl.ident.effects.REGISTRY`, ``EffectSpec.twin``)
  maps one to one onto its entry of ``stagectl.friction.effects`` (``effects:``), both ways;
* ``backlash`` becomes the model file's ``backlash:`` section (:class:`stagectl.friction.Backlash`): the play
  ``gap_m``; the friction is on the load when the fit says the friction is lost inside the play (more than
  half the Coulomb level), else on the motor; ``other_mass_kg`` is the side without friction (the mass carried
  inside the play, or the mass lost in it); the sensor is on the motor (lost motion is seen there). Read back,
  the section restores the effect with its play.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from stagectl.errors import ConfigError
from stagectl.friction import StageModel, load_model_file
from stagectl.ident import effects as fx
from stagectl.ident.hypothesis import Hyp
from stagectl.outputs import plain
from stagectl.schema import load

COULOMB_ELEMENT_FRACTION = 0.5


def _friction_spec(h: Hyp) -> dict[str, Any]:
    """The ``friction:`` mapping of a fitted hypothesis (see the module docstring)."""
    f = fx.friction_fit(h)
    if h.given_spec is not None:
        return scale_friction_spec(h.given_spec, max(f.given_scale, 1e-9))
    fc, ds = f.coulomb_n, f.stribeck_excess_n
    if f.elements is None:
        return {"model": "stribeck", "fc_n": max(fc, 0.0), "fs_n": max(fc, 0.0) + ds, "vs_m_s": f.vs_m_s,
                "delta": f.delta, "viscous_n_s_m": f.viscous_n_s_m, "lag_s": f.lag_s}
    ws: list[float] = []
    dl: list[float] = []
    s1: list[float] = []
    if fc > 0:
        ws.append(fc)
        dl.append(COULOMB_ELEMENT_FRACTION * min(e.break_displacement_m for e in f.elements))
        s1.append(0.0)
    wtot = sum(e.slip_force_n for e in f.elements)
    for e in f.elements:
        if e.slip_force_n > 1e-6 * max(wtot + fc, 1e-300):
            ws.append(e.slip_force_n)
            dl.append(e.break_displacement_m)
            s1.append(e.damping_n_s_m)
    wsum = float(sum(ws))
    if wsum <= 0:
        raise ConfigError("presliding: fitted slip forces are all zero; cannot build a GMS model")
    k = [wi / di for wi, di in zip(ws, dl)]
    alpha = [wi / wsum for wi in ws]
    fs = wsum + ds
    c = fs / f.lag_s if f.lag_s > 0 else fs / 1e-5
    return {"model": "gms", "k_n_m": k, "alpha": alpha, "fc_n": wsum, "fs_n": fs, "vs_m_s": f.vs_m_s,
            "delta": f.delta, "c_n_s": c, "sigma1_n_s_m": s1, "viscous_n_s_m": f.viscous_n_s_m}


def hyp_to_spec(h: Hyp, meta: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Model-file mapping (``mass_kg``, ``friction``, ``effects``, ``meta``) of a fitted hypothesis."""
    friction = _friction_spec(h)
    effects: dict[str, Any] = {}
    for spec in fx.REGISTRY:
        if spec.twin is not None and spec.to_twin is not None and h.has(spec.name):
            effects[spec.twin] = plain(spec.to_twin(spec.params(h)))
    out: dict[str, Any] = {}
    m = h.theta.get("m", h.fixed_mass_kg)
    if m is not None and m > 0:
        out["mass_kg"] = float(m)
    out["friction"] = friction
    if effects:
        out["effects"] = effects
    if h.has(fx.BACKLASH.name):
        out["backlash"] = _backlash_spec(h)
    if meta:
        out["meta"] = dict(meta)
    return out


def _backlash_spec(h: Hyp) -> dict[str, Any]:
    """The ``backlash:`` mapping of a fitted hypothesis with the backlash effect (see the module docstring)."""
    p = fx.BACKLASH.params(h)
    on_load, other = fx.backlash_split(p)
    if not (0.0 < other < p.mass_kg):
        raise ConfigError(f"backlash: the fitted mass lost in the play ({p.mass_lost_kg:.4g} kg of "
                          f"{p.mass_kg:.4g} kg) leaves no valid motor/load split; not written (not clipped)")
    beyond = fx.BACKLASH.bounds(p) if fx.BACKLASH.bounds is not None else []
    if beyond:  # discovery never accepts such a fit; refuse it here too rather than write an unphysical plant
        raise ConfigError(f"backlash: the fit is beyond a physical bound ({'; '.join(beyond)}); not written")
    return {"gap_m": float(p.gap_m), "other_mass_kg": float(other), "friction_side": "load" if on_load else "motor",
            "sensor_side": "motor"}


def scale_friction_spec(spec: dict[str, Any], c: float) -> dict[str, Any]:
    """A friction spec whose force is ``c`` times the original's for every trajectory.

    Every force-valued parameter (keys ending in ``_n``, ``_n_m``, ``_n_s_m``, ``_n_s``) is multiplied by ``c``;
    displacement and velocity scales are unchanged. Hsieh's plastic law ``x_h = |F|^a/ψ`` needs ``ψ·c^a``.
    """
    out: dict[str, Any] = {}
    for k, v in spec.items():
        if k != "model" and k.endswith(("_n", "_n_m", "_n_s_m", "_n_s")) and v is not None:
            if isinstance(v, (list, tuple)):
                out[k] = [float(x) * c for x in v]
            elif isinstance(v, (int, float)) and math.isfinite(float(v)):
                out[k] = float(v) * c
            else:
                out[k] = v
        else:
            out[k] = v
    if spec.get("model") == "hsieh" and "psi" in spec:
        out["psi"] = float(spec["psi"]) * c ** float(spec.get("a", 1.0))
    return out


def hyp_to_model(h: Hyp, meta: Mapping[str, Any] | None = None) -> StageModel:
    """Validated :class:`StageModel` of a fitted hypothesis."""
    return load(StageModel, plain(hyp_to_spec(h, meta)), "")


def model_to_hyp(model: StageModel) -> Hyp:
    """Starting hypothesis from a model file (``stribeck`` and ``gms``/``maxwell_slip`` are converted into the
    regression's parametrisation; any other friction model is kept as a fixed force shape with a fitted scale;
    each active entry of ``effects:`` becomes the registered effect whose twin it is). The linear parameters
    are refitted from the data; the structure and the shapes are kept.
    """
    spec = model.friction.spec()
    tag = spec["model"]
    h = Hyp(fixed_mass_kg=None)
    if tag == "stribeck":
        if spec["fs_n"] > spec["fc_n"]:
            h = fx.STRIBECK.reshaped(h.adding(fx.STRIBECK.name), vs_m_s=spec["vs_m_s"], delta=spec["delta"])
            if spec.get("lag_s", 0.0) > 0:
                h = fx.LAG.reshaped(h.adding(fx.LAG.name), lag_s=spec["lag_s"])
    elif tag in ("gms", "maxwell_slip"):
        k = np.asarray(spec["k_n_m"], float)
        if tag != "gms" and spec.get("w_n") is not None:
            w = np.asarray(spec["w_n"], float)
        else:
            w = np.asarray(spec["alpha"], float) * spec["fs_n"]
        h = fx.PRESLIDING.reshaped(h.adding(fx.PRESLIDING.name), deltas_m=tuple(float(v) for v in w / k))
        if tag == "gms" and spec["fs_n"] > spec["fc_n"]:
            h = fx.STRIBECK.reshaped(h.adding(fx.STRIBECK.name), vs_m_s=spec["vs_m_s"], delta=spec["delta"])
    else:
        h.given_spec = spec
    for eff in fx.REGISTRY:
        value = getattr(model.effects, eff.twin) if eff.twin is not None else None
        if value is not None and eff.from_twin is not None:
            h = eff.from_twin(h, value)
    if model.backlash is not None:
        h = fx.BACKLASH.reshaped(h.adding(fx.BACKLASH.name), gap_m=float(model.backlash.gap_m))
    h.theta = {}
    return h


def load_start(path: str) -> Hyp:
    """Starting hypothesis from a model file path."""
    return model_to_hyp(load_model_file(path))
