"""Models from the commissioning recordings: the friction regression, ``discover`` for the effects, and the
model file's content (``docs/commissioning.md`` §4).

* mass: the FRF fit (its rigid-body mass, independent of friction), cross-checked against the
  inverse-dynamics regression over the constant-velocity passes; when they differ by more than
  ``MASS_DISAGREEMENT`` the latter is used (an FRF around a standing position measures a stage held by its
  friction: a heavy ball-screw axis);
* ``discover`` runs on the nested reversals (estimation: pre-sliding loops, long moves both ways over half
  the stroke) validated on the constant-velocity passes (a separate experiment: an effect must transfer to
  be accepted), starting from the FRF mass (fixed) plus Coulomb and viscous friction. The other way round
  (estimation on the passes) named the same effects but cost 10–50× more (the passes are 3× longer, and the
  pre-sliding search grows faster than the samples); the slow passes' two reversals were too few to
  validate pre-sliding on a GMS stage. It names the effects the data need (Stribeck, pre-sliding, cogging,
  offset, spring, ripple, asymmetry, ...) and fits them;
* the model file is the discovered model (:func:`stagectl.ident.modelio.hyp_to_spec`) with the FRF mass and
  the sliding levels (Coulomb, static, Stribeck velocity and shape, viscous) of the constant-velocity
  segment fit.

``identify --model gms`` also runs on the reversal recording; its virgin-curve fit is reported beside.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from stagectl.errors import DataError
from stagectl.ident.discover import discover
from stagectl.ident.hypothesis import Hyp
from stagectl.ident.modelio import hyp_to_spec
from stagectl.ident.recording import Recording
from stagectl.outputs import plain
from stagectl.recorder import Recorder

#: relative difference between the FRF mass and the inverse-dynamics mass that the report warns about
MASS_DISAGREEMENT = 0.2
#: highest sample rate handed to discover [Hz]
DISCOVER_RATE_HZ = 500.0


def to_recording(rec: Recorder, name: str, step: int = 1) -> Recording:
    """A loop recording as an identification recording (t, x, u, x_ref, v), every ``step``-th sample with
    ``u`` averaged over the ``step`` samples it replaces (the zero-order-hold force over the longer interval)."""
    n = (rec.n // step) * step
    u = np.array(rec.col("u"))[:n].reshape(-1, step).mean(axis=1)
    return Recording(t=np.array(rec.col("t"))[:n:step], x=np.array(rec.col("x"))[:n:step], u=u,
                     x_ref=np.array(rec.col("x_ref"))[:n:step], v=np.array(rec.col("v"))[:n:step],
                     source=f"recordings/{name}.csv")


def fit_models(recordings: dict[str, Recorder], mass_kg: float, period_s: float,
               sliding: dict[str, float] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """The discovery summary and the model file's mapping (module docstring). ``sliding``: the Stribeck
    curve of the constant-velocity segment means (``fc_n, fs_n, vs_m_s, delta, viscous_n_s_m``), which
    replaces the discovered sliding levels when given (a direct measurement of exactly these parameters;
    discover fits them jointly with the pre-sliding elements, whose damping can trade with the viscous
    term)."""
    res_recordings = recordings
    # a second, independent mass: the inverse-dynamics regression (m·a + Coulomb + viscous) over the
    # acceleration ramps of the constant-velocity passes (ident.identify.measure)
    from stagectl.ident.identify import measure

    try:
        m_id = measure(to_recording(res_recordings["friction_cv"], "friction_cv")).mass_kg
    except DataError:
        m_id = None
    m = mass_kg
    warning = None
    if m_id is not None and abs(m_id / mass_kg - 1) > MASS_DISAGREEMENT:
        # the FRF stands still: on a stage held by its friction it measures the friction, not the mass
        m = float(m_id)
        warning = (f"the FRF mass {mass_kg:.4g} kg and the inverse-dynamics mass {m_id:.4g} kg of the "
                   f"constant-velocity passes differ by more than {100 * MASS_DISAGREEMENT:.0f} %: the FRF "
                   "probably measured a stage held by its friction; the model and the gains use the "
                   "inverse-dynamics mass")
    # discover's cost grows with the samples: the loop rate is decimated to at most DISCOVER_RATE_HZ
    step = max(1, round(1.0 / (period_s * DISCOVER_RATE_HZ)))
    est = to_recording(res_recordings["reversals"], "reversals", step)
    val = to_recording(res_recordings["friction_cv"], "friction_cv", step)
    x = est.x
    start = Hyp(fixed_mass_kg=m, x_center_m=float(0.5 * (x.min() + x.max())))
    d = discover(est, validate=val, start=start)
    spec = hyp_to_spec(d.final.hyp, {"source": "stagectl commission"})
    spec["mass_kg"] = float(m)
    fr = spec["friction"]
    if sliding is not None and fr.get("model") in ("gms", "stribeck"):
        fr.update({k: float(sliding[k]) for k in ("fc_n", "fs_n", "vs_m_s", "delta", "viscous_n_s_m")})
        fr["fs_n"] = max(fr["fs_n"], fr["fc_n"])
    discovery: dict[str, Any] = {
        "estimation": est.source, "validation": val.source,
        "gap_before_n": d.gap_before, "gap_after_n": d.gap_after,
        "effects": [plain(e.as_json(), json=True) for e in d.effects],
        "rejected": [plain(e.as_json(), json=True) for e in d.rejected],
        "coulomb_n": float(d.final.hyp.theta.get("fc", math.nan)),
        "viscous_n_s_m": float(d.final.hyp.theta.get("fv", math.nan)),
        "elapsed_s": d.elapsed_s,
        "mass_kg_inverse_dynamics": m_id,
        "mass_kg_used": m,
    }
    if warning is not None:
        discovery["mass_warning"] = warning
    model_spec: dict[str, Any] = plain(spec, json=True)
    try:
        from stagectl.ident.identify import identify

        gi = identify(to_recording(res_recordings["reversals"], "reversals"), "gms", mass_kg=m)
        discovery["reversals_gms"] = {"friction": plain(gi.spec, json=True),
                                          "fit": plain(gi.quality.get("fit", {}), json=True)}
    except DataError as exc:
        discovery["reversals_gms"] = {"error": str(exc)}
    return discovery, model_spec
