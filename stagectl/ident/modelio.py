"""Conversion between fitted hypotheses (:class:`stagectl.ident.regress.Hyp`) and model files.

A hypothesis becomes a :class:`stagectl.friction.StageModel` (``mass_kg`` + ``friction`` + ``effects``):

* no pre-sliding: ``model: stribeck`` with ``fc_n``, ``fs_n`` (= fc_n without a Stribeck effect), ``vs_m_s``,
  ``delta``, ``viscous_n_s_m``, ``lag_s`` (frictional lag);
* with pre-sliding: ``model: gms`` whose elements are the fitted Maxwell-slip elements: ``k_i = W_i/Δ_i``,
  ``α_i = W_i/ΣW``; the Coulomb column (a jump at reversal) becomes one stiff element with
  ``Δ = COULOMB_ELEMENT_FRACTION·min Δ``; ``c_n_s`` from the frictional lag (τ = Fs/C) or fast (τ = 10 µs);
* effects map one to one onto ``stagectl.friction.effects``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from stagectl.errors import ConfigError
from stagectl.friction import StageModel, load_model_file
from stagectl.schema import load
from stagectl.ident.regress import Hyp

COULOMB_ELEMENT_FRACTION = 0.5


def hyp_to_spec(h: Hyp, meta: dict[str, Any] | None = None) -> dict[str, Any]:
    """Model-file mapping (``mass_kg``, ``friction``, ``effects``, ``meta``) of a fitted hypothesis."""
    from stagectl.ident.discover import describe_params

    th, nl = h.theta, h.nl
    fc = float(th.get("fc", 0.0))
    ds = float(th.get("ds", 0.0)) if h.has("stribeck") else 0.0
    fv = max(float(th.get("fv", 0.0)), 0.0)
    vs = float(nl.get("vs_m_s", 1e-3))
    delta = float(nl.get("delta", 2.0))
    lag = float(nl.get("lag_s", 0.0)) if h.has("frictional_lag") else 0.0
    friction: dict[str, Any]
    if "given_spec" in nl:
        friction = scale_friction_spec(nl["given_spec"], max(float(th.get("given", 1.0)), 1e-9))
    elif h.has("presliding"):
        d = np.asarray(nl["deltas_m"], float)
        w = np.array([max(th.get(f"w{i}", 0.0), 0.0) for i in range(d.size)])
        sig1 = np.array([max(th.get(f"s{i}", 0.0), 0.0) for i in range(d.size)])
        ws, dl, s1 = [], [], []
        if fc > 0:
            ws.append(fc)
            dl.append(COULOMB_ELEMENT_FRACTION * float(d.min()))
            s1.append(0.0)
        for wi, di, si in zip(w, d, sig1):
            if wi > 1e-6 * max(w.sum() + fc, 1e-300):
                ws.append(float(wi))
                dl.append(float(di))
                s1.append(float(si))
        wsum = float(sum(ws))
        if wsum <= 0:
            raise ConfigError("presliding: fitted slip forces are all zero; cannot build a GMS model")
        k = [wi / di for wi, di in zip(ws, dl)]
        alpha = [wi / wsum for wi in ws]
        fs = wsum + ds
        c = fs / lag if lag > 0 else fs / 1e-5
        friction = {"model": "gms", "k_n_m": k, "alpha": alpha, "fc_n": wsum, "fs_n": fs, "vs_m_s": vs,
                    "delta": delta, "c_n_s": c, "sigma1_n_s_m": s1, "viscous_n_s_m": fv}
    else:
        friction = {"model": "stribeck", "fc_n": max(fc, 0.0), "fs_n": max(fc, 0.0) + ds, "vs_m_s": vs,
                    "delta": delta, "viscous_n_s_m": fv, "lag_s": lag}
    effects: dict[str, Any] = {}
    for name in ("asymmetry", "position_ripple", "cogging", "offset", "spring", "delay"):
        if h.has(name):
            p = describe_params(h, name)
            if name == "asymmetry":
                p["ratio"] = float(np.clip(p["ratio"], -0.99, 0.99))
            if name == "position_ripple":
                p["amplitude"] = float(min(p["amplitude"], 0.99))
            effects[name] = p
    if h.has("spring") and h.has("offset"):
        # both contain a constant: keep it in the offset, the spring rest position at the data centre
        effects["spring"]["x0_m"] = h.x_center_m
    out: dict[str, Any] = {}
    m = th.get("m", h.fixed_mass_kg)
    if m is not None and m > 0:
        out["mass_kg"] = float(m)
    out["friction"] = friction
    if effects:
        out["effects"] = effects
    if meta:
        out["meta"] = meta
    return out


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


def hyp_to_model(h: Hyp, meta: dict[str, Any] | None = None) -> StageModel:
    """Validated :class:`StageModel` of a fitted hypothesis."""
    return load(StageModel, _plain(hyp_to_spec(h, meta)), "")


def _plain(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    return obj


def model_to_hyp(model: StageModel) -> Hyp:
    """Starting hypothesis from a model file (``stribeck`` and ``gms``/``maxwell_slip`` are converted into the
    regression's parametrisation; any other friction model is kept as a fixed force shape with a fitted scale).
    """
    fr = model.friction
    spec = fr.spec()
    tag = spec["model"]
    h = Hyp(fixed_mass_kg=None)
    eff: list[str] = []
    theta: dict[str, float] = {}
    nl: dict[str, Any] = {}
    if tag == "stribeck":
        theta.update(fc=spec["fc_n"], fv=spec["viscous_n_s_m"])
        if spec["fs_n"] > spec["fc_n"]:
            eff.append("stribeck")
            nl.update(vs_m_s=spec["vs_m_s"], delta=spec["delta"])
            theta["ds"] = spec["fs_n"] - spec["fc_n"]
            if spec.get("lag_s", 0.0) > 0:
                eff.append("frictional_lag")
                nl["lag_s"] = spec["lag_s"]
    elif tag in ("gms", "maxwell_slip"):
        k = np.asarray(spec["k_n_m"], float)
        if tag == "gms":
            w = np.asarray(spec["alpha"], float) * spec["fs_n"]
        elif spec.get("w_n") is not None:
            w = np.asarray(spec["w_n"], float)
        else:
            w = np.asarray(spec["alpha"], float) * spec["fs_n"]
        d = w / k
        eff.append("presliding")
        nl["deltas_m"] = [float(v) for v in d]
        for i, wi in enumerate(w):
            theta[f"w{i}"] = float(wi)
        theta["fv"] = spec.get("viscous_n_s_m", 0.0)
        if tag == "gms" and spec["fs_n"] > spec["fc_n"]:
            eff.append("stribeck")
            nl.update(vs_m_s=spec["vs_m_s"], delta=spec["delta"])
    else:
        nl["given_spec"] = spec
    e = model.effects
    if e.asymmetry is not None:
        eff.append("asymmetry")
        nl["r"] = e.asymmetry.ratio
    if e.position_ripple is not None:
        eff.append("position_ripple")
        nl["ripple_lambda_m"] = e.position_ripple.wavelength_m
    if e.cogging is not None:
        eff.append("cogging")
        nl["cogging_lambda_m"] = e.cogging.wavelength_m
    if e.offset is not None:
        eff.append("offset")
    if e.spring is not None:
        eff.append("spring")
        h.x_center_m = e.spring.x0_m
    if e.delay is not None:
        eff.append("delay")
        nl["delay_s"] = e.delay.delay_s
    h.effects = tuple(eff)
    h.nl = nl
    h.theta = {}  # the linear parameters are refitted from the data; the structure is kept
    return h


def load_start(path: str) -> Hyp:
    """Starting hypothesis from a model file path."""
    return model_to_hyp(load_model_file(path))


