"""Reference trajectories: jerk-limited moves, cosine/sine, triangular scans, dwell (pure, no clock).

A trajectory is a queue of *segments*. Each segment spec (a frozen dataclass, loadable from YAML with
:func:`parse_segments`) is *bound* to the reference state (x, v, a) at the instant it starts, so that
consecutive segments join without a position jump, and a move requested at run time (the daemon's
``move``) starts from the current reference state.

Segments (``kind:`` in YAML)
----------------------------
``move``      jerk-limited rest-to-rest point-to-point move to ``to_m`` (absolute) or by ``by_m``
              (relative) with limits |v| <= ``max_velocity_m_s``, |a| <= ``max_acceleration_m_s2``,
              |j| <= ``max_jerk_m_s3``. Velocity profile: two symmetric jerk-limited velocity changes
              (0 -> V_p -> 0) with an optional cruise; the velocity never changes sign, so there is no
              overshoot; the end position equals the target exactly (snapped).
``cosine``    x = x0 + A·(1 − cos 2πf t)/2 for ``cycles`` periods (starts at rest; a_ref steps to
              A·(2πf)²/2 at t = 0).
``sine``      x = x0 + A·sin(2πf t) (v_ref steps to 2πfA at t = 0).
``triangle``  scan between x0 and x0 + ``span_m`` at constant speed ``velocity_m_s`` with rounded
              reversals: each reversal is a jerk-limited velocity change +V -> −V with |a| <= A_max,
              |j| <= J_max, whose turning point (v = 0) lands exactly on the scan end; cruise lengths
              are computed from the exact overtravel of the reversal profile.
``dwell``     hold the position for ``duration_s``.

Every segment but ``move`` starts at rest. A ``sine`` (and a ``cosine`` of fractional cycles) ends moving; the
reference then stops at once where the segment ended (v and a step to 0) and the next segment (or the hold
after the last one, or a scenario's ``settle_s``) starts from rest there. A ``move`` after it starts from the
moving state instead (jerk-limited stop first, no jump in x, v or a).

Symbols: x position [m], v velocity [m/s], a acceleration [m/s²], j jerk [m/s³], t time [s].
When the queue is empty the generator holds the last position at rest.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from stagectl.control.api import Reference
from stagectl.errors import ConfigError, short
from stagectl.schema import load, param

__all__ = [
    "Cosine",
    "Dwell",
    "ForceBudget",
    "Move",
    "Scenario",
    "SegmentSpec",
    "Sine",
    "TrajectoryGenerator",
    "Triangle",
    "benchmark_scenarios",
    "demo_scenario",
    "parse_segments",
]

# ------------------------------------------------------------------------------------------ specs


@dataclass(frozen=True)
class Move:
    """Jerk-limited rest-to-rest move (``kind: move``). Give exactly one of ``to_m`` / ``by_m``."""

    to_m: float | None = param(None, unit="m", desc="absolute target position")
    by_m: float | None = param(None, unit="m", desc="relative displacement from the segment start")
    max_velocity_m_s: float = param(1e-3, unit="m/s", desc="velocity limit", gt=0.0)
    max_acceleration_m_s2: float = param(0.1, unit="m/s^2", desc="acceleration limit", gt=0.0)
    max_jerk_m_s3: float = param(100.0, unit="m/s^3", desc="jerk limit", gt=0.0)

    def __post_init__(self) -> None:
        if (self.to_m is None) == (self.by_m is None):
            raise ValueError("move: give exactly one of to_m or by_m")


@dataclass(frozen=True)
class ForceBudget:
    """The force a planned move may ask of the actuator (the loop's move planning; ``safety.move_force_fraction``).

    A move's peak force is bounded by ``F_move = m·a_max + F_s + F_v·v_max`` [N] (inertia at the largest
    acceleration plus the model's largest friction, its static level F_s, and its viscous force at the largest
    speed). A move within ``force_n`` (already the fraction of the usable force: the rest is the feedback's room)
    runs as given; a faster one is planned slower (:meth:`fit`) instead of saturating the actuator, where the
    stage would lag, the integrator wind and the stop overshoot.

    Attributes: ``mass_kg`` [kg], ``force_n`` [N], ``static_n`` F_s [N] (0: no model), ``viscous_n_s_m`` F_v
    [N·s/m].
    """

    mass_kg: float
    force_n: float
    static_n: float = 0.0
    viscous_n_s_m: float = 0.0

    def move_force_n(self, spec: Move) -> float:
        """``F_move`` of ``spec`` [N] (class docstring)."""
        return (self.mass_kg * spec.max_acceleration_m_s2 + self.static_n
                + self.viscous_n_s_m * spec.max_velocity_m_s)

    def fit(self, spec: Move) -> Move:
        """``spec`` itself when ``F_move ≤ force_n``; else the same move planned within the budget:

            v' = min(v_max, max((F − F_s)/(2·F_v), (F − F_s − m·a_max)/F_v))
                 (the viscous force at most half the room above F_s, or what the asked acceleration leaves)
            a' = (F − F_s − F_v·v')/m,   j' = j_max·a'/a_max   (the same jerk time a/j)

        Where friction alone takes the budget (``F_s ≥ F``) nothing fits: ``spec`` is returned unchanged (the
        loop says so; the move runs saturated)."""
        room = self.force_n - self.static_n
        if self.move_force_n(spec) <= self.force_n * (1.0 + 1e-12) or not room > 0.0 or not self.mass_kg > 0.0:
            return spec
        v = spec.max_velocity_m_s
        if self.viscous_n_s_m > 0.0:
            # (only half the room when the acceleration needs more than the other half: a move just over the
            # budget by its speed keeps about its speed, not half the room's)
            v = min(v, max(0.5 * room, room - self.mass_kg * spec.max_acceleration_m_s2) / self.viscous_n_s_m)
        a = min(spec.max_acceleration_m_s2, (room - self.viscous_n_s_m * v) / self.mass_kg)
        j = spec.max_jerk_m_s3 * a / spec.max_acceleration_m_s2
        return Move(to_m=spec.to_m, by_m=spec.by_m, max_velocity_m_s=v, max_acceleration_m_s2=a, max_jerk_m_s3=j)


@dataclass(frozen=True)
class Cosine:
    """Raised cosine ``x = x0 + A·(1 − cos 2πft)/2`` (``kind: cosine``)."""

    amplitude_m: float = param(unit="m", desc="peak-to-peak excursion A (sign gives the direction)")
    frequency_hz: float = param(unit="Hz", desc="frequency f", gt=0.0)
    cycles: float = param(1.0, unit="", desc="number of periods", gt=0.0)


@dataclass(frozen=True)
class Sine:
    """Plain sine ``x = x0 + A·sin 2πft`` (``kind: sine``)."""

    amplitude_m: float = param(unit="m", desc="amplitude A")
    frequency_hz: float = param(unit="Hz", desc="frequency f", gt=0.0)
    cycles: float = param(1.0, unit="", desc="number of periods", gt=0.0)


@dataclass(frozen=True)
class Triangle:
    """Triangular scan x0 -> x0+span -> x0 with rounded reversals (``kind: triangle``)."""

    span_m: float = param(unit="m", desc="scan length (sign gives the first direction)")
    velocity_m_s: float = param(unit="m/s", desc="scan speed V", gt=0.0)
    max_acceleration_m_s2: float = param(0.1, unit="m/s^2", desc="acceleration limit at reversals", gt=0.0)
    max_jerk_m_s3: float = param(100.0, unit="m/s^3", desc="jerk limit at reversals", gt=0.0)
    cycles: int = param(1, unit="", desc="number of out-and-back scans", ge=1)


@dataclass(frozen=True)
class Dwell:
    """Hold position (``kind: dwell``)."""

    duration_s: float = param(unit="s", desc="hold time", gt=0.0)


SegmentSpec = Move | Cosine | Sine | Triangle | Dwell

_KINDS: dict[str, type] = {"move": Move, "cosine": Cosine, "sine": Sine, "triangle": Triangle, "dwell": Dwell}


def parse_segments(value: Any, path: str, problems: list[str]) -> tuple[SegmentSpec, ...] | None:
    """``stagectl.schema`` parse hook: a YAML list of ``{kind: ..., ...}`` mappings -> segment specs."""
    if not isinstance(value, (list, tuple)):
        problems.append(f"{path}: expected a list of segments, got {short(value)}")
        return None
    out: list[SegmentSpec] = []
    n0 = len(problems)
    for i, item in enumerate(value):
        p = f"{path}[{i}]"
        if isinstance(item, (Move, Cosine, Sine, Triangle, Dwell)):
            out.append(item)
            continue
        if not isinstance(item, Mapping) or item.get("kind") not in _KINDS:
            kind = item.get("kind") if isinstance(item, Mapping) else None
            problems.append(f"{p}.kind: must be one of {', '.join(_KINDS)} (got {short(kind)})")
            continue
        rest = {k: v for k, v in item.items() if k != "kind"}
        try:
            out.append(load(_KINDS[item["kind"]], rest, p))
        except ConfigError as exc:
            problems.extend(exc.problems)
    return tuple(out) if len(problems) == n0 else None


@dataclass(frozen=True)
class Scenario:
    """A named list of segments, starting from ``start_m`` (None: wherever the stage is)."""

    name: str = param(desc="scenario name")
    segments: tuple[SegmentSpec, ...] = param(desc="segments in order", parse=parse_segments)
    start_m: float | None = param(None, unit="m", desc="start position (None: current position)")
    settle_s: float = param(0.0, unit="s", desc="extra hold at the end", ge=0.0)

    def duration_s(self, x0_m: float = 0.0) -> float:
        """Total duration [s] when started at rest at ``x0_m``."""
        gen = TrajectoryGenerator(x0_m)
        gen.load(self)
        return gen.remaining_s()

    def problems(self, x0_m: float = 0.0, path: str = "segments") -> list[str]:
        """What keeps the segments from being bound one after the other from rest at ``x0_m`` (or ``start_m``):
        one line per segment that cannot run (e.g. a triangle too short for its speed), naming its index."""
        out: list[str] = []
        ref = Reference(self.start_m if self.start_m is not None else x0_m)
        for i, spec in enumerate(self.segments):
            try:
                ref = _bind(spec, ref).end
            except ValueError as exc:
                out.append(f"{path}[{i}] ({type(spec).__name__.lower()}): {exc}")
        return out


# ------------------------------------------------------------------------------------------ bound segments


class _Bound(ABC):
    """A segment bound to its start state. ``sample(tau)`` with 0 <= tau <= duration."""

    duration: float
    end: Reference

    @abstractmethod
    def sample(self, tau: float) -> Reference:
        """Reference at ``tau`` [s] after the segment start."""

    def rest_ahead(self, tau: float) -> float:
        """Where the reference next comes to rest inside the segment after ``tau`` [s] [m], if it gets there
        without reversing; NaN when it reverses (or may reverse) first; +inf when it travels on to the
        segment's end without either."""
        return math.nan


#: |a| below which a state with v at rest counts as a rest (not a turning point) [m/s²]
_A_REST = 1e-9
_TURN, _REST = 0, 1


def _sgn(v: float) -> int:
    return 1 if v > 0.0 else (-1 if v < 0.0 else 0)


class _Phases(_Bound):
    """Piecewise-constant-jerk motion from (x0, v0, a0): phases ``(T, j)``; exact polynomial integration."""

    def __init__(self, x0: float, v0: float, a0: float, phases: Sequence[tuple[float, float]],
                 x_end: float | None = None):
        self.starts: list[tuple[float, float, float, float, float]] = []  # (t0, x, v, a, j)
        t = 0.0
        x, v, a = x0, v0, a0
        for T, j in phases:
            if T <= 0.0:
                continue
            self.starts.append((t, x, v, a, j))
            x, v, a = _integrate(x, v, a, j, T)
            t += T
        self.duration = t
        if x_end is not None:  # snap: remove the rounding residue of the polynomial sums
            x = x_end
            if abs(v) < 1e-15:
                v = 0.0
            if abs(a) < 1e-12:
                a = 0.0
        self.end = Reference(x, v, a)
        self._k = 0
        # the rests (v = a = 0) and turns (v changes sign) in time order, each at the end of the phase it
        # happens in (a turn is thus reported until its phase ends: conservative, see rest_ahead)
        self.events: list[tuple[float, int, float]] = []
        ends = [(st[0], st[1], st[2], st[3]) for st in self.starts[1:]] + [(t, x, v, a)]
        s_prev = _sgn(v0) if abs(v0) > _V_REST else 0
        for te, xe, ve, ae in ends:
            s_e = _sgn(ve) if abs(ve) > _V_REST else 0
            if s_e == 0 and abs(ae) <= _A_REST:
                self.events.append((te, _REST, xe))
                s_prev = 0
                continue
            if s_e == 0:  # at rest for an instant, accelerating: it goes on in the direction of a
                s_e = _sgn(ae)
            if s_prev != 0 and s_e != s_prev:
                self.events.append((te, _TURN, math.nan))
            s_prev = s_e

    def rest_ahead(self, tau: float) -> float:
        for te, kind, xe in self.events:
            if te >= tau:
                return xe if kind == _REST else math.nan
        return math.inf

    def sample(self, tau: float) -> Reference:
        if tau >= self.duration:
            return self.end
        st = self.starts
        k = self._k
        if k >= len(st) or st[k][0] > tau:
            k = 0
        while k + 1 < len(st) and st[k + 1][0] <= tau:
            k += 1
        self._k = k
        t0, x, v, a, j = st[k]
        x, v, a = _integrate(x, v, a, j, tau - t0)
        return Reference(x, v, a)


def _integrate(x: float, v: float, a: float, j: float, T: float) -> tuple[float, float, float]:
    """Exact constant-jerk update over T: x += vT + aT²/2 + jT³/6, v += aT + jT²/2, a += jT."""
    return (x + v * T + a * T * T / 2.0 + j * T * T * T / 6.0, v + a * T + j * T * T / 2.0, a + j * T)


def _vel_change(dv: float, a_max: float, j_max: float) -> list[tuple[float, float]]:
    """Phases (T, j) changing velocity by ``dv`` from a = 0 to a = 0 (symmetric jerk profile)."""
    if dv == 0.0:
        return []
    s = 1.0 if dv > 0 else -1.0
    m = abs(dv)
    if m >= a_max * a_max / j_max:  # trapezoidal acceleration
        tj = a_max / j_max
        ta = m / a_max - tj
        return [(tj, s * j_max), (ta, 0.0), (tj, -s * j_max)]
    tj = math.sqrt(m / j_max)  # triangular acceleration, peak sqrt(m·j) < a_max
    return [(tj, s * j_max), (tj, -s * j_max)]


def _vel_change_time(m: float, a_max: float, j_max: float) -> float:
    if m >= a_max * a_max / j_max:
        return m / a_max + a_max / j_max
    return 2.0 * math.sqrt(m / j_max)


def _move_phases(dist: float, v_max: float, a_max: float, j_max: float) -> list[tuple[float, float]]:
    """Rest-to-rest phases for a signed distance: 0 -> ±V_p -> 0, with cruise if V_p = v_max."""
    if dist == 0.0:
        return []
    s = 1.0 if dist > 0 else -1.0
    D = abs(dist)
    # distance of 0 -> V -> 0 without cruise = V · T(V)  (each symmetric change covers V·T/2)
    if v_max * _vel_change_time(v_max, a_max, j_max) <= D:
        vp = v_max
        cruise = (D - vp * _vel_change_time(vp, a_max, j_max)) / vp
    else:
        cruise = 0.0
        q = a_max * a_max / j_max
        vp = (-a_max * a_max / j_max + math.sqrt((a_max * a_max / j_max) ** 2 + 4.0 * a_max * D)) / 2.0
        if vp < q:  # triangular acceleration: 2·V·sqrt(V/j) = D
            vp = (D * math.sqrt(j_max) / 2.0) ** (2.0 / 3.0)
        vp = min(vp, v_max)
    up = _vel_change(s * vp, a_max, j_max)
    down = _vel_change(-s * vp, a_max, j_max)
    return up + ([(cruise, 0.0)] if cruise > 0.0 else []) + down


class _Analytic(_Bound):
    def __init__(self, x0: float, amp: float, f: float, cycles: float, cosine: bool):
        self.x0, self.amp, self.w, self.cos = x0, amp, 2.0 * math.pi * f, cosine
        self.duration = cycles / f
        self.end = self._at(self.duration)
        if abs(cycles - round(cycles)) < 1e-12:  # whole periods: exact return to the start
            self.end = Reference(x0, 0.0 if cosine else self.end.v_m_s, self.end.a_m_s2)

    def _at(self, t: float) -> Reference:
        w, A = self.w, self.amp
        if self.cos:  # x0 + A(1 - cos wt)/2
            c, s = math.cos(w * t), math.sin(w * t)
            return Reference(self.x0 + A * (1.0 - c) / 2.0, A * w * s / 2.0, A * w * w * c / 2.0)
        c, s = math.cos(w * t), math.sin(w * t)
        return Reference(self.x0 + A * s, A * w * c, -A * w * w * s)

    def sample(self, tau: float) -> Reference:
        return self.end if tau >= self.duration else self._at(tau)

    def rest_ahead(self, tau: float) -> float:
        # turns: sine at wt = π/2 + kπ, raised cosine at wt = kπ (k >= 1); +inf when none is left before the end
        w = self.w
        off = 0.0 if self.cos else 0.5 * math.pi
        k = max(math.ceil((w * tau - off) / math.pi - 1e-9), 1 if self.cos else 0)
        t_turn = (off + k * math.pi) / w
        return math.inf if t_turn >= self.duration * (1.0 - 1e-12) else math.nan


class _Hold(_Bound):
    def __init__(self, x: float, duration: float):
        self.duration = duration
        self.end = Reference(x, 0.0, 0.0)

    def sample(self, tau: float) -> Reference:
        return self.end

    def rest_ahead(self, tau: float) -> float:
        return self.end.x_m


def _stop_phases(v0: float, a0: float, a_max: float, j_max: float) -> list[tuple[float, float]]:
    """Jerk-limited phases bringing (v0, a0) to rest: ramp a to 0, then a symmetric velocity change."""
    phases: list[tuple[float, float]] = []
    v = v0
    if a0 != 0.0:
        T = abs(a0) / j_max
        j = -math.copysign(j_max, a0)
        phases.append((T, j))
        v = v0 + a0 * T + j * T * T / 2.0
    phases += _vel_change(-v, a_max, j_max)
    return phases


#: |v| below which a reference counts as at rest for segments that must start at rest [m/s]
_V_REST = 1e-12


def _bind(spec: SegmentSpec, start: Reference) -> _Bound:
    """``spec`` bound to the reference state ``start`` where it begins.

    A move starts from any state (a jerk-limited stop first). Every other segment starts at rest: after a
    segment that ends moving (a ``sine``, a cosine of fractional cycles) the reference stops at once at the
    reached position, as it does when that segment is the last one (module docstring)."""
    x0, v0, a0 = start
    # a step in a_ref is allowed between segments (a cosine starts and ends with a ≠ 0)
    if isinstance(spec, Dwell):
        return _Hold(x0, spec.duration_s)
    if isinstance(spec, Move):
        target = spec.to_m if spec.to_m is not None else x0 + (spec.by_m or 0.0)
        stop: list[tuple[float, float]] = []
        xs = x0
        if v0 != 0.0 or a0 != 0.0:  # replace a running motion: jerk-limited stop first, then the move
            stop = _stop_phases(v0, a0, spec.max_acceleration_m_s2, spec.max_jerk_m_s3)
            xs = _Phases(x0, v0, a0, stop).end.x_m
        phases = stop + _move_phases(target - xs, spec.max_velocity_m_s, spec.max_acceleration_m_s2,
                                     spec.max_jerk_m_s3)
        return _Phases(x0, v0, a0, phases, x_end=target)
    if isinstance(spec, Cosine):
        return _Analytic(x0, spec.amplitude_m, spec.frequency_hz, spec.cycles, cosine=True)
    if isinstance(spec, Sine):
        return _Analytic(x0, spec.amplitude_m, spec.frequency_hz, spec.cycles, cosine=False)
    if isinstance(spec, Triangle):
        s = 1.0 if spec.span_m > 0 else -1.0
        L = abs(spec.span_m)
        V, A, J = spec.velocity_m_s, spec.max_acceleration_m_s2, spec.max_jerk_m_s3
        d_half = V * _vel_change_time(V, A, J) / 2.0  # distance of a 0 -> V change
        rev = _vel_change(-2.0 * V, A, J)
        t_rev = sum(T for T, _ in rev)
        d_peak = _Phases(0.0, V, 0.0, rev).sample(t_rev / 2.0).x_m  # overtravel of a reversal (v = 0 at mid)
        end_cruise = L - d_half - d_peak
        mid_cruise = L - 2.0 * d_peak
        if min(end_cruise, mid_cruise) < 0.0:
            raise ValueError(
                f"triangle: span {L:g} m too short for velocity {V:g} m/s with acceleration {A:g} m/s^2 "
                f"(needs >= {max(d_half + d_peak, 2 * d_peak):g} m)")
        ph: list[tuple[float, float]] = list(_vel_change(s * V, A, J)) + [(end_cruise / V, 0.0)]
        sign = s
        n_rev = 2 * spec.cycles - 1
        for i in range(n_rev):
            ph += _vel_change(-2.0 * sign * V, A, J)
            sign = -sign
            ph.append(((mid_cruise if i + 1 < n_rev else end_cruise) / V, 0.0))
        ph += _vel_change(-sign * V, A, J)
        return _Phases(x0, 0.0, 0.0, ph, x_end=x0)
    raise TypeError(f"unknown segment {short(spec)}")


# ------------------------------------------------------------------------------------------ generator


@dataclass
class TrajectoryState:
    """Diagnostics of the generator: time in the current segment, queue length, current reference."""

    t_s: float = 0.0
    tau_s: float = 0.0
    segment: str = "hold"
    queued: int = 0
    ref: Reference = field(default_factory=lambda: Reference(0.0))


class TrajectoryGenerator:
    """Queue of segments producing ``Reference(x, v, a)`` at each ``step(dt)``.

    Real-time safe apart from :meth:`move`/:meth:`load` (which bind a segment: a few float operations).
    ``step(dt)`` advances the time by ``dt`` and returns the reference at the new time; :meth:`sample`
    returns the current one without advancing.
    """

    def __init__(self, x0_m: float = 0.0):
        self.state = TrajectoryState()
        self._queue: deque[SegmentSpec] = deque()
        self._cur: _Bound = _Hold(x0_m, math.inf)
        self._name = "hold"
        #: moves (and stops) are planned within this force (:class:`ForceBudget`; None: as given)
        self.force_budget: ForceBudget | None = None
        #: called with (asked, planned) each time a move starts planned slower than asked (the loop logs it)
        self.on_move_slowed: Callable[[Move, Move], None] | None = None
        self.moves_slowed = 0  # moves started planned slower than asked, since construction
        self.reset(x0_m)

    # ---------------------------------------------------------------- control
    def reset(self, x0_m: float) -> None:
        """Drop every segment; hold ``x0_m`` at rest, time 0."""
        if not math.isfinite(x0_m):
            raise ValueError(f"x0_m must be finite (got {x0_m})")
        self._queue.clear()
        self._cur = _Hold(float(x0_m), math.inf)
        self._name = "hold"
        self.state = TrajectoryState(ref=Reference(float(x0_m)))

    def load(self, scenario: Scenario) -> None:
        """Replace the queue with a scenario's segments (a move to ``start_m`` first when given)."""
        segs: list[SegmentSpec] = list(scenario.segments)
        if scenario.start_m is not None and scenario.start_m != self.state.ref.x_m:
            segs.insert(0, Move(to_m=scenario.start_m))
        if scenario.settle_s > 0.0:
            segs.append(Dwell(scenario.settle_s))
        self.replace(segs)

    def queue(self, segments: SegmentSpec | Iterable[SegmentSpec]) -> None:
        """Append segments after the ones already queued."""
        if isinstance(segments, (Move, Cosine, Sine, Triangle, Dwell)):
            segments = [segments]
        self._queue.extend(segments)
        self.state.queued = len(self._queue)
        if isinstance(self._cur, _Hold) and math.isinf(self._cur.duration):
            self._advance_segment(self.state.ref)

    def replace(self, segments: SegmentSpec | Iterable[SegmentSpec]) -> None:
        """Abandon the current motion and queue; start ``segments`` from the current reference state.

        A move starting while the reference is moving first brings it to rest with the move's
        acceleration/jerk limits (no jump in x, v or a); other segments need a rest start
        (a move is inserted before them if needed).
        """
        if isinstance(segments, (Move, Cosine, Sine, Triangle, Dwell)):
            segments = [segments]
        segs = list(segments)
        ref = self.state.ref
        if segs and not isinstance(segs[0], Move) and abs(ref.v_m_s) > _V_REST:
            segs.insert(0, Move(by_m=0.0))
        self._queue.clear()
        self._queue.extend(segs)
        self._advance_segment(ref)

    def move(self, target_m: float, max_velocity_m_s: float = 1e-3, max_acceleration_m_s2: float = 0.1,
             max_jerk_m_s3: float = 100.0, *, replace: bool = True) -> None:
        """Request a point-to-point move (replacing the current motion, or queued after it)."""
        if not math.isfinite(target_m):
            raise ValueError(f"target_m must be finite (got {target_m})")
        spec = Move(to_m=float(target_m), max_velocity_m_s=max_velocity_m_s,
                    max_acceleration_m_s2=max_acceleration_m_s2, max_jerk_m_s3=max_jerk_m_s3)
        (self.replace if replace else self.queue)(spec)

    def stop(self, max_acceleration_m_s2: float = 0.1, max_jerk_m_s3: float = 100.0) -> float:
        """Abandon the current motion and queue; bring the reference to rest (jerk-limited) and hold there.

        From the current reference state (x0, v0, a0): first ramp a to 0 at ±J_max, then a symmetric
        velocity change to v = 0 with |a| <= A_max, |j| <= J_max. No jump in x, v or a, and no move back:
        the reference holds where it comes to rest. Returns that position [m].
        """
        if not (max_acceleration_m_s2 > 0.0 and max_jerk_m_s3 > 0.0
                and math.isfinite(max_acceleration_m_s2) and math.isfinite(max_jerk_m_s3)):
            raise ValueError("stop: max_acceleration_m_s2 and max_jerk_m_s3 must be > 0 and finite")
        x0, v0, a0 = self.state.ref
        self._queue.clear()
        if v0 == 0.0 and a0 == 0.0:
            self._advance_segment(Reference(x0))
            return x0
        fb = self.force_budget
        if fb is not None and fb.mass_kg > 0.0:
            # the stop's deceleration within the budget too. Braking, the friction works with the actuator (its
            # force is m·a − F_s − F_v·|v|, at most m·|a| in size), so the deceleration may take the whole budget:
            # a = F/m. (Charging the friction against it, as an acceleration, slowed the stop without bound as
            # F_s + F_v·|v0| neared F: a scan at 29.9 mm/s on a 1.2 N budget, F_s 0.9 N, F_v 10 N·s/m, stopped
            # in 894 mm instead of 4.5 mm.)
            a_fit = fb.force_n / fb.mass_kg
            if 0.0 < a_fit < max_acceleration_m_s2:
                max_jerk_m_s3 *= a_fit / max_acceleration_m_s2
                max_acceleration_m_s2 = a_fit
        phases = _stop_phases(v0, a0, max_acceleration_m_s2, max_jerk_m_s3)
        b = _Phases(x0, v0, a0, phases, x_end=_Phases(x0, v0, a0, phases).end.x_m)  # snap v, a to exact rest
        self._cur = b
        self._name = "stop"
        self.state.queued = 0
        self.state.tau_s = 0.0
        self.state.segment = self._name
        return b.end.x_m

    # ---------------------------------------------------------------- stepping
    def sample(self) -> Reference:
        return self.state.ref

    def step(self, dt: float) -> Reference:
        """Advance by ``dt`` [s] and return the reference at the new time."""
        if not (dt > 0.0 and math.isfinite(dt)):
            raise ValueError(f"dt must be > 0 and finite (got {dt})")
        st = self.state
        st.t_s += dt
        tau = st.tau_s + dt
        while tau >= self._cur.duration and self._queue:
            tau -= self._cur.duration
            self._advance_segment(self._cur.end, keep_time=True)
        if tau >= self._cur.duration and not math.isinf(self._cur.duration):
            end = self._cur.end
            self._cur = _Hold(end.x_m, math.inf)
            self._name = "hold"
            tau = 0.0
        st.tau_s = tau
        st.ref = self._cur.sample(tau)
        st.segment = self._name
        return st.ref

    def stop_m(self, repeat: Scenario | None = None) -> float:
        """Where the reference next comes to rest (v = 0, holding or starting a new segment from rest) [m], when
        it gets there without reversing first; NaN when a reversal (a scan's turn) may come first.

        A segment ending with the hold after it, or with a ``dwell`` or ``triangle`` after it (it stops at once
        there: module docstring), rests at its end; so does one ending at rest (v = 0 and a = 0) with a ``move``
        after it. One ending moving, or at a turning point (v = 0, a ≠ 0: a cosine's end), with a ``move`` after
        it does not (NaN: the move's stop phases are not bound yet, and from a ≠ 0 they reverse first), nor does
        one followed by a ``cosine`` or ``sine`` (of non-zero amplitude), which starts moving at once (a ≠ 0 or
        v ≠ 0): a cosine straight into a cosine turns at the junction, as within one. ``repeat``: the scenario
        loaded again when the queue runs out (a repeated motion, ``ReferenceSource``), whose first segment then
        follows the last one (after a hold sample; a move to its ``start_m`` first when the last one ends
        elsewhere). Real-time safe (no binding). The friction feed-forward uses it to keep its look-ahead point from going past the stop, or
        back before it (:mod:`stagectl.control.friction_ff`)."""
        cur = self._cur
        x = cur.rest_ahead(self.state.tau_s)
        if x != math.inf:
            return x
        end = cur.end
        if self._queue:
            nxt = self._queue[0]
        elif repeat is None or not repeat.segments or (repeat.start_m is not None and repeat.start_m != end.x_m):
            return end.x_m
        else:
            nxt = repeat.segments[0]
            if isinstance(nxt, Move):
                return end.x_m  # (it starts from the hold sample: at rest)
        if isinstance(nxt, Move):
            return end.x_m if abs(end.v_m_s) <= _V_REST and abs(end.a_m_s2) <= _A_REST else math.nan
        if isinstance(nxt, (Cosine, Sine)) and nxt.amplitude_m != 0.0:
            return math.nan
        return end.x_m

    def remaining_s(self) -> float:
        """Time [s] until the queue is finished (0 when holding)."""
        if math.isinf(self._cur.duration):
            rest = 0.0
        else:
            rest = self._cur.duration - self.state.tau_s
        ref = self._cur.end
        for spec in self._queue:
            b = _bind(self._planned(spec), ref)
            rest += b.duration
            ref = b.end
        return rest

    def final_reference(self) -> Reference:
        """The reference state where the current motion and every queued segment end (binds the queue)."""
        ref = self._cur.end
        for spec in self._queue:
            ref = _bind(self._planned(spec), ref).end
        return ref

    @property
    def done(self) -> bool:
        return math.isinf(self._cur.duration) and not self._queue

    def _planned(self, spec: SegmentSpec) -> SegmentSpec:
        """``spec`` as it is planned: a move within :attr:`force_budget` (:meth:`ForceBudget.fit`)."""
        if self.force_budget is None or not isinstance(spec, Move):
            return spec
        return self.force_budget.fit(spec)

    def _advance_segment(self, start: Reference, keep_time: bool = False) -> None:
        if self._queue:
            spec = self._queue.popleft()
            planned = self._planned(spec)
            if planned is not spec and isinstance(spec, Move) and isinstance(planned, Move):
                self.moves_slowed += 1
                if self.on_move_slowed is not None:
                    self.on_move_slowed(spec, planned)
            self._cur = _bind(planned, start)
            self._name = type(spec).__name__.lower()
        else:
            self._cur = _Hold(start.x_m, math.inf)
            self._name = "hold"
            start = Reference(start.x_m)
        self.state.queued = len(self._queue)
        if not keep_time:
            self.state.tau_s = 0.0
            self.state.ref = start if start.v_m_s or start.a_m_s2 else Reference(start.x_m)
        self.state.segment = self._name


# ------------------------------------------------------------------------------------------ scenarios


def benchmark_scenarios() -> dict[str, Scenario]:
    """The three benchmark scenarios of issue 4 (all start at rest at 0 m).

    * ``cosine``: 0 -> 10 µm -> 0 raised cosine at 1 Hz, 3 periods (pre-sliding);
    * ``triangle``: 1 mm triangle scan at 1.57 mm/s, |a| <= 20 mm/s², |j| <= 1 m/s³, 2 cycles (sliding, reversals);
    * ``steps``: 10 µm point-to-point steps (+10, +10, −10, −10 µm) with 0.25 s dwells.
    """
    step = dict(max_velocity_m_s=1e-3, max_acceleration_m_s2=0.05, max_jerk_m_s3=20.0)
    return {
        "cosine": Scenario(name="cosine", segments=(Cosine(amplitude_m=10e-6, frequency_hz=1.0, cycles=3),),
                           start_m=0.0, settle_s=0.2),
        "triangle": Scenario(name="triangle", segments=(
            Triangle(span_m=1e-3, velocity_m_s=1.57e-3, max_acceleration_m_s2=0.02, max_jerk_m_s3=1.0, cycles=2),
        ), start_m=0.0, settle_s=0.2),
        "steps": Scenario(name="steps", segments=(
            Move(by_m=10e-6, **step), Dwell(0.25), Move(by_m=10e-6, **step), Dwell(0.25),
            Move(by_m=-10e-6, **step), Dwell(0.25), Move(by_m=-10e-6, **step), Dwell(0.25),
        ), start_m=0.0),
    }


def demo_scenario() -> Scenario:
    """A short demo motion for ``stagectl run`` on the simulated stage (~3.7 s): 100 µm move, 10 µm cosine,
    100 µm triangle scan, return."""
    lim = dict(max_velocity_m_s=2e-3, max_acceleration_m_s2=0.05, max_jerk_m_s3=20.0)
    return Scenario(name="demo", segments=(
        Move(by_m=100e-6, **lim), Dwell(0.3),
        Cosine(amplitude_m=10e-6, frequency_hz=1.0, cycles=2), Dwell(0.2),
        Triangle(span_m=-100e-6, velocity_m_s=0.5e-3, max_acceleration_m_s2=0.02, max_jerk_m_s3=1.0, cycles=1),
        Dwell(0.2), Move(by_m=-100e-6, **lim), Dwell(0.3),
    ), start_m=None)
