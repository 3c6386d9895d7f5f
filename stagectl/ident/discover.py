"""The discovery workflow: find where model and measurement disagree, name the missing effect, add it,
show the validation gap shrink, iterate (issue 6).

Gap metric (``GAP_METRIC``): **filtered inverse-dynamics force residual, RMS [N], on validation data**::

    r = L[moving · (ū_τ − m·a − F_model(x, v) − F_other(x))]        (see stagectl.ident.signals)

evaluated on moving samples away from stick phases. It is a closed-loop-safe metric: it needs no
integration of the plant (an open-loop replay of a double integrator drifts) and is insensitive to the
controller. Validation data is the ``--validate`` recording, or contiguous held-out blocks of the same file
(block ``k`` of ``HOLDOUT_BLOCKS`` equal blocks, with a guard of filter length removed at each boundary).

Decision rule (docs/discovery.md §4): each round every catalogue effect not in the model is added in turn,
refitted on estimation data and scored on validation data. An effect is *acceptable* if

1. the validation gap shrinks by at least ``MIN_REL_GAIN`` (relative), a margin above what noise-only
   recordings with a complete model reach (the null tests in ``tests/ident`` measure it),
2. the force it explains, ``sqrt(gap_before² − gap_after²)``, is at least ``MIN_EXPLAINED_FRACTION`` of
   the RMS non-inertial force ``ū − m̂·a`` and ``MIN_EXPLAINED_NOISE`` times the sensor-noise floor of the metric, and
3. the mean per-sample reduction of the squared residual is positive at the 97.5 % level of a circular
   block bootstrap (block length from the autocorrelation of the per-sample gain, >= 0.1 s).

An effect that acts in one regime (``EffectSpec.regime``: pre-sliding and backlash near reversals, Stribeck
and frictional lag at low speed) is also acceptable when these tests pass on the validation samples of its
regime and the global gap does not get worse (docs/discovery.md §7). A fit at or beyond a physical bound
(``EffectSpec.bounds``), without gain on estimation data, or whose defining evidence the validation data do not
resolve (``EffectSpec.resolved``: a backlash that leaves the friction on the motor must show the load's lost
inertia above the explained-force floor, docs/discovery.md §10) is never acceptable. A richer effect is also tried
jointly with the simpler one it contains (``asymmetry+offset``), so that neither is fitted with the other frozen;
forms that occur together are tried jointly too (``viscous_asymmetry+offset``: independent viscous and Coulomb
asymmetries, ``EffectSpec.tried_with``).

Among acceptable candidates the one with the smallest validation gap is named, except that a simpler candidate
(fewer effects, or one the chosen contains) that it does not beat significantly is preferred (parsimony);
unrelated candidates that fit within ``TIE_MARGIN`` and are not significantly different are reported as a tie
with the experiment that would separate them. Every candidate carries its verdict (accepted, superseded,
rejected and why) into the report. Rejected candidates (fit on estimation data but fail on
validation data) are reported with their figures. Rounds repeat until nothing more is accepted.

Two refinements of the greedy search:

* **pairs**: when no single effect validates, pairs of the best-fitting candidates are tried (interacting
  effects, e.g. an offset and a cogging whose position coverage differs between estimation and validation
  blocks, each biasing the other's fit alone); a pair must pass the same test;
* **pruning**: at the end, an accepted effect that later, richer effects made redundant (an offset accepted
  before the asymmetry or spring that contains it) is removed when the model without it is not
  significantly worse; it is then listed under ``rejected`` with the reason.

Stick phases (docs/discovery.md §5) are excluded explicitly (see :mod:`stagectl.ident.signals`); a frictional lag
shorter than two samples is treated as no lag; ripple/cogging phases are fitted on estimation data only, so a
phase-locked ripple that does not transfer fails validation and is rejected (§6).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from stagectl.errors import DataError
from stagectl.ident import effects as fx
from stagectl.ident import regress as rg
from stagectl.ident.hypothesis import FitResult, Hyp
from stagectl.ident.localise import Disagreement, ResidualView, localise, regimes
from stagectl.ident.recording import Recording
from stagectl.ident.results import (
    BOOT_QUANTILE,
    BOOT_SAMPLES,
    MIN_REL_GAIN,
    AcceptedEffect,
    Candidate,
    CandidateError,
    CandidateFit,
    Comparison,
    RejectedEffect,
    Round,
    compare,
)
from stagectl.ident.signals import Signals, prepare

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

__all__ = ["BOOT_QUANTILE", "BOOT_SAMPLES", "GAP_METRIC", "MIN_EXPLAINED_FRACTION", "MIN_EXPLAINED_NOISE",
           "MIN_REL_GAIN", "Dataset", "DiscoveryResult", "compare", "discover", "fit_candidate", "fit_start", "gap",
           "localise", "make_dataset", "regimes"]

GAP_METRIC = (
    "force_residual_rms_n: RMS [N] of the zero-phase low-pass filtered inverse-dynamics force residual "
    "L[ū_τ − m·a − F_friction(x,v) − F_other(x)] on validation data, moving samples outside stick phases "
    "(ZOH-consistent: the second difference of x is paired with the hat-kernel average of the held, possibly "
    "delayed force; (u[k−1]+u[k])/2 without delay)"
)
#: minimum force an effect must explain on validation data, sqrt(gap_before² − gap_after²): the larger of
#: MIN_EXPLAINED_FRACTION of the RMS non-inertial force ū − m̂·a (physically negligible below) and MIN_EXPLAINED_NOISE
#: times the sensor-noise floor of the metric (m·σ_x·gain; at a few times that floor, sampling and
#: discretisation residue, not physics, is what a flexible effect fits)
MIN_EXPLAINED_FRACTION = 0.002
MIN_EXPLAINED_NOISE = 1.5
HOLDOUT_BLOCKS = 6
HOLDOUT_VALIDATION = (1, 4)
PAIR_CANDIDATES = 4
#: fewest validation samples in an effect's regime for the regime-aware test (docs/discovery.md §7)
MIN_REGIME_SAMPLES = 40
#: candidates whose validation gaps are within this fraction of each other (and not significantly different)
#: are reported as a tie the data cannot separate
TIE_MARGIN = 0.03
#: a candidate that cannot be fitted on these data (recorded as a CandidateError, not raised)
_FIT_ERRORS = (ValueError, np.linalg.LinAlgError)


# ================================================================================================ data
@dataclass
class Dataset:
    """Estimation and validation signals with their evaluation rows."""

    est: Signals
    est_rows: BoolArray
    val: Signals
    val_rows: BoolArray
    split: str
    val_rec: Recording | None = None  # the recording the validation signals come from (filter checks)
    alt: dict[str, Signals] = field(default_factory=dict)  # validation signals at other filter cut-offs

    @property
    def val_regimes(self) -> dict[str, BoolArray]:
        """Regime masks of the validation data (:func:`stagectl.ident.localise.regimes`), computed once."""
        got = self.val.cache.get("regimes:" + str(id(self.val_rows)))
        if got is None:
            got = regimes(self.val, self.val_rows)
            self.val.cache["regimes:" + str(id(self.val_rows))] = got
        return got  # type: ignore[return-value]


def make_dataset(
    rec: Recording, validate: Recording | None = None, cutoff_hz: float | None = None
) -> Dataset:
    """Prepare estimation/validation data (held-out contiguous blocks when ``validate`` is None)."""
    est = prepare(rec, cutoff_hz=cutoff_hz)
    if validate is not None:
        val = prepare(validate, cutoff_hz=est.cutoff_hz)
        return Dataset(est, est.evaluate.copy(), val, val.evaluate.copy(), f"validation file {validate.source}",
                       validate)
    n = est.n
    edges = np.linspace(0, n, HOLDOUT_BLOCKS + 1).astype(int)
    vmask = np.zeros(n, bool)
    for b in HOLDOUT_VALIDATION:
        vmask[edges[b] : edges[b + 1]] = True
    # guard: a few filter lengths at every block boundary, so that estimation and validation residuals are
    # not correlated through the filter
    g = 4 * est.guard
    boundary = np.zeros(n, bool)
    for e in edges[1:-1]:
        boundary[max(e - g, 0) : e + g] = True
    val_rows = est.evaluate & vmask & ~boundary
    est_rows = est.evaluate & ~vmask & ~boundary
    if val_rows.sum() < 50 or est_rows.sum() < 50:
        raise DataError(f"{rec.source}: not enough moving samples to hold out validation blocks")
    # est.t, not rec.t: a resampled recording has a different number of samples
    blocks = ", ".join(f"{est.t[edges[b]]:.3g}-{est.t[edges[b + 1] - 1]:.3g} s" for b in HOLDOUT_VALIDATION)
    return Dataset(est, est_rows, est, val_rows, f"held-out contiguous blocks of {rec.source}: {blocks}", rec)


# ================================================================================================ fitting
def fit_start(ds: Dataset, start: Hyp | None = None) -> FitResult:
    """Start model: the given hypothesis refitted, or mass + Coulomb + viscous."""
    h = start.copy() if start is not None else Hyp()
    if start is None:
        x = ds.est.xf[ds.est_rows]
        h.x_center_m = float(0.5 * (x.min() + x.max()))
    return rg.fit_linear(ds.est, h, ds.est_rows)


def _fitter(ds: Dataset) -> rg.LinearFitter:
    return rg.LinearFitter(ds.est, ds.est_rows)


def fit_candidate(ds: Dataset, cur: FitResult, name: str) -> FitResult:
    """Add effect ``name`` to the current model and fit it (its shape searched) on estimation data; a
    pre-sliding micro-damping the joint refit pushes beyond its physical bound is left out
    (:func:`stagectl.ident.effects.bound_damping`)."""
    fr = fx.REGISTRY.get(name).search(_fitter(ds), cur, fx.REGISTRY.with_effect(cur.hyp, name))
    return fx.bound_damping(_fitter(ds), fr)


def gap(sig: Signals, rows: BoolArray, h: Hyp) -> tuple[float, FloatArray]:
    """Validation gap (RMS [N]) and the residual on ``rows``."""
    r = rg.residual(sig, h)[rows]
    return float(np.sqrt(np.mean(r * r))), r


def _val_compare(ds: Dataset, before: Hyp, after: Hyp, min_explained: float) -> Comparison:
    _, r0 = gap(ds.val, ds.val_rows, before)
    _, r1 = gap(ds.val, ds.val_rows, after)
    return compare(r0, r1, ds.est.dt_s, min_explained)


def evidence(name: str, sig: Signals, rows: BoolArray, r_before: FloatArray, after: Hyp, cmp: Comparison) -> str:
    """One paragraph: what in the residual points to ``name`` and what the fit found."""
    spec = fx.REGISTRY.get(name)
    txt = spec.evidence(ResidualView(sig, rows, r_before), spec.params(after))
    boot = f"{cmp.boot_lower:.3g} N² > 0" if cmp.boot_lower > 0 else f"{cmp.boot_lower:.3g} N²"
    return (f"{txt}; validation gap {cmp.gap_before:.4g} N -> {cmp.gap_after:.4g} N ({100 * cmp.rel_gain:.0f} % "
            f"smaller, block-bootstrap lower bound of the per-sample MSE gain {boot})")


def _accept(ds: Dataset, name: str, fr: FitResult, before: Hyp, cmp: Comparison, suffix: str = "",
            **extra: str) -> AcceptedEffect:
    text = evidence(name, ds.val, ds.val_rows, rg.residual(ds.val, before), fr.hyp, cmp) + suffix
    return AcceptedEffect(name, fx.REGISTRY.get(name).params(fr.hyp), cmp.gap_before, cmp.gap_after, text, **extra)


# ================================================================================================ workflow
def _refresh(ds: Dataset, fr: FitResult) -> FitResult:
    """Re-search the cheap shapes that trade off with effects added later (asymmetry ratio, delay) around
    their current values; each is kept only if the estimation fit improves."""
    best = fr
    for spec in fx.REGISTRY:
        if spec.refresh is not None and fr.hyp.has(spec.name):
            best = spec.refresh(_fitter(ds), best)
    return fx.bound_damping(_fitter(ds), best)


def _upgrade_nested(ds: Dataset, cur: FitResult, effects: list[AcceptedEffect], rejected: list[RejectedEffect],
                    min_explained: float) -> FitResult:
    """A simpler effect named while a richer one could not yet be told apart (e.g. offset vs asymmetry before
    the Stribeck curve was in the model) is replaced by the richer one if, with everything else found since,
    the richer one is now significantly better on validation data."""
    nested = fx.REGISTRY.nested()
    simpler = {s for ss in nested.values() for s in ss}
    richer_of = {s: [r for r, ss in nested.items() if s in ss] for s in fx.REGISTRY.names if s in simpler}
    for item in list(effects):
        for rich in richer_of.get(item.name, []):
            if cur.hyp.has(rich):
                continue
            try:
                base = rg.fit_linear(ds.est, cur.hyp.without(item.name), ds.est_rows)
                fr = fit_candidate(ds, base, rich)
            except _FIT_ERRORS:
                continue
            c = _val_compare(ds, cur.hyp, fr.hyp, min_explained)
            if c.significant:
                new = _accept(ds, rich, fr, cur.hyp, c, f" (replaces {item.name}, named earlier when the two could "
                              "not yet be told apart)", replaces=item.name)
                effects[effects.index(item)] = replace(new, gap_before=item.gap_before)
                rejected.append(RejectedEffect(item, f"replaced by the richer {rich}, significantly better on "
                                               f"validation data once the other effects were in the model "
                                               f"({c.gap_before:.4g} N -> {c.gap_after:.4g} N)"))
                cur = fr
                break
    return cur


def _out_of_bounds(h: Hyp) -> list[str]:
    return [spec.name for spec in fx.REGISTRY.active(h) if spec.bounds is not None and spec.bounds(spec.params(h))]


def _within_bounds(ds: Dataset, fr: FitResult) -> FitResult | None:
    """``fr``, or ``fr`` with the shape of each effect outside its physical bounds searched again (with the
    other effects in place), or None when that does not bring it back within them."""
    for name in _out_of_bounds(fr.hyp):
        try:
            fr = fit_candidate(ds, rg.fit_linear(ds.est, fr.hyp.without(name), ds.est_rows), name)
        except _FIT_ERRORS:
            return None
    return None if _out_of_bounds(fr.hyp) else fr


def _prune(ds: Dataset, cur: FitResult, effects: list[AcceptedEffect], rejected: list[RejectedEffect],
           min_explained: float) -> FitResult:
    """Backward check: an accepted effect that a later, richer one made redundant (e.g. an offset accepted
    before the asymmetry or spring that contains it) is removed if the model without it is not significantly
    worse on validation data and every remaining effect stays within its physical bounds (a fit outside them is
    never accepted, so it is not the model left behind either)."""
    changed = True
    while changed and len(effects) > 1:
        changed = False
        for item in list(effects[:-1]):
            if fx.REGISTRY.implied_by_others(cur.hyp, item.name):
                continue
            h = cur.hyp.without(item.name)
            try:
                fr = rg.fit_linear(ds.est, h, ds.est_rows)
                for spec in fx.REGISTRY.active(h):
                    if spec.after_removal is not None:
                        fr = spec.after_removal(_fitter(ds), fr.hyp)  # hooks chain: each refines the last
            except _FIT_ERRORS:
                continue
            kept = _within_bounds(ds, fr)
            if kept is None:
                continue  # without it, another effect's fit leaves its physical bounds: it is not redundant
            fr = kept
            c = _val_compare(ds, fr.hyp, cur.hyp, min_explained)
            if not c.significant and c.rel_gain < 0.5 * MIN_REL_GAIN:
                effects.remove(item)
                rejected.append(RejectedEffect(item, f"made redundant by the effects found after it: removing it "
                                               f"changes the validation gap from {c.gap_after:.4g} N to "
                                               f"{c.gap_before:.4g} N ({100 * c.rel_gain:.1f} % of the gap with it, "
                                               "not a significant loss)"))
                cur = fr
                changed = True
                break
    return cur


def _try_pairs(
    ds: Dataset, cur: FitResult, cands: dict[str, tuple[FitResult, Comparison, FloatArray]], r_cur: FloatArray,
    force_rms: float,
) -> tuple[tuple[str, str], FitResult, Comparison] | None:
    """Interacting effects: when no single effect validates, try pairs of the candidates that fit the
    estimation data best (e.g. an offset plus a cogging whose position coverage differs between estimation
    and validation blocks, where each alone absorbs part of the other). The pair must pass the same test."""
    nested = fx.REGISTRY.nested()
    # effects that act in one regime are judged singly, there (docs/discovery.md §7): paired with a global
    # effect, their columns only absorb fitting residue at the extremes of the motion
    est = sorted((k for k in cands if "+" not in k and fx.REGISTRY.get(k).regime is None),
                 key=lambda k: cands[k][0].rss)
    top = [k for k in est if 1.0 - math.sqrt(cands[k][0].rss / max(cur.rss, 1e-300)) >= 0.5 * MIN_REL_GAIN]
    top = top[:PAIR_CANDIDATES]
    best: tuple[tuple[str, str], FitResult, Comparison] | None = None
    for i, a in enumerate(top):
        for b in top[i + 1:]:
            if b in nested.get(a, ()) or a in nested.get(b, ()):
                continue
            try:
                fr = fit_candidate(ds, cands[a][0], b)
            except _FIT_ERRORS:
                continue
            _, r_new = gap(ds.val, ds.val_rows, fr.hyp)
            cmp = compare(r_cur, r_new, ds.est.dt_s, force_rms)
            if cmp.significant and (best is None or cmp.gap_after < best[2].gap_after):
                best = ((a, b), fr, cmp)
    if best is None:
        return None
    # nested effects: a pair with the simpler member is preferred unless the richer pair is significantly better
    (a, b), fr, cmp = best
    for rich, other in ((a, b), (b, a)):
        for simpler in nested.get(rich, ()):
            if cur.hyp.has(simpler) or simpler == other:
                continue
            try:
                base = cands[other][0] if other in cands else fit_candidate(ds, cur, other)
                fr2 = fit_candidate(ds, base, simpler)
            except (*_FIT_ERRORS, KeyError):
                continue
            _, r2 = gap(ds.val, ds.val_rows, fr2.hyp)
            c2 = compare(r_cur, r2, ds.est.dt_s, force_rms)
            if not c2.significant:
                continue
            _, r_rich = gap(ds.val, ds.val_rows, fr.hyp)
            if not compare(r2, r_rich, ds.est.dt_s, force_rms).significant:
                return (other, simpler), fr2, c2
    return best


@dataclass
class DiscoveryResult:
    """What :func:`discover` found: start and final fits, validation gaps [N], the effects accepted (in
    order) and rejected, every round's candidates, and where the residual lives before and after."""

    start: FitResult
    final: FitResult
    gap_before: float
    gap_after: float
    effects: list[AcceptedEffect]
    rejected: list[RejectedEffect]
    rounds: list[Round]
    disagreement_before: list[Disagreement]
    disagreement_after: list[Disagreement]
    split: str
    elapsed_s: float
    history: list[Hyp] = field(default_factory=list)
    dataset: Dataset | None = None
    noise_floor_n: float = 0.0
    min_explained_n: float = 0.0


def _regime_mask(ds: Dataset, name: str) -> BoolArray | None:
    """Mask over the validation rows (``r[rows]`` indexing) of the regime whose key starts with ``name``."""
    for k, m in ds.val_regimes.items():
        if k.startswith(name):
            return np.asarray(m[ds.val_rows], dtype=bool)
    return None


def _fit_label(ds: Dataset, cur: FitResult, label: str) -> FitResult:
    """Fit a candidate label: one effect, or ``rich+simple`` (the richer effect searched with the nested
    simpler one already in the model, so that neither is fitted with the other frozen)."""
    names = label.split("+")
    fr = cur
    for name in reversed(names):
        fr = fit_candidate(ds, fr, name)
    return fr


def _score(ds: Dataset, cur: FitResult, label: str, fr: FitResult, r_cur: FloatArray, force_rms: float
           ) -> tuple[CandidateFit, Comparison, FloatArray]:
    """Validation comparison of a fitted candidate: globally and, for an effect that lives in one regime,
    there (regime-aware acceptance, docs/discovery.md §7); physical bounds; the report row."""
    names = label.split("+")
    _, r_new = gap(ds.val, ds.val_rows, fr.hyp)
    cmp = compare(r_cur, r_new, ds.est.dt_s, force_rms)
    est_gain = 1.0 - math.sqrt(fr.rss / max(cur.rss, 1e-300))
    specs = [fx.REGISTRY.get(n) for n in names]
    params = [sp.params(fr.hyp) for sp in specs]
    bounds = tuple(b for sp, p in zip(specs, params) if sp.bounds is not None for b in sp.bounds(p))
    # an effect already in the model that this candidate's joint fit pushes beyond its bounds (the linear
    # coefficients are refitted together): the model file could not hold it, so the candidate is not accepted
    was_out = set(_out_of_bounds(cur.hyp))
    bounds += tuple(f"{sp.name} (already in the model): {b}" for sp in fx.REGISTRY.active(fr.hyp)
                    if sp.name not in names and sp.name not in was_out and sp.bounds is not None
                    for b in sp.bounds(sp.params(fr.hyp)))
    keys = "; ".join(sp.key(p) for sp, p in zip(specs, params) if sp.key is not None) or None
    regime = specs[0].regime if len(specs) == 1 else None
    rc: Comparison | None = None
    if regime is not None:
        m = _regime_mask(ds, regime)
        if m is not None and int(m.sum()) >= MIN_REGIME_SAMPLES:
            rc = compare(r_cur[m], r_new[m], ds.est.dt_s, force_rms)
    unresolved = tuple(u for sp in specs if sp.resolved is not None
                       for u in sp.resolved(ds.val, ds.val_rows, fr.hyp, force_rms, r_new))
    in_regime = rc is not None and rc.significant and cmp.gap_after <= cmp.gap_before
    if fx.DELAY.name in names and (cmp.significant or in_regime) and est_gain > 0.0 and not bounds \
            and not unresolved:  # the costlier check only where it decides (docs/discovery.md §13)
        unresolved += tuple(_delay_moves_with_filter(ds, fr))
    ok = (cmp.significant or in_regime) and est_gain > 0.0 and not bounds and not unresolved
    row = CandidateFit(
        label, params[0] if len(params) == 1 else tuple(params), est_gain, cmp.gap_before, cmp.gap_after,
        cmp.rel_gain, cmp.boot_lower, cmp.block, cmp.explained_n, cmp.min_explained_n, ok, key_parameter=keys,
        regime=regime, regime_gap_before=None if rc is None else rc.gap_before,
        regime_gap_after=None if rc is None else rc.gap_after, regime_rel_gain=None if rc is None else rc.rel_gain,
        regime_significant=None if rc is None else rc.significant, bounds=bounds, unresolved=unresolved)
    return row, cmp, r_new


#: a delay refitted at another filter cut-off may move by at most this fraction (or a quarter sample)
DELAY_FILTER_TOLERANCE = 0.3


def _delay_moves_with_filter(ds: Dataset, fr: FitResult) -> list[str]:
    """An actuation delay is a property of the drive, not of the analysis: refitted on the validation data
    with the low-pass cut-off doubled (halved when doubling would pass 0.4·fs), its τ must stay within
    ``DELAY_FILTER_TOLERANCE`` (or dt/4) of τ refitted at the cut-off used.

    Measured (docs/discovery.md §13): a closed loop answering an unmeasured force disturbance makes the
    zero-phase filtered residual correlate with the command's later changes, and a delay fits that with a τ
    set by the filter (2.2 ms at 100 Hz, 3.8 ms at 50 Hz, 0.7 ms at 200 Hz on a recording with no delay);
    the EMPS drive's delay is 0.28 / 0.27 ms at 100 / 200 Hz."""
    if ds.val_rec is None:
        return []
    c0 = ds.val.cutoff_hz
    fs = 1.0 / ds.val.dt_s
    c1 = 2.0 * c0 if 2.0 * c0 < 0.4 * fs else 0.5 * c0
    key = f"{c1:.9g}"
    sig1 = ds.alt.get(key)
    if sig1 is None:
        try:
            sig1 = prepare(ds.val_rec, cutoff_hz=c1)
        except DataError:
            return []
        ds.alt[key] = sig1
    if sig1.n != ds.val.n:
        return []
    taus = []
    for sig, rows in ((ds.val, ds.val_rows), (sig1, ds.val_rows & sig1.evaluate)):
        f = rg.LinearFitter(sig, rows)
        try:
            got = fx.DELAY.search(f, f.fit(fr.hyp), fr.hyp)
        except _FIT_ERRORS:
            return []
        taus.append(float(fx.DELAY.shape(got.hyp).delay_s))
    t0, t1 = taus
    if abs(t1 - t0) <= max(DELAY_FILTER_TOLERANCE * max(t0, t1), 0.25 * ds.val.dt_s):
        return []
    return [(f"the fitted delay moves with the analysis filter: τ = {1e3 * t0:.3g} ms at the {c0:.3g} Hz "
             f"cut-off, {1e3 * t1:.3g} ms at {c1:.3g} Hz (validation data); an actuation delay does not depend on "
             "the filter. A closed loop answering a force disturbance that is not in the recording gives such a "
             "lag")]


def _round(ds: Dataset, cur: FitResult, catalogue: tuple[str, ...], r_cur: FloatArray, force_rms: float,
           on_candidate: Callable[[int, int, str], None] | None = None,
           ) -> tuple[list[Candidate], dict[str, tuple[FitResult, Comparison, FloatArray]]]:
    """Every catalogue effect not in the model, added in turn, fitted and compared on validation data; a
    richer effect that contains a simpler one not yet in the model is also tried jointly with it
    (``asymmetry+offset``): nesting must not hide the truth (docs/discovery.md §2)."""
    cands: dict[str, tuple[FitResult, Comparison, FloatArray]] = {}
    info: list[Candidate] = []
    labels: list[str] = []
    for name in catalogue:
        if cur.hyp.has(name):
            continue
        labels.append(name)
        spec = fx.REGISTRY.get(name)
        for simpler in (*spec.contains, *spec.tried_with):
            joint = f"{name}+{simpler}"
            if (simpler in catalogue and not cur.hyp.has(simpler)
                    and simpler not in spec.implies):  # an implied effect is always fitted with it
                labels.append(joint)
    for i, label in enumerate(labels):
        if on_candidate is not None:
            on_candidate(i, len(labels), label)
        try:
            fr = _fit_label(ds, cur, label)
        except _FIT_ERRORS as exc:  # a candidate that cannot be fitted here
            info.append(CandidateError(label, str(exc)))
            continue
        single = cands.get(label.split("+")[0]) if "+" in label else None
        if single is not None and abs(fr.rss - single[0].rss) <= 1e-9 * max(single[0].rss, 1e-300):
            continue  # the richer effect already carries the simpler one (a spring its constant force)
        row, cmp, r_new = _score(ds, cur, label, fr, r_cur, force_rms)
        cands[label] = (fr, cmp, r_new)
        info.append(row)
    return info, cands


def _effects_of(label: str) -> set[str]:
    return set(label.split("+"))


def _complexity(label: str) -> int:
    """Parsimony order: the number of effects, a richer (containing) effect counting more than a plain one."""
    return sum(2 + (1 if fx.REGISTRY.get(n).contains else 0) for n in label.split("+"))


def _related(simple: str, rich: str) -> bool:
    """``simple`` is nested in ``rich``: a subset of its effects, or contained by one of them."""
    a, b = _effects_of(simple), _effects_of(rich)
    if a < b:
        return True
    contained = {c for n in b for c in fx.REGISTRY.get(n).contains} | b
    return a <= contained and a != b


def _note(info: list[Candidate], label: str, note: str) -> None:
    for i, item in enumerate(info):
        if item.name == label and isinstance(item, CandidateFit):
            old = item.note
            info[i] = replace(item, note=note if not old else f"{old}; {note}")


def _choose(ds: Dataset, cur: FitResult, info: list[Candidate],
            cands: dict[str, tuple[FitResult, Comparison, FloatArray]], force_rms: float) -> str | None:
    """The acceptable candidate with the smallest validation gap, except that a richer candidate that does
    not beat an acceptable simpler, nested one significantly gives way to it (parsimony; noted on the
    richer one); unrelated candidates that fit about as well are named as ties the data cannot separate."""
    ok_names = {c.name for c in info if isinstance(c, CandidateFit) and c.acceptable}
    ok = {k: v for k, v in cands.items() if k in ok_names}
    if not ok:
        return None
    chosen = min(ok, key=lambda k: ok[k][1].gap_after)
    moved = True
    while moved:  # parsimony: a simpler candidate that the chosen one does not beat significantly is preferred
        moved = False
        simpler = [k for k in ok if _complexity(k) < _complexity(chosen)
                   and not compare(ok[k][2], ok[chosen][2], ds.est.dt_s, force_rms).significant]
        if simpler:
            best = min(simpler, key=lambda k: ok[k][1].gap_after)
            c2 = compare(ok[best][2], ok[chosen][2], ds.est.dt_s, force_rms)
            _note(info, chosen, f"superseded: did not beat the simpler {best} significantly on validation data "
                  f"({100 * c2.rel_gain:.1f} % further gain)")
            chosen, moved = best, True
    g = ok[chosen][1].gap_after
    for other, (_, oc, r_o) in ok.items():
        if other == chosen or _related(other, chosen) or _related(chosen, other):
            continue
        if oc.gap_after <= (1.0 + TIE_MARGIN) * g and not compare(r_o, ok[chosen][2], ds.est.dt_s,
                                                                  force_rms).significant:
            how = "; ".join(dict.fromkeys(fx.REGISTRY.get(n).separate_by for n in (*other.split("+"),
                                                                                   *chosen.split("+"))))
            _note(info, chosen, f"tie with {other} (validation gap {g:.4g} N vs {oc.gap_after:.4g} N): these data "
                  f"cannot separate them; to separate: {how}")
    return chosen


def _regime_text(row: CandidateFit) -> str:
    return (f"; accepted in its regime ({row.regime}): there the validation residual went "
            f"{row.regime_gap_before:.4g} N -> {row.regime_gap_after:.4g} N ({100 * (row.regime_rel_gain or 0):.0f} % "
            f"smaller), while the global gap did not get worse ({row.gap_before:.4g} N -> {row.gap_after:.4g} N, "
            f"{100 * row.rel_gain:.1f} %)")


def _why_not(c: CandidateFit) -> str:
    """Why a candidate was not accepted, in the words of the acceptance rule (docs/discovery.md §4, §7)."""
    if c.bounds:
        return "fit at or beyond a physical bound, so not accepted (and not clipped): " + "; ".join(c.bounds)
    if c.unresolved:
        return "the recording does not resolve its defining evidence, so not accepted: " + "; ".join(c.unresolved)
    if c.estimation_rel_gain <= 0.0:
        return f"no gain on the estimation data ({100 * c.estimation_rel_gain:.1f} %)"
    txt = (f"estimation gain {100 * c.estimation_rel_gain:.1f} %, validation gap {c.gap_before:.4g} N -> "
           f"{c.gap_after:.4g} N ({100 * c.rel_gain:.1f} %; needs >= {100 * MIN_REL_GAIN:.0f} %, a positive "
           f"bootstrap bound (got {c.bootstrap_lower_n2:.3g} N²) and >= {c.min_explained_n:.3g} N explained "
           f"(got {c.explained_n:.3g} N))")
    if c.regime is not None:
        if c.regime_rel_gain is None:
            txt += f"; too few validation samples in its regime ({c.regime}) to judge it there"
        else:
            txt += (f"; in its regime ({c.regime}) {c.regime_gap_before:.4g} N -> {c.regime_gap_after:.4g} N "
                    f"({100 * c.regime_rel_gain:.1f} %, {'significant' if c.regime_significant else 'not significant'}"
                    f"{'' if c.gap_after <= c.gap_before else ', but the global gap got worse'})")
    return txt


def _verdicts(info: list[Candidate], chosen: str | None) -> list[Candidate]:
    """Every candidate's verdict: accepted, superseded (acceptable, but another was named), rejected (why)."""
    out: list[Candidate] = []
    for c in info:
        if not isinstance(c, CandidateFit):
            out.append(c)
            continue
        if chosen is not None and c.name == chosen:
            v = "accepted" + (f" ({c.note})" if c.note else "")
        elif c.acceptable:
            v = f"superseded: acceptable, but {chosen} was named this round" + (f" ({c.note})" if c.note else "")
        else:
            v = "rejected: " + _why_not(c)
        out.append(replace(c, verdict=v))
    return out


def discover(
    rec: Recording,
    validate: Recording | None = None,
    start: Hyp | None = None,
    catalogue: tuple[str, ...] | None = None,
    max_rounds: int = 6,
    cutoff_hz: float | None = None,
    progress: Callable[[float, str], None] | None = None,
) -> DiscoveryResult:
    """Run the workflow (see module docstring). ``start`` is the starting hypothesis (None: m + Coulomb +
    viscous); ``catalogue`` the effects to try (None: every registered effect). ``progress(done, what)`` is told
    before each candidate fit: ``done`` = rounds finished + the fraction of this round's candidates tried (of at
    most ``max_rounds``)."""
    t0 = time.perf_counter()
    cat = fx.REGISTRY.names if catalogue is None else catalogue
    ds = make_dataset(rec, validate, cutoff_hz)
    cur = fit_start(ds, start)
    start_fit = cur
    g0, _ = gap(ds.val, ds.val_rows, cur.hyp)
    dis_before = localise(ds.val, ds.val_rows, rg.residual(ds.val, cur.hyp))
    m_hat = float(cur.hyp.theta.get("m", cur.hyp.fixed_mass_kg or 0.0))
    # the non-inertial force ū − m̂·a (friction and other forces): the physical scale an effect is judged
    # against. The commanded force itself scales with how hard the motion accelerates (a fast point-to-point
    # recording of a heavy stage has an RMS force hundreds of times its friction), not with the physics sought.
    uf = (ds.val.filt(ds.val.ubar()) - m_hat * ds.val.acc_f)[ds.val_rows]
    noise_floor = ds.val.noise_floor_n(m_hat)
    force_rms = max(MIN_EXPLAINED_FRACTION * float(np.sqrt(np.mean(uf * uf))), MIN_EXPLAINED_NOISE * noise_floor)
    effects: list[AcceptedEffect] = []
    rejected: list[RejectedEffect] = []
    rounds: list[Round] = []
    history = [cur.hyp]
    for rnd in range(max_rounds):
        _, r_cur = gap(ds.val, ds.val_rows, cur.hyp)
        tell = None if progress is None else (
            lambda i, n, label, rnd=rnd: progress(rnd + i / max(n, 1), f"round {rnd + 1}, candidate {i + 1} of {n} "
                                                  f"({label})"))
        info, cands = _round(ds, cur, cat, r_cur, force_rms, tell)
        chosen = _choose(ds, cur, info, cands, force_rms)
        if chosen is None:
            pair = _try_pairs(ds, cur, cands, r_cur, force_rms)
            if pair is not None:
                (a, b), fr, cmp = pair
                rounds.append(Round(_verdicts(info, f"{a}+{b}"), f"{a}+{b}"))
                for name in (a, b):
                    effects.append(_accept(ds, name, fr, cur.hyp, cmp, f" (neither {a} nor {b} validated alone: each "
                                           "biases the other's fit; accepted as a pair)",
                                           accepted_jointly_with=b if name == a else a))
                cur = _refresh(ds, fr)
                history.append(cur.hyp)
                continue
            rounds.append(Round(_verdicts(info, None), None))
            for item in rounds[-1].candidates:
                if isinstance(item, CandidateFit):
                    rejected.append(RejectedEffect(item, item.verdict or "not acceptable"))
            break
        rounds.append(Round(_verdicts(info, chosen), chosen))
        fr, cmp, _ = cands[chosen]
        row = next(c for c in info if c.name == chosen and isinstance(c, CandidateFit))
        names = chosen.split("+")
        for name in names:
            suffix = _regime_text(row) if not cmp.significant else ""
            if len(names) > 1:
                suffix += f" (fitted jointly with the nested {' and '.join(n for n in names if n != name)}: " \
                          "neither is fitted with the other frozen)"
            effects.append(_accept(ds, name, fr, cur.hyp, cmp, suffix,
                                   **({"accepted_jointly_with": "+".join(n for n in names if n != name)}
                                      if len(names) > 1 else {})))
        cur = _refresh(ds, fr)
        history.append(cur.hyp)
    cur = _prune(ds, cur, effects, rejected, force_rms)
    cur = _upgrade_nested(ds, cur, effects, rejected, force_rms)
    g1, _ = gap(ds.val, ds.val_rows, cur.hyp)
    dis_after = localise(ds.val, ds.val_rows, rg.residual(ds.val, cur.hyp))
    return DiscoveryResult(
        start=start_fit, final=cur, gap_before=g0, gap_after=g1, effects=effects, rejected=rejected, rounds=rounds,
        disagreement_before=dis_before, disagreement_after=dis_after, split=ds.split,
        elapsed_s=time.perf_counter() - t0, history=history, dataset=ds, noise_floor_n=noise_floor,
        min_explained_n=force_rms,
    )
