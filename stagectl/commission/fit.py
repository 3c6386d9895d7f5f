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

* cogging and pre-sliding are decided by the experiments designed for them, not by discover's global
  acceptance (a 20 % cut of the validation gap on the constant-velocity passes, which rejected both on the
  commissioning test stage with Coulomb 1.0 N: model Stribeck only, cosine 3.7 µm RMS against 1.6 nm):
  cogging by :func:`cogging_evidence` on the slow passes, confirmed on the constant-velocity passes
  (:func:`cogging_confirmation`: a second experiment its period and phase were not fitted on), pre-sliding
  by the ratio of a rigid friction's residual to the Maxwell-slip regression's (:func:`fit_presliding`,
  ``PRESLIDING_EVIDENCE_RATIO``), the offset by the constant-velocity passes' even part, confirmed by the slow
  passes (:func:`stagectl.commission.analysis.offset_evidence`; left to discover where it named a spring or an
  asymmetry, which contain one); a spring discover named gets its stiffness and rest position from the slow
  passes (:func:`slow_pass_spring`: discover's constant part is confounded with the pre-sliding elements);
  discover's verdict is reported beside (``discovery.evidence``);
* pre-sliding (when named): the GMS elements are refitted on the reversals and the pre-sliding
  loops (the constant-velocity passes only when these have no slow rows: :func:`presliding_recordings`)
  by a Maxwell-slip regression
  (:func:`fit_presliding`): stiffnesses by non-negative least squares for break-away displacements on a
  log-spaced grid, then the break-aways free, jointly with the cogging period, a stiffness-proportional
  micro-damping and the force's delay (variable projection). On the commissioning test plant (hidden
  plant, 16 Hz PID + 100 Hz DOB) the 10 µm cosine's RMS error went from 34 nm (the grid regression on the
  reversals and passes; exact model 1.5 nm) to 2.0–2.1 nm; the steps: :func:`fit_presliding`.

``identify --model gms`` also runs on the reversal recording; its virgin-curve fit is reported beside.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from stagectl.commission import analysis as an
from stagectl.errors import DataError
from stagectl.friction.effects import Cogging, Effects
from stagectl.ident.discover import discover
from stagectl.ident.effects import REGISTRY
from stagectl.ident.hypothesis import Hyp
from stagectl.ident.modelio import hyp_to_spec
from stagectl.ident.recording import Recording
from stagectl.jit import kernel
from stagectl.outputs import plain
from stagectl.recorder import Recorder

FloatArray = npt.NDArray[np.float64]

#: relative difference between the FRF mass and the inverse-dynamics mass that the report warns about
MASS_DISAGREEMENT = 0.2
#: the inverse-dynamics mass replaces the FRF's only within this factor of it (:func:`reconcile_mass`)
MASS_ID_MAX_RATIO = 2.0
#: highest sample rate handed to discover [Hz]
DISCOVER_RATE_HZ = 500.0
#: pre-sliding regression: number of Maxwell-slip elements, range of their break-away displacements [m]
#: (at Fs), moving-average length applied to every column (suppresses the acceleration's noise) [samples]
PRESLIDING_ELEMENTS = 24
PRESLIDING_DELTA_M = (30e-9, 100e-6)
#: (40 samples blurred the break-aways: at a loop's speed they span 5-16 % of its travel)
PRESLIDING_SMOOTH = 10
#: rows kept after the moving average (every PRESLIDING_DECIMATE-th) and evaluations of the free
#: break-away refinement
PRESLIDING_DECIMATE = 2
PRESLIDING_MAX_EVALS = 150
#: rows used by the pre-sliding fit: at least PRESLIDING_SETTLE_S [s] after the last sample faster than
#: PRESLIDING_V_FRACTION of the Stribeck velocity
PRESLIDING_V_FRACTION = 0.5
PRESLIDING_SETTLE_S = 0.15
#: ... the curve's own Stribeck velocity counts where the passes only bound it (stick-slip), unless it leaves
#: fewer than this fraction of the rows the slowest pass's speed would (:func:`_presliding_rows`)
PRESLIDING_VS_ROWS_FRACTION = 0.2
#: the recordings of the pre-sliding regression, and the one read only when they leave no slow rows
#: (:func:`presliding_recordings`)
PRESLIDING_RECORDINGS = ("reversals", "presliding")
PRESLIDING_FALLBACK = ("friction_cv",)
#: the element states are computed on the measured path interpolated (cubic spline) to this many points
#: per sampling period: a play operator remembers the path's extrema, and after a fast move the stage rings
#: at its pre-sliding resonance (85 Hz on tests/commission/plant_gen.py seed 18, 12 samples a period) with
#: turning points between samples; the sampled path missed them by tens of nm and left the play's states
#: 16 mN away from the plant's GMS for the following slow rows, with the plant's own parameters (noise-free
#: sensor, true mass and delay): 3.9 mN RMS residual on the slow rows, 0.9 mN at 4 points (0.9 at 10), and
#: the fit shortened every break-away by 0.5-1 % to absorb it
PRESLIDING_UPSAMPLE = 4
#: upper bound of the stiffness-proportional micro-damping σ1_i/k_i [sampling periods]
PRESLIDING_MAX_DAMPING = 5.0
#: the force's delay is refined within ± this many sampling periods of the FRF's
PRESLIDING_DELAY_SPAN = 0.5
#: the cogging period is refitted within −20/+25 % of the slow passes'; a result beyond this log-distance
#: (the bounds are ln 0.8 = −0.223, ln 1.25 = 0.223) is refused and the slow passes' cogging kept
PRESLIDING_LAMBDA_EDGE = 0.2
#: pre-sliding is named when the rigid model's residual (one element of the smallest break-away: a friction
#: at rest that keeps its last sliding level) over the Maxwell-slip regression's is at least this ratio
#: (measured: 50-940 on generated GMS plants, 1.9 on the Stribeck-only 60 kg axis of the tests)
PRESLIDING_EVIDENCE_RATIO = 5.0
#: weight of the row Σ k_i·Δ_i = Fs in the pre-sliding regression [per √rows]: 0, the level is measured
#: (the constant-velocity passes extrapolate Fs from their slowest speed: 2 % low on a generated plant,
#: which left a 10 µm cosine at 16 nm RMS against 1.0 nm; with the level free the residual went from
#: 6.7 mN to 0.5 mN and the level to 0.616 N, true 0.6164 N; tests/commission/plant_gen.py seed 6)
PRESLIDING_LEVEL_WEIGHT = 0.0
#: cogging (slow passes, :func:`cogging_evidence`): peak over median amplitude of the period scan needed,
#: moving average and decimation [samples], settling time after a cruise starts [s], shortest period
#: scanned [row spacings]
COGGING_EVIDENCE_RATIO = 5.0
COGGING_SMOOTH = 20
COGGING_DECIMATE = 5
COGGING_SETTLE_S = 0.3
COGGING_MIN_SAMPLES = 10
#: longest period scanned: the travel over this many periods (a third of the 2 mm travel missed a 1.06 mm
#: cogging on a generated plant, tests/commission/plant_gen.py seed 2; the per-direction constant and slope
#: keep a linear trend from posing as a long period)
COGGING_MIN_PERIODS = 1.5
#: a scan peak at or beyond this fraction of the longest period scanned is a trend, not a period, unless
#: the sinusoid survives a per-direction cubic: its amplitude, refitted with ``x²`` and ``x³`` per direction
#: added to the nuisance, stays at least this fraction of the scan's (a sinusoid of 1.4 periods over the
#: travel keeps 0.35–0.64 of its norm against a cubic, and least squares keeps its amplitude; a smooth trend
#: is taken by the cubic. Generated plant 44: a 0.113 N, 1.412 mm cogging over 1.98 mm was refused as a trend
#: and the commissioned cosine tracked 21× the exact model's)
COGGING_EDGE_FRACTION = 0.95
COGGING_EDGE_KEEP = 0.7


@kernel
def _play_kernel(x: FloatArray, deltas: FloatArray, scale: FloatArray, out: FloatArray) -> None:  # pragma: no cover
    n, m = x.shape[0], deltas.shape[0]
    z = np.zeros(m)
    mode = np.zeros(m)
    for k in range(1, n):
        dx = x[k] - x[k - 1]
        if dx != 0.0:
            s = 1.0 if dx > 0.0 else -1.0
            for i in range(m):
                w = deltas[i] * scale[k]
                if mode[i] != 0.0 and mode[i] != s:
                    mode[i] = 0.0
                if mode[i] == 0.0:
                    z[i] += dx
                    if s * z[i] >= w:
                        z[i] = s * w
                        mode[i] = s
                else:
                    z[i] = s * w
        for i in range(m):
            out[k, i] = z[i]


def _play(x: FloatArray, deltas: FloatArray, scale: FloatArray) -> FloatArray:
    """Normalised element deflections of a Maxwell-slip model along the measured path (GMS with C → ∞).

    Element ``i`` sticks (``z_i += dx``) until ``sgn(dx)·z_i`` reaches ``Δ_i·scale`` (``scale = g(v)/Fs``,
    the Stribeck curve over its static level), then slips at that bound; a reversal of the increment
    ``dx = x_k − x_{k−1}`` makes it stick again; ``dx = 0`` holds. The direction is the sign of the same
    increment that loads the elements, as in the plant's GMS step: a direction taken from a central
    difference disagrees with the increment wherever the sensor noise reverses it (at rest, at a turning
    point) and then drove slipping elements back to the bound against the increment, 10 mN RMS away from
    the GMS along the same measured path on the commissioning test stage. Returns ``z`` [m], shape
    (len(x), len(deltas)); the element force is ``k_i·z_i`` (linear in ``k_i``)."""
    out = np.zeros((x.shape[0], deltas.shape[0]))
    _play_kernel(np.ascontiguousarray(x, np.float64), np.ascontiguousarray(deltas, np.float64),
                 np.ascontiguousarray(scale, np.float64), out)
    return out


def _moving_average(c: FloatArray, length: int, every: int) -> FloatArray:
    """Moving average of ``length`` samples along axis 0, every ``every``-th (``(Σ_{j<L} c[i+j])/L`` for
    i = 0, every, ...; valid part only)."""
    cs = np.cumsum(np.concatenate([np.zeros((1,) + c.shape[1:]), c]), axis=0)
    out: FloatArray = ((cs[length:] - cs[:-length]) / length)[::every]
    return out


@dataclass
class _Rows:
    """One recording's pieces for the pre-sliding regression (:func:`fit_presliding`)."""

    x: FloatArray          # measured position [m]
    u: FloatArray          # commanded force [N]
    scale: FloatArray      # g(v)/Fs along xf (increment velocity)
    skip: int              # first sample used (room for the largest delay shift and the differences)
    period_s: float
    xf: FloatArray | None = None    # x interpolated to PRESLIDING_UPSAMPLE points a period (None: x itself)
    keep: FloatArray | None = None  # rows used (boolean, after smoothing)
    rest: FloatArray | None = None  # smoothed m·a + F_v·v + F_eff [N]
    y: FloatArray | None = None     # smoothed target force at the current delay [N]

    def smooth(self, c: FloatArray) -> FloatArray:
        """:func:`_moving_average` of ``PRESLIDING_SMOOTH`` samples after ``skip``, every
        ``PRESLIDING_DECIMATE``-th, the kept rows only."""
        out = _moving_average(c[self.skip:], PRESLIDING_SMOOTH, PRESLIDING_DECIMATE)
        return out if self.keep is None else out[self.keep]

    def target(self, delay_s: float) -> FloatArray:
        """``u(t − τ) − m·a − F_v·v − F_eff``, smoothed, with ``τ = delay_s + T/2`` (zero-order hold)."""
        n = self.u.shape[0]
        i = np.arange(n, dtype=np.float64)
        assert self.rest is not None
        return self.smooth(np.interp(i - (delay_s / self.period_s + 0.5), i, self.u)) - self.rest

    def play(self, deltas: FloatArray) -> FloatArray:
        """:func:`_play` along the interpolated path, at the samples: shape (len(x), len(deltas))."""
        if self.xf is None:
            return _play(self.x, deltas, self.scale)
        up = (self.xf.shape[0] - 1) // (self.x.shape[0] - 1)
        return _play(self.xf, deltas, self.scale)[::up]


def upsample_path(x: FloatArray, up: int) -> FloatArray:
    """``x`` interpolated by a not-a-knot cubic spline through the samples to ``up`` points per sampling
    period (``(len(x) − 1)·up + 1`` points, every ``up``-th one a sample)."""
    from scipy.interpolate import CubicSpline

    n = x.shape[0]
    if up <= 1 or n < 4:
        return x
    out: FloatArray = np.asarray(CubicSpline(np.arange(n, dtype=np.float64), x)(
        np.arange((n - 1) * up + 1, dtype=np.float64) / up), np.float64)
    return out


def _presliding_rows(rec: Recorder, mass_kg: float, period_s: float, delay_s: float, sliding: dict[str, float],
                     effects: dict[str, Any] | None) -> _Rows:
    """One recording's path and target force (:func:`fit_presliding`); ``F_eff`` leaves out a cogging force
    (refitted jointly). ``delay_s``: the largest delay the fit will try."""
    from stagectl.friction import StageModel
    from stagectl.schema import load

    T = period_s
    x = np.asarray(rec.col("x"), np.float64)
    u = np.asarray(rec.col("u"), np.float64)
    n = x.shape[0]
    if n < 4 * PRESLIDING_SMOOTH:
        raise DataError("pre-sliding fit: recording too short")
    v = np.gradient(x, T)
    a = np.zeros(n)
    a[1:-1] = (x[2:] - 2.0 * x[1:-1] + x[:-2]) / (T * T)
    fc, fs, vs, dl, fv = (float(sliding[k]) for k in ("fc_n", "fs_n", "vs_m_s", "delta", "viscous_n_s_m"))
    fs = max(fs, fc)
    vb = np.concatenate([[0.0], np.diff(x) / T])  # the increment's velocity, as the plant's GMS step uses
    up = PRESLIDING_UPSAMPLE if n >= 4 else 1
    xf = upsample_path(x, up)
    vf = np.concatenate([[0.0], np.diff(xf) / (T / up)])
    g = fc + (fs - fc) * np.exp(-np.abs(vf / vs) ** dl)
    other = np.zeros(n)
    rest = {k: v_ for k, v_ in (effects or {}).items() if k != "cogging"}
    if rest:
        eff = load(StageModel, {"friction": {"model": "stribeck", "fc_n": 0.0, "fs_n": 0.0}, "effects": rest},
                   "").effects
        other = np.asarray(eff.other_force_array(x), np.float64) + np.asarray(eff.velocity_force_array(v), np.float64)
    r = _Rows(x, u, g / fs, math.ceil(delay_s / T + 0.5) + 2, T, xf=xf if up > 1 else None)
    # rows kept: after the path has left its start by more than twice the largest break-away (the elements'
    # state at the recording's start is unknown; after that move it is the one the play computes), and
    # at least PRESLIDING_SETTLE_S after the last sample faster than PRESLIDING_V_FRACTION of the Stribeck
    # velocity: the fast moves carry no pre-sliding information, and the end of their transients was the
    # largest residual (20 mN for 60 ms after a 10 mm/s move, even for the exact model, against a 1 mN
    # median) and pulled the elements
    moved = np.maximum.accumulate(np.abs(x - x[0])) > 2.0 * PRESLIDING_DELTA_M[1]
    left = r.smooth(moved.astype(np.float64)) >= 1.0
    settle = max(1, round(PRESLIDING_SETTLE_S / T))

    def slow_rows(v_slow: float) -> np.ndarray:
        fast = (np.abs(vb) >= PRESLIDING_V_FRACTION * v_slow).astype(np.float64)
        cf = np.cumsum(np.concatenate([[0.0], fast]))
        recent = cf[1:] - cf[np.maximum(np.arange(1, n + 1) - settle, 0)]  # fast samples in the last settle time
        out: np.ndarray = (r.smooth((recent > 0).astype(np.float64)) == 0.0) & left
        return out

    # (a Stribeck velocity below the slowest constant-velocity pass is an extrapolation: that pass's speed
    # counts instead, or a wrong vs of 32 µm/s, true 0.30 mm/s, left no slow rows on a generated plant) ...
    v_min = float(sliding.get("v_min_m_s", 0.0))
    if "rows_v_m_s" in sliding:  # the caller's speed (the loops' vs search, :func:`_vs_from_loops`)
        keep = slow_rows(float(sliding["rows_v_m_s"]))
    else:
        keep = slow_rows(max(vs, v_min))
    if "rows_v_m_s" not in sliding and v_min > vs and "vs_bound_m_s" in sliding:
        # ... but where the passes only bound vs (stick-slip, ``vs_bound_m_s`` of :func:`_refit_stribeck`), the
        # rows up to that speed include speeds around vs, where the play's scale g(v)/Fs is the curve's
        # steepest function of vs, and the level Σ k_i·Δ_i takes vs's error; below vs/2 the scale is near 1
        # whatever vs is. Fresh plant k111 (tests/commission/plant_kinds.py: Fs 2.057 N, vs 0.314 mm/s, passes
        # from 1 mm/s, vs at the bound 0.285 mm/s): rows to 0.5 mm/s, the level 2.065 N after three refits
        # and creeping to 2.082 N; below vs/2 2.0573 N in two (cosine 85.6 -> 50.0 nm RMS, exact model
        # 2.5 nm). Unless that leaves fewer than PRESLIDING_VS_ROWS_FRACTION of the rows
        narrow = slow_rows(vs)
        if int(narrow.sum()) >= max(10.0, PRESLIDING_VS_ROWS_FRACTION * float(keep.sum())):
            keep = narrow
    if int(keep.sum()) < 10:
        raise DataError("pre-sliding fit: too few slow samples after the first long move")
    r.keep = keep
    r.rest = r.smooth(mass_kg * a + fv * v + other)
    return r


def _presliding_lsq(rows: list[_Rows], deltas: FloatArray, fs: float, wavelength_m: float | None,
                    damping_s: float = 0.0, level_weight: float = PRESLIDING_LEVEL_WEIGHT
                    ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Non-negative least squares for the element stiffnesses at break-away displacements ``deltas`` (and
    a cogging force's sine and cosine amplitudes at ``wavelength_m``, either sign); element ``i`` pulls
    ``k_i·(z_i + c·ż_i)`` with ``c = damping_s`` (stiffness-proportional micro-damping σ1_i = c·k_i, ``ż``
    the backward difference). Returns the stiffnesses, the cogging [sin, cos] amplitudes and the residual."""
    from scipy.optimize import nnls

    blocks: list[FloatArray] = []
    yy: list[FloatArray] = []
    for r in rows:
        assert r.y is not None
        Z = r.play(deltas)
        if damping_s > 0.0:
            Z[1:] += damping_s * np.diff(Z, axis=0) / r.period_s
        cols = [Z]
        if wavelength_m is not None:
            ph = 2.0 * math.pi * r.x / wavelength_m
            sc = np.column_stack([np.sin(ph), np.cos(ph)])
            cols.append(np.hstack([sc, -sc]))
        blocks.append(r.smooth(np.hstack(cols)))
        yy.append(r.y)
    A = np.vstack(blocks)
    y = np.concatenate(yy)
    nd = deltas.shape[0]
    w = level_weight * math.sqrt(y.shape[0])
    crow = np.zeros(A.shape[1])
    crow[:nd] = deltas / fs
    c, _ = nnls(np.vstack([A, w * crow]), np.concatenate([y, [w]]), maxiter=50 * A.shape[1])
    cog = c[nd:nd + 2] - c[nd + 2:nd + 4] if wavelength_m is not None else np.zeros(2)
    return c[:nd], cog, y - A @ c


def fit_presliding(recs: Recorder | list[Recorder], mass_kg: float, period_s: float, delay_s: float,
                   sliding: dict[str, float], effects: dict[str, Any] | None,
                   keep_cogging: bool = False, level_weight: float = PRESLIDING_LEVEL_WEIGHT) -> dict[str, Any]:
    """GMS pre-sliding elements from recordings with reversals, by separable least squares.

    The force balance ``u(t − τ) − m·a − F_v·v − F_eff(x) = Σ_i k_i·(z_i + c·ż_i) + A·sin(2πx/λ + φ)``
    holds with ``z_i`` the element deflections of :func:`_play` for break-away displacements ``Δ_i`` (at
    Fs; scaled by ``g(v)/Fs``, ``g`` the constant-velocity Stribeck curve) along the measured path
    interpolated to ``PRESLIDING_UPSAMPLE`` points a period (:func:`upsample_path`; the turning points of
    the ringing after a fast move fall between samples) and read at the samples, ``c`` a stiffness-proportional
    micro-damping (σ1_i = c·k_i), ``τ`` the force's delay plus half a sample (zero-order hold), ``a`` the
    second difference of ``x``, ``F_eff`` the discovered position-dependent effects other than cogging and
    ``A, λ, φ`` the cogging force (when discover named one; refitted here). For fixed ``Δ_i, c, τ, λ`` the
    force is linear in ``k_i ≥ 0`` and in ``A·cos φ, A·sin φ``: non-negative least squares on the columns
    smoothed by a ``PRESLIDING_SMOOTH``-sample moving average (rows of several recordings stacked), with
    one row weighted by ``level_weight`` (``PRESLIDING_LEVEL_WEIGHT``) for ``Σ k_i·Δ_i = Fs`` (0: the level ``Σ k_i·Δ_i`` is measured and
    returned as ``level_n``; the GMS levels ``α_i = k_i·Δ_i/Σ k_j·Δ_j`` sum to one).
    Only slow rows are used (:func:`_presliding_rows`; ``sliding["rows_v_m_s"]``, when given, is the speed
    that counts for them).

    1. ``Δ_i`` on a fixed log-spaced grid (``PRESLIDING_ELEMENTS`` over ``PRESLIDING_DELTA_M``), ``c = 0``,
       ``τ = delay_s`` (the FRF's);
    2. the grid points that carry stiffness become free ``Δ_i``: ``log Δ_i``, ``λ`` (within −20/+25 %),
       ``c`` and ``τ`` (within ± ``PRESLIDING_DELAY_SPAN`` samples) by bounded nonlinear least squares, the
       linear parameters solved inside each evaluation (variable projection). ``c`` and ``τ`` trade
       (``u(t − τ + c) ≈ u(t − τ) + c·u̇``): their sum is what the data fix.
    The step-2 result is kept when its residual is lower. Why (commissioning test plant, docs/commissioning.md):
    the grid's break-aways fall between the true ones, and the grid alone left 7 mN RMS of feed-forward error
    on a 10 µm reversal against 1–2 mN with the true ``Δ_i``; the FRF's delay is 0.08 ms short, and a
    discover cogging period 1 % off left 20 mN at ±1 mm. Returns the GMS ``k_n_m``, ``alpha`` and
    ``sigma1_n_s_m``, the break-away displacements, ``c`` and ``τ``, the refitted cogging (or None) and the
    residual of step 1 and of the result [N]."""
    from scipy.optimize import least_squares

    T = period_s
    d_lo, d_hi = max(delay_s - PRESLIDING_DELAY_SPAN * T, 0.0), delay_s + PRESLIDING_DELAY_SPAN * T
    rows: list[_Rows] = []
    errors: list[str] = []
    for rec in (recs if isinstance(recs, list) else [recs]):
        try:  # a recording without slow rows is left out; the fit needs one with
            rows.append(_presliding_rows(rec, mass_kg, period_s, d_hi, sliding, effects))
        except DataError as exc:
            errors.append(str(exc))
    if not rows:
        raise DataError(errors[0] if errors else "pre-sliding fit: no recordings")
    for r in rows:
        r.y = r.target(delay_s)
    fs = max(float(sliding["fs_n"]), float(sliding["fc_n"]))
    cog_in = (effects or {}).get("cogging")
    lam0 = float(cog_in["wavelength_m"]) if cog_in else None
    span = max(float(np.ptp(r.smooth(r.x))) for r in rows)
    cog_fixed = lam0 is not None and (keep_cogging or span < COGGING_MIN_PERIODS * lam0)
    if cog_in and cog_fixed:
        # the rows see less than COGGING_MIN_PERIODS periods: the amplitude would trade with the element
        # levels (0.33 N fitted for a true 0.069 N at 1.06 mm over 1 mm of rows, tests/commission/plant_gen.py
        # seed 2); the cogging the slow passes measured over the stroke is subtracted as it is
        for r in rows:
            assert r.rest is not None
            r.rest = r.rest + r.smooth(_cogging_force(cog_in, r.x))
            r.y = r.target(delay_s)
        lam0 = None
    grid = np.geomspace(*PRESLIDING_DELTA_M, PRESLIDING_ELEMENTS)
    k0, cog0, res0 = _presliding_lsq(rows, grid, fs, lam0, level_weight=level_weight)
    # step 2: the stiff grid points, free; with the cogging period, the micro-damping and the delay
    d0 = grid[k0 > 0]
    nd = d0.shape[0]
    lo, hi = math.log(PRESLIDING_DELTA_M[0]), math.log(PRESLIDING_DELTA_M[1])
    cg = [math.log(lam0)] if lam0 is not None else []
    p0 = np.concatenate([np.clip(np.log(d0), lo, hi), cg, [0.5, delay_s / T]])
    lb = np.concatenate([np.full(nd, lo), [math.log(0.8 * lam0)] if lam0 is not None else [], [0.0, d_lo / T]])
    ub = np.concatenate([np.full(nd, hi), [math.log(1.25 * lam0)] if lam0 is not None else [],
                         [PRESLIDING_MAX_DAMPING, d_hi / T]])

    def unpack(p: FloatArray) -> tuple[FloatArray, float | None, float, float]:
        return (np.exp(p[:nd]), (math.exp(float(p[nd])) if lam0 is not None else None), float(p[-2]) * T,
                float(p[-1]) * T)

    cache: dict[float, list[FloatArray]] = {}

    def solve(p: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        d, lam, c, dl = unpack(p)
        if dl not in cache:
            cache.clear()
            cache[dl] = [r.target(dl) for r in rows]
        for r, y in zip(rows, cache[dl], strict=True):
            r.y = y
        return _presliding_lsq(rows, d, fs, lam, c, level_weight)

    deltas, k, cog, resid, lam, c, delay = grid, k0, cog0, res0, lam0, 0.0, delay_s
    if nd:
        # lsmr: the exact trust-region solver's SVD of the (rows × parameters) Jacobian was 60 % of the time
        sol = least_squares(lambda p: solve(p)[2], p0, bounds=(lb, ub), method="trf", diff_step=1e-3,
                            tr_solver="lsmr", ftol=1e-6, xtol=1e-6, max_nfev=PRESLIDING_MAX_EVALS)
        k1, cog1, res1 = solve(sol.x)
        if float(np.sqrt(np.mean(res1 ** 2))) < float(np.sqrt(np.mean(res0 ** 2))):
            (deltas, lam, c, delay), k, cog, resid = unpack(sol.x), k1, cog1, res1
        if lam0 is not None and lam is not None and abs(math.log(lam / lam0)) > PRESLIDING_LAMBDA_EDGE:
            # the period ran to its bound: the rows (clustered where the stage stands and reverses) do not
            # fix the cogging; the slow passes' cogging (over the whole stroke) is kept as it is. Generated
            # plant 3: 1.338 mm at the +25 % bound, phase 0.27 rad, for a true 1.135 mm (slow passes 1.073 mm,
            # phase 0): triangle 259 nm against 84 nm with the exact model; with the period alone kept the
            # refitted phase stayed 0.27 rad (297 nm)
            out = fit_presliding(recs, mass_kg, period_s, delay_s, sliding, effects, keep_cogging=True,
                                 level_weight=level_weight)
            out["cogging_period_at_bound_m"] = lam
            return out
    # the evidence: the same regression with one element of the smallest break-away (a rigid friction that
    # keeps the last direction's level: what a model without pre-sliding predicts at the slow rows), at the
    # chosen delay, cogging period and damping
    for r in rows:
        r.y = r.target(delay)
    _k, _c, res_rigid = _presliding_lsq(rows, np.array([PRESLIDING_DELTA_M[0]]), fs, lam)
    keep = k > 0
    order = np.argsort(deltas[keep])
    kk, dd = k[keep][order], deltas[keep][order]
    alpha = kk * dd / fs
    cogging = dict(cog_in) if cog_in and cog_fixed else None
    if lam is not None:
        amp = float(np.hypot(cog[0], cog[1]))
        cogging = {"amplitude_n": amp, "wavelength_m": float(lam), "phase_rad": float(math.atan2(cog[1], cog[0]))}
    yy = np.concatenate([r.y for r in rows if r.y is not None])
    return {"k_n_m": [float(v_) for v_ in kk], "alpha": [float(v_) for v_ in alpha / alpha.sum()],
            "sigma1_n_s_m": [float(c * v_) for v_ in kk], "damping_s": c, "delay_s": delay,
            "break_away_m": [float(v_) for v_ in dd], "cogging": cogging, "cogging_refitted": not cog_fixed,
            "rows_span_m": span,
            "residual_rms_n": float(resid.std()), "grid_residual_rms_n": float(res0.std()),
            "rigid_residual_rms_n": float(res_rigid.std()), "level_n": float(np.sum(kk * dd)),
            "evidence_ratio": float(res_rigid.std() / max(float(resid.std()), 1e-12)),
            "force_rms_n": float(yy.std()), "samples": int(yy.shape[0])}



def presliding_recordings(recordings: Mapping[str, Recorder], mass_kg: float, period_s: float,
                          sliding: dict[str, float]) -> list[Recorder]:
    """The recordings the pre-sliding regression (:func:`fit_presliding`) reads: the experiments designed for
    it, ``PRESLIDING_RECORDINGS`` (nested reversals, pre-sliding loops: slow moves, every turning point on
    the sampled path); ``PRESLIDING_FALLBACK`` (the constant-velocity passes) only when these leave no slow
    rows. The passes' slow rows follow stops from up to the velocity limit, after which the stage rings at
    its pre-sliding resonance ``√(Σk_i/m)/2π``, up to a third of the sampling rate on a light stiff stage,
    with turning points no interpolation of the samples recovers: the element states the play computes then
    stay off the plant's for as long as the stage stands (generated plant 29, tests/commission/plant_gen.py,
    0.60 kg on 2.1·10⁶ N/m: 296 Hz; with the plant's own model, mass and delay the residual was 5.3 mN RMS on
    the passes' rows, up to 38 mN, against 0.6-0.8 mN on the reversals and loops). The regression bent the
    elements and the level to fit them: the 10 µm cosine tracked 211 nm RMS against 146 nm without the passes
    (exact model 77 nm); gen 34 11.3 → 5.1 nm (exact 4.2 nm)."""
    designed = [recordings[k] for k in PRESLIDING_RECORDINGS if k in recordings]
    for rec in designed:
        try:
            _presliding_rows(rec, mass_kg, period_s, period_s, sliding, None)
            return designed
        except DataError:
            continue
    return designed + [recordings[k] for k in PRESLIDING_FALLBACK if k in recordings]


def _settled_cruise_rows(rec: Recorder, mass_kg: float, period_s: float
                         ) -> tuple[FloatArray, FloatArray, FloatArray, np.ndarray]:
    """Position x [m], the force less inertia y = u − m·ẍ [N] (ẍ by central differences), the reference
    speed v_ref [m/s], and the mask of rows at least ``COGGING_SETTLE_S`` into a cruise (v_ref ≠ 0, a_ref = 0)."""
    T = period_s
    x = np.asarray(rec.col("x"), np.float64)
    u = np.asarray(rec.col("u"), np.float64)
    vr = np.asarray(rec.col("v_ref"), np.float64)
    ar = np.asarray(rec.col("a_ref"), np.float64)
    n = x.shape[0]
    a = np.zeros(n)
    a[1:-1] = (x[2:] - 2.0 * x[1:-1] + x[:-2]) / (T * T)
    cruise = (np.abs(vr) > 0.0) & (ar == 0.0)
    settle = max(1, round(COGGING_SETTLE_S / T))
    run = np.zeros(n, np.int64)
    for i in range(1, n):
        run[i] = run[i - 1] + 1 if cruise[i] else 0
    return x, u - mass_kg * a, vr, cruise & (run >= settle)


def slow_pass_slope(rec: Recorder, mass_kg: float, period_s: float,
                    cogging: Mapping[str, Any] | None = None) -> float:
    """The position force's slope along the stroke [N/m] (a spring's stiffness, 0 for an offset) from the slow
    passes (:func:`slow_pass_levels`); 0 when the passes do not cover both directions."""
    lv = slow_pass_levels(rec, mass_kg, period_s, cogging)
    return 0.0 if lv is None else lv[1]


def slow_pass_levels(rec: Recorder, mass_kg: float, period_s: float,
                     cogging: Mapping[str, Any] | None = None) -> tuple[float, float, float] | None:
    """The slow passes' even part [N], slope along the stroke [N/m] and travel [m]: ``y = u − m·ẍ`` at the
    settled cruise rows (:func:`_settled_cruise_rows`), less the cogging when given, regressed on a constant
    per direction ``c₊, c₋`` (the sliding friction plus what the stage needs either way) and one slope in ``x``
    common to both directions (a position force does not depend on the direction). The even part is
    ``(c₊ + c₋)/2`` at the rows' mean position (an offset, or a spring's force there). None when the passes do
    not cover both directions."""
    f = _slow_pass_fit(rec, mass_kg, period_s, cogging)
    return None if f is None else (f["even_n"], f["slope_n_m"], f["travel_m"])


def _slow_pass_fit(rec: Recorder, mass_kg: float, period_s: float,
                   cogging: Mapping[str, Any] | None = None) -> dict[str, float] | None:
    """:func:`slow_pass_levels`' regression with what a spring's rest position needs besides: the rows' mean
    position ``x_mean_m`` [m] (where the even part is), the odd part ``(c₊ − c₋)/2`` [N] and the mean
    speed [m/s]."""
    x, y, vr, ok = _settled_cruise_rows(rec, mass_kg, period_s)
    if cogging is not None:
        y = y - _cogging_force(cogging, x)
    pos, neg = ok & (vr > 0), ok & (vr < 0)
    if pos.sum() < 10 or neg.sum() < 10:
        return None
    sel = pos | neg
    xm = float(np.mean(x[sel]))
    A = np.column_stack([pos[sel].astype(np.float64), neg[sel].astype(np.float64), x[sel] - xm])
    th = np.linalg.lstsq(A, y[sel], rcond=None)[0]
    return {"even_n": float(0.5 * (th[0] + th[1])), "slope_n_m": float(th[2]), "travel_m": float(np.ptp(x[sel])),
            "x_mean_m": xm, "odd_n": float(0.5 * (th[0] - th[1])), "speed_m_s": float(np.mean(np.abs(vr[sel])))}


#: a spring discover named takes its stiffness and rest position from the slow passes when their slope has
#: its sign and lies within this factor of its stiffness (the factor the offset's two experiments must agree
#: within, analysis.OFFSET_AGREEMENT)
SPRING_AGREEMENT = 2.0


def slow_pass_spring(rec: Recorder, mass_kg: float, period_s: float, spring: Mapping[str, Any],
                     effects: Mapping[str, Any], cogging: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The spring ``k·(x − x0)`` that discover named (``spring``: its ``stiffness_n_m``, ``x0_m``), measured
    on the slow passes over the stroke (:func:`slow_pass_levels`' regression).

    ``k`` is the passes' slope; their even part ``ē`` at their mean position ``x̄`` is what the stage needs
    there whichever way it moves: ``ē = k·(x̄ − x0) + F_0 + r·ō + d_v·|v|`` with the other named effects'
    even parts (an ``offset`` ``F_0``; an ``asymmetry`` ``r`` times the passes' friction level ``ō =
    (c₊ − c₋)/2``; a ``viscous_asymmetry`` ``d_v`` at their speed), so ``x0 = x̄ − (ē − F_0 − r·ō −
    d_v·|v|)/k``. A spring and a constant force are confounded over a stroke unless both directions are
    read at the same positions, which the slow passes do and discover's estimation set (the nested
    reversals, held near the stroke's centre, read jointly with the pre-sliding elements) does not: on fresh
    plant k111 of tests/commission/plant_kinds.py (444.74 N/m, x0 −198.0 µm) discover fitted 453.0 N/m,
    x0 −208.8 µm (4.8 mN off everywhere), the slow passes 443.8 N/m, −198.0 µm, and the constant-velocity
    passes' even part (another experiment) −198.5 µm. ``used``: the passes cover both directions and their
    slope has discover's sign within ``SPRING_AGREEMENT``×; otherwise discover's spring stands (``reason``)."""
    k_d = float(spring.get("stiffness_n_m", 0.0))
    out: dict[str, Any] = {"used": False, "discover": {k: float(v) for k, v in spring.items()}}
    f = _slow_pass_fit(rec, mass_kg, period_s, cogging)
    if f is None:
        return {**out, "reason": "the slow passes do not cover both directions"}
    k = f["slope_n_m"]
    out.update(f)
    if not (k * k_d > 0 and max(abs(k), abs(k_d)) <= SPRING_AGREEMENT * min(abs(k), abs(k_d))):
        return {**out, "reason": f"the slow passes' slope {k:.4g} N/m does not confirm discover's {k_d:.4g} N/m"}
    other = float((effects.get("offset") or {}).get("force_n", 0.0))
    other += float((effects.get("asymmetry") or {}).get("ratio", 0.0)) * f["odd_n"]
    other += float((effects.get("viscous_asymmetry") or {}).get("difference_n_s_m", 0.0)) * f["speed_m_s"]
    x0 = f["x_mean_m"] - (f["even_n"] - other) / k
    return {**out, "used": True, "stiffness_n_m": k, "x0_m": float(x0), "other_even_n": other}


def _cogging_scan(x: FloatArray, y: FloatArray, nuis: FloatArray, lams: FloatArray) -> FloatArray:
    """Amplitudes of ``a·sin(2πx/λ) + b·cos(2πx/λ)`` fitted to ``y`` jointly with the nuisance columns, for
    each ``λ`` in ``lams``; returns (len(lams), 4): amplitude [N], ``a``, ``b``, residual sum of squares [N²]."""
    q, _ = np.linalg.qr(nuis)
    y0 = y - q @ (q.T @ y)
    out = np.zeros((lams.shape[0], 4))
    for i, lam in enumerate(lams.tolist()):
        ph = 2.0 * math.pi * x / lam
        sc = np.column_stack([np.sin(ph), np.cos(ph)])
        sc -= q @ (q.T @ sc)
        ab = np.linalg.lstsq(sc, y0, rcond=None)[0]
        r = y0 - sc @ ab
        out[i] = (math.hypot(ab[0], ab[1]), ab[0], ab[1], float(r @ r))
    return out


def cogging_evidence(rec: Recorder, mass_kg: float, period_s: float) -> dict[str, Any]:
    """Is there a position-periodic force the same in both directions? From the slow passes.

    The force ``y = u − m·a`` at the constant-velocity rows of each pass (after ``COGGING_SETTLE_S``),
    smoothed by a ``COGGING_SMOOTH``-sample moving average, is regressed on ``A·sin(2πx/λ + φ)`` plus, per
    direction, a constant and a slope in ``x`` (the sliding friction's level and an offset or spring), for
    ``λ`` from ``COGGING_MIN_SAMPLES`` row spacings to the travel over ``COGGING_MIN_PERIODS``,
    on a grid whose phase error over the travel ``L`` stays below π/4 (``Δλ = λ²/(8L)``). Evidence: the
    peak amplitude over the median amplitude of the scan (the floor of what the residual's noise and
    unmodelled force give at any period); and the two directions fitted separately at the peak's ``λ`` agree
    in phase within 45° and in amplitude within 2× (a cogging force does not depend on the direction; a
    friction ripple changes sign with it). Named when the ratio ≥ ``COGGING_EVIDENCE_RATIO``, the
    directions agree and the peak is inside the scan (below ``COGGING_EDGE_FRACTION`` of its longest period:
    a smooth force along the pass, e.g. a spring's curvature, peaks at that edge) or, at that edge, keeps
    ``COGGING_EDGE_KEEP`` of its amplitude with a per-direction cubic in ``x`` added; confidence ``high`` at
    twice the ratio. Returns the decision, the ratio, ``A, λ, φ``."""
    x, y, vr, ok = _settled_cruise_rows(rec, mass_kg, period_s)

    def sm(c: FloatArray) -> FloatArray:
        return _moving_average(c, COGGING_SMOOTH, COGGING_DECIMATE)

    okd = sm(ok.astype(np.float64)) == 1.0
    xs, ys, ds = sm(x)[okd], sm(y)[okd], np.sign(sm(vr))[okd]
    none: dict[str, Any] = {"present": False, "confidence": "none", "ratio": 0.0, "rows": int(xs.shape[0])}
    if xs.shape[0] < 50 or not ((ds > 0).any() and (ds < 0).any()):
        return {**none, "reason": "too few constant-velocity rows in both directions"}
    span = float(xs.max() - xs.min())
    dx = float(np.median(np.abs(np.diff(xs))))
    lam_lo, lam_hi = max(COGGING_MIN_SAMPLES * dx, 1e-9), span / COGGING_MIN_PERIODS
    if lam_lo >= lam_hi:
        return {**none, "reason": f"travel too short for {COGGING_MIN_PERIODS:g} periods"}
    lams = [lam_lo]
    while lams[-1] < lam_hi:
        lams.append(lams[-1] + lams[-1] ** 2 / (8.0 * span))
    grid = np.array(lams)
    xc = xs - 0.5 * (xs.max() + xs.min())
    pos, neg = (ds > 0).astype(np.float64), (ds < 0).astype(np.float64)
    nuis = np.column_stack([pos, neg, pos * xc, neg * xc])
    amp = _cogging_scan(xs, ys, nuis, grid)
    i = int(np.argmax(amp[:, 0]))
    # refine between the second neighbours, by least squares (the lowest residual): the largest amplitude
    # is biased where few periods fit the travel, since the nuisance slope takes a part of the sinusoid that
    # grows with λ (generated plant 3, 1.135 mm over 2 mm: 1.073 mm by amplitude, 1.135 mm by residual; the
    # commissioned triangle 157 nm against 95 nm with the true period)
    hi = grid[min(i + 2, grid.shape[0] - 1)]
    if grid[i] >= COGGING_EDGE_FRACTION * lam_hi:
        # a peak at the scan's edge: the least-squares period may lie beyond it, up to one period over the
        # travel (a 1.412 mm cogging over 1.86 mm of settled rows read 1.336 mm at the grid's end)
        hi = max(hi, span)
    fine = np.linspace(grid[max(i - 2, 0)], hi, 81)
    famp = _cogging_scan(xs, ys, nuis, fine)
    j = int(np.argmin(famp[:, 3]))
    lam, A, ca, cb = float(fine[j]), float(famp[j, 0]), float(famp[j, 1]), float(famp[j, 2])
    floor = float(np.median(amp[:, 0]))
    ratio = A / max(floor, 1e-12)
    per_dir = []
    for m_ in (pos, neg):
        sel = m_ > 0
        r = _cogging_scan(xs[sel], ys[sel], np.column_stack([np.ones(int(sel.sum())), xc[sel]]), np.array([lam]))
        per_dir.append(r[0])
    dphi = abs(math.remainder(math.atan2(per_dir[0][2], per_dir[0][1]) - math.atan2(per_dir[1][2], per_dir[1][1]),
                              2.0 * math.pi))
    amp_ratio = max(per_dir[0][0], per_dir[1][0]) / max(min(per_dir[0][0], per_dir[1][0]), 1e-12)
    agree = dphi < math.pi / 4 and amp_ratio < 2.0
    # a peak at the longest period scanned is no period: a smooth force along the pass (a spring's curvature,
    # a slow transient) peaks there too, since the scan's sinusoids are the closest thing to it it has
    at_edge = lam >= COGGING_EDGE_FRACTION * lam_hi
    extra: dict[str, Any] = {}
    trend = False
    if at_edge and ratio >= COGGING_EVIDENCE_RATIO and j == fine.shape[0] - 1 and hi >= span:
        # the least squares still falls at one period over the travel, the longest allowed: no period was
        # found, the force only rises or bends along the stroke (a cable carrier's saturating pull, |x|);
        # one hump of a sinusoid is not told from such a force (plain-simulation oracle, both were named)
        trend = True
        extra["reason"] = (f"the least-squares period runs to the travel ({span * 1e3:.3g} mm): a smooth trend "
                           "along the stroke, not a period; only a longer stroke could tell them apart")
    elif at_edge and ratio >= COGGING_EVIDENCE_RATIO:
        # told from a smooth trend by the curvature terms: refit the sinusoid at λ with, per direction, a
        # constant, x, x² and x³; a sinusoid keeps its amplitude, a trend goes to the polynomial
        xn = xc / max(0.5 * span, 1e-12)
        cubic = np.column_stack([nuis, pos * xn ** 2, neg * xn ** 2, pos * xn ** 3, neg * xn ** 3])
        a_cubic = float(_cogging_scan(xs, ys, cubic, np.array([lam]))[0, 0])
        extra["amplitude_with_cubic_n"] = a_cubic
        trend = a_cubic < COGGING_EDGE_KEEP * A or a_cubic / max(floor, 1e-12) < COGGING_EVIDENCE_RATIO
        if trend:
            extra["reason"] = (f"the peak is at the longest period scanned ({lam * 1e3:.3g} mm, travel "
                               f"{span * 1e3:.3g} mm) and a cubic along the pass takes it ({A * 1e3:.3g} → "
                               f"{a_cubic * 1e3:.3g} mN): a smooth trend, not a period; only a longer stroke "
                               "could tell them apart")
    speeds = _cogging_speed_check(xs, ys, np.abs(sm(vr)[okd]), ds, lam, A, math.atan2(cb, ca))
    if speeds:
        extra["speeds"] = speeds
        slow = [s_ for s_ in speeds if s_["in_phase_n"] < COGGING_SPEED_FRACTION * A]
        if ratio >= COGGING_EVIDENCE_RATIO and agree and not trend and slow:
            trend = True  # not a trend, but refused as well: the reason says why
            extra["reason"] = (
                f"the {lam * 1e3:.3g} mm period is not a force of position: the passes at "
                + ", ".join(f"{1e3 * s_['speed_m_s']:.3g}" for s_ in slow) + " mm/s show "
                + ", ".join(f"{1e3 * s_['in_phase_n']:.3g}" for s_ in slow)
                + f" mN of its {1e3 * A:.3g} mN in its phase (needs {100 * COGGING_SPEED_FRACTION:.0f} %): a ripple "
                "periodic in time at one speed (a limit cycle), whose wavelength follows the speed")
    present = bool(ratio >= COGGING_EVIDENCE_RATIO and agree and not trend)
    conf = "none" if not present else ("high" if ratio >= 2 * COGGING_EVIDENCE_RATIO else "moderate")
    return {**extra, "present": present, "confidence": conf, "ratio": ratio, "floor_n": floor, "amplitude_n": A,
            "wavelength_m": lam, "phase_rad": float(math.atan2(cb, ca)), "directions_phase_deg": math.degrees(dphi),
            "directions_amplitude_ratio": float(amp_ratio), "rows": int(xs.shape[0]),
            "scan_m": [lam_lo, lam_hi, int(grid.shape[0])]}


#: a cogging is a force of position alone, so every speed of the slow-pass recording (the passes and the
#: slower moves to and from them) that covers one of its periods with COGGING_SPEED_MIN_ROWS smoothed rows
#: must show at least this fraction of its amplitude in its phase (:func:`_cogging_speed_check`). A ripple
#: periodic in time (a stick-slip limit cycle at f) reads as λ = v/f at one speed v and not at another.
#: Measured: a 1 kg GMS stage with a spring and no cogging limit-cycled at 35 Hz in the 1.5 mm/s passes
#: (115 mN at λ = 40 µm, in both directions) and showed 0.03 mN of it at 0.3 mm/s over 4.4 mm
COGGING_SPEED_FRACTION = 0.5
COGGING_SPEED_MIN_ROWS = 50
#: speeds within this relative distance are one speed
COGGING_SPEED_GROUP = 0.1


def _cogging_speed_check(xs: FloatArray, ys: FloatArray, speed: FloatArray, ds: FloatArray, lam: float,
                         amp_n: float, phase_rad: float) -> list[dict[str, Any]]:
    """Per speed ``|v_ref|`` (grouped within ``COGGING_SPEED_GROUP``) whose rows span at least one period ``λ``
    with ``COGGING_SPEED_MIN_ROWS`` rows: ``y`` regressed on a constant and a slope in ``x`` per direction plus
    ``a·sin(2πx/λ) + b·cos(2πx/λ)``, and the amplitude in the pooled phase ``φ``, ``a·cos φ + b·sin φ`` [N].
    Empty when fewer than two speeds qualify (one speed cannot tell position from time)."""
    speed = np.round(speed, 9)
    order = np.unique(speed)
    groups: list[list[float]] = []
    for v in order.tolist():
        if v <= 0.0:
            continue
        if groups and v <= groups[-1][0] * (1.0 + COGGING_SPEED_GROUP):
            groups[-1].append(v)
        else:
            groups.append([v])
    out: list[dict[str, Any]] = []
    u = np.array([math.cos(phase_rad), math.sin(phase_rad)])
    for g in groups:
        sel = (speed >= g[0]) & (speed <= g[-1])
        if int(sel.sum()) < COGGING_SPEED_MIN_ROWS or float(np.ptp(xs[sel])) < lam:
            continue
        xx, dd = xs[sel], ds[sel]
        xc = xx - 0.5 * (xx.max() + xx.min())
        cols = []
        for d in (1.0, -1.0):
            m_ = (dd == d).astype(np.float64)
            if m_.sum() > 0:
                cols += [m_, m_ * xc]
        r = _cogging_scan(xx, ys[sel], np.column_stack(cols), np.array([lam]))[0]
        p = float(u @ r[1:3])
        out.append({"speed_m_s": float(np.median(speed[sel])), "rows": int(sel.sum()), "amplitude_n": float(r[0]),
                    "in_phase_n": p, "fraction": p / max(amp_n, 1e-300)})
    return out if len(out) >= 2 else []


#: a cogging the slow passes show is named only when the constant-velocity passes, a second experiment over the
#: same positions that its period and phase were not fitted on, show at least this fraction of its amplitude
#: in its phase, at least COGGING_CONFIRM_SIGMA standard errors above zero (:func:`cogging_confirmation`)
COGGING_CONFIRM_FRACTION = 0.5
COGGING_CONFIRM_SIGMA = 3.0


def cogging_confirmation(rec: Recorder, mass_kg: float, period_s: float, ce: Mapping[str, Any]) -> dict[str, Any]:
    """Does a held-out experiment show the cogging the slow passes found? ``rec`` is the constant-velocity
    passes (``friction_cv``): the force ``y = u − m·a`` at their settled rows, smoothed and decimated as in
    :func:`cogging_evidence`, is regressed on ``a·sin(2πx/λ) + b·cos(2πx/λ)`` at the slow passes' ``λ``
    (fixed) plus a constant per pass (each speed and direction has its own friction level) and a slope in
    ``x`` per direction. The amplitude in the slow passes' phase ``φ`` is the projection
    ``p = a·cos φ + b·sin φ``; its standard error ``σ_p`` from the residual (``s²·(AᵀA)⁻¹``, inflated by the
    ``COGGING_SMOOTH/COGGING_DECIMATE`` rows a smoothed sample spans). Confirmed when ``p >=
    COGGING_CONFIRM_FRACTION·A`` and ``p >= COGGING_CONFIRM_SIGMA·σ_p``.

    A cogging is a force of position alone, so every pass over the same positions carries it; what one
    experiment's period scan picks out of a slow transient or a settling controller does not recur in the
    other. Measured (docs/commissioning.md §4): on ten generated plants with a hidden cogging the passes
    show 0.99–1.03 of the slow passes' amplitude; on the 30 kg axis of fresh plant k109 (no cogging) the slow
    passes' scan peaked at 68 mN, 6.97 mm (ratio 48, "high") and the passes show 0.00 of it."""
    lam, A, phi = float(ce["wavelength_m"]), float(ce["amplitude_n"]), float(ce.get("phase_rad", 0.0))
    x, y, vr, ok = _settled_cruise_rows(rec, mass_kg, period_s)

    def sm(c: FloatArray) -> FloatArray:
        return _moving_average(c, COGGING_SMOOTH, COGGING_DECIMATE)

    okd = sm(ok.astype(np.float64)) == 1.0
    out: dict[str, Any] = {"experiment": "friction_cv", "confirmed": False, "amplitude_n": 0.0}
    seg = np.cumsum(np.diff(okd.astype(np.int64), prepend=0) == 1)[okd]  # one id per settled cruise (a pass)
    xs, ys, vs = sm(x)[okd], sm(y)[okd], sm(vr)[okd]
    if xs.shape[0] < 50 or float(np.ptp(xs)) < lam:
        return {**out, "reason": f"{xs.shape[0]} settled rows over {1e3 * float(np.ptp(xs)) if xs.size else 0.0:.3g} "
                                 f"mm: too few to cover one period ({1e3 * lam:.3g} mm)"}
    xc = xs - 0.5 * (xs.max() + xs.min())
    cols = [(seg == k).astype(np.float64) for k in np.unique(seg)]
    cols += [(vs > 0) * xc, (vs < 0) * xc]
    ph = 2.0 * math.pi * xs / lam
    X = np.column_stack([*cols, np.sin(ph), np.cos(ph)])
    th, _, rank, _ = np.linalg.lstsq(X, ys, rcond=None)
    if rank < X.shape[1]:
        return {**out, "reason": "the passes cannot separate the period from their levels and slopes"}
    r = ys - X @ th
    s2 = float(r @ r) / max(X.shape[0] - X.shape[1], 1) * (COGGING_SMOOTH / COGGING_DECIMATE)
    cov = s2 * np.linalg.inv(X.T @ X)[-2:, -2:]
    u = np.array([math.cos(phi), math.sin(phi)])
    p = float(u @ th[-2:])
    sd = float(math.sqrt(max(float(u @ cov @ u), 0.0)))
    ok_ = p >= COGGING_CONFIRM_FRACTION * A and p >= COGGING_CONFIRM_SIGMA * sd
    out.update(confirmed=bool(ok_), amplitude_n=p, amplitude_std_n=sd, fraction=p / max(A, 1e-300),
               rows=int(xs.shape[0]))
    if not ok_:
        out["reason"] = (f"the constant-velocity passes show {1e3 * p:.3g} ± {1e3 * sd:.2g} mN of it in its phase "
                         f"({100 * p / max(A, 1e-300):.0f} % of the slow passes' {1e3 * A:.3g} mN; needs "
                         f"{100 * COGGING_CONFIRM_FRACTION:.0f} % and {COGGING_CONFIRM_SIGMA:g} standard errors): "
                         "not a force of position")
    return out


def cogging_decided(recs: Mapping[str, Recorder], mass_kg: float, period_s: float) -> dict[str, Any]:
    """The slow passes' cogging evidence (:func:`cogging_evidence`), named only when the constant-velocity
    passes confirm it (:func:`cogging_confirmation`; its figures under ``held_out``)."""
    ce = cogging_evidence(recs["slow_passes"], mass_kg, period_s)
    if ce["present"] and "friction_cv" in recs:
        conf = cogging_confirmation(recs["friction_cv"], mass_kg, period_s, ce)
        ce["held_out"] = conf
        if not conf["confirmed"]:
            ce.update(present=False, confidence="none", reason=conf["reason"])
    return ce


#: a friction ripple discover names is kept only when the slow passes show at least this fraction of the
#: force it predicts there (see :func:`ripple_evidence`)
RIPPLE_CONFIRM_FRACTION = 0.5


def ripple_evidence(rec: Recorder, mass_kg: float, period_s: float, ripple: dict[str, Any],
                    level_n: float) -> dict[str, Any]:
    """Does the slow passes' force show the friction ripple discover named? ``F·(1 + a·sin(2πx/λ + φ))``
    changes sign with the direction, so at the settled rows of the slow passes (as :func:`cogging_evidence`,
    not smoothed: λ may be a few µm) the force ``u − m·a`` is regressed on, per direction, a constant and a
    slope in ``x``, plus ``d·(s·sin(2πx/λ) + c·cos(2πx/λ))`` with ``d`` = ±1 the direction; the amplitude
    ``hypot(s, c)`` is compared with the predicted ``a·level_n``. Confirmed when it reaches
    ``RIPPLE_CONFIRM_FRACTION`` of it and the passes sample λ with at least 4 rows per period; otherwise the
    ripple is not backed by the experiment designed for position-dependent effects and is left out.
    Generated plant 38 (no ripple): discover named λ = 1.6 µm, a = 0.16 (25 mN predicted), accepted as a
    pair with a true offset on the reversals/passes validation; it made the cosine 270× the exact model's."""
    x, y, vr, ok = _settled_cruise_rows(rec, mass_kg, period_s)
    lam, amp = float(ripple["wavelength_m"]), float(ripple["amplitude"])
    predicted = abs(amp * level_n)
    d = np.sign(vr[ok])
    out: dict[str, Any] = {"wavelength_m": lam, "predicted_n": predicted, "present": False}
    if ok.sum() < 50 or not ((d > 0).any() and (d < 0).any()):
        return {**out, "reason": "too few slow-pass rows in both directions"}
    # the spatial sampling: the travel per row at the passes' speed, or the sensor's quantum (the smallest
    # step it reports) where that is coarser (a 1 µm quantum at 0.3 µm per row: most rows repeat the position,
    # the median step is 0 and λ = 1.6 µm looked sampled 1.6e9 times per period)
    dx = np.abs(np.diff(x[ok]))
    moved = dx[dx > 0.0]
    step = max(float(np.median(np.abs(vr[ok]))) * period_s, float(moved.min()) if moved.size else 0.0)
    out["rows_per_period"] = lam / max(step, 1e-15)
    if out["rows_per_period"] < 4.0:
        return {**out, "reason": f"the slow passes sample λ = {lam:.3g} m with {out['rows_per_period']:.2g} rows "
                                 "per period (< 4): the ripple cannot be checked"}
    xs, ys = x[ok], y[ok]
    xc = xs - 0.5 * (xs.max() + xs.min())
    pos, neg = (d > 0).astype(np.float64), (d < 0).astype(np.float64)
    r = _cogging_scan(xs, d * ys, np.column_stack([pos, neg, pos * xc, neg * xc]), np.array([lam]))
    out["measured_n"] = float(r[0, 0])
    out["present"] = bool(r[0, 0] >= RIPPLE_CONFIRM_FRACTION * predicted)
    if not out["present"]:
        out["reason"] = (f"the slow passes show {1e3 * r[0, 0]:.3g} mN at λ = {lam:.3g} m, the ripple predicts "
                         f"{1e3 * predicted:.3g} mN")
    return out


def to_recording(rec: Recorder, name: str, step: int = 1) -> Recording:
    """A loop recording as an identification recording (t, x, u, x_ref, v), every ``step``-th sample with
    ``u`` averaged over the ``step`` samples it replaces (the zero-order-hold force over the longer interval)."""
    n = (rec.n // step) * step
    u = np.array(rec.col("u"))[:n].reshape(-1, step).mean(axis=1)
    return Recording(t=np.array(rec.col("t"))[:n:step], x=np.array(rec.col("x"))[:n:step], u=u,
                     x_ref=np.array(rec.col("x_ref"))[:n:step], v=np.array(rec.col("v"))[:n:step],
                     source=f"recordings/{name}.csv")


#: the constant-velocity Stribeck curve's Fs counts as measured when at least this fraction of its excess
#: Fs − Fc is left at the slowest pass (exp(−(v_min/vs)^δ)); below, Fs comes from the pre-sliding level
STRIBECK_OBSERVED_FRACTION = 0.5
#: at most this many refits with Fs held at the pre-sliding level, until the level changes by less than
#: STRIBECK_LEVEL_TOLERANCE (generated plant 12: 1.914 N from the extrapolated curve, then 1.756, true 1.729)
STRIBECK_REFITS = 3
STRIBECK_LEVEL_TOLERANCE = 0.005
#: the Stribeck shape exponent held when the passes stick-slipped (the Gaussian curve, δ = 2, the most common
#: shape and the shipped models'): the sliding passes then see only the curve's tail, which any δ fits with a
#: matching vs (:func:`_refit_stribeck`)
STRIBECK_DELTA_UNOBSERVED = 2.0
#: ... and its vs at least the fastest stick-slipping pass's speed over this ratio: there the Gaussian curve's
#: slope −dF/dv is still 0.45 of its steepest (at vs/√2); beyond 2·vs it is 0.07
STICK_SLIP_VS_RATIO = math.sqrt(2.0)
#: the bound on vs is kept while the fit's RMS stays within twice the free fit's or this [N]
STICK_SLIP_BOUND_RMS_N = 1e-3


#: the pre-sliding level replaces the passes' Fs when it differs from it by more than this many of the
#: points' median standard error ... (:func:`_level_within_passes`)
STRIBECK_LEVEL_Z = 3.0
#: ... and the curve with Fs held there raises the passes' χ² by at most this (χ²₁ at 95 %)
STRIBECK_LEVEL_CHI2 = 3.84


def _held_delta(fr: dict[str, Any]) -> float | None:
    """The passes' shape exponent δ when :func:`stagectl.commission.analysis._stribeck_shape` held it (the
    passes did not fix it: a refit keeps it), else None (free)."""
    return float(fr["delta"]) if fr.get("delta_held") else None


def _level_within_passes(level: float, fr: dict[str, Any], cv_points: tuple[FloatArray, ...],
                         sig: FloatArray | None, err: FloatArray) -> dict[str, Any] | None:
    """The sliding curve with Fs held at the pre-sliding ``level`` [N] when the passes measured the curve's
    dip (:func:`_refit_stribeck`) but not its end at rest, and allow the level: None unless ``|level − Fs|``
    exceeds ``STRIBECK_LEVEL_Z`` median point errors (``err``, :func:`stagectl.commission.analysis.stribeck_point_errors`)
    and the held curve raises ``χ² = Σ_pairs (r_i/err_i)²`` by at most ``STRIBECK_LEVEL_CHI2`` (the level
    within the passes' 95 % profile-likelihood interval of Fs).

    The level ``Σ k_i·Δ_i`` is measured at rest; the passes' Fs below the slowest pass is an extrapolation
    of the fitted shape. Generated plant 38 (Fs 0.5707 N, vs 0.355 mm/s, δ 2; slowest pass 0.16 mm/s, where
    72 % of the excess is left): the passes' curve took Fs 0.5849 N with δ 1.57 (12 mN high at 30 µm/s), the
    level 0.5718 N; Fs held there the passes' χ² rose by 0.9 and the curve took vs 0.352 mm/s, δ 1.96. The
    pre-sliding elements fitted on the passes' curve were 2-5 % off in the largest break-aways (1.1 mN
    residual; on the true curve 0.4 mN and within 0.5 %), and the cosine tracked 2.2× the exact model's."""
    from stagectl.commission.analysis import stribeck_curve_at
    from stagectl.ident.identify import fit_stribeck_curve

    v, f = cv_points[0], cv_points[1]
    n = v.size // 2
    gap = abs(level - float(fr["fs_n"]))
    if n < 1 or gap <= STRIBECK_LEVEL_Z * float(np.median(err[:n])):
        return None
    held = fit_stribeck_curve(v, f, fs_n=level, sigma_n=sig, delta=_held_delta(fr))

    def chi2(c: dict[str, Any]) -> float:  # (the points are odd parts mirrored: no offset)
        r = (f - stribeck_curve_at({**c, "offset_n": 0.0}, v)) / err
        return float(np.sum(r[:n] ** 2))

    rise = chi2(held) - chi2(fr)
    if not rise <= STRIBECK_LEVEL_CHI2:
        return None
    out: dict[str, Any] = dict(held, level_chi2_rise=rise, level_gap_n=gap)
    out["fs_n"] = max(float(out["fs_n"]), float(out["fc_n"]))
    return out


def _refit_stribeck(presliding: dict[str, Any], fr: dict[str, Any],
                    cv_points: tuple[FloatArray, ...] | None, force: bool = False) -> dict[str, Any] | None:
    """The sliding curve refitted with Fs held at the pre-sliding level when the passes' Fs is an
    extrapolation (:func:`fit_models`); None when the passes measured it or there is nothing to refit.
    Generated plant 12 (tests/commission/plant_gen.py: Fs 1.73 N, vs 0.30 mm/s, slowest pass 0.16 mm/s):
    the passes alone gave Fs 2.30 N at vs 32 µm/s, δ 0.5, and the commissioned cosine was 12 µm RMS against
    14 nm with the exact model."""
    from stagectl.ident.identify import fit_stribeck_curve

    if cv_points is None or presliding["evidence_ratio"] < PRESLIDING_EVIDENCE_RATIO:
        return None
    v_min, vs, dl = float(fr.get("v_min_m_s", 0.0)), float(fr["vs_m_s"]), float(fr["delta"])
    # passes left out as stick-slip (analysis.cv_segments): the dip lies below the slowest sliding pass, so
    # whatever the free curve made of Fs there is an extrapolation (generated plant 36: Fc 0 N, vs 51 mm/s on
    # a plain simulation of it, or Fs 0.62 N for a true 0.78 N)
    stick_slip = float(fr.get("stick_slip_m_s", 0.0)) > 0.0
    level = float(presliding["level_n"])
    # the points' standard errors when the passes' curve was weighted (analysis.stribeck_point_errors), and
    # about the curve
    sig = cv_points[2] if len(cv_points) > 2 and cv_points[2].size else None
    err = cv_points[3] if len(cv_points) > 3 else None
    if not force and not stick_slip and (v_min <= 0.0 or fr["fs_n"] <= fr["fc_n"]
                      or math.exp(-((v_min / vs) ** dl)) >= STRIBECK_OBSERVED_FRACTION):
        if v_min <= 0.0 or fr["fs_n"] <= fr["fc_n"] or err is None or not level > 0.0:
            return None
        return _level_within_passes(level, fr, cv_points, sig, err)
    if not level > 0.0:
        return None
    if not stick_slip:
        out: dict[str, Any] = dict(fit_stribeck_curve(cv_points[0], cv_points[1], fs_n=level, sigma_n=sig,
                                                      delta=_held_delta(fr)))
    else:
        # δ held, and vs at least the fastest stick-slipping pass's speed over STICK_SLIP_VS_RATIO: a pass
        # stick-slips only where the curve still falls steeply. Fresh plant k111 (vs 0.31 mm/s, passes from
        # 1 mm/s, whose means show none of the dip) took vs 50 µm/s, the grid's end, and its cosine was 41x
        # the exact model's. The bound stays only while it costs the fit no more than the pairs' scatter
        free = fit_stribeck_curve(cv_points[0], cv_points[1], fs_n=level, delta=STRIBECK_DELTA_UNOBSERVED,
                                  sigma_n=sig)
        out = dict(free)
        v_ss = float(fr["stick_slip_m_s"]) / STICK_SLIP_VS_RATIO
        if free["vs_m_s"] < v_ss:
            bound = fit_stribeck_curve(cv_points[0], cv_points[1], fs_n=level, delta=STRIBECK_DELTA_UNOBSERVED,
                                       vs_min_m_s=v_ss, sigma_n=sig)
            if bound["rms_n"] <= max(2.0 * free["rms_n"], STICK_SLIP_BOUND_RMS_N):
                out = dict(bound, vs_bound_m_s=v_ss, free_vs_m_s=free["vs_m_s"])
    out["fs_n"] = max(float(out["fs_n"]), float(out["fc_n"]))
    return out


#: the loops' Stribeck velocity search (:func:`_vs_from_loops`): the level held by a row of this weight,
#: log vs to this tolerance, and kept only when it lowers the loops' residual by at least this fraction
VS_LOOPS_LEVEL_WEIGHT = 10.0
VS_LOOPS_XTOL = 0.01
VS_LOOPS_MIN_GAIN = 0.05


def _vs_from_loops(recs: list[Recorder], mass_kg: float, period_s: float, delay_s: float, fr: dict[str, Any],
                   effects: dict[str, Any] | None) -> dict[str, Any] | None:
    """The Stribeck velocity from the pre-sliding loops where the passes only bound it (vs below the slowest
    pass's speed ``v_min``, at the stick-slip bound; :func:`fit_models` calls it then): the loops' rows up to
    ``v_min``/2 pass through speeds around vs, where the play's scale ``g(v)/Fs`` falls with the curve. With
    the level held at ``fr["fs_n"]`` (measured on the rows below vs, where the scale is ~1:
    :func:`_presliding_rows`) the elements are fitted on those rows for each vs in
    ``[max(bound, v_min/20), v_min]`` (bound: the fastest stick-slipping pass's speed over
    ``STICK_SLIP_VS_RATIO``), and the vs of the lowest residual is returned (bounded scalar search on log vs)
    when it lowers the residual at ``fr["vs_m_s"]`` by at least ``VS_LOOPS_MIN_GAIN``; None when vs is
    observed or nothing is gained. Not where the passes' tail fixed vs (fresh plant k112: the passes' vs
    right, the loops' minimum 10 % above it). With the level free, vs and the level trade (fresh plant k111: 2.070 N at
    vs 0.285 mm/s, 2.057 N at 0.314); held, the residual has one minimum: 6.8 mN at the stick-slip bound
    0.285 mm/s, 2.5-2.7 mN at 0.31-0.314 mm/s (true 0.314), 13 mN at 0.36."""
    from scipy.optimize import minimize_scalar

    v_min = float(fr.get("v_min_m_s", 0.0))
    vs0 = float(fr["vs_m_s"])
    if not (v_min > vs0 > 0.0) or not float(fr["fs_n"]) > float(fr["fc_n"]):
        return None
    ss = float(fr.get("stick_slip_m_s", 0.0))
    lo = max(ss / STICK_SLIP_VS_RATIO, v_min / 20.0)
    if not lo < v_min:
        return None

    def resid(log_vs: float) -> float:
        sl = dict(fr, vs_m_s=math.exp(log_vs), rows_v_m_s=v_min)
        return float(fit_presliding(recs, mass_kg, period_s, delay_s, sl, effects,
                                    level_weight=VS_LOOPS_LEVEL_WEIGHT)["residual_rms_n"])

    r0 = resid(math.log(vs0))
    sol = minimize_scalar(resid, bounds=(math.log(lo), math.log(v_min)), method="bounded",
                          options={"xatol": VS_LOOPS_XTOL})
    vs, r1 = math.exp(float(sol.x)), float(sol.fun)
    out = {"vs_m_s": vs, "residual_rms_n": r1, "from_vs_m_s": vs0, "from_residual_rms_n": r0,
           "range_m_s": [lo, v_min], "evaluations": int(sol.nfev) + 1, "level_n": float(fr["fs_n"])}
    return out if r1 <= (1.0 - VS_LOOPS_MIN_GAIN) * r0 else None


def _cogging_force(cog: Mapping[str, Any], x_m: FloatArray) -> FloatArray:
    """The force ``A·sin(2πx/λ + φ)`` [N] at ``x_m`` [m] of a cogging given as ``amplitude_n``, ``wavelength_m``,
    ``phase_rad``: the model's own definition (:class:`~stagectl.friction.effects.Cogging`)."""
    c = Cogging(amplitude_n=float(cog["amplitude_n"]), wavelength_m=float(cog["wavelength_m"]),
                phase_rad=float(cog.get("phase_rad", 0.0)))
    return Effects(cogging=c).other_force_array(x_m)


def reconcile_mass(mass_kg: float, mass_id_kg: float | None) -> tuple[float, str | None]:
    """The mass the model and the gains use [kg], and the report's note on it (None when nothing to say).

    ``mass_kg`` is the FRF's (or the probe's, when the FRF's was not credible), ``mass_id_kg`` the
    inverse-dynamics regression's over the passes' ramps. With ``r = m_id/m``:

    * ``|r − 1| ≤ MASS_DISAGREEMENT`` (20 %): the FRF mass, no note;
    * ``1/MASS_ID_MAX_RATIO ≤ r ≤ MASS_ID_MAX_RATIO`` otherwise: the inverse-dynamics mass (an FRF on a
      stage held by its friction measures the friction, not the mass), with a note;
    * outside: the FRF mass, with a note. The FRF mass used here already passed ``FRF_MASS_PLAUSIBLE``
      against the probe with a relative std of at most ``FRF_MASS_MAX_REL_STD`` (25 %): a factor 2 is 4σ of
      the loosest FRF mass admitted, more than its uncertainty explains, so the inverse-dynamics regression
      is the suspect (a cogging left in the ramps with a wrong phase gave 1.6–4.9 kg for a 0.79 kg stage).
    """
    if mass_id_kg is None or not math.isfinite(mass_id_kg) or abs(mass_id_kg / mass_kg - 1) <= MASS_DISAGREEMENT:
        return mass_kg, None
    r = mass_id_kg / mass_kg
    head = (f"the FRF mass {mass_kg:.4g} kg and the inverse-dynamics mass {mass_id_kg:.4g} kg of the "
            f"constant-velocity passes differ by more than {100 * MASS_DISAGREEMENT:.0f} %")
    if 1.0 / MASS_ID_MAX_RATIO <= r <= MASS_ID_MAX_RATIO:
        return float(mass_id_kg), (f"{head}: the FRF probably measured a stage held by its friction; the model "
                                   "and the gains use the inverse-dynamics mass")
    return mass_kg, (f"{head} by more than a factor {MASS_ID_MAX_RATIO:g}, which the FRF's uncertainty (at most "
                     f"{100 * an.FRF_MASS_MAX_REL_STD:.0f} %) does not explain: the model and the gains keep the "
                     "FRF mass (the inverse-dynamics regression is suspect: a cogging or an offset left in its ramps)")


def _discover_reversals(rec: Recorder, val: Recording, mass_kg: float, step: int
                        ) -> tuple[Any, str, str | None]:
    """``discover`` on the nested reversals (estimation) validated on ``val``: (its result or None, the
    estimation set's name, a line for the report or None).

    The reversals are first decimated by ``step`` (discover's cost grows with the samples); that halves the
    low-pass cut-off of :func:`stagectl.ident.signals.prepare`, whose position noise is the scatter about the
    low-pass, so a stage that rings or stick-slips above the lower cut-off reads as a noisy sensor and too few
    samples count as moving (fresh plant k112: 0.32 µm "noise" at 500 Hz, 20 usable samples; 0.17 µm and 141 at
    the loop rate, for a 1 nm encoder). A ``DataError`` there is retried at the loop rate; a second one leaves
    discover out (None): the model is then what the dedicated experiments measured, and the report says so."""
    x = np.asarray(rec.col("x"), np.float64)
    start = Hyp(fixed_mass_kg=mass_kg, x_center_m=float(0.5 * (x.min() + x.max())))
    failed: list[str] = []
    for s in dict.fromkeys((step, 1)):
        est = to_recording(rec, "reversals", s)
        try:
            d = discover(est, validate=val, start=start)
        except DataError as exc:
            failed.append(f"at {1.0 / (s * float(np.median(np.diff(rec.col('t'))))):.4g} Hz: {exc}")
            continue
        name = est.source if s == step else f"{est.source} (every sample)"
        return d, name, (None if not failed else "discover ran on the reversals at the loop rate (decimated "
                         + failed[0] + ")")
    return None, "none", ("discover skipped (the model is the constant-velocity passes' sliding curve with the "
                          "cogging and pre-sliding that their own experiments decide; offset, spring, ripple and "
                          "asymmetry were not searched): " + "; ".join(failed))


def fit_models(recordings: dict[str, Recorder], mass_kg: float, period_s: float,
               sliding: dict[str, float] | None = None,
               delay_s: float | None = None,
               cv_points: tuple[FloatArray, ...] | None = None,
               cv_segments: list[an.CvSegment] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """The discovery summary and the model file's mapping (module docstring). ``sliding``: the Stribeck
    curve of the constant-velocity segment means (``fc_n, fs_n, vs_m_s, delta, viscous_n_s_m``), which
    replaces the discovered sliding levels when given (a direct measurement of exactly these parameters;
    discover fits them jointly with the pre-sliding elements, whose damping can trade with the viscous
    term). ``cv_points``: the segment means (velocities [m/s], forces [N]) that curve was fitted to; when the
    curve has dropped by more than ``1 − STRIBECK_OBSERVED_FRACTION`` of its excess at the slowest speed (its
    Fs is an extrapolation) and pre-sliding is named, the curve is refitted with Fs held at the pre-sliding
    level ``Σ k_i·Δ_i`` and the elements fitted again on it (:func:`_refit_stribeck`). ``cv_segments``: the
    passes' segment means with the position force taken off; with them and the slow passes the passes decide
    the offset (:func:`stagectl.commission.analysis.offset_evidence`) unless discover named an effect that
    contains one (a spring, an asymmetry)."""
    res_recordings = recordings
    # a second, independent mass: the inverse-dynamics regression (m·a + Coulomb + viscous) over the
    # acceleration ramps of the constant-velocity passes (ident.identify.measure), less the cogging
    from stagectl.ident.identify import measure

    # a cogging the slow passes show is taken off the passes' force first: over a ramp it correlates with
    # the acceleration (generated plant 44: a 0.113 N, 1.41 mm cogging made the inverse-dynamics mass
    # 1.002 kg, true 0.786, FRF 0.731; with it taken off 0.744 kg, and the FRF mass stays)
    cv_rec = to_recording(res_recordings["friction_cv"], "friction_cv")
    spring_n_m = 0.0
    ce0: dict[str, Any] = {}
    lv0: tuple[float, float, float] | None = None
    if "slow_passes" in res_recordings:
        ce0 = cogging_decided(res_recordings, mass_kg, period_s)
        if ce0["present"]:
            cv_rec.u = cv_rec.u - _cogging_force(ce0, cv_rec.x)
        # and so does a spring: the passes accelerate at one end of their range and brake at the other, so
        # k·x reads as −m·a (fresh plant k111 of tests/commission/plant_kinds.py, 445 N/m over ±1 mm: 2.56 kg
        # for 3.37, which replaced the probe's 3.367); its slope along the slow passes is taken off first
        # (slow_pass_slope's: the levels' slope)
        lv0 = slow_pass_levels(res_recordings["slow_passes"], mass_kg, period_s, ce0 if ce0["present"] else None)
        spring_n_m = 0.0 if lv0 is None else lv0[1]
        cv_rec.u = cv_rec.u - spring_n_m * (cv_rec.x - float(np.mean(cv_rec.x)))
    try:
        m_id = measure(cv_rec).mass_kg
    except DataError:
        m_id = None
    m, warning = reconcile_mass(mass_kg, m_id)
    # discover's cost grows with the samples: the loop rate is decimated to at most DISCOVER_RATE_HZ
    step = max(1, round(1.0 / (period_s * DISCOVER_RATE_HZ)))
    val = to_recording(res_recordings["friction_cv"], "friction_cv", step)
    d, est, skipped = _discover_reversals(res_recordings["reversals"], val, m, step)
    if d is not None:
        spec = hyp_to_spec(d.final.hyp, {"source": "stagectl commission"})
    elif sliding is not None:
        # nothing for discover to read: the model is what the dedicated experiments measured (the passes'
        # sliding curve; cogging and pre-sliding below), without discover's search for the other effects
        spec = {"friction": {"model": "stribeck", "lag_s": 0.0}, "meta": {"source": "stagectl commission"}}
    else:
        raise DataError(skipped or "discover: no estimation data")
    spec["mass_kg"] = float(m)
    fr = spec["friction"]
    if sliding is not None and fr.get("model") in ("gms", "stribeck"):
        fr.update({k: float(sliding[k]) for k in ("fc_n", "fs_n", "vs_m_s", "delta", "viscous_n_s_m")})
        fr["fs_n"] = max(fr["fs_n"], fr["fc_n"])
    # the dedicated experiments decide cogging and pre-sliding (discover's acceptance, a validation on the
    # constant-velocity passes, is reported beside): cogging from the slow passes, pre-sliding from the
    # Maxwell-slip regression on the reversals and loops against a rigid friction (docs/commissioning.md §4)
    names = {e.name for e in d.effects} if d is not None else set()
    decided: dict[str, dict[str, Any]] = {}
    offset_passes: dict[str, Any] | None = None
    spring_passes: dict[str, Any] | None = None
    effects = dict(spec.get("effects") or {})
    if "slow_passes" in res_recordings:
        # with the mass unchanged by reconcile_mass (the common case) the cogging and the levels found above for
        # the mass regression are the same computation: reused; a reconciled mass changes u − m·ẍ, recomputed
        same_mass = m == mass_kg
        ce = dict(ce0) if same_mass else cogging_decided(res_recordings, m, period_s)
        ce["discover"] = "cogging" in names
        decided["cogging"] = ce
        if ce["present"]:  # the slow passes' period scan covers every period; discover's search may not
            effects["cogging"] = {k: ce[k] for k in ("amplitude_n", "wavelength_m", "phase_rad")}
        elif not ce["present"] and "cogging" in effects:
            del effects["cogging"]
        if "position_ripple" in effects:  # discover named it: the slow passes must show it (ripple_evidence)
            assert d is not None  # (a discovered effect)
            re_ = ripple_evidence(res_recordings["slow_passes"], m, period_s, effects["position_ripple"],
                                  float(fr.get("fc_n", d.final.hyp.theta.get("fc", 0.0))))
            ratio = float(re_.get("measured_n", 0.0)) / max(float(re_["predicted_n"]), 1e-12)
            decided["position_ripple"] = {**re_, "ratio": ratio, "discover": True,
                                          "confidence": "moderate" if re_["present"] else "none"}
            if not re_["present"]:
                del effects["position_ripple"]
        if cv_segments is not None:
            # the offset: the passes' even part, confirmed along the stroke by the slow passes. discover's
            # validation on the passes rejected true offsets of 5 % of Coulomb (generated plants 3 and 61: the
            # gap fell 4 and 13 %, short of its 20 %, the rest of the gap being the sliding levels it fits
            # jointly with pre-sliding), which the passes measure to 0.1-0.5 mN (docs/commissioning.md §4)
            lv = (lv0 if same_mass else
                  slow_pass_levels(res_recordings["slow_passes"], m, period_s, ce if ce["present"] else None))
            oe = an.offset_evidence(cv_segments, None if lv is None else lv[0], 0.0 if lv is None else lv[1],
                                    0.0 if lv is None else lv[2])
            oe["discover"] = "offset" in names
            holders = {k for k, inner in REGISTRY.nested().items() if "offset" in inner and k in names}
            r_d = float((effects.get("asymmetry") or {}).get("ratio", 0.0))
            # how many of the passes' standard errors discover's asymmetry ratio lies from theirs
            miss = an.asymmetry_miss(oe, r_d) if holders == {"asymmetry"} else 0.0
            if miss > oe.get("joint_t_needed", math.inf):
                # the passes refute it: its even part would grow with the friction level, theirs is a constant
                # (generated plant 38: discover's r = 0.105 for a 52 mN offset; the passes allow r = 0.006 ±
                # 0.001, their even parts 52.0-53.6 mN over friction levels 0.49-0.76 N)
                decided["asymmetry"] = {
                    "present": False, "discover": True, "confidence": "none", "ratio": miss / oe["joint_t_needed"],
                    "reason": f"the passes' even part is a constant {oe['force_n']:+.4g} N (an offset): they allow "
                              f"r = {oe['asymmetry_ratio']:+.3g} ± {oe['asymmetry_std']:.2g}, not {r_d:+.3g}"}
                effects.pop("asymmetry", None)
            elif holders:  # its constant part is the offset (docs/discovery.md §2): discover's verdict stands
                oe.update(decided=False, reason=f"discover named {', '.join(sorted(holders))}, which contains "
                                                "an offset")
            if oe["decided"]:
                decided["offset"] = oe
                if oe["present"]:
                    effects["offset"] = {"force_n": float(oe["force_n"])}
                else:
                    effects.pop("offset", None)
            offset_passes = oe
        if "spring" in effects:
            # discover's spring, read with the pre-sliding elements on the reversals near the stroke's centre,
            # has its constant part confounded with them; the slow passes measure it (slow_pass_spring)
            spring_passes = slow_pass_spring(res_recordings["slow_passes"], m, period_s, effects["spring"],
                                             effects, ce if ce["present"] else None)
            if spring_passes["used"]:
                effects["spring"] = {k: spring_passes[k] for k in ("stiffness_n_m", "x0_m")}
        if effects:
            spec["effects"] = effects
        else:
            spec.pop("effects", None)
    presliding: dict[str, Any] | None = None
    if sliding is not None and fr.get("model") in ("gms", "stribeck"):
        fr["v_min_m_s"] = float(sliding.get("v_min_m_s", 0.0))
        fr["stick_slip_m_s"] = float(sliding.get("stick_slip_m_s", 0.0))
        if sliding.get("delta_held"):  # the passes did not fix δ (analysis._stribeck_shape): the refits keep it
            fr["delta_held"] = 1.0
        pre_recs = presliding_recordings(res_recordings, m, period_s, fr)
        tau = period_s if delay_s is None else delay_s
        try:
            presliding = fit_presliding(pre_recs, m, period_s, tau, fr, spec.get("effects"))
            refit = _refit_stribeck(presliding, fr, cv_points)
            if refit is not None:
                # the level depends on the curve (the play's scale g(v)/Fs): refit until it holds still
                refit["extrapolated_fs_n"], levels = fr["fs_n"], [presliding["level_n"]]
                for i in range(STRIBECK_REFITS):
                    cur = dict(fr, **refit)
                    presliding = fit_presliding(pre_recs, m, period_s, tau, cur, spec.get("effects"))
                    levels.append(presliding["level_n"])
                    if abs(levels[-1] / levels[-2] - 1.0) < STRIBECK_LEVEL_TOLERANCE or i == STRIBECK_REFITS - 1:
                        break
                    nxt = _refit_stribeck(presliding, fr, cv_points, force=True) or {}
                    if nxt:  # (a bound an earlier refit needed and this one does not is not kept)
                        refit.pop("vs_bound_m_s", None)
                        refit.pop("free_vs_m_s", None)
                    refit.update(nxt)
                refit["levels_n"] = levels
                fr.update({k: refit[k] for k in ("fc_n", "fs_n", "vs_m_s", "delta", "viscous_n_s_m")})
                # vs below the slowest pass: the loops' rows around it decide it, the level held
                vl = None
                if "vs_bound_m_s" in refit:  # the passes only bound vs (stick-slip)
                    # held at the level the curve was refitted with, fr["fs_n"] (the last pre-sliding fit's
                    # level_n is within STRIBECK_LEVEL_TOLERANCE of it once the refits have converged, further
                    # after STRIBECK_REFITS that have not): vs is searched at one level; the loops refitted below
                    # with the vs found give the level_n the model then carries (fr["fs_n"] further down)
                    vl = _vs_from_loops(pre_recs, m, period_s, tau, fr, spec.get("effects"))
                if vl is not None:
                    fr["vs_m_s"] = refit["vs_m_s"] = vl["vs_m_s"]
                    presliding = fit_presliding(pre_recs, m, period_s, tau,
                                                dict(fr, vs_bound_m_s=refit["vs_bound_m_s"]), spec.get("effects"))
                    refit["vs_loops"] = vl
                presliding = dict(presliding, stribeck_refit=refit)
        except DataError as exc:
            presliding = {"error": str(exc)}
        fr.pop("v_min_m_s", None)
        fr.pop("stick_slip_m_s", None)
        fr.pop("delta_held", None)
        if "error" not in presliding:
            ratio = presliding["evidence_ratio"]
            present = bool(ratio >= PRESLIDING_EVIDENCE_RATIO and len(presliding["k_n_m"]) > 0)
            decided["presliding"] = {
                "present": present, "ratio": ratio, "discover": fr.get("model") == "gms",
                "confidence": "none" if not present else ("high" if ratio >= 2 * PRESLIDING_EVIDENCE_RATIO
                                                          else "moderate"),
                "residual_rms_n": presliding["residual_rms_n"],
                "rigid_residual_rms_n": presliding["rigid_residual_rms_n"]}
            if presliding["cogging"] is not None and "cogging" in spec.get("effects", {}):
                spec["effects"]["cogging"] = dict(presliding["cogging"])
            if present:
                fr["model"] = "gms"
                for key in ("lag_s", "stick_velocity_m_s"):  # the GMS has its own slip dynamics (c_n_s)
                    fr.pop(key, None)
                fr["k_n_m"], fr["alpha"] = presliding["k_n_m"], presliding["alpha"]
                # the break-away level the elements measured at pre-sliding speeds (Σ k_i·Δ_i)
                fr["fs_n"] = presliding["level_n"]
                fr["sigma1_n_s_m"] = presliding["sigma1_n_s_m"]
                # slip attraction: a slipping element reaches its level within a tenth of a period
                fr["c_n_s"] = float(10.0 * fr["fs_n"] / period_s)
            else:
                fr["model"] = "stribeck"
                for key in ("k_n_m", "alpha", "sigma1_n_s_m", "c_n_s"):
                    fr.pop(key, None)
    accepted = [plain(e.as_json(), json=True) for e in d.effects] if d is not None else []
    rejected = [plain(e.as_json(), json=True) for e in d.rejected] if d is not None else []
    for name, ev in decided.items():
        mine = [e for e in accepted + rejected if e.get("name") == name]
        accepted = [e for e in accepted if e.get("name") != name]
        rejected = [e for e in rejected if e.get("name") != name]
        entry = dict(mine[0]) if mine else {"name": name, "parameters": {}}
        entry["evidence"] = ev
        by = {"presliding": "presliding regression", "offset": "friction_cv even part, slow_passes",
              "asymmetry": "friction_cv even part"}
        entry["decided_by"] = by.get(name, "slow_passes") + (
            f": ratio {ev['ratio']:.3g}, confidence {ev['confidence']}"
            f" (discover {'accepted' if ev['discover'] else 'rejected'} it)")
        if name in ("cogging", "offset") and ev["present"]:
            if entry["parameters"]:
                entry["discover_parameters"] = entry["parameters"]
            keys = ("amplitude_n", "wavelength_m", "phase_rad") if name == "cogging" else ("force_n",)
            entry["parameters"] = {k: ev[k] for k in keys}
        (accepted if ev["present"] else rejected).append(entry)
    for entry in accepted:
        if entry.get("name") == "spring" and spring_passes is not None and spring_passes["used"]:
            entry["discover_parameters"] = entry.get("parameters", {})
            entry["parameters"] = {k: spring_passes[k] for k in ("stiffness_n_m", "x0_m")}
            entry["decided_by"] = "discover; stiffness and rest position from slow_passes (slope, even part)"
    discovery: dict[str, Any] = {
        "estimation": est, "validation": val.source,
        "gap_before_n": d.gap_before if d is not None else math.nan,
        "gap_after_n": d.gap_after if d is not None else math.nan,
        "effects": accepted,
        "rejected": rejected,
        "evidence": decided,
        "coulomb_n": float(d.final.hyp.theta.get("fc", math.nan)) if d is not None else math.nan,
        "viscous_n_s_m": float(d.final.hyp.theta.get("fv", math.nan)) if d is not None else math.nan,
        "elapsed_s": d.elapsed_s if d is not None else 0.0,
        "mass_kg_inverse_dynamics": m_id,
        "inverse_dynamics_spring_n_m": spring_n_m,
        "mass_kg_used": m,
        "presliding_regression": presliding,
        "offset_passes": offset_passes,
        "spring_passes": spring_passes,
    }
    if warning is not None:
        discovery["mass_warning"] = warning
    if skipped is not None:
        discovery["discover_skipped" if d is None else "discover_note"] = skipped
    model_spec: dict[str, Any] = plain(spec, json=True)
    try:
        from stagectl.ident.identify import identify

        gi = identify(to_recording(res_recordings["reversals"], "reversals"), "gms", mass_kg=m)
        discovery["reversals_gms"] = {"friction": plain(gi.spec, json=True),
                                          "fit": plain(gi.quality.get("fit", {}), json=True)}
    except DataError as exc:
        discovery["reversals_gms"] = {"error": str(exc)}
    return discovery, model_spec
