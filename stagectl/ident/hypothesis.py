"""The vocabulary of discovery: a model hypothesis, its fit, and what one effect must declare to take part.

* :class:`Hyp` -- which effects a model holds, each effect's nonlinear *shape* (a frozen dataclass per
  effect, e.g. the Stribeck velocity), and the fitted linear coefficients of its design columns;
* :class:`EffectSpec` -- everything the regression, the search, the report and the model file need to know
  about one effect; :class:`Registry` -- the ordered catalogue of specs (the instance in use is
  :data:`stagectl.ident.effects.REGISTRY`);
* :class:`Fitter` -- the linear fit an effect's nonlinear-parameter search calls (implemented by
  :class:`stagectl.ident.regress.LinearFitter`, so that the effects sit below the regression engine).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeVar

import numpy as np
import numpy.typing as npt

from stagectl.errors import short
from stagectl.friction.effects import Effects
from stagectl.ident.localise import ResidualView
from stagectl.ident.signals import Signals

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class NoShape:
    """Shape of an effect without nonlinear parameters (every parameter enters linearly)."""


@dataclass
class Hyp:
    """A model hypothesis: which effects, their nonlinear shapes, the fitted linear parameters.

    ``shapes`` maps an effect name to its shape dataclass (absent: the shape's defaults). ``theta`` maps
    design-column names to fitted coefficients; the base columns are ``m`` [kg], ``fc`` [N] (Coulomb),
    ``fv`` [N·s/m] (viscous) and ``given`` (scale of ``given_spec``, a fixed friction model from a model file
    that replaces the Coulomb/Stribeck/pre-sliding columns); every other column belongs to one effect, which
    alone reads it (:meth:`EffectSpec.params`).
    """

    effects: tuple[str, ...] = ()
    shapes: dict[str, object] = field(default_factory=dict)
    theta: dict[str, float] = field(default_factory=dict)
    fixed_mass_kg: float | None = None
    x_center_m: float = 0.0
    given_spec: dict[str, Any] | None = None

    def has(self, name: str) -> bool:
        return name in self.effects

    def copy(self) -> Hyp:
        return dataclasses.replace(self, shapes=dict(self.shapes), theta=dict(self.theta))

    def adding(self, *names: str) -> Hyp:
        """A copy with ``names`` appended (those not already present), in order."""
        eff = list(self.effects)
        for n in names:
            if n not in eff:
                eff.append(n)
        h = self.copy()
        h.effects = tuple(eff)
        return h

    def without(self, name: str) -> Hyp:
        """A copy without effect ``name`` and without fitted coefficients (shapes are kept)."""
        h = self.copy()
        h.effects = tuple(e for e in h.effects if e != name)
        h.theta = {}
        return h


@dataclass
class FitResult:
    """A hypothesis with its fitted linear parameters, residual sum of squares [N²] over ``n`` samples."""

    hyp: Hyp
    rss: float
    n: int

    @property
    def rms(self) -> float:
        return math.sqrt(self.rss / max(self.n, 1))


@dataclass(frozen=True)
class Column:
    """One raw (unfiltered) design-matrix column.

    ``cache_key`` identifies the filtered column in the signal cache (None: it depends on the previous fit,
    never cached); ``nonneg`` bounds its coefficient at zero from below; ``follows_friction``: the column is
    proportional to the current friction estimate (it carries the friction scaling, e.g. the asymmetry).
    """

    name: str
    values: FloatArray
    cache_key: str | None
    nonneg: bool = False
    follows_friction: bool = False


@dataclass
class HiddenStage:
    """A simulated stage mapping being given a hidden effect (:func:`stagectl.ident.synth.hide`): an effect's
    ``hide`` hook draws its parameters from ``rng`` over plausible ranges and edits ``friction`` (the
    ``friction:`` mapping) or ``effects`` (the ``effects:`` mapping) in place. ``coulomb_n`` is the stage's
    Coulomb level Fc [N], ``sign`` a random ±1 drawn for every effect, ``span_m`` the travel [m]."""

    friction: dict[str, Any]
    effects: dict[str, Any]
    coulomb_n: float
    sign: float
    mass_kg: float
    span_m: float
    rng: np.random.Generator
    backlash: dict[str, Any] | None = None  # a stagectl.sim.backlash.BacklashConfig mapping (motor + load)


class Fitter(Protocol):
    """Linear least squares on the estimation data, as an effect's nonlinear search calls it."""

    @property
    def sig(self) -> Signals: ...

    @property
    def rows(self) -> BoolArray: ...

    def fit(self, h: Hyp) -> FitResult:
        """Fit the linear parameters of ``h`` (shapes fixed)."""

    def residual(self, h: Hyp) -> FloatArray:
        """Filtered force residual of the fitted ``h`` [N] (all samples)."""

    def friction_force(self, h: Hyp) -> FloatArray:
        """Raw friction force of the fitted ``h`` before scaling effects [N]."""


if TYPE_CHECKING:
    S = TypeVar("S", bound=DataclassInstance)
else:
    S = TypeVar("S")
P = TypeVar("P")


@dataclass(frozen=True, eq=False)
class EffectSpec(Generic[S, P]):
    """One discovery effect: how it enters the regression, how its shape is searched, what it reports,
    and how it maps to and from the model file's ``effects:`` section.

    Regression hooks (any may be None):

    * ``friction_columns(sig, h)`` -- columns that are part of the friction force (scaled by ``scaling``);
    * ``columns(sig, h, f_est)`` -- further columns, given the current friction estimate ``f_est`` [N];
    * ``scaling(h)`` -- ``r`` of a friction multiplier ``1 + r·sgn(F)`` (at most one effect has it);
    * ``target_delay(h)`` -- delay [s] of the applied force behind the command.

    ``column_rank`` orders the columns in the design matrix (catalogue order is the registry's order);
    ``iterative``: the columns depend on the previous fit, so each fit takes two passes. ``refresh`` re-searches
    the shape after later effects were accepted, ``after_removal`` after another effect was pruned; ``hide``
    puts the effect into a simulated stage (synthetic recordings for tests and demos).

    Report and acceptance: ``regime`` names the motion regime the effect acts in (a prefix of a
    :func:`stagectl.ident.localise.regimes` key, e.g. ``near_reversal``): the effect may be accepted on its gain
    there while the global gap does not get worse (docs/discovery.md §7); ``bounds(params)`` lists the physical
    bounds the fitted parameters reach or cross (a fit outside is never accepted, and never clipped);
    ``resolved(sig, rows, h, floor_n, r)`` (``r`` the residual of ``h`` on ``rows``) lists what the effect's
    defining evidence lacks on the validation
    samples ``rows`` of ``sig`` (a force below ``floor_n`` [N], the smallest force the acceptance rule credits):
    a fit whose signature the recording does not resolve is not accepted, whatever its gain; ``key``
    formats the key parameter (wavelength, ratio, ...) for the report; ``separate_by`` is the experiment that
    tells this effect from a look-alike when the data cannot.
    """

    name: str
    shape_type: type[S]
    params: Callable[[Hyp], P]
    evidence: Callable[[ResidualView, P], str]
    search: Callable[[Fitter, FitResult, Hyp], FitResult]
    column_rank: int
    friction_columns: Callable[[Signals, Hyp], list[Column]] | None = None
    columns: Callable[[Signals, Hyp, FloatArray], list[Column]] | None = None
    scaling: Callable[[Hyp], float] | None = None
    target_delay: Callable[[Hyp], float] | None = None
    iterative: bool = False
    implies: tuple[str, ...] = ()
    contains: tuple[str, ...] = ()
    #: effects this one is also tried jointly with (``name+other``), without nesting: forms that occur together
    #: (a viscous and a Coulomb asymmetry, the latter an offset while sliding, docs/discovery.md §1)
    tried_with: tuple[str, ...] = ()
    twin: str | None = None
    to_twin: Callable[[P], object] | None = None
    from_twin: Callable[[Hyp, Any], Hyp] | None = None
    refresh: Callable[[Fitter, FitResult], FitResult] | None = None
    after_removal: Callable[[Fitter, Hyp], FitResult] | None = None
    hide: Callable[[HiddenStage], None] | None = None
    regime: str | None = None
    bounds: Callable[[P], list[str]] | None = None
    key: Callable[[P], str] | None = None
    separate_by: str = ""
    resolved: Callable[[Signals, npt.NDArray[np.bool_], Hyp, float, npt.NDArray[np.float64]], list[str]] | None = None

    def shape(self, h: Hyp) -> S:
        """This effect's shape in ``h`` (its defaults when ``h`` has none)."""
        v = h.shapes.get(self.name)
        return v if isinstance(v, self.shape_type) else self.shape_type()

    def reshaped(self, h: Hyp, **changes: Any) -> Hyp:
        """A copy of ``h`` whose shape of this effect has ``changes`` applied."""
        hh = h.copy()
        hh.shapes[self.name] = dataclasses.replace(self.shape(h), **changes)
        return hh

    def fit_with(self, fitter: Fitter, h: Hyp, **changes: Any) -> FitResult:
        """Fit ``h`` with this effect's shape changed by ``changes``."""
        return fitter.fit(self.reshaped(h, **changes))


class Registry(Sequence[EffectSpec[Any, Any]]):
    """The discovery catalogue: effect specs in search/report order, looked up by name."""

    def __init__(self, specs: Sequence[EffectSpec[Any, Any]]) -> None:
        self._specs = tuple(specs)
        self._by_name = {s.name: s for s in self._specs}
        self._active: dict[tuple[str, ...], tuple[EffectSpec[Any, Any], ...]] = {}
        problems = []
        if len(self._by_name) != len(self._specs):
            problems.append("duplicate effect names")
        for s in self._specs:
            for dep in (*s.implies, *s.contains):
                if dep not in self._by_name:
                    problems.append(f"{s.name}: unknown effect {short(dep)}")
        if sum(s.scaling is not None for s in self._specs) > 1:
            problems.append("more than one friction-scaling effect")
        if sum(s.target_delay is not None for s in self._specs) > 1:
            problems.append("more than one effect delaying the force")
        twins = [s.twin for s in self._specs if s.twin is not None]
        model_file_effects = {f.name for f in dataclasses.fields(Effects)}
        for s in self._specs:
            if s.twin is not None and s.twin not in model_file_effects:
                problems.append(f"{s.name}: twin {short(s.twin)} is not a model-file effect "
                                f"(stagectl.friction.effects."
                                f"Effects has {', '.join(sorted(model_file_effects))})")
        if len(set(twins)) != len(twins):
            problems.append("two effects map to the same model-file effect")
        if problems:
            raise ValueError("effect registry: " + "; ".join(problems))

    def __getitem__(self, i: int) -> EffectSpec[Any, Any]:  # type: ignore[override]
        return self._specs[i]

    def __len__(self) -> int:
        return len(self._specs)

    def __iter__(self) -> Iterator[EffectSpec[Any, Any]]:
        return iter(self._specs)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self._specs)

    def get(self, name: str) -> EffectSpec[Any, Any]:
        try:
            return self._by_name[name]
        except KeyError:
            raise ValueError(f"unknown effect {short(name)}") from None

    def active(self, h: Hyp) -> list[EffectSpec[Any, Any]]:
        """The specs of the effects in ``h`` (registered ones only), in design-column order."""
        key = tuple(h.effects)
        got = self._active.get(key)  # asked several times per fit: kept per tuple of effect names
        if got is None:
            got = self._active[key] = tuple(sorted((s for s in self._specs if h.has(s.name)),
                                                         key=lambda s: s.column_rank))
        return list(got)

    def nested(self) -> dict[str, tuple[str, ...]]:
        """Richer effect -> the simpler effects it contains, the latest-registered richer effect first (the
        order in which the workflow tries a richer replacement for a simpler effect)."""
        return {s.name: s.contains for s in reversed(self._specs) if s.contains}

    def with_effect(self, h: Hyp, name: str) -> Hyp:
        """A copy of ``h`` with effect ``name`` and the effects it implies (those first)."""
        return h.adding(*self.get(name).implies, name)

    def implied_by_others(self, h: Hyp, name: str) -> bool:
        """Another effect in ``h`` presupposes ``name`` (it cannot be removed alone)."""
        return any(name in s.implies for s in self._specs if h.has(s.name) and s.name != name)
