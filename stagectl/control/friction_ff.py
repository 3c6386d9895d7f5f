"""Friction feed-forward driven by the *reference* motion (docs/friction-models.md §3.5, §6.2).

Model feed-forward (``kind: model``): a copy of any library friction model (GMS by default) is advanced
with the reference motion and its force, with the model file's effects, is commanded::

    u_ff = E_mod( F̂(x_r, v_r; state), x_r ) + F_other(x_r)        [N]

where F̂ is ``FrictionModel.step(state, dx, v, dt)`` of :mod:`stagectl.friction`, E_mod is
``Effects.modify_friction`` (position ripple, asymmetry) and F_other is ``Effects.other_force``
(cogging + offset + spring), all as in the plant ``m·a = u − F − F_other``.

Look-ahead: with an actuation delay τ (``effects.delay``) plus ``lookahead_s``, the reference is
evaluated ahead by τ_a = τ + lookahead_s: x_r = x_ref + v_ref·τ_a + a_ref·τ_a²/2, v_r = v_ref + a_ref·τ_a.
The force is held over the control period T (zero-order hold), so the right look-ahead is
T/2 + (I/O delay of the actuator path): on the seed stage at 1 kHz with one cycle of I/O delay the exact-
model PID + GMS FF error is 32 nm RMS without look-ahead and 0.7 nm with 1.5 ms (10 µm cosine).

Reversal detection that ignores jitter: the model is fed the reference position through a
direction latch. The direction d ∈ {+1, −1} changes only when the reference has moved back from its
extreme in the current direction by more than ``reversal_threshold_m`` **or** its velocity exceeds
``reversal_velocity_m_s`` in the opposite direction. While a move-back is unconfirmed the model is held
(not stepped, its force kept); on confirmation the whole move-back is fed at once, so no displacement is
lost. The model's own reversal logic therefore sees one clean reversal per real one.

A reference that stops at once (a hold, v = a = 0, right after a sample moving in the latched direction: the end
of a ``sine`` segment, a cosine of fractional cycles) takes the look-ahead point back by the overshoot v·τ_a it
had extrapolated; that is no move back: the latch's extreme and the fed position go back to the stop position
(:meth:`DirectionLatch.stop_at`; the model's state is not stepped), so the direction stays the last motion's
(the controller's stop synchronisation judges "ahead"/"behind" of the reference by it).

A reference that comes to rest through a jerk-limited stop (the end of a ``move``, a ``stop``): with τ_a longer
than half the final jerk phase, the look-ahead point x_ref + v·τ_a + a·τ_a²/2 of the constant deceleration before
it turns back before the stop (v < |a|·τ_a) and comes forward again in the final jerk phase (1 ms at the move
defaults 0.1 m/s², 100 m/s³ with τ_a = 1.5 ms: ~50 nm back, then forward): the latch reversed and reversed back
one cycle later (+2 reversals, the model stepped back and forth). When the reference source knows where the
reference next comes to rest without reversing first (``stop_m``,
:meth:`stagectl.control.trajectory.TrajectoryGenerator.stop_m`, passed to :meth:`FrictionFeedforward.step`), the
look-ahead point is kept on the reference's own travel: not past that stop, and, while the reference travels to it
in the latched direction, not back before the latch's extreme (the model is held there, as for an unconfirmed
move-back). A reversal the reference makes (a scan's turn, a cosine's, a move back) has no rest before it:
``stop_m`` is NaN and the look-ahead is as above. Without ``stop_m`` (NaN) nothing changes.

Two forms of the model's step, the same arithmetic: the compiled kernel (numba; what a process that simulates a
plant uses anyway) or, with ``plain=True``, the kernel's own source run as plain Python
(:meth:`~stagectl.friction.FrictionModel.plain_stepper`, ~2-3 µs for GMS N = 6): a real stage's controller then
never imports numba (``stagectl.app.build_stage`` chooses it when no plant runs in the process).

Coulomb baseline (``kind: coulomb``): u_ff = d·F_c + c_v·v_r (+ effects' other force) with the same
direction latch (no sgn(v) chatter), ``coulomb_n`` = F_c [N], ``viscous_n_s_m`` = c_v [N·s/m].
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from stagectl.control.api import Reference
from stagectl.control.pid import check_dt
from stagectl.friction.base import FloatArray, FrictionModel
from stagectl.friction.effects import NO_EFFECTS, Effects


@dataclass
class FrictionFfState:
    """Diagnostics: friction part, other-force part, total [N]; direction latch; fed position."""

    f_friction_n: float = 0.0
    f_other_n: float = 0.0
    u_ff_n: float = 0.0
    direction: int = 0
    x_fed_m: float = math.nan  # position last fed to the model
    x_extreme_m: float = math.nan  # extreme of the reference in the current direction
    holding: bool = False
    reversals: int = 0
    x_rev_m: float = math.nan  # fed position at the last confirmed reversal (or first motion)
    f_rev_n: float = 0.0  # model friction force there [N]


class DirectionLatch:
    """Jitter-immune direction of a reference signal (see module docstring). Pure, scalar."""

    def __init__(self, threshold_m: float, velocity_m_s: float):
        if not (threshold_m >= 0.0 and velocity_m_s > 0.0):
            raise ValueError("reversal threshold must be >= 0 m and velocity threshold > 0 m/s")
        self.threshold_m = threshold_m
        self.velocity_m_s = velocity_m_s
        self.direction = 0
        self.extreme = math.nan

    def reset(self, x_m: float) -> None:
        self.direction = 0
        self.extreme = x_m

    def stop_at(self, x_m: float) -> None:
        """The reference stopped at once at ``x_m`` [m] (module docstring): a look-ahead step-back from the
        extreme to ``x_m`` is no move back; the extreme becomes ``x_m`` (the direction stays)."""
        if (self.extreme - x_m) * self.direction > 0.0:
            self.extreme = x_m

    def update(self, x_m: float, v_m_s: float) -> bool:
        """Feed a sample; return True when the direction changed (a confirmed reversal or first motion)."""
        d = self.direction
        if math.isnan(self.extreme):
            self.extreme = x_m
        if d == 0:
            dx = x_m - self.extreme
            if abs(dx) > self.threshold_m or abs(v_m_s) > self.velocity_m_s:
                s = dx if dx != 0.0 else v_m_s
                self.direction = 1 if s > 0 else -1
                self.extreme = x_m
                return True
            return False
        if (x_m - self.extreme) * d > 0.0:
            self.extreme = x_m  # moving further in the current direction
            return False
        back = (self.extreme - x_m) * d
        if back > self.threshold_m or -v_m_s * d > self.velocity_m_s:
            self.direction = -d
            self.extreme = x_m
            return True
        return False


def bounded_ahead(xr: float, vr: float, x_ref: float, stop_m: float, latch: DirectionLatch) -> tuple[float, float]:
    """The look-ahead point (``xr`` [m], ``vr`` [m/s]) kept on the reference's own travel to its next rest
    ``stop_m`` [m] (module docstring): not past it, and, while the reference (at ``x_ref``) travels to it in the
    latched direction, not back before the latch's extreme. Returned unchanged when ``stop_m`` is NaN."""
    if stop_m != stop_m:
        return xr, vr
    to = stop_m - x_ref
    if to == 0.0:  # the reference is at its rest
        return stop_m, 0.0
    ds = 1 if to > 0.0 else -1
    if (xr - stop_m) * ds > 0.0:  # past the stop
        xr, vr = stop_m, 0.0
    elif latch.direction == ds and (latch.extreme - xr) * ds > 0.0:  # back before the extreme: no move back
        xr = latch.extreme
    if vr * ds < 0.0:
        vr = 0.0
    return xr, vr


class FrictionFeedforward:
    """Model-based friction feed-forward (``kind: model``). ``step`` is real-time safe if the model's is."""

    def __init__(self, model: FrictionModel, effects: Effects = NO_EFFECTS, *, reversal_threshold_m: float = 5e-9,
                 reversal_velocity_m_s: float = 1e-5, lookahead_s: float = 0.0, plain: bool = False):
        self.model = model
        stepper = model.plain_stepper() if plain else None
        #: True: the model steps as plain Python on a state list (no numba); False: its compiled kernel
        self.plain = stepper is not None
        self._step: Callable[[Any, float, float, float], float] = stepper if stepper is not None else model.step
        self.effects = effects
        #: no effect changes the force (delay aside, which is in lookahead_s): step() skips the effects' calls
        self._no_effects = (effects.asymmetry is None and effects.viscous_asymmetry is None
                            and effects.position_ripple is None and effects.cogging is None
                            and effects.offset is None and effects.spring is None)
        self.lookahead_s = lookahead_s + (effects.delay.delay_s if effects.delay is not None else 0.0)
        self.latch = DirectionLatch(reversal_threshold_m, reversal_velocity_m_s)
        self.state = FrictionFfState()
        self.input_scale = 1.0  # β: the model is fed β·dx (pre-sliding stiffness ×β, Stribeck velocity ÷β)
        self._mstate = self._relaxed()
        self._probe: Any = None
        self._f_model = 0.0
        self._v_ref = 0.0  # the reference's own velocity at the last step [m/s] (an abrupt stop: module docstring)
        # the model's first step loads its compiled kernel (numba: 0.5-0.9 s on a loaded PC): here, at
        # construction, not in the control loop's first moving cycle (a drive's heartbeat consumer faults on that)
        self._step(self._relaxed(), 1e-9, 1e-6, 1e-3)

    def _relaxed(self) -> Any:
        s = self.model.initial_state()
        return s.tolist() if self.plain else s

    @property
    def model_state(self) -> FloatArray:
        """The model copy's internal state (the array itself, a list when :attr:`plain`; do not modify)."""
        return self._mstate  # type: ignore[no-any-return]

    def reset(self, x_m: float) -> None:
        """Relaxed model state (no pre-sliding memory) at ``x_m``; the plant should be relaxed too (§6.2)."""
        self._mstate = self._relaxed()
        self._f_model = 0.0
        self._v_ref = 0.0
        self.latch.reset(x_m)
        self.state = FrictionFfState(x_fed_m=x_m, x_extreme_m=x_m)

    def _stopped(self, x_m: float) -> None:
        """The reference stopped at once at ``x_m`` (module docstring): the latch keeps its direction and a fed
        position beyond ``x_m`` (the look-ahead's overshoot) goes back to it without stepping the model."""
        self.latch.stop_at(x_m)
        if (self.state.x_fed_m - x_m) * self.latch.direction > 0.0:
            self.state.x_fed_m = x_m

    def _ahead(self, ref: Reference) -> tuple[float, float]:
        ta = self.lookahead_s
        if ta == 0.0:
            return ref.x_m, ref.v_m_s
        return (ref.x_m + ref.v_m_s * ta + 0.5 * ref.a_m_s2 * ta * ta, ref.v_m_s + ref.a_m_s2 * ta)

    @property
    def model_force_n(self) -> float:
        """The friction model's own force at the last step [N] (before effects, scales and velocity terms)."""
        return self._f_model

    def step(self, dt: float, ref: Reference, stop_m: float = math.nan) -> float:
        """Advance the model copy along the reference; return u_ff [N]. ``stop_m`` [m]: where the reference next
        comes to rest without reversing first (NaN: unknown; module docstring)."""
        if not (dt > 0.0 and dt < math.inf):
            check_dt(dt)
        st = self.state
        ta = self.lookahead_s
        if ta == 0.0:
            xr, vr = ref[0], ref[1]
        else:  # as _ahead
            x_r, v_r, a_r = ref
            xr, vr = x_r + v_r * ta + 0.5 * a_r * ta * ta, v_r + a_r * ta
        if st.x_fed_m != st.x_fed_m:
            self.reset(xr)
        if stop_m == stop_m and ta != 0.0:
            xr, vr = bounded_ahead(xr, vr, ref[0], stop_m, self.latch)
        v_prev, self._v_ref = self._v_ref, ref[1]
        if v_prev != 0.0 and ta != 0.0 and ref[1] == 0.0 and ref[2] == 0.0 and v_prev * self.latch.direction > 0.0:
            self._stopped(xr)  # stopped at once: the look-ahead's overshoot is no move back (module docstring)
        changed = self.latch.update(xr, vr)
        if changed and st.direction != 0:
            st.reversals += 1
        if changed:
            st.x_rev_m = st.x_fed_m
            st.f_rev_n = self._f_model
        d = self.latch.direction
        st.direction = d
        dx = xr - st.x_fed_m
        if d != 0 and dx * d > 0.0:
            # motion in the confirmed direction (includes the catch-up of a just-confirmed move-back)
            b = self.input_scale
            f = self._step(self._mstate, b * dx, b * dx / dt, dt)
            st.x_fed_m = xr
            st.holding = False
            self._f_model = f
        else:
            st.holding = dx != 0.0  # unconfirmed move-back (jitter) or no motion: hold the model
            f = self._f_model
        if self._no_effects:  # what the three calls below return without effects (+ 0.0 as they add it)
            f = f + 0.0
            fo = 0.0
        else:
            eff = self.effects
            f = eff.modify_friction(f, xr) + eff.velocity_force(vr)
            fo = eff.other_force(xr)
        st.f_friction_n, st.f_other_n = f, fo
        st.x_extreme_m = self.latch.extreme
        st.u_ff_n = f + fo
        return st.u_ff_n


    def feed_at(self, x_m: float) -> None:
        """Take ``x_m`` [m] as the position the model copy was last fed, without stepping its state (real-time
        safe): a reference that then travels in the model's direction up to ``x_m`` leaves the state as it is
        (:meth:`step` holds it while the reference has not passed the fed position). At standstill the controller
        feeds the model at the stage's position when the stage is stuck ahead of the reference."""
        self.state.x_fed_m = x_m

    def tangent_n_m(self, direction: int, probe_m: float = 1e-8, probe_s: float = 1.0) -> float:
        """The model's stiffness for a further displacement of the reference in ``direction`` (+1/−1) from its
        present state [N/m] (real-time safe: two probe steps on a copy of the state in a buffer kept for it; the
        state itself is not changed). Probes of ``probe_m`` and 2·``probe_m`` taken slowly (over ``probe_s``, so
        that rate terms such as GMS's micro-damping σ1·v do not count), differenced so that elements already
        slipping count in neither. Includes the input scale β. GMS: Σk_i of the elements not at their slip
        limit in that direction (all of them right after a reversal, none in gross sliding)."""
        buf = self._probe
        if buf is None or len(buf) != len(self._mstate):
            buf = self._probe = self._mstate.copy()
        sgn = 1.0 if direction >= 0 else -1.0
        dx = self.input_scale * probe_m * sgn
        buf[:] = self._mstate
        f1 = self._step(buf, dx, dx / probe_s, probe_s)
        buf[:] = self._mstate
        f2 = self._step(buf, 2.0 * dx, 2.0 * dx / probe_s, probe_s)
        return (f2 - f1) / (probe_m * sgn)

    def nudge(self, dx_m: float, dt: float) -> float:
        """Move the model copy's *state* by a virtual displacement ``dx_m`` [m] over ``dt`` [s] without moving
        its fed position (real-time safe): at standstill the controller loads the model's pre-sliding springs
        so that its force matches the force the plant is measured to hold (feed-forward through the stop).
        Returns the new u_ff [N] at the held reference."""
        st = self.state
        if dx_m == 0.0 or math.isnan(st.x_fed_m):
            return st.u_ff_n
        f = self._step(self._mstate, dx_m, dx_m / dt, dt)
        self._f_model = f
        eff = self.effects
        x = st.x_fed_m
        f = eff.modify_friction(f, x) + eff.velocity_force(0.0)
        st.f_friction_n = f
        st.u_ff_n = f + st.f_other_n
        return st.u_ff_n


class CoulombFeedforward:
    """Static baseline ``u_ff = d·F_c + c_v·v_r`` with the jitter-immune direction latch (``kind: coulomb``)."""

    def __init__(self, coulomb_n: float, viscous_n_s_m: float = 0.0, effects: Effects = NO_EFFECTS, *,
                 reversal_threshold_m: float = 5e-9, reversal_velocity_m_s: float = 1e-5, lookahead_s: float = 0.0):
        self.coulomb_n = coulomb_n
        self.viscous_n_s_m = viscous_n_s_m
        self.effects = effects
        self.lookahead_s = lookahead_s + (effects.delay.delay_s if effects.delay is not None else 0.0)
        self.latch = DirectionLatch(reversal_threshold_m, reversal_velocity_m_s)
        self.state = FrictionFfState()
        self._v_ref = 0.0  # the reference's own velocity at the last step [m/s]

    def reset(self, x_m: float) -> None:
        self.latch.reset(x_m)
        self._v_ref = 0.0
        self.state = FrictionFfState(x_fed_m=x_m, x_extreme_m=x_m)

    def step(self, dt: float, ref: Reference, stop_m: float = math.nan) -> float:
        check_dt(dt)
        ta = self.lookahead_s
        xr = ref.x_m + ref.v_m_s * ta + 0.5 * ref.a_m_s2 * ta * ta
        vr = ref.v_m_s + ref.a_m_s2 * ta
        st = self.state
        if math.isnan(st.x_fed_m):
            self.reset(xr)
        if stop_m == stop_m and ta != 0.0:
            xr, vr = bounded_ahead(xr, vr, ref.x_m, stop_m, self.latch)
        v_prev, self._v_ref = self._v_ref, ref.v_m_s
        if (v_prev != 0.0 and ta != 0.0 and ref.v_m_s == 0.0 and ref.a_m_s2 == 0.0
                and v_prev * self.latch.direction > 0.0):
            self.latch.stop_at(xr)  # stopped at once: the look-ahead's overshoot is no move back (module docstring)
        if self.latch.update(xr, vr) and st.direction != 0:
            st.reversals += 1
        d = self.latch.direction
        st.direction = d
        st.x_fed_m = xr
        f = d * self.coulomb_n + self.viscous_n_s_m * vr
        f = self.effects.modify_friction(f, xr) + self.effects.velocity_force(vr)
        fo = self.effects.other_force(xr)
        st.f_friction_n, st.f_other_n = f, fo
        st.u_ff_n = f + fo
        return st.u_ff_n
