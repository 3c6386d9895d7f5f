"""Shared numba helpers for friction kernels (pure math).

Kernel calling convention (see :class:`stagectl.friction.base.FrictionKernel`)::

    step(p, state, dx, v, dt) -> F      advance ``state`` in place over one interval
    force(p, state, v) -> F             force for the current state, without advancing

with ``p`` and ``state`` C-contiguous float64 1-D arrays (``state`` may have length 0) and the scalars
float64. Compiled loops (the plant, :func:`along`, :func:`along_batch`) receive ``step`` / ``force`` as
*first-class function* arguments of type :data:`STEP_FN` / :data:`FORCE_FN` (wrapped in one-element
typed lists, :func:`kernel_lists`, which unbox ~30× faster from Python): numba calls through a function
pointer, so a loop is compiled and cached once for all models (``cache=True`` works; a
``Dispatcher``-typed argument would defeat the on-disk cache). Any ``@njit`` function with the
signature :data:`STEP_SIG` / :data:`FORCE_SIG` can be used, lazily compiled ones included.

Also here: the Stribeck curve, used by every model that has one::

    g(v) = Fc + (Fs − Fc)·exp(−|v/Vs|^δ)       unsigned magnitude [N]
    s(v) = sgn(v)·g(v)                          signed [N]
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from stagectl.jit import dispatcher, kernel, plain

FloatArray = npt.NDArray[np.float64]

#: numba's types for compiled loops that take kernels as arguments, made on first use (:func:`_numba_types`;
#: importing this module imports no numba): ``STEP_SIG``/``FORCE_SIG`` the signatures of a kernel
#: ``step(p, state, dx, v, dt) -> F`` / ``force(p, state, v) -> F``, ``STEP_FN``/``FORCE_FN`` their first-class
#: function types, ``STEP_LIST``/``FORCE_LIST`` typed lists of them, ``List`` numba's typed list. Read them as
#: attributes of this module.
_NUMBA_NAMES = ("STEP_SIG", "FORCE_SIG", "STEP_FN", "FORCE_FN", "STEP_LIST", "FORCE_LIST", "List")
# declared, not assigned: the names exist once _numba_types() ran (the module __getattr__ runs it)
STEP_SIG: Any
FORCE_SIG: Any
STEP_FN: Any
FORCE_FN: Any
STEP_LIST: Any
FORCE_LIST: Any
List: Any


def _numba_types() -> None:
    """Put numba's types of :data:`_NUMBA_NAMES` into this module's globals (where the compiled wrappers below
    read them; this imports numba)."""
    g = globals()
    if "STEP_FN" in g:
        return
    from numba import types
    from numba.typed import List

    arr = types.float64[::1]
    step_sig = types.float64(arr, arr, types.float64, types.float64, types.float64)
    force_sig = types.float64(arr, arr, types.float64)
    step_fn = types.FunctionType(step_sig)
    force_fn = types.FunctionType(force_sig)
    g.update(STEP_SIG=step_sig, FORCE_SIG=force_sig, STEP_FN=step_fn, FORCE_FN=force_fn,
             STEP_LIST=types.ListType(step_fn),  # type: ignore[no-untyped-call]  # numba types are unannotated
             FORCE_LIST=types.ListType(force_fn), List=List)  # type: ignore[no-untyped-call]


def __getattr__(name: str) -> Any:
    if name in _NUMBA_NAMES:
        _numba_types()
        return globals()[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


@kernel(inline="always")
def sgn(v: float) -> float:
    """sgn(v) with sgn(0) = 0."""
    if v > 0.0:
        return 1.0
    if v < 0.0:
        return -1.0
    return 0.0


@kernel(inline="always")
def stribeck_excess(v: float, vs: float, delta: float) -> float:
    """exp(−|v/Vs|^δ) [–], fast: δ = 2 and δ = 1 avoid ``pow``, and arguments past the underflow
    threshold return 0 directly (glibc's underflow path of ``exp`` is ~10× slower than a normal call)."""
    r = abs(v / vs)
    if delta == 2.0:
        e = r * r
    elif delta == 1.0:
        e = r
    else:
        e = r**delta
    if e > 745.0:
        return 0.0
    return math.exp(-e)


@kernel(inline="always")
def stribeck_g(v: float, fc: float, fs: float, vs: float, delta: float) -> float:
    """Unsigned Stribeck magnitude g(v) = Fc + (Fs − Fc)·exp(−|v/Vs|^δ) [N]."""
    return fc + (fs - fc) * stribeck_excess(v, vs, delta)


# typed lists holding one kernel function each (STEP_LIST, FORCE_LIST). Passing a first-class function from Python
# costs ~20-30 µs per call (boxing); a typed list holding it unboxes in ~1 µs (plant step, short force_along).


@kernel
def wrap_step(f: Any) -> Any:  # pragma: no cover - compiled
    """A one-element typed list holding a kernel ``step`` function."""
    out = List.empty_list(STEP_FN)
    out.append(f)
    return out


@kernel
def wrap_force(f: Any) -> Any:  # pragma: no cover - compiled
    """A one-element typed list holding a kernel ``force`` function."""
    out = List.empty_list(FORCE_FN)
    out.append(f)
    return out


@kernel
def along(kls: Any, klf: Any, p: FloatArray, state: FloatArray, x: FloatArray, t: FloatArray,
          out: FloatArray) -> None:  # pragma: no cover - compiled
    """``force_along`` convention of ``stagectl.friction.base`` into ``out`` (state advanced in place)."""
    step = kls[0]
    force = klf[0]
    n = x.shape[0]
    v0 = (x[1] - x[0]) / (t[1] - t[0]) if n > 1 else 0.0
    out[0] = force(p, state, v0)
    for k in range(1, n):
        dx = x[k] - x[k - 1]
        dt = t[k] - t[k - 1]
        out[k] = step(p, state, dx, dx / dt, dt)


@kernel
def along_batch(kls: Any, klf: Any, P: FloatArray, S: FloatArray, x: FloatArray, t: FloatArray,
                out: FloatArray) -> None:  # pragma: no cover - compiled
    """:func:`along` for every row of the packed-parameter matrix ``P`` (states in rows of ``S``)."""
    step = kls[0]
    force = klf[0]
    n = x.shape[0]
    for j in range(P.shape[0]):
        p = P[j]
        st = S[j]
        v0 = (x[1] - x[0]) / (t[1] - t[0]) if n > 1 else 0.0
        out[j, 0] = force(p, st, v0)
        for k in range(1, n):
            dx = x[k] - x[k - 1]
            dt = t[k] - t[k - 1]
            out[j, k] = step(p, st, dx, dx / dt, dt)


_LISTS: dict[tuple[str, int], Any] = {}
_KEEP: list[Any] = []  # the dispatchers behind _LISTS' ids stay alive


def _typed_list(kind: str, fn: Any) -> Any:
    fn = dispatcher(fn)  # compiled code takes numba's dispatcher as a first-class function, not a LazyKernel
    key = (kind, id(fn))
    got = _LISTS.get(key)
    if got is None:
        _numba_types()
        wrap: Any
        wrap, sig = (wrap_step, STEP_LIST(STEP_FN)) if kind == "step" else (wrap_force, FORCE_LIST(FORCE_FN))
        if not wrap.signatures:
            # compile (or load) the wrapper for its one signature and lock it: called with a dispatcher it then
            # converts it to the first-class function type instead of specialising on the dispatcher's own
            # type (which could not be cached)
            wrap.compile(sig)
            wrap.disable_compile()
        got = wrap(fn)
        _LISTS[key] = got
        _KEEP.append(fn)
    return got


def step_list(kstep: Any) -> Any:
    """A typed list holding ``kstep`` (made once per dispatcher; the plant needs only this one)."""
    return _typed_list("step", kstep)


def kernel_lists(kstep: Any, kforce: Any) -> tuple[Any, Any]:
    """Typed lists for ``(kstep, kforce)``, made once per dispatcher."""
    return step_list(kstep), _typed_list("force", kforce)


def run_along(kstep: Any, kforce: Any, p: FloatArray, state: FloatArray, x: FloatArray,
              t: FloatArray) -> FloatArray:
    """Python entry to :func:`along` (arrays already checked)."""
    out = np.empty(x.shape[0])
    kls, klf = kernel_lists(kstep, kforce)
    along(kls, klf, p, state, x, t, out)
    return out


def run_along_batch(kstep: Any, kforce: Any, packed: Sequence[FloatArray], states: Sequence[FloatArray],
                    x: FloatArray, t: FloatArray) -> FloatArray:
    """Python entry to :func:`along_batch`; all packed vectors (and states) must have equal length."""
    P = np.ascontiguousarray(np.stack(packed), dtype=np.float64)
    ns = len(states[0]) if len(states) else 0
    S = np.zeros((len(packed), ns)) if ns == 0 else np.ascontiguousarray(np.stack(states), dtype=np.float64)
    out = np.empty((P.shape[0], x.shape[0]))
    kls, klf = kernel_lists(kstep, kforce)
    along_batch(kls, klf, P, S, x, t, out)
    return out


# ---------------------------------------------------------------------------------------------- mixin
from stagectl.friction.base import FrictionKernel, FrictionModel, _check_xt  # noqa: E402


class KernelModel(FrictionModel):
    """Base for models whose every path runs on one compiled kernel.

    A subclass provides ``_pack(params) -> ndarray`` (static), ``_relaxed(params) -> ndarray`` (static),
    the module-level ``@njit`` functions ``_kstep`` / ``_kforce`` (class attributes holding the
    dispatchers) and the Karnopp values through :meth:`_stick`. :meth:`step`, :meth:`force`,
    :meth:`force_along` and :meth:`force_along_batch` then all run the same compiled equations; the tests
    cross-check them against independent plain-Python references.
    """

    _kstep: Any
    _kforce: Any

    def __init__(self, params: Any):
        super().__init__(params)
        self._p = self._pack(params)
        self._s0 = self._relaxed(params)

    # subclass hooks ---------------------------------------------------------------------------
    @staticmethod
    def _pack(params: Any) -> FloatArray:  # pragma: no cover - abstract
        raise NotImplementedError

    @staticmethod
    def _relaxed(params: Any) -> FloatArray:  # pragma: no cover - abstract
        raise NotImplementedError

    def _stick(self) -> tuple[float, float]:
        """(breakaway_n, stick_velocity_m_s) for a plant's Karnopp band; (0, 0) for dynamic models."""
        return 0.0, 0.0

    # FrictionModel ----------------------------------------------------------------------------
    @property
    def n_states(self) -> int:
        return int(self._s0.shape[0])

    def initial_state(self) -> FloatArray:
        return self._s0.copy()

    def step(self, state: FloatArray, dx: float, v: float, dt: float) -> float:
        """Advance ``state`` in place over one interval; real-time safe (one compiled call, ~1 µs)."""
        return float(type(self)._kstep(self._p, state, float(dx), float(v), float(dt)))

    def force(self, state: FloatArray, v: float) -> float:
        return float(type(self)._kforce(self._p, state, float(v)))

    def plain_stepper(self) -> Callable[[list[float], float, float, float], float]:
        """The model's step kernel run as plain Python (:func:`stagectl.jit.plain`: its own source, the kernels
        it calls likewise) with the packed parameters as a list: ``f(state, dx, v, dt) -> F``. A GMS (N = 6)
        step costs ~2-3 µs in the interpreter (docs/performance.md)."""
        return functools.partial(plain(type(self)._kstep), self._p.tolist())

    def kernel(self) -> FrictionKernel:
        fb, dv = self._stick()
        # the compiled form: numba's dispatchers (this imports numba), which compiled loops take as values
        return FrictionKernel(dispatcher(type(self)._kstep), dispatcher(type(self)._kforce), self._p.copy(), fb, dv)

    def force_along(self, x: npt.ArrayLike, t: npt.ArrayLike) -> FloatArray:
        xa, ta = _check_xt(x, t)
        return run_along(type(self)._kstep, type(self)._kforce, self._p, self.initial_state(), xa, ta)

    @classmethod
    def force_along_batch(cls, params: Sequence[Any], x: npt.ArrayLike, t: npt.ArrayLike) -> FloatArray:
        xa, ta = _check_xt(x, t)
        models = [cls(p) for p in params]
        if not models:
            return np.empty((0, xa.shape[0]))
        if len({m._p.shape[0] for m in models}) != 1:  # e.g. GMS sets with different N
            return np.stack([m.force_along(xa, ta) for m in models])
        return run_along_batch(cls._kstep, cls._kforce, [m._p for m in models],
                               [m.initial_state() for m in models], xa, ta)
