"""The simulated stage plant: rigid body + any friction model + additional effects + sensor/actuator.

Equations (SI units; friction and F_other oppose motion, see ``stagectl.friction.effects``)::

    m·dv/dt = u_a(t) − F'(x, v, z) − F_other(x),     dx/dt = v
    u_a(t)  = sat(u(t − τ), ±max_force_n)              actuator: force limit, delay τ = effects.delay.delay_s
    F'      = effects.modify_friction(F, x)            position ripple, then asymmetry,
              + effects.velocity_force(v)               plus the viscous asymmetry d_v·|v|
    F_other = effects.other_force(x)                   cogging + offset + spring

``u`` is the commanded force, held constant over each ``step(u, dt)`` call (zero-order hold). The delayed
force ``u(t − τ)`` is exact for any τ, including sub-sample τ: each sub-step uses the time average of the
delayed piecewise-constant command over the sub-step. Before the first command u = 0.

Integration (fused, compiled with numba, one loop per friction model with the model's step pasted in; a plain
plant's ``step`` runs a small per-cycle kernel that calls the model's compiled step instead, cheap to compile for
a cold start, same arithmetic and bits):
``step(dt)`` uses ``n = ceil(dt/substep_s)`` equal sub-steps h = dt/n of semi-implicit (symplectic) Euler::

    v ← v + h·(u_a − F' − F_other(x))/m ;  Δx = h·v ;  x ← x + Δx ;  F ← friction.step(state, Δx, v, h)

Friction state updates are the models' own exact updates (elastic clipping, exponential slip), so the
only stability limits are the explicit mechanical ones. With K the pre-sliding stiffness (Σk_i, σ0)
and c the total damping (viscous + micro-damping)::

    h·√(K/m) < 2      and      h·c/m < 1      (stable; keep h·√(K/m) < 0.2 for < 0.2 % frequency error)

The default ``substep_s = 1e-5`` s satisfies this up to K = 2e6 N/m at m = 0.5 kg (h·ω = 0.02).

Static models (kernel ``breakaway_n > 0``) get a Karnopp zero-velocity band: while ``|v| <
stick_velocity_m_s`` (or right after v changes sign within a sub-step) the stage is held (v = 0, x
frozen) as long as ``|u_a − F_other| <= Fs`` (ripple/asymmetry applied to Fs); the friction then equals
``u_a − F_other``. Above, it breaks away with ``F = ±Fs``.

Sensor: ``measure()`` returns the position after the last ``step`` (delayed by ``delay_steps`` calls),
plus white Gaussian noise (std ``noise_std_m``, drawn once per step), quantised to ``resolution_m``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from stagectl.errors import ConfigError, short
from stagectl.friction import Effects, FrictionModel, StageModel, parse_effects, parse_friction
from stagectl.friction.effects import modify_friction_kernel as _modify
from stagectl.friction.effects import other_force_kernel as _other
from stagectl.friction.effects import velocity_force_kernel as _vforce
from stagectl.jit import dispatcher, inlined, kernel, plain
from stagectl.schema import load, param

FloatArray = npt.NDArray[np.float64]


# ================================================================================================ config
@dataclass(frozen=True)
class SensorConfig:
    """Position sensor model: noise, then quantisation, then a delay in whole plant steps."""

    resolution_m: float = param(1e-9, unit="m", desc="quantisation step (one count)", ge=1e-15)
    noise_std_m: float = param(0.0, unit="m", desc="white Gaussian noise std added before quantisation", ge=0.0,
                               le=1.0)
    delay_steps: int = param(0, unit="", desc="measurement delay in plant.step() calls", ge=0, le=100000)


@dataclass(frozen=True)
class ActuatorConfig:
    """Force actuator limit (its delay is ``effects.delay``, the single source of truth)."""

    max_force_n: float = param(math.inf, unit="N", desc="force saturation |u| <= max_force_n", gt=0.0,
                               allow_inf=True)


def _unresolved_model_file(value: Any, path: str, problems: list[str]) -> None:
    """Parse hook of ``PlantConfig.model_file``: the schema never accepts the key by itself (through
    :func:`~stagectl.schema.load`, a section parser or an enclosing section), since nothing there reads the
    file; only :meth:`PlantConfig.from_mapping`, handed the resolved model, takes it."""
    if value is None:
        return None
    if not isinstance(value, str):
        problems.append(f"{path}: expected a path string, got {short(value)}")
    else:
        problems.append(f"{path}: {value} is not loaded (load the configuration with stagectl.config, or pass "
                        "the StageModel to PlantConfig.from_mapping as model=)")
    return None


@dataclass(frozen=True)
class PlantConfig:
    """Stage plant configuration (YAML block, e.g. ``plant:``). Build from YAML with :meth:`from_mapping`."""

    mass_kg: float = param(unit="kg", desc="moving mass m", gt=0.0)
    friction: FrictionModel = param(desc="friction model (model: tag + parameters)", parse=parse_friction)
    effects: Effects = param(default_factory=Effects, desc="additional effects (offset, ripple, cogging, ...)",
                             parse=parse_effects)
    substep_s: float = param(1e-5, unit="s", desc="maximum integration sub-step h", ge=1e-7, le=1e-2)
    sensor: SensorConfig = param(default_factory=SensorConfig, desc="position sensor model")
    actuator: ActuatorConfig = param(default_factory=ActuatorConfig, desc="force actuator model")
    x0_m: float = param(0.0, unit="m", desc="initial position")
    seed: int = param(0, unit="", desc="seed of the sensor-noise generator", ge=0)
    model_file: str | None = param(None, desc="model file (StageModel) supplying mass/friction/effects; "
                                   "inline keys override; relative to the YAML file's directory (loaded by "
                                   "the configuration layer and handed to from_mapping as model=)",
                                   parse=_unresolved_model_file)

    def __post_init__(self) -> None:
        # explicit-integration stability (module docstring): h·√(K/m) < 2 and h·c/m < 1, checked with margin
        # for models that declare their pre-sliding stiffness K / total damping c
        k = getattr(self.friction, "stiffness_n_m", None)
        if isinstance(k, float) and k > 0.0 and self.substep_s * math.sqrt(k / self.mass_kg) > 1.0:
            h_max = 1.0 / math.sqrt(k / self.mass_kg)
            raise ValueError(f"substep_s: must be <= {h_max:.3g} s for stiffness {k:.4g} N/m and mass "
                             f"{self.mass_kg:g} kg (h·√(K/m) <= 1; got {self.substep_s:g} s)")
        c = getattr(self.friction, "damping_n_s_m", None)
        if isinstance(c, float) and c > 0.0 and self.substep_s * c / self.mass_kg > 0.5:
            raise ValueError(f"substep_s: must be <= {0.5 * self.mass_kg / c:.3g} s for damping {c:.4g} N·s/m "
                             f"and mass {self.mass_kg:g} kg (h·c/m <= 0.5; got {self.substep_s:g} s)")

    @classmethod
    def from_mapping(cls, data: Any, path: str = "plant", model: StageModel | None = None) -> PlantConfig:
        """Validate a YAML mapping into a :class:`PlantConfig`, merged over ``model``.

        ``model`` is the stage model of ``model_file`` as loaded by the configuration layer (this method
        reads no file): its ``mass_kg``, ``friction`` and ``effects`` are the defaults; inline keys override
        them. An inline ``friction`` mapping without ``model:`` updates the model's friction parameters; an
        inline ``effects`` mapping updates the model's effects one effect at a time.

        Raises
        ------
        ConfigError
            Every problem at once, each prefixed with its key path; ``model_file`` given without ``model``.
        """
        if data is None:
            data = {}
        if not isinstance(data, Mapping):
            raise ConfigError(f"{path}: expected a mapping, got {type(data).__name__} {short(data)}")
        merged: dict[str, Any] = dict(data)
        mf = merged.get("model_file")
        if mf is not None and not isinstance(mf, str):
            raise ConfigError(f"{path}.model_file: expected a path string, got {short(mf)}")
        if mf is not None and model is None:
            problems: list[str] = []
            _unresolved_model_file(mf, f"{path}.model_file", problems)
            raise ConfigError(problems)
        if mf is not None:
            del merged["model_file"]  # resolved: given to the dataclass below, past the schema's refusal
        sm = model
        if sm is not None:
            if "mass_kg" not in merged and sm.mass_kg is not None:
                merged["mass_kg"] = sm.mass_kg
            fr = merged.get("friction")
            if fr is None:
                merged["friction"] = sm.friction
            elif isinstance(fr, Mapping) and "model" not in fr:
                merged["friction"] = {**sm.friction.spec(), **fr}
            eff = merged.get("effects")
            if eff is None:
                merged["effects"] = sm.effects
            elif isinstance(eff, Mapping):
                merged["effects"] = {**sm.effects.spec(), **eff}
        cfg = load(cls, merged, path)
        return dataclasses.replace(cfg, model_file=mf) if mf is not None else cfg


# ================================================================================================ kernels
@kernel
def _u_avg(ht: FloatArray, hu: FloatArray, nh: int, a: float, b: float) -> float:  # pragma: no cover
    """Time average over [a, b] of the command u(s) = hu[j] on [ht[j], ht[j+1]) (0 before ht[0])."""
    if nh == 0 or b <= ht[0]:
        return 0.0
    j = np.searchsorted(ht[:nh], a, side="right") - 1
    acc = 0.0
    s = a
    while s < b:
        if j < 0:
            end = ht[0]
            val = 0.0
        else:
            end = ht[j + 1] if j + 1 < nh else np.inf
            val = hu[j]
        e = end if end < b else b
        if e > s:
            acc += val * (e - s)
            s = e
        j += 1
    return acc / (b - a)


# ps (plant state) layout
_T, _X, _V, _FF, _FO, _UA, _STUCK, _WIN, _WF, _WO = range(10)
#: the loop's locals x, v, ff, stuck, win, wf, wo (see :func:`load_state`)
_Locals = tuple[float, float, float, float, float, float, float]


@kernel(inline="always")
def load_state(ps: FloatArray) -> _Locals:  # pragma: no cover - compiled
    """``(x, v, ff, stuck, win, wf, wo)`` of the plant state array ``ps`` (the loop's locals)."""
    return ps[_X], ps[_V], ps[_FF], ps[_STUCK], ps[_WIN], ps[_WF], ps[_WO]


@kernel(inline="always")
def store_state(ps: FloatArray, x: float, v: float, ff: float, stuck: float, win: float, wf: float,
                wo: float) -> None:  # pragma: no cover - compiled
    """Write the loop's locals back into ``ps`` (inverse of :func:`load_state`)."""
    ps[_X] = x
    ps[_V] = v
    ps[_FF] = ff
    ps[_STUCK] = stuck
    ps[_WIN] = win
    ps[_WF] = wf
    ps[_WO] = wo


@kernel(inline="always")
def substep(kstep: Any, kp: FloatArray, fs: FloatArray, ep: FloatArray, fb: float, dv: float, inv_m: float,
            h: float, ua: float, x: float, v: float, ff: float, stuck: float, win: float, wf: float,
            wo: float) -> _Locals:  # pragma: no cover - compiled
    """One general sub-step h [s] (module docstring), inlined where it is used: the plant's general loop and the
    friction side of ``stagectl.sim.backlash``. ``kstep`` is the friction kernel (parameters ``kp``, state ``fs``
    advanced in place), ``ep`` the packed effects, ``fb``/``dv`` the Karnopp break-away [N] and band [m/s] (fb = 0:
    no band), ``ua`` the applied force [N]. Returns the new ``(x, v, ff, stuck, win, wf, wo)``: position [m],
    velocity [m/s], friction F' [N], stuck flag, work totals applied/friction/other [J]."""
    fo = _other(ep, x)
    fe = ua - fo
    if fb > 0.0 and (stuck != 0.0 or abs(v) < dv):
        # Karnopp band (static models): hold while the net force stays below break-away
        lim = _modify(ep, fb, x) if fe > 0.0 else -_modify(ep, -fb, x)
        if abs(fe) <= lim:
            kstep(kp, fs, 0.0, 0.0, h)  # lag states relax at rest
            return x, 0.0, fe, 1.0, win, wf, wo
        ff = lim if fe > 0.0 else -lim
        v = v + h * (fe - ff) * inv_m
        dx = h * v
        kstep(kp, fs, dx, v, h)
        return x + dx, v, ff, 0.0, win + ua * dx, wf + ff * dx, wo + fo * dx
    v_old = v
    v = v + h * (fe - ff) * inv_m
    if fb > 0.0 and v * v_old < 0.0:
        # velocity crossed zero inside the sub-step: stop here, the stick test follows
        lim = _modify(ep, fb, x) if fe > 0.0 else -_modify(ep, -fb, x)
        ff = fe if abs(fe) <= lim else (lim if fe > 0.0 else -lim)
        kstep(kp, fs, 0.0, 0.0, h)
        return x, 0.0, ff, 1.0, win, wf, wo
    dx = h * v
    x = x + dx
    win = win + ua * dx
    wf = wf + ff * dx
    wo = wo + fo * dx
    ff = _modify(ep, kstep(kp, fs, dx, v, h), x) + _vforce(ep, v)
    return x, v, ff, stuck, win, wf, wo


# par layout: [mass, breakaway_n, stick_velocity, delay_s]

@kernel(inline="always")
def _step_end(t: float, dt: float, cnt: int, every: int, j: int, ot: FloatArray, ox: FloatArray, ov: FloatArray,
              of: FloatArray, x: float, v: float, ff: float) -> tuple[float, int, int]:  # pragma: no cover
    """End of one held command of ``dt`` [s]: the time advanced and, every ``every``-th step, the outputs stored
    into row ``j`` of those of ``ot`` [s], ``ox`` [m], ``ov`` [m/s], ``of`` [N] that are not empty. Returns the
    new ``(t, cnt, j)``."""
    t = t + dt
    cnt += 1
    if cnt != every:
        return t, cnt, j
    if ot.shape[0] > 0:
        ot[j] = t
    if ox.shape[0] > 0:
        ox[j] = x
    if ov.shape[0] > 0:
        ov[j] = v
    if of.shape[0] > 0:
        of[j] = ff
    return t, 0, j + 1


@kernel(inline="always")
def _finish(ps: FloatArray, t: float, fo: float, ua: float, x: float, v: float, ff: float, stuck: float, win: float,
            wf: float, wo: float) -> None:  # pragma: no cover - compiled
    """The loop's end state into ``ps``: time, F_other, applied force and the locals of :func:`load_state`."""
    ps[_T] = t
    ps[_FO] = fo
    ps[_UA] = ua
    store_state(ps, x, v, ff, stuck, win, wf, wo)


def plain_effects(ep: FloatArray) -> bool:
    """Whether the packed effects ``ep`` (:meth:`~stagectl.friction.Effects.packed`) are the plain loops' kind:
    no friction modifier (asymmetry, position ripple), no velocity force (viscous asymmetry) and a constant
    F_other (no cogging, no spring; an offset is constant). The delay is the caller's to check."""
    return bool(ep[0] == 0.0 and ep[1] == 0.0 and ep[4] == 0.0 and ep[8] == 0.0 and ep[11] == 0.0)


#: :func:`plain_effects` for the compiled loops (pasted in)
_plain_effects = kernel(inline="always")(plain_effects)


def _make_plain(kstep: Any) -> Any:
    """The plain loop (no delay, no Karnopp band, no friction modifier, constant F_other) specialised on one
    friction kernel; ``kstep`` is pasted into the sub-step (``stagectl.jit.inlined``: called as a function it
    cost ~15 % of a GMS plant step). No reference counting (``_nrt=False``; the loop allocates nothing): numba
    would count the arrays handed to the pasted-in step on every sub-step. Compiled on first use and cached
    (keyed on the model kernel's module and source). Same arguments as :func:`_make_integrate`'s loop; ``ht``,
    ``hu``, ``nh0`` are not used."""

    @kernel(_nrt=False)
    def plain_loop(kp, fs, ep, par, ps, ht, hu, nh0, u, dt, nsub, every, ot, ox, ov, of):  # type: ignore[no-untyped-def]  # pragma: no cover
        """``u[k]`` held for ``dt`` in ``nsub`` sub-steps each (see the module docstring)."""
        if par[1] != 0.0 or par[3] != 0.0 or not _plain_effects(ep):
            raise ValueError("plain plant loop called with delay, stick band or position effects")
        inv_m = 1.0 / par[0]
        h = dt / nsub
        t = ps[_T]
        x, v, ff, stuck, win, wf, wo = load_state(ps)
        ua = 0.0
        fo_c = ep[7]
        cnt = 0
        j = 0
        for k in range(u.shape[0]):
            ua = u[k]
            fe = ua - fo_c
            for i in range(nsub):
                v = v + h * (fe - ff) * inv_m
                dx = h * v
                x += dx
                win += ua * dx
                wf += ff * dx
                wo += fo_c * dx
                ff = kstep(kp, fs, dx, v, h)
            t, cnt, j = _step_end(t, dt, cnt, every, j, ot, ox, ov, of, x, v, ff)
        _finish(ps, t, fo_c, ua, x, v, ff, stuck, win, wf, wo)

    return plain_loop


def _make_cycle(kstep: Any) -> Any:
    """The per-cycle step of a plain plant (what :meth:`StagePlant.step` runs: one held command, a few to a
    few hundred sub-steps) specialised on one friction kernel. Unlike :func:`_make_plain`'s loop it *calls*
    ``kstep`` (the same compiled kernel the feed-forward calls: compiled once per process or cache, not pasted
    in and typed again): a cold start
    compiles it in ~0.15 s instead of the plain loop's ~0.75 s, and a step runs as fast (docs/performance.md).
    The arithmetic is the plain loop's, in the same order: its results are bit-identical
    (``tests/sim/test_plant_fast.py``). ``simulate`` keeps the fully optimised plain loop."""

    @kernel(_nrt=False)
    def cycle(kp, fs, ps, inv_m, fo_c, u, dt, nsub):  # type: ignore[no-untyped-def]  # pragma: no cover
        """``u`` [N] held for ``dt`` [s] in ``nsub`` sub-steps (1/m ``inv_m`` [1/kg], constant F_other
        ``fo_c`` [N]); plant state in ``ps``, friction state in ``fs`` (both advanced in place)."""
        # written out, not load_state/_finish: pasting kernels in is what costs compile time here
        h = dt / nsub
        x = ps[_X]
        v = ps[_V]
        ff = ps[_FF]
        win = ps[_WIN]
        wf = ps[_WF]
        wo = ps[_WO]
        fe = u - fo_c
        for i in range(nsub):
            v = v + h * (fe - ff) * inv_m
            dx = h * v
            x += dx
            win += u * dx
            wf += ff * dx
            wo += fo_c * dx
            ff = kstep(kp, fs, dx, v, h)
        ps[_T] = ps[_T] + dt
        ps[_X] = x
        ps[_V] = v
        ps[_FF] = ff
        ps[_FO] = fo_c
        ps[_UA] = u
        ps[_WIN] = win
        ps[_WF] = wf
        ps[_WO] = wo

    return cycle


def _make_integrate(kstep: Any, plain_loop: Any) -> Any:
    """The general fused loop specialised on one friction kernel ``kstep`` (a direct call). A run that is plain
    at run time goes to ``plain_loop`` (:func:`_make_plain`, one call per run). One compiled loop per model,
    compiled on first use and cached (``stagectl.jit``: keyed on the model kernel's module and source)."""

    @kernel(_nrt=False)
    def integrate(kp, fs, ep, par, ps, ht, hu, nh0, u, dt, nsub, every, ot, ox, ov, of):  # type: ignore[no-untyped-def]  # pragma: no cover
        """``u[k]`` held for ``dt`` in ``nsub`` sub-steps each (see the module docstring).

        Plant state in ``ps`` (read at the start, written at the end), friction state in ``fs``; the command
        history ``ht/hu`` holds ``nh0`` earlier commands followed by ``u`` (only used when τ > 0). Outputs after
        every ``every``-th step into ``ot`` [s], ``ox`` [m], ``ov`` [m/s], ``of`` [N] (an output of length 0
        is not stored).
        """
        m = par[0]
        inv_m = 1.0 / m
        fb = par[1]
        dv = par[2]
        tau = par[3]
        if tau == 0.0 and fb == 0.0 and _plain_effects(ep):
            plain_loop(kp, fs, ep, par, ps, ht, hu, nh0, u, dt, nsub, every, ot, ox, ov, of)
            return
        h = dt / nsub
        t = ps[_T]
        x, v, ff, stuck, win, wf, wo = load_state(ps)
        ua = 0.0
        cnt = 0
        j = 0
        for k in range(u.shape[0]):
            nh = nh0 + k + 1
            ua = u[k]
            for i in range(nsub):
                if tau > 0.0:
                    t0 = t + i * h
                    ua = _u_avg(ht, hu, nh, t0 - tau, t0 + h - tau)
                x, v, ff, stuck, win, wf, wo = substep(kstep, kp, fs, ep, fb, dv, inv_m, h, ua, x, v, ff, stuck,
                                                       win, wf, wo)
            t, cnt, j = _step_end(t, dt, cnt, every, j, ot, ox, ov, of, x, v, ff)
        _finish(ps, t, _other(ep, x), ua, x, v, ff, stuck, win, wf, wo)

    return integrate


def _make_batch(kstep: Any, integrate: Any) -> Any:
    """The batch loop for one friction kernel (see :func:`simulate_batch`)."""

    @kernel
    def run_batch(P, S, ep, PAR, ps0, ht, hu, nh0, u, dt, nsub, ox, ov, of):  # type: ignore[no-untyped-def]  # pragma: no cover
        """Every packed parameter row of ``P`` over one input (friction states in the rows of ``S``, plant
        parameters in the rows of ``PAR``). Plain runs (no delay, no Karnopp band, no friction modifier,
        constant F_other) interleave the sets per time step: their dependency chains overlap in the CPU.
        Anything else runs :func:`integrate` set by set."""
        n_sets = P.shape[0]
        plain = nh0 < 0 and _plain_effects(ep)
        for q in range(n_sets):
            if PAR[q, 1] != 0.0 or PAR[q, 3] != 0.0:
                plain = False
        if not plain:
            ps = np.empty(ps0.shape[0])
            ot = np.empty(0)
            for q in range(n_sets):
                ps[:] = ps0
                integrate(P[q], S[q], ep, PAR[q], ps, ht, hu, nh0, u, dt, nsub, 1, ot, ox[q], ov[q], of[q])
            return
        h = dt / nsub
        fo_c = ep[7]
        x = np.full(n_sets, ps0[_X])
        v = np.full(n_sets, ps0[_V])
        ff = np.full(n_sets, ps0[_FF])
        inv_m = np.empty(n_sets)
        for q in range(n_sets):
            inv_m[q] = 1.0 / PAR[q, 0]
        for k in range(u.shape[0]):
            fe = u[k] - fo_c
            for i in range(nsub):
                for q in range(n_sets):
                    vq = v[q] + h * (fe - ff[q]) * inv_m[q]
                    dx = h * vq
                    v[q] = vq
                    x[q] += dx
                    ff[q] = kstep(P[q], S[q], dx, vq, h)
            for q in range(n_sets):
                ox[q, k] = x[q]
                ov[q, k] = v[q]
                of[q, k] = ff[q]

    return run_batch


def _make_batch_sets(ksets: Any) -> Any:
    """The plain batch loop for a model with a many-sets kernel ``ksets`` (e.g. ``gms._ksets``): per time step
    the rigid-body update of every set, then one ``ksets`` call for all of them (no per-set calls, no array
    views; the sets' loops have no data-dependent branches)."""

    @kernel
    def run_sets(PT, ST, m, fo_c, x0, u, dt, nsub, ox, ov, of):  # type: ignore[no-untyped-def]  # pragma: no cover
        ns = PT.shape[1]
        h = dt / nsub
        st_x = ox.shape[0] > 0
        st_v = ov.shape[0] > 0
        st_f = of.shape[0] > 0
        x = np.full(ns, x0)
        v = np.zeros(ns)
        ff = np.zeros(ns)
        dx = np.empty(ns)
        inv_m = np.empty(ns)
        for q in range(ns):
            inv_m[q] = 1.0 / m[q]
        for k in range(u.shape[0]):
            fe = u[k] - fo_c
            for i in range(nsub):
                for q in range(ns):
                    vq = v[q] + h * (fe - ff[q]) * inv_m[q]
                    v[q] = vq
                    dx[q] = h * vq
                    x[q] += dx[q]
                ksets(PT, ST, dx, v, h, ff)
            if st_x:
                for q in range(ns):
                    ox[q, k] = x[q]
            if st_v:
                for q in range(ns):
                    ov[q, k] = v[q]
            if st_f:
                for q in range(ns):
                    of[q, k] = ff[q]

    return run_sets


@functools.cache  # keyed on the kernel object itself (identity), which the cache keeps alive
def batch_sets_loop(ksets: Any) -> Any:
    """:func:`_make_batch_sets` made once per many-sets kernel."""
    if dispatcher(ksets) is not ksets:
        return batch_sets_loop(dispatcher(ksets))  # one loop per kernel, however it is handed in
    return _make_batch_sets(ksets)


_LOOPS: dict[int, tuple[Any, Any, Any, Any]] = {}
_OUTPUTS = ("t", "x", "v", "friction", "x_meas")
_EMPTY = np.empty(0)  # an output not stored
_EMPTY1 = np.zeros(1)  # the command history when there is no delay


def loops_for(kstep: Any, plain_only: bool = False) -> tuple[Any, Any]:
    """(loop, run_batch) specialised on the friction kernel ``kstep`` (made once per kernel). The loop is the
    general one (:func:`_make_integrate`), or with ``plain_only`` the plain one alone (:func:`_make_plain`:
    about half the compile time, for plants that are plain by configuration); run_batch is always general."""
    kstep = dispatcher(kstep)  # one set of loops per kernel, however it is handed in
    got = _LOOPS.get(id(kstep))
    if got is None:
        plain = _make_plain(inlined(kstep))
        integ = _make_integrate(kstep, plain)
        got = (plain, integ, _make_batch(kstep, integ), kstep)  # kstep kept alive: its id stays valid
        _LOOPS[id(kstep)] = got
    return (got[0] if plain_only else got[1]), got[2]


@functools.cache  # keyed on the kernel object itself (identity), which the cache keeps alive
def cycle_for(kstep: Any) -> Any:
    """:func:`_make_cycle` made once per friction kernel: the per-cycle step of plain plants."""
    if dispatcher(kstep) is not kstep:
        return cycle_for(dispatcher(kstep))  # one cycle per kernel, however it is handed in
    return dispatcher(_make_cycle(kstep))  # StagePlant.step calls it every cycle: the dispatcher, no proxy


@functools.cache  # keyed on the kernel object itself (identity), which the cache keeps alive
def plain_cycle(kstep: Any) -> Any:
    """:func:`_make_cycle`'s per-cycle step as plain Python (:func:`stagectl.jit.plain`: the same source, ``kstep``'s
    twin inside; no numba), on lists ``kp``, ``fs``, ``ps``: the same arithmetic in the same order
    (``tests/loop/test_bench_tier.py``). For ``stagectl bench startup --switch``: too slow for the loop (~240 µs a
    1 ms cycle of 100 sub-steps, docs/performance.md §1)."""
    return plain(_make_cycle(kstep))


# ================================================================================================ plant
class StagePlant:
    """Rigid-body stage with friction, effects, sensor and actuator models (see module docstring).

    ``step`` and ``measure`` are cheap (one compiled call, a few µs) and allocation-free apart from
    the delay history; the constructor compiles or loads the numba cache of the kernel ``step`` runs, so
    the first ``step`` costs no more than the others. ``simulate`` compiles (or loads) its loop on its first
    call.
    """

    _HIST_CAP = 4096

    def __init__(self, cfg: PlantConfig):
        if not isinstance(cfg, PlantConfig):
            raise TypeError(f"StagePlant needs a PlantConfig, got {type(cfg).__name__}")
        self.cfg = cfg
        kern = cfg.friction.kernel()
        self._kstep = kern.step
        ep = cfg.effects.packed()
        plain = (kern.breakaway_n == 0.0 and not (cfg.effects.delay is not None and cfg.effects.delay.delay_s > 0.0)
                 and plain_effects(ep))
        self._integrate, _ = loops_for(kern.step, plain_only=plain)
        #: the per-cycle step of a plain plant (``step``); ``simulate`` runs ``_integrate``, compiled on its first
        #: call. None: the general loop serves ``step`` too.
        self._cycle = cycle_for(kern.step) if plain else None
        self._kp = np.ascontiguousarray(kern.p, dtype=np.float64)
        self._ep = np.ascontiguousarray(cfg.effects.packed(), dtype=np.float64)
        self._tau = float(cfg.effects.delay.delay_s) if cfg.effects.delay is not None else 0.0
        self._par = np.array([cfg.mass_kg, kern.breakaway_n, kern.stick_velocity_m_s, self._tau])
        self._inv_m = 1.0 / float(cfg.mass_kg)  # as the plain loop computes it (1.0 / par[0])
        self._fo_c = float(self._ep[7])  # the constant F_other of a plain plant
        self._umax = float(cfg.actuator.max_force_n)
        self._res = float(cfg.sensor.resolution_m)
        self._noise = float(cfg.sensor.noise_std_m)
        self._nd = int(cfg.sensor.delay_steps)
        self._ps = np.zeros(10)
        self._u1 = np.zeros(1)
        self._o1 = (np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1))
        self._ht = np.zeros(self._HIST_CAP)
        self._hu = np.zeros(self._HIST_CAP)
        self._nh = 0
        self._ring = np.zeros(self._nd + 1, dtype=np.int64)
        self._ri = 0
        # Compile (or load from the numba cache) the kernel of ``step`` now, not on the first cycle: a virtual
        # drive that built this plant would otherwise stall for the compile (0.01 s from a warm cache, ~0.5 s
        # from an empty one) inside the cyclic exchange and look like a dead drive to its master.
        self.reset()
        self.step(0.0, self.cfg.substep_s)
        self.reset()

    # ------------------------------------------------------------------------------------ lifecycle
    def reset(self, x0_m: float | None = None, seed: int | None = None) -> None:
        """Relaxed friction state, v = 0, t = 0, empty delay history, sensor ring filled with x0."""
        x0 = self.cfg.x0_m if x0_m is None else float(x0_m)
        if not math.isfinite(x0):
            raise ValueError(f"x0_m must be finite (got {x0})")
        self._rng = np.random.default_rng(self.cfg.seed if seed is None else seed)
        self._fs = np.ascontiguousarray(self.cfg.friction.initial_state(), dtype=np.float64)
        ps = self._ps
        ps[:] = 0.0
        ps[_X] = x0
        # a relaxed state at rest carries no friction force (FrictionModel.initial_state; every model is checked
        # in tests/sim): the force kernel is not needed, so a run does not compile it
        ps[_FF] = 0.0
        ps[_FO] = self.cfg.effects.other_force(x0)
        self._nh = 0
        self._ring[:] = self._counts_of(x0)
        self._ri = 0

    # ------------------------------------------------------------------------------------ stepping
    def _nsub(self, dt_s: float) -> int:
        if not (dt_s > 0.0 and math.isfinite(dt_s)):
            raise ValueError(f"dt_s must be > 0 and finite (got {dt_s})")
        return max(1, math.ceil(dt_s / self.cfg.substep_s - 1e-9))

    def _clamp(self, u_n: float) -> float:
        u = float(u_n)
        if not math.isfinite(u):
            raise ValueError(f"u_n must be finite (got {u_n})")
        return min(max(u, -self._umax), self._umax)

    def _push_command(self, t: float, u: float) -> None:
        if self._nh >= self._HIST_CAP:
            self._prune(t)
        self._ht[self._nh] = t
        self._hu[self._nh] = u
        self._nh += 1

    def _prune(self, t_now: float) -> None:
        """Drop commands that can no longer be applied (ended before t_now − τ)."""
        n = self._nh
        keep_from = int(np.searchsorted(self._ht[:n], t_now - self._tau, side="right")) - 1
        keep_from = max(keep_from, 0)
        if keep_from == 0 and n >= self._HIST_CAP:
            raise RuntimeError("delay history overflow: too many commands within delay_s")
        m = n - keep_from
        self._ht[:m] = self._ht[keep_from:n]
        self._hu[:m] = self._hu[keep_from:n]
        self._nh = m

    def step(self, u_n: float, dt_s: float) -> None:
        """Hold the commanded force ``u_n`` [N] for ``dt_s`` [s] (clamped to ±max_force_n, delayed by τ).

        Real-time safe: one compiled call (~1-4 µs for 10 sub-steps of GMS N = 6); no allocation except
        an occasional compaction of the delay history when τ > 0.
        """
        nsub = self._nsub(dt_s)
        u = self._clamp(u_n)
        if self._cycle is not None:
            self._cycle(self._kp, self._fs, self._ps, self._inv_m, self._fo_c, u, float(dt_s), nsub)
            self._sample(self._ps[_X])
            return
        nh0 = -1
        if self._tau > 0.0:
            self._push_command(self._ps[_T], u)
            nh0 = self._nh - 1
        self._u1[0] = u
        o = self._o1
        self._integrate(self._kp, self._fs, self._ep, self._par, self._ps, self._ht,
                        self._hu, nh0, self._u1, float(dt_s), nsub, 1, o[0], o[1], o[2], o[3])
        self._sample(self._ps[_X])

    def simulate(self, u: npt.ArrayLike, dt_s: float, outputs: Sequence[str] | None = None, every: int = 1,
                 out: Mapping[str, FloatArray] | None = None) -> dict[str, FloatArray]:
        """Open-loop fast path: equivalent to ``for uk in u: step(uk, dt_s); measure()``.

        Continues from the current state and leaves the plant where the run ends.

        Parameters
        ----------
        outputs : names, optional
            Which of ``t``, ``x``, ``v``, ``friction``, ``x_meas`` to return (default: all). Only these are
            stored: a long run that needs just ``x`` writes 8 bytes per step, not 40.
        every : int
            Store every ``every``-th step only (steps ``every−1, 2·every−1, …``; ``len(u) // every`` samples).
            ``x_meas`` needs ``every = 1``.
        out : mapping name → array, optional
            Preallocated float64 arrays of length ``len(u) // every`` to write into (repeated runs then touch
            no fresh memory); returned as they are.

        Without ``x_meas`` the sensor is refreshed from the end state only (as :meth:`reset` fills it): a
        following :meth:`measure` reads the final position, without the earlier steps' sensor delay.

        Returns
        -------
        dict
            The requested outputs after each (stored) step: ``t`` [s], ``x`` [m], ``v`` [m/s], ``friction`` [N]
            (F', after effects), ``x_meas`` [m] (sensor reading).
        """
        names = _OUTPUTS if outputs is None else tuple(outputs)
        bad = [nm for nm in names if nm not in _OUTPUTS]
        if bad:
            raise ValueError(f"outputs: unknown {bad} (known: {', '.join(_OUTPUTS)})")
        every = int(every)
        if every < 1:
            raise ValueError(f"every must be >= 1 (got {every})")
        meas_wanted = "x_meas" in names
        if meas_wanted and every != 1:
            raise ValueError(f"x_meas needs every=1 (got every={every}): the sensor delay works on whole steps")
        ua = np.ascontiguousarray(u, dtype=np.float64).ravel()
        if not math.isfinite(float(np.add.reduce(ua))):  # finite sum <=> every entry finite (no temporary)
            raise ValueError("u must be finite")
        nsub = self._nsub(dt_s)
        if math.isfinite(self._umax) and ua.size and float(np.max(np.abs(ua))) > self._umax:
            ua = np.clip(ua, -self._umax, self._umax)
        n = ua.shape[0]
        n_out = n // every
        bufs: dict[str, FloatArray] = {}
        for nm in ("t", "x", "v", "friction"):
            if nm in names or (nm == "x" and meas_wanted):
                given = out.get(nm) if out is not None else None
                if given is not None:
                    if given.dtype != np.float64 or given.shape != (n_out,) or not given.flags.c_contiguous:
                        raise ValueError(f"out[{nm!r}]: needs a C-contiguous float64 array of shape ({n_out},)")
                    bufs[nm] = given
                else:
                    bufs[nm] = np.empty(n_out)
        if n == 0:
            return {nm: bufs.get(nm, np.empty(0)) for nm in names}
        ot, ox, ov, of = (bufs.get(nm, _EMPTY) for nm in ("t", "x", "v", "friction"))
        if self._tau > 0.0:
            if self._nh:
                self._prune(self._ps[_T])
            nh0 = self._nh
            ht = np.empty(nh0 + n)
            hu = np.empty(nh0 + n)
            ht[:nh0] = self._ht[:nh0]
            hu[:nh0] = self._hu[:nh0]
            # the same sequential sums as repeated step() calls (t ← t + dt), so both paths agree bit for bit
            ht[nh0:] = np.cumsum(np.concatenate([[self._ps[_T]], np.full(n - 1, float(dt_s))]))[:n]
            hu[nh0:] = ua
        else:
            nh0 = -1  # the history is not used without delay
            ht = _EMPTY1
            hu = _EMPTY1
        self._integrate(self._kp, self._fs, self._ep, self._par, self._ps, ht, hu,
                        nh0, ua, float(dt_s), nsub, every, ot, ox, ov, of)
        if self._tau > 0.0:
            # keep the tail of the command history for later step() calls
            keep = int(np.searchsorted(ht, self._ps[_T] - self._tau, side="right")) - 1
            keep = max(keep, 0)
            tail_t, tail_u = ht[keep:], hu[keep:]
            if tail_t.shape[0] > self._HIST_CAP:
                raise RuntimeError("delay history overflow: too many commands within delay_s")
            self._nh = tail_t.shape[0]
            self._ht[: self._nh] = tail_t
            self._hu[: self._nh] = tail_u
        result = {nm: bufs[nm] for nm in names if nm != "x_meas"}
        if not meas_wanted:
            self._ring[:] = self._counts_of(float(self._ps[_X]))
            self._ri = 0
            return result
        # sensor: noise (one draw per step), quantisation, delay
        xn = ox + self._rng.normal(0.0, self._noise, n) if self._noise > 0.0 else ox
        counts = np.floor(xn / self._res + 0.5).astype(np.int64)
        if self._nd > 0:
            ring = np.concatenate([self._ordered_ring(), counts])
            meas = ring[1 : n + 1]  # value seen after step k is the one from nd steps before
            tail = ring[-(self._nd + 1):]
            self._ring[:] = tail
            self._ri = 0
        else:
            meas = counts
            self._ring[0] = counts[-1] if n else self._ring[0]
        result["x_meas"] = meas.astype(np.float64) * self._res
        return {nm: result[nm] for nm in names}

    # ------------------------------------------------------------------------------------ sensor
    def _counts_of(self, x: float) -> int:
        if self._noise > 0.0:
            x = x + float(self._rng.normal(0.0, self._noise))
        return math.floor(x / self._res + 0.5)

    def _sample(self, x: float) -> None:
        c = self._counts_of(x)
        if self._nd == 0:
            self._ring[0] = c
        else:
            self._ri = (self._ri + 1) % (self._nd + 1)
            self._ring[self._ri] = c  # newest at _ri, oldest at _ri + 1

    def _ordered_ring(self) -> npt.NDArray[np.int64]:
        """Ring contents oldest → newest (length delay_steps + 1)."""
        return np.roll(self._ring, -(self._ri + 1))

    def measure_counts(self) -> int:
        """Sensor reading in counts of ``resolution_m`` (unbounded integer; wrapping is the device's job)."""
        if self._nd == 0:
            return int(self._ring[0])
        return int(self._ring[(self._ri + 1) % (self._nd + 1)])

    def measure(self) -> float:
        """Sensor reading [m]: position ``delay_steps`` steps ago + noise, quantised to resolution_m."""
        return self.measure_counts() * self._res

    # ------------------------------------------------------------------------------------ readouts
    @property
    def t_s(self) -> float:
        """Simulated time [s]."""
        return float(self._ps[_T])

    @property
    def x_m(self) -> float:
        """True position [m]."""
        return float(self._ps[_X])

    @property
    def v_m_s(self) -> float:
        """True velocity [m/s]."""
        return float(self._ps[_V])

    @property
    def friction_n(self) -> float:
        """Friction force F' (after ripple/asymmetry) at the end of the last sub-step [N]."""
        return float(self._ps[_FF])

    @property
    def other_n(self) -> float:
        """F_other(x) = cogging + offset + spring at the current position [N]."""
        return float(self._ps[_FO])

    @property
    def applied_n(self) -> float:
        """Force applied by the actuator during the last sub-step (after clamp and delay) [N]."""
        return float(self._ps[_UA])

    @property
    def friction_state(self) -> FloatArray:
        """A copy of the friction model's internal state."""
        return self._fs.copy()

    def work_j(self) -> dict[str, float]:
        """Work since reset [J]: by the actuator (∫u_a dx), against friction (∫F' dx) and F_other."""
        return {"applied": float(self._ps[_WIN]), "friction": float(self._ps[_WF]),
                "other": float(self._ps[_WO])}


def simulate_batch(cfg: PlantConfig, frictions: Sequence[FrictionModel], u: npt.ArrayLike,
                   dt_s: float, outputs: Sequence[str] = ("x", "v", "friction")) -> dict[str, FloatArray]:
    """Open-loop runs of the plant ``cfg`` with each friction model in ``frictions`` (one compiled call).

    For fitting and benchmarks: every run starts from rest at ``cfg.x0_m`` with a relaxed friction state;
    mass, effects, actuator and sub-step come from ``cfg`` (``cfg.friction`` is not used). All models must
    be of one class with equally long packed parameters (e.g. GMS sets with the same N).

    ``outputs`` names the arrays wanted: on the many-sets path of GMS only those are written (each is one
    strided store per set and step: three of them cost a batch run of 1000 sets ~10 %).

    Returns
    -------
    dict
        ``x`` [m], ``v`` [m/s], ``friction`` [N] as named in ``outputs``: arrays of shape
        ``(len(frictions), len(u))``.
    """
    bad = [nm for nm in outputs if nm not in ("x", "v", "friction")]
    if bad:
        raise ValueError(f"outputs: unknown {bad} (known: x, v, friction)")
    if not frictions:
        raise ValueError("frictions is empty")
    kerns = [f.kernel() for f in frictions]
    if len({type(f) for f in frictions}) != 1 or len({k.p.shape[0] for k in kerns}) != 1:
        raise ValueError("simulate_batch needs models of one class with equal parameter length")
    plant = StagePlant(dataclasses.replace(cfg, friction=frictions[0]))
    ua = np.clip(np.asarray(u, dtype=np.float64).ravel(), -plant._umax, plant._umax)
    if not np.all(np.isfinite(ua)):
        raise ValueError("u must be finite")
    nsub = plant._nsub(dt_s)
    n = ua.shape[0]
    P = np.ascontiguousarray(np.stack([k.p for k in kerns]), dtype=np.float64)
    states = [f.initial_state() for f in frictions]
    S = (np.ascontiguousarray(np.stack(states), dtype=np.float64) if states[0].shape[0]
         else np.zeros((len(frictions), 0)))
    if plant._tau > 0.0:
        ht = np.cumsum(np.concatenate([[0.0], np.full(max(n - 1, 0), float(dt_s))]))[:n]
        hu = ua.copy()
        nh0 = 0
    else:
        ht, hu, nh0 = np.zeros(1), np.zeros(1), -1
    ox, ov, of = (np.empty((P.shape[0], n)) for _ in range(3))  # not written are not touched (no page faults)
    ksets = getattr(type(frictions[0]), "_ksets", None)
    ep = plant._ep
    if (ksets is not None and plant._tau == 0.0 and plain_effects(ep) and all(k.breakaway_n == 0.0 for k in kerns)
            and S.shape[1] > 0 and float(plant._ps[_FF]) == 0.0 and float(plant._ps[_V]) == 0.0):
        # branch-free many-sets kernel, parameters and states one column per set
        PT = np.ascontiguousarray(P.T)
        ST = np.ascontiguousarray(S.T)
        masses = np.full(P.shape[0], float(plant._par[0]))
        none = np.empty((0, 0))
        bx, bv, bf = (ox if "x" in outputs else none, ov if "v" in outputs else none,
                      of if "friction" in outputs else none)
        batch_sets_loop(ksets)(PT, ST, masses, float(ep[7]), float(plant._ps[_X]), ua, float(dt_s), nsub,
                               bx, bv, bf)
        return {nm: {"x": ox, "v": ov, "friction": of}[nm] for nm in outputs}
    PAR = np.ascontiguousarray(np.tile(plant._par, (len(kerns), 1)))
    PAR[:, 1] = [k.breakaway_n for k in kerns]
    PAR[:, 2] = [k.stick_velocity_m_s for k in kerns]
    run_batch = loops_for(plant._kstep)[1]
    run_batch(P, S, plant._ep, PAR, plant._ps.copy(), ht, hu, nh0, ua, float(dt_s), nsub, ox, ov, of)
    return {nm: {"x": ox, "v": ov, "friction": of}[nm] for nm in outputs}


def plant_from_model(model: StageModel, **overrides: Any) -> StagePlant:
    """Convenience: a plant from a stage model (e.g. :func:`stagectl.friction.load_model_file`); ``mass_kg``
    must be in the model or in ``overrides``."""
    return StagePlant(PlantConfig.from_mapping(overrides, path="plant", model=model))


__all__ = ["ActuatorConfig", "PlantConfig", "SensorConfig", "StagePlant", "plant_from_model", "simulate_batch"]
