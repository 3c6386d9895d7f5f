"""The one interface every friction model implements (pure math: no I/O, clock, logging, threads).

Sign convention (project-wide)
------------------------------
The friction force ``F`` [N] *opposes* motion: ``F > 0`` while sliding with ``v > 0``. The plant is
``m·a = u − F − F_other``.

State
-----
A model is immutable: it holds only its frozen parameter dataclass (``model.params``, SI units).
Its internal state is a separate ``numpy.float64`` 1-D array of length ``model.n_states``
(0 for static models), created relaxed by :meth:`FrictionModel.initial_state` and advanced in place.
The same model object can therefore drive the plant, a feed-forward copy and a fit at once.

Three paths, one set of equations
---------------------------------
* :meth:`step` -- scalar, per sample, real-time safe (used by the control loop's feed-forward).
* :meth:`kernel` -- numba-jitted ``step``/``force`` functions plus a packed parameter vector, which the
  plant (``stagectl.sim``) fuses into its compiled integration loop, and fitting uses for batches.
* :meth:`force_along` / :meth:`force_along_batch` -- a whole prescribed trajectory (fast path).
A test checks that all paths agree (docs/architecture.md section 1).

``force_along(x, t)`` semantics: starting from the relaxed state, for k >= 1 the sample interval
has ``dx = x[k] − x[k−1]``, ``dt = t[k] − t[k−1]``, ``v = dx/dt`` (constant over the interval) and
``F[k] = step(state, dx, v, dt)``. ``F[0] = force(relaxed state, v0)`` with ``v0`` the first
difference velocity (0 for a single sample).
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar, NamedTuple

import numpy as np
import numpy.typing as npt

from stagectl.outputs import plain
from stagectl.schema import load

FloatArray = npt.NDArray[np.float64]


class FrictionKernel(NamedTuple):
    """Compiled form of a model for fused loops (plant integration, batch fitting).

    Attributes
    ----------
    step : numba dispatcher
        ``step(p, state, dx, v, dt) -> F``: advance ``state`` in place over an interval with
        displacement ``dx`` [m] at velocity ``v`` [m/s] during ``dt`` [s]; return ``F`` [N] at its end.
    force : numba dispatcher
        ``force(p, state, v) -> F`` without advancing.
    p : ndarray
        Packed float64 parameter vector understood by ``step`` and ``force``.
    breakaway_n : float
        For static models (no pre-sliding state): the break-away level Fs [N] that a plant must use for
        a Karnopp stick band (``|v| < stick_velocity_m_s`` and ``|F_ext| <= breakaway_n`` -> stuck,
        ``F = F_ext``). ``0.0`` for dynamic models, which need no stick treatment.
    stick_velocity_m_s : float
        Half-width of the Karnopp zero-velocity band [m/s] (0.0 for dynamic models).
    """

    step: Any
    force: Any
    p: FloatArray
    breakaway_n: float
    stick_velocity_m_s: float


class FrictionModel(ABC):
    """Base class of all friction models. Subclasses are registered with :func:`register`."""

    #: registry tag used as ``model:`` in YAML
    tag: ClassVar[str]
    #: the frozen parameter dataclass type (fields declared with ``stagectl.schema.param``)
    Params: ClassVar[type[Any]]

    def __init__(self, params: Any):
        if not isinstance(params, self.Params):
            raise TypeError(f"{type(self).__name__} needs {self.Params.__name__}, got {type(params).__name__}")
        self.params: Any = params  # subclasses narrow it to their Params dataclass

    # ----------------------------------------------------------------- state
    @property
    @abstractmethod
    def n_states(self) -> int:
        """Number of internal states (0 for static models)."""

    @abstractmethod
    def initial_state(self) -> FloatArray:
        """A new relaxed state array (all elements unloaded, no memory), shape ``(n_states,)``."""

    # ----------------------------------------------------------------- scalar path (real-time safe)
    @abstractmethod
    def step(self, state: FloatArray, dx: float, v: float, dt: float) -> float:
        """Advance ``state`` in place; return the friction force [N] at the end of the interval.

        Real-time safe: no allocation beyond Python floats, no I/O.
        """

    @abstractmethod
    def force(self, state: FloatArray, v: float) -> float:
        """Friction force [N] for the current ``state`` at velocity ``v`` [m/s], without advancing."""

    def plain_stepper(self) -> Callable[[list[float], float, float, float], float] | None:
        """:meth:`step` in plain Python, imports no numba: ``f(state, dx, v, dt) -> F`` on a state *list*
        (``initial_state().tolist()``, the same layout), advanced in place; the same results as :meth:`step`
        (bit for bit in the tests). None: this model has no plain form (then :meth:`step` is the only one)."""
        return None

    def derivative(self, state: FloatArray, v: float) -> FloatArray:
        """State derivative d(state)/dt at velocity ``v`` (for ODE cross-checks). Static models: empty."""
        raise NotImplementedError(f"{self.tag}: no continuous-time derivative form")

    # ----------------------------------------------------------------- compiled path
    @abstractmethod
    def kernel(self) -> FrictionKernel:
        """Compiled step/force functions and packed parameters (see :class:`FrictionKernel`)."""

    # ----------------------------------------------------------------- trajectory paths
    def force_along(self, x: npt.ArrayLike, t: npt.ArrayLike) -> FloatArray:
        """Friction force [N] along a prescribed position trajectory ``x`` [m] sampled at ``t`` [s].

        Starts from the relaxed state. See the module docstring for the exact sampling convention.
        """
        xa, ta = _check_xt(x, t)
        out = np.empty(xa.shape[0])
        state = self.initial_state()
        v0 = (xa[1] - xa[0]) / (ta[1] - ta[0]) if xa.shape[0] > 1 else 0.0
        out[0] = self.force(state, float(v0))
        for k in range(1, xa.shape[0]):
            dx = float(xa[k] - xa[k - 1])
            dt = float(ta[k] - ta[k - 1])
            out[k] = self.step(state, dx, dx / dt, dt)
        return out

    @classmethod
    def force_along_batch(cls, params: Sequence[Any], x: npt.ArrayLike, t: npt.ArrayLike) -> FloatArray:
        """Force for many parameter sets along one trajectory: shape ``(len(params), len(x))``."""
        return np.stack([cls(p).force_along(x, t) for p in params])

    # ----------------------------------------------------------------- serialisation
    def spec(self) -> dict[str, Any]:
        """The YAML mapping (``model:`` tag + parameters) that :func:`stagectl.friction.build` accepts."""
        out: dict[str, Any] = {"model": self.tag}
        for f in dataclasses.fields(self.params):
            val = getattr(self.params, f.name)
            out[f.name] = plain(val)
        return out

    def replace(self, **changes: Any) -> FrictionModel:
        """A new model of the same kind with some parameters changed (validated again).

        Raises
        ------
        ConfigError
            An unknown parameter name or a value out of range, naming the key.
        """
        spec = self.spec()
        del spec["model"]
        spec.update({k: plain(v) for k, v in changes.items()})
        return type(self)(load(self.Params, spec, "friction"))

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.params!r})"


def _check_xt(x: npt.ArrayLike, t: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    xa = np.ascontiguousarray(x, dtype=np.float64)
    ta = np.ascontiguousarray(t, dtype=np.float64)
    if xa.ndim != 1 or ta.shape != xa.shape:
        raise ValueError(f"x and t must be 1-D arrays of the same length (got {xa.shape} and {ta.shape})")
    if xa.shape[0] == 0:
        raise ValueError("x is empty")
    if not (np.all(np.isfinite(xa)) and np.all(np.isfinite(ta))):
        raise ValueError("x and t must be finite")
    if xa.shape[0] > 1 and not np.all(np.diff(ta) > 0):
        raise ValueError("t must be strictly increasing")
    return xa, ta


_REGISTRY: dict[str, type[FrictionModel]] = {}


def register(cls: type[FrictionModel]) -> type[FrictionModel]:
    """Class decorator: make ``cls`` buildable as ``model: <cls.tag>``."""
    if cls.tag in _REGISTRY and _REGISTRY[cls.tag] is not cls:
        raise ValueError(f"friction model tag {cls.tag!r} registered twice")
    _REGISTRY[cls.tag] = cls
    return cls


def registry() -> Mapping[str, type[FrictionModel]]:
    return dict(_REGISTRY)


Builder = Callable[[Mapping[str, Any]], FrictionModel]
