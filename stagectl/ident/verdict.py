"""A quality verdict for an identified friction model: how well it fits, how well the recording determines
each parameter, and what to record when it does not.

Method (local, linearised least squares, as a prediction-error identification reports its covariance):

* residual ``r = F_meas − L[F_model(θ)]`` over the evaluated samples, with ``F_meas = ū − m·a`` the
  inverse-dynamics force and ``L`` the recording's low-pass (the same one the fit used);
* Jacobian ``J_j = ∂r/∂θ_j`` by forward differences on the simulated model (relative step 1e-4), and
  ``∂r/∂m = −L[a]`` when the mass was estimated;
* covariance ``Σ = κ·s²·(JᵀJ)⁺`` with ``s² = rᵀr/(n − p)`` and ``κ = fs/(2·fc) ≥ 1``: the low-pass makes
  neighbouring residuals correlated, so only about ``n/κ`` samples are independent;
* per parameter the relative standard deviation ``σ_j/|θ_j|``; for the model as a whole the uncertainty
  of its *prediction* ``σ_F = sqrt(diag(J Σ Jᵀ))`` relative to the RMS friction force (parameters that trade
  off against each other leave the prediction determined).

Verdict: ``good`` (force error ≤ 10 % of the RMS friction force, prediction determined to ≤ 5 %, mass
to ≤ 5 % when estimated), ``poor`` (error > 30 %, prediction > 10 % or mass > 15 %), ``fair`` between.
The figures are local and assume the model structure is right: a structurally wrong model shows up in the
force error, not in the standard deviations.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy import signal

from stagectl.errors import StageError
from stagectl.friction import build

FloatArray = npt.NDArray[np.float64]

GOOD_ERROR, POOR_ERROR = 0.10, 0.30
GOOD_PREDICTION, POOR_PREDICTION = 0.05, 0.10
GOOD_MASS, POOR_MASS = 0.05, 0.15

#: plausible moving masses [kg] and position spans [m] of a linear stage (outside: units are likely wrong)
MASS_RANGE_KG = (1e-3, 1e5)
MAX_SPAN_M = 10.0

#: what to record when a parameter is not determined, by the parameter's kind
ADVICE = {
    "mass": "a motion with acceleration (fast reversals or a multisine) so inertia carries >= 20 % of the force",
    "sliding": "constant-velocity passes in both directions at 5 or more speeds, log-spaced from the lowest "
               "usable speed to the top speed",
    "presliding": "reversals with small nested amplitudes (a few times the pre-sliding distance) after a long move",
    "fit": "a recording that exercises the regime the model describes (see the notes)",
}
_SLIDING = ("fc_n", "fs_n", "vs_m_s", "delta", "viscous_n_s_m", "c_n_s")


def _kind(name: str) -> str:
    if name == "mass_kg":
        return "mass"
    return "sliding" if name.split("[")[0] in _SLIDING else "presliding"


def _leaves(spec: dict[str, Any]) -> list[tuple[str, Any, float]]:
    """(name, key path, value) for every non-zero numeric parameter of a friction spec."""
    out: list[tuple[str, Any, float]] = []
    for key, val in spec.items():
        if key == "model" or isinstance(val, bool):
            continue
        if isinstance(val, (int, float)) and val != 0 and math.isfinite(val):
            out.append((key, (key,), float(val)))
        elif isinstance(val, list):
            for i, v in enumerate(val):
                if isinstance(v, (int, float)) and v != 0 and math.isfinite(v):
                    out.append((f"{key}[{i}]", (key, i), float(v)))
    return out


def _set(spec: dict[str, Any], path: Any, value: float) -> dict[str, Any]:
    s = copy.deepcopy(spec)
    if len(path) == 1:
        s[path[0]] = value
    else:
        s[path[0]][path[1]] = value
    return s


def assess(sig: Any, force: FloatArray, spec: dict[str, Any], rows: npt.NDArray[np.bool_], *,
           mass_estimated: float | None, offset_n: float = 0.0, model: str = "",
           on_run: Callable[[], None] | None = None) -> dict[str, Any]:
    """The verdict dict (see module docstring) for ``spec`` fitted to ``force`` over ``rows``.

    ``sig`` is the recording's :class:`~stagectl.ident.signals.Signals` (time, filtered position, the
    low-pass); ``mass_estimated`` the mass in kg when the fit estimated it (``None`` when it was given).
    """

    def predict(s: dict[str, Any]) -> FloatArray:
        f = build(s).force_along(sig.xf, sig.t) + offset_n
        if on_run is not None:  # progress: one model run along the recording (1 + one per parameter)
            on_run()
        return np.asarray(signal.sosfiltfilt(sig.sos, f), dtype=np.float64)[rows]

    f0 = predict(spec)
    y = force[rows]
    r = y - f0
    n = int(r.size)
    ref_rms = max(float(np.sqrt(np.mean(y * y))), 1e-300)
    rel_err = float(np.sqrt(np.mean(r * r))) / ref_rms
    params = _leaves(spec)
    names = [p[0] for p in params]
    values = [p[2] for p in params]
    cols: list[FloatArray] = []
    for _, path, v in params:
        h = 1e-4 * abs(v)
        try:  # forward; backward where the step leaves the model's valid range (fs_n >= fc_n, alpha sum ...)
            f1 = predict(_set(spec, path, v + h))
        except StageError:
            h = -h
            f1 = predict(_set(spec, path, v + h))
        cols.append((f1 - f0) / h)
    if mass_estimated is not None and mass_estimated > 0:
        acc = np.asarray(signal.sosfiltfilt(sig.sos, sig.acc_raw), dtype=np.float64)[rows]
        cols.append(acc)  # F_meas = ū − m·a: a larger m lowers F_meas, i.e. raises the residual's model side
        names.append("mass_kg")
        values.append(float(mass_estimated))
    p = len(cols)
    if p == 0 or n <= p:
        return {"verdict": "poor", "force_error_relative": rel_err, "parameters": {},
                "reasons": ["too few samples to judge the fit"], "record_instead": [ADVICE["fit"]]}
    J = np.column_stack(cols) * np.asarray(values)  # relative parameters: columns ∂r/∂ln θ
    fs = 1.0 / float(np.median(np.diff(sig.t)))
    kappa = max(1.0, fs / (2.0 * float(sig.cutoff_hz)))
    s2 = float(r @ r) / (n - p)
    cov_rel = kappa * s2 * np.linalg.pinv(J.T @ J, rcond=1e-12)
    rel_std = np.sqrt(np.clip(np.diag(cov_rel), 0.0, None))
    # null-space directions (pinv drops them) are undetermined, not perfectly known
    col_norm = np.linalg.norm(J, axis=0)
    rel_std = np.where(col_norm < 1e-12 * max(float(col_norm.max()), 1e-300), np.inf, rel_std)
    pf = len(params)  # the friction parameters' columns: the mass moves the measurement, not the prediction
    sig_f = np.sqrt(np.clip(np.einsum("ij,jk,ik->i", J[:, :pf], cov_rel[:pf, :pf], J[:, :pf]), 0.0, None))
    pred_rel = float(np.sqrt(np.mean(sig_f * sig_f))) / ref_rms
    table: dict[str, dict[str, Any]] = {}
    for name, v, rs in zip(names, values, rel_std, strict=True):
        state = "determined" if rs <= 0.1 else "loosely determined" if rs <= 0.5 else "not determined"
        table[name] = {"value": v, "relative_std": float(rs) if math.isfinite(rs) else None, "identifiability": state}
    mass_rel = float(rel_std[-1]) if names and names[-1] == "mass_kg" else None
    reasons: list[str] = []
    kinds: list[str] = []
    verdict = "good"

    def worse(level: str, why: str, kind: str) -> None:
        nonlocal verdict
        order = ("good", "fair", "poor")
        if order.index(level) > order.index(verdict):
            verdict = level
        reasons.append(why)
        if kind not in kinds:
            kinds.append(kind)

    if rel_err > POOR_ERROR:
        worse("poor", f"force error {100 * rel_err:.0f} % of the RMS friction force (> {100 * POOR_ERROR:.0f} %): "
                      f"the {model or 'model'} does not describe this recording", "fit")
    elif rel_err > GOOD_ERROR:
        worse("fair", f"force error {100 * rel_err:.0f} % of the RMS friction force", "fit")
    if pred_rel > POOR_PREDICTION:
        worse("poor", f"the recording determines the model's force only to ±{100 * pred_rel:.0f} %", "sliding")
    elif pred_rel > GOOD_PREDICTION:
        worse("fair", f"the model's force is determined to ±{100 * pred_rel:.0f} %", "sliding")
    if mass_rel is not None:
        if not mass_rel <= POOR_MASS:
            worse("poor", f"mass {mass_estimated:.4g} kg ± {100 * mass_rel:.0f} %: not determined by this recording "
                          "(give --mass-kg, or record with more acceleration)", "mass")
        elif mass_rel > GOOD_MASS:
            worse("fair", f"mass {mass_estimated:.4g} kg ± {100 * mass_rel:.0f} %", "mass")
    if mass_estimated is not None and not MASS_RANGE_KG[0] <= mass_estimated <= MASS_RANGE_KG[1]:
        worse("poor", f"mass {mass_estimated:.3g} kg is outside {MASS_RANGE_KG[0]:g}…{MASS_RANGE_KG[1]:g} kg, "
                      "implausible for a stage: are positions in µm or mm written as metres, or forces in mN?", "fit")
    span = float(np.ptp(sig.xf))
    if span > MAX_SPAN_M:
        worse("poor", f"the recording spans {span:.3g} m (> {MAX_SPAN_M:g} m): are positions in µm or nm written "
                      "as metres?", "fit")
    loose = [nm for nm, row in table.items() if row["identifiability"] == "not determined" and nm != "mass_kg"]
    if loose:
        for nm in loose:
            if _kind(nm) not in kinds and verdict != "good":
                kinds.append(_kind(nm))
    advice = [ADVICE[k] for k in kinds if k != "fit"] or ([ADVICE["fit"]] if "fit" in kinds else [])
    return {
        "verdict": verdict,
        "force_error_relative": rel_err,
        "prediction_std_relative": pred_rel,
        "mass_std_relative": mass_rel,
        "independent_samples": n / kappa,
        "parameters": table,
        "not_determined": loose,
        "reasons": reasons,
        "record_instead": advice if verdict != "good" else [],
    }
