"""Typed results of the discovery workflow and the validation statistics they carry.

* :func:`compare` -- the validation comparison of two residuals (gap before/after, relative gain, block
  bootstrap lower bound, explained force) and its acceptance test :attr:`Comparison.significant`;
* :class:`CandidateFit` / :class:`CandidateError` (one row of a round), :class:`Round`,
  :class:`AcceptedEffect`, :class:`RejectedEffect`: what ``report.json`` lists; ``as_json()`` gives each
  entry's mapping there (plain data; keys that do not apply are left out).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from stagectl.outputs import plain

FloatArray = npt.NDArray[np.float64]

#: minimum relative reduction of the validation gap for an effect to be accepted
MIN_REL_GAIN = 0.20
#: bootstrap confidence for the "gap reduced" test
BOOT_QUANTILE = 0.025
BOOT_SAMPLES = 400


# ================================================================================================ statistics
def block_length(d: FloatArray, dt_s: float) -> int:
    """Block length for the bootstrap: 2× the lag where the autocorrelation of ``d`` falls below 0.1
    (at least 0.1 s, at most a tenth of the data)."""
    n = d.shape[0]
    x = d - d.mean()
    nf = 1 << int(math.ceil(math.log2(2 * n)))
    f = np.fft.rfft(x, nf)
    ac = np.fft.irfft(f * np.conj(f), nf)[:n]
    ac = ac / ac[0] if ac[0] > 0 else ac
    below = np.flatnonzero(ac < 0.1)
    lag = int(below[0]) if below.size else n // 10
    return int(min(max(2 * lag, int(0.1 / dt_s), 10), max(n // 10, 10)))


def bootstrap_lower(d: FloatArray, block: int, seed: int = 0) -> float:
    """Lower ``BOOT_QUANTILE`` quantile of the mean of ``d`` under a circular block bootstrap."""
    n = d.shape[0]
    rng = np.random.default_rng(seed)
    nb = int(math.ceil(n / block))
    cs = np.concatenate([[0.0], np.cumsum(np.concatenate([d, d[:block]]))])
    starts = rng.integers(0, n, size=(BOOT_SAMPLES, nb))
    sums = (cs[starts + block] - cs[starts]).sum(axis=1)
    means = sums / (nb * block)
    return float(np.quantile(means, BOOT_QUANTILE))


@dataclass(frozen=True)
class Comparison:
    """Validation comparison of the residuals before and after adding an effect (see :func:`compare`)."""

    gap_before: float
    gap_after: float
    rel_gain: float
    boot_lower: float
    block: int
    explained_n: float
    min_explained_n: float

    @property
    def significant(self) -> bool:
        return (self.rel_gain >= MIN_REL_GAIN and self.boot_lower > 0.0
                and self.explained_n >= self.min_explained_n)


def compare(r_before: FloatArray, r_after: FloatArray, dt_s: float, min_explained_n: float = 0.0) -> Comparison:
    """Validation comparison of two residuals (same samples); ``min_explained_n``: explained-force floor [N]."""
    d = r_before**2 - r_after**2
    blk = block_length(d, dt_s)
    gb = float(np.sqrt(np.mean(r_before**2)))
    ga = float(np.sqrt(np.mean(r_after**2)))
    expl = math.sqrt(max(gb * gb - ga * ga, 0.0))
    return Comparison(gb, ga, (gb - ga) / gb if gb > 0 else 0.0, bootstrap_lower(d, blk), blk, expl,
                      min_explained_n)



# ================================================================================================ results
def _json(obj: object, *optional: str) -> dict[str, Any]:
    d: dict[str, Any] = plain(obj, json=True)
    for k in optional:
        if d.get(k) is None:
            d.pop(k, None)
    return d


@dataclass(frozen=True)
class CandidateFit:
    """A catalogue effect added to the current model, fitted on estimation data, scored on validation data."""

    name: str
    parameters: object  # the effect's typed parameters (EffectSpec.params)
    estimation_rel_gain: float
    gap_before: float
    gap_after: float
    rel_gain: float
    bootstrap_lower_n2: float
    block_samples: int
    explained_n: float
    min_explained_n: float
    acceptable: bool
    note: str | None = None
    key_parameter: str | None = None
    regime: str | None = None  # the regime the effect acts in (judged there too)
    regime_gap_before: float | None = None
    regime_gap_after: float | None = None
    regime_rel_gain: float | None = None
    regime_significant: bool | None = None
    bounds: tuple[str, ...] = ()  # physical bounds reached or crossed by the fit
    unresolved: tuple[str, ...] = ()  # defining evidence the recording does not resolve (EffectSpec.resolved)
    verdict: str | None = None  # accepted / rejected / superseded, with the reason

    def as_json(self) -> dict[str, Any]:
        return _json(self, "note", "key_parameter", "regime", "regime_gap_before", "regime_gap_after",
                     "regime_rel_gain", "regime_significant", "verdict")


@dataclass(frozen=True)
class CandidateError:
    """A catalogue effect that could not be fitted to these data."""

    name: str
    error: str

    def as_json(self) -> dict[str, Any]:
        return _json(self)


Candidate = CandidateFit | CandidateError


@dataclass
class Round:
    """One round: every candidate tried and the effect (or ``a+b`` pair) chosen, if any."""

    candidates: list[Candidate]
    chosen: str | None

    def as_json(self) -> dict[str, Any]:
        return {"chosen": self.chosen, "candidates": [c.as_json() for c in self.candidates]}


@dataclass(frozen=True)
class AcceptedEffect:
    """An effect named by the workflow, with its validation gap before/after and the evidence text."""

    name: str
    parameters: object
    gap_before: float
    gap_after: float
    evidence: str
    accepted_jointly_with: str | None = None  # accepted as a pair with this effect
    replaces: str | None = None  # a simpler effect named earlier that this one replaced

    def as_json(self) -> dict[str, Any]:
        d = _json(self, "accepted_jointly_with", "replaces")
        d["evidence"] = d.pop("evidence")  # the evidence text last, as report.json always had it
        return d


@dataclass(frozen=True)
class RejectedEffect:
    """A candidate that fit the estimation data but did not validate, or an accepted effect removed later."""

    entry: CandidateFit | AcceptedEffect
    reason: str

    @property
    def name(self) -> str:
        return self.entry.name

    def as_json(self) -> dict[str, Any]:
        return {**self.entry.as_json(), "reason": self.reason}
