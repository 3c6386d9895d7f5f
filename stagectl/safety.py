"""Safety supervisor: limits and watchdogs that latch a named fault (a stage must never run away).

Checks, run by the loop every cycle (all real-time safe: scalar arithmetic, no allocation on the
good path):

=====================  ===============================================================================
fault name             condition
=====================  ===============================================================================
``not_finite``         NaN/inf in the measured position, the reference or the controller output
``<device kind>``      a device reports a fault (``Measurement.fault`` / ``device.fault``): the name is
                       the :class:`~stagectl.drivers.base.FaultKind` value (``drive_fault``, ``emcy``,
                       ``heartbeat_lost``, ``bus_off``, ``sensor_error``, ...)
``stale_position``     ``stale_cycles`` consecutive reads without a fresh sample (a hard cap); while moving,
                       earlier when the stage may have travelled more than ``stale_travel_m`` unseen since
                       the last fresh sample (see *Unseen travel* below); ``stale_rest_cycles`` while
                       the stage (nearly) stands: reference speed and \\|v̂\\| at the last fresh sample both
                       <= ``quick_stop_standstill_m_s``. Unseen it travels that speed times the gap (0.1 mm/s ·
                       0.5 s = 50 µm) plus what the held force does: nothing while friction holds it (stuck),
                       up to (F_held/m)·gap²/2 if it slides (10 mN on 2 kg: 0.6 mm in 0.5 s). Use it only
                       where the held force at rest stays below break-away; on a PC without a real-time kernel
                       the drive's process may be held off the CPU for 0.1-0.4 s
``position_limit``     x < ``min_position_m`` or x > ``max_position_m`` (soft limits)
``following_error``    \\|x_ref − x\\| > ``following_error_m`` for longer than ``following_error_time_s`` (fresh
                       samples only: a stale one holds the old position)
``position_jump``      a fresh sample moved further since the previous fresh one than the stage physically
                       can: \\|Δx\\| > v_max·Δt + (F_max/m)·Δt²/2 + ``jump_margin_m`` (Δt: time between the two
                       samples, T when none was stale; v_max = ``max_velocity_m_s``, F_max = ``max_force_n``,
                       m the moving mass given to :class:`Safety`; off without a mass). After a gap of
                       ``stale_cycles`` or more (only the rest allowance lets one through: the stage stood, the
                       controller held a force below break-away) the bound is what that allowance assumes,
                       v_s·Δt + the one-period bound (v_s = ``quick_stop_standstill_m_s``), if smaller
``velocity_limit``     \\|v̂\\| > ``max_velocity_m_s``; v̂ is the backward difference Δx/Δt between fresh samples,
                       Δt their measured interval (loop time; a sample less than T/2 after the last one waits for the
                       next), low-passed at
                       ``velocity_filter_hz`` (first order: v̂ += α(Δx/Δt − v̂), α = 1 − e^{−2π f Δt}), so a
                       skipped cycle or a dropped sample does not read as a velocity jump
``force_limit``        the output is clamped to ±``max_force_n`` every cycle; being clamped continuously
                       for longer than ``force_saturation_time_s`` (a blocked stage, a limit cycle at full force)
                       is a fault; the controller's own output clamp (``Command.limited`` holds ``"force"``)
                       counts as clamped too, else a controller clamping at or below ``max_force_n`` hides it
``loop_error``         an unexpected exception in the cycle (raised by the loop, recorded here)
``unclean_shutdown``   latched at start by the daemon when the previous run did not end cleanly
=====================  ===============================================================================

:data:`SAFETY_FAULTS` lists the names above that are not device kinds.

Position-jump bound: a stage that was inside the velocity limit at the previous sample and is pushed by at most
F_max moves at most v_max·Δt + (F_max/m)·Δt²/2 by the next one; ``jump_margin_m`` covers sensor noise and
sampling jitter. For the seed stage (2 kg, 10 N, 0.02 m/s, 1 ms, margin 1 µm) that is 20 + 2.5 + 1 = 23.5 µm,
where a sensor's own glitch check (``max_speed_m_s``) allows 2 mm. A larger step is a sensor glitch or a
collision; either way the position can no longer be trusted to close the loop on.

Unseen travel (``stale_travel_m``): a stale sample leaves the loop blind; what matters is not how many cycles
it stays blind but how far the stage can have gone meanwhile. A stage with only passive friction (friction
opposes the motion: it can stop the stage, never push it on) that moved at v₀ at the last fresh sample and is
pushed by at most F̄ moves, τ after that sample, at most::

    D(τ) = v_b·τ + (F̄/m)·τ²/2,   v_b = max(|v̂|, |v_ref|),   F̄ = max |u| written since the last fresh sample

(v̂ the velocity estimate at the last fresh sample, |v_ref| the reference speed then and now: the estimate's
low-pass lags an accelerating stage, the reference it follows does not; F̄ starts from the force written the
cycle before that sample, which the one-cycle I/O delay still applies after it; m the moving mass). While
moving (the rest allowance not in force) ``stale_position`` latches as soon as D(τ) > ``stale_travel_m``,
and at ``stale_cycles`` at the latest. The bound ignores friction (it may be lower than modelled), so the
force term counts the whole force as accelerating: the seed stage (2 kg) scanning at 1.6 mm/s against its
0.85 N of friction reaches 50 µm after 12 ms, at 18 mm/s after 2.8 ms, so a fast stage that goes blind
faults within 3 cycles while a scan rides out the few late samples of a loaded PC (``stagectl bench timing``
sees runs of up to 3). Unset (or without a mass) only the cycle counts apply. A sensible value is the
following-error window: the loop stops trusting its blind guess before the stage can be further off than
the tracking error the application already tolerates. The CiA 402 driver's ``max_missed`` (reads without
any TPDO) should not be tighter than ``stale_cycles``, else it decides first (the embedded virtual drive's
default follows ``stale_cycles``).

The first fault latches (:attr:`Safety.fault`) with its cause, time and cycle; later ones do not
overwrite it. Only :meth:`Safety.clear` (an explicit operator reset) clears it. The loop reacts to a
latched fault in the same cycle: for ``following_error``, ``velocity_limit`` and ``position_limit`` (the
position is valid and the drive obeys) it brakes the stage to standstill on a velocity ramp with
``quick_stop_deceleration_m_s2`` within ``max_force_n`` and then commands the drive's quick stop
(:mod:`stagectl.runtime.quickstop`); for every other fault it commands the quick stop at once (zero force
within the 3-cycle budget).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from stagectl.clock import Timing
from stagectl.errors import ConfigError
from stagectl.schema import param


@dataclass(frozen=True)
class SafetyConfig:
    """Limits and watchdog settings (SI units)."""

    min_position_m: float = param(unit="m", desc="soft limit: lowest allowed measured position")
    max_position_m: float = param(unit="m", desc="soft limit: highest allowed measured position")
    following_error_m: float = param(1e-4, unit="m", desc="following-error window |x_ref - x|", gt=0)
    following_error_time_s: float = param(
        0.0, unit="s", desc="how long the following error may stay outside the window", ge=0
    )
    max_force_n: float = param(20.0, unit="N", desc="hard clamp of the commanded force", gt=0)
    force_saturation_time_s: float = param(
        0.5, unit="s", desc="continuous clamping longer than this latches force_limit", gt=0
    )
    max_velocity_m_s: float = param(0.05, unit="m/s", desc="velocity limit on the measured motion", gt=0)
    velocity_filter_hz: float = param(100.0, unit="Hz", desc="low-pass of the velocity estimate", gt=0)
    stale_cycles: int = param(3, desc="consecutive cycles without a fresh position before faulting (the hard cap "
                              "when stale_travel_m is set)", ge=1)
    stale_rest_cycles: int | None = param(
        None, desc="the same while the stage (nearly) stands: reference speed and |v| at the last fresh sample <= "
        "quick_stop_standstill_m_s (unseen it travels that speed times the gap, plus (F_held/m)*gap^2/2 if the "
        "held force makes it slide; never below stale_cycles; None: stale_cycles)", ge=1)
    stale_travel_m: float | None = param(
        None, unit="m", desc="while moving, stale_position as soon as the stage may have travelled more than this "
        "unseen since the last fresh sample: max(|v|, |v_ref|)*gap + (F/m)*gap^2/2, F the largest force written "
        "since (stale_cycles stays the hard cap; e.g. following_error_m; None: the cycle counts only)", gt=0)
    jump_margin_m: float = param(
        1e-6, unit="m", desc="sensor noise and sampling-jitter margin added to the physical per-cycle position bound "
        "(position_jump)", ge=0)
    move_velocity_fraction: float = param(
        0.9, desc="moves are planned at most at this fraction of max_velocity_m_s (tracking overshoot must not "
        "trip velocity_limit); faster requests are refused", gt=0, le=1)
    move_force_fraction: float = param(
        0.8, desc="moves are planned so that their peak force m*a_max + F_s + F_v*v_max (the controller's mass and "
        "friction model) is at most this fraction of the usable force (the least of controller.max_force_n, "
        "max_force_n and the drive's own limit); a faster move is planned slower, with a warning, instead of "
        "saturating the actuator (0: moves run as given)", ge=0, le=1)
    quick_stop_deceleration_m_s2: float | None = param(
        None, unit="m/s^2", desc="fault reaction: deceleration of the braking ramp after following_error, "
        "velocity_limit or position_limit, before the drive is released (None: 0.9 max_force_n / moving mass)",
        gt=0)
    quick_stop_standstill_m_s: float = param(
        1e-4, unit="m/s", desc="fault reaction: the brake ends (drive released) below this velocity", gt=0)

    def __post_init__(self) -> None:
        if not self.min_position_m < self.max_position_m:
            raise ConfigError(
                f"safety.max_position_m: must be > min_position_m ({self.min_position_m:g} m), "
                f"got {self.max_position_m:g} m"
            )


@dataclass(frozen=True, slots=True)
class SafetyFault:
    """A latched fault: ``name`` (see module table), human-readable ``cause``, time [s] and cycle."""

    name: str
    cause: str
    t_s: float
    cycle: int

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "cause": self.cause, "t_s": self.t_s, "cycle": self.cycle}

    def __str__(self) -> str:
        return f"{self.name}: {self.cause} (t={self.t_s:.6f} s, cycle {self.cycle})"


_isfinite = math.isfinite

#: fault names the supervisor itself latches; a device fault is latched under its kind's name (the
#: ``FaultKind`` values of :mod:`stagectl.drivers.base`)
SAFETY_FAULTS = ("not_finite", "stale_position", "position_limit", "position_jump", "following_error",
                 "velocity_limit", "force_limit", "loop_error", "unclean_shutdown")


class Safety:
    """Stateful supervisor for one loop (see module docstring). Not thread-safe: loop thread only.

    Parameters
    ----------
    cfg : SafetyConfig
    timing : Timing or float
        The loop's timing (or its period T [s]); the velocity filter coefficient α is derived from it once here.
    mass_kg : float, optional
        The moving mass m [kg] (the controller's ``mass_kg``): with it, the ``position_jump`` check bounds each
        step by v_max·Δt + (F_max/m)·Δt²/2 + ``jump_margin_m``; None turns that check off.
    """

    def __init__(self, cfg: SafetyConfig, timing: Timing | float, mass_kg: float | None = None) -> None:
        t = Timing.of(timing)
        self.cfg = cfg
        self.timing = t
        self.period_s = t.period_s
        self._alpha = 1.0 - math.exp(-2.0 * math.pi * cfg.velocity_filter_hz * t.period_s)
        if mass_kg is not None and not (_isfinite(mass_kg) and mass_kg > 0):
            raise ConfigError(f"safety: moving mass must be a finite number > 0 kg, got {mass_kg!r}")
        self.mass_kg = mass_kg
        #: largest plausible acceleration F_max/m [m/s²] (None: no position_jump check)
        self.max_accel_m_s2 = cfg.max_force_n / mass_kg if mass_kg is not None else None
        self._act_lim = math.inf  # the actuator's own force limit [N] (set_actuator_limit)
        self.fault: SafetyFault | None = None
        self.n_faults = 0
        self.v_est_m_s = 0.0
        self._x_prev: float | None = None
        self._t_prev: float | None = None
        self._stale = 0
        self._t_fresh: float | None = None  # time [s] of the last fresh sample (unseen travel)
        self._v_ref_fresh = 0.0  # |v_ref| [m/s] when it came
        self._u_last = 0.0  # |u| [N] of the last force written
        self._u_gap = 0.0  # largest |u| [N] written since the last fresh sample (and the one before it)
        self._fe_since: float | None = None
        self._sat_since: float | None = None
        #: |v_ref| of the last cycle [m/s] (set by the loop; selects ``stale_rest_cycles``)
        self.reference_speed_m_s = math.inf

    # ----------------------------------------------------------------- latch / clear
    def latch(self, name: str, cause: str, t_s: float, cycle: int) -> SafetyFault:
        """Latch ``name`` unless a fault is already latched; returns the latched fault."""
        if self.fault is None:
            self.fault = SafetyFault(name, cause, t_s, cycle)
            self.n_faults += 1
        return self.fault

    def clear(self) -> None:
        """Explicit reset: forget the latched fault and the watchdog timers."""
        self.fault = None
        self.restart(None)

    def max_step_m(self, dt_s: float) -> float:
        """The largest plausible position change [m] in ``dt_s`` [s]: v_max·Δt + (F_max/m)·Δt²/2 + margin
        (inf without a mass)."""
        a = self.max_accel_m_s2
        if a is None:
            return math.inf
        return self.cfg.max_velocity_m_s * dt_s + 0.5 * a * dt_s * dt_s + self.cfg.jump_margin_m

    def unseen_travel_m(self, tau_s: float) -> float:
        """The bound D(τ) [m] on the stage's travel ``tau_s`` [s] after the last fresh sample (module docstring,
        *Unseen travel*): max(|v̂|, |v_ref|)·τ + (F̄/m)·τ²/2; inf without a mass."""
        m = self.mass_kg
        if m is None:
            return math.inf
        vr = self.reference_speed_m_s
        v = max(abs(self.v_est_m_s), self._v_ref_fresh, vr if vr < math.inf else 0.0)
        return v * tau_s + 0.5 * (self._u_gap / m) * tau_s * tau_s

    def persisting(self, x_m: float, fresh: bool) -> tuple[str, ...]:
        """Causes of supervisor faults still present at position ``x_m`` (``fresh``: this cycle's sample is
        new): a reset is refused while this is not empty (it would latch again at once). A non-finite position
        or one outside the soft limits always counts; a stale sample when the latched fault is about one."""
        cfg = self.cfg
        if not _isfinite(x_m):
            return (f"not_finite: measured position is {x_m}",)
        out: list[str] = []
        latched = self.fault.name if self.fault is not None else None
        if not fresh and latched in ("stale_position", "missed_frame"):
            out.append(f"{latched}: still no fresh position this cycle")
        if x_m < cfg.min_position_m or x_m > cfg.max_position_m:
            out.append(f"position_limit: x = {x_m:.9g} m outside soft limits [{cfg.min_position_m:g}, "
                       f"{cfg.max_position_m:g}] m (bring the stage inside with the drive disabled)")
        return tuple(out)

    def restart(self, x_m: float | None, t_s: float | None = None) -> None:
        """Reset the estimators and timers (at start and on reset) without touching a latched fault; ``t_s``:
        the time [s] of the sample ``x_m`` (the position-jump bound is measured from it)."""
        self.v_est_m_s = 0.0
        self._x_prev = x_m
        self._t_prev = t_s
        self._stale = 0
        self._t_fresh = t_s
        self._v_ref_fresh = 0.0
        self._u_gap = self._u_last
        self._fe_since = None
        self._sat_since = None

    # ----------------------------------------------------------------- per-cycle checks
    def check_measurement(self, t_s: float, cycle: int, x_m: float, fresh: bool, device_fault: object) -> bool:
        """Position, freshness and device-fault checks. Returns True when a fault is latched.

        ``t_s`` is the loop time of this sample [s]: the velocity estimate divides by the measured interval
        since the previous fresh sample (at least T/2; T when there is no previous one)."""
        cfg = self.cfg
        if device_fault is not None:
            kind = getattr(device_fault, "kind", None)
            name = getattr(kind, "value", None) or "device_fault"
            self.latch(name, f"device reported {device_fault}", t_s, cycle)
            return True
        if not _isfinite(x_m):
            self.latch("not_finite", f"measured position is {x_m}", t_s, cycle)
            return True
        if not fresh:
            self._stale += 1
            limit = cfg.stale_cycles
            slow = cfg.quick_stop_standstill_m_s
            rest = (cfg.stale_rest_cycles is not None and self.reference_speed_m_s <= slow
                    and abs(self.v_est_m_s) <= slow)
            if rest:
                limit = max(limit, cfg.stale_rest_cycles or limit)
            if self._stale >= limit:
                self.latch("stale_position", f"no fresh position for {self._stale} consecutive cycles", t_s, cycle)
                return True
            allow = cfg.stale_travel_m
            if allow is not None and not rest and self.mass_kg is not None:  # at rest friction holds it (above)
                tf = self._t_fresh
                tau = self._stale * self.period_s if tf is None else t_s - tf
                d = self.unseen_travel_m(tau)
                if d > allow:
                    self.latch("stale_position", f"no fresh position for {self._stale} consecutive cycles "
                               f"({tau * 1e3:.3g} ms): the stage may have moved {d:.3g} m unseen (force up to "
                               f"{self._u_gap:.3g} N) > stale_travel_m {allow:g} m", t_s, cycle)
                    return True
            return self.fault is not None
        gap = self._stale
        self._stale = 0
        self._t_fresh = t_s
        vr = self.reference_speed_m_s
        self._v_ref_fresh = vr if vr < math.inf else 0.0
        self._u_gap = self._u_last
        if x_m < cfg.min_position_m or x_m > cfg.max_position_m:
            self.latch(
                "position_limit",
                f"x = {x_m:.9g} m outside soft limits [{cfg.min_position_m:g}, {cfg.max_position_m:g}] m",
                t_s,
                cycle,
            )
            return True
        xp, tp = self._x_prev, self._t_prev
        T = self.period_s
        dt = T if tp is None else t_s - tp
        if dt < 0.5 * T:  # a sample right after the last one (late wake-up): keep the longer baseline
            return self.fault is not None
        self._x_prev, self._t_prev = x_m, t_s
        if xp is not None:
            if self.max_accel_m_s2 is not None:
                bound = self.max_step_m(dt)
                if gap >= cfg.stale_cycles:  # only the rest allowance lets such a gap through: the stage stood
                    bound = min(bound, cfg.quick_stop_standstill_m_s * dt + self.max_step_m(T))
                if abs(x_m - xp) > bound:
                    self.latch(
                        "position_jump",
                        f"position moved {x_m - xp:.4g} m in {dt:.4g} s; physically at most {bound:.4g} m "
                        f"(v_max·Δt + F_max/m·Δt²/2 + jump_margin_m: max_velocity_m_s {cfg.max_velocity_m_s:g}, "
                        f"max_force_n {cfg.max_force_n:g} N, mass {self.mass_kg:g} kg)",
                        t_s,
                        cycle,
                    )
                    return True
            alpha = self._alpha if abs(dt - T) <= 1e-9 * T else (
                1.0 - math.exp(-2.0 * math.pi * cfg.velocity_filter_hz * dt))
            v_raw = (x_m - xp) / dt
            self.v_est_m_s += alpha * (v_raw - self.v_est_m_s)
            if abs(self.v_est_m_s) > cfg.max_velocity_m_s:
                self.latch(
                    "velocity_limit",
                    f"|v| = {abs(self.v_est_m_s):.6g} m/s > max_velocity_m_s {cfg.max_velocity_m_s:g} m/s",
                    t_s,
                    cycle,
                )
                return True
        return self.fault is not None

    def check_tracking(self, t_s: float, cycle: int, x_m: float, x_ref_m: float, fresh: bool = True) -> bool:
        """Reference finiteness and following-error window. Returns True when a fault is latched.

        A stale sample (``fresh`` False) is the old position held: x_ref − x is then no measurement (a moving
        reference would read as a growing error), so the window's timer neither starts nor resets on it; the
        stale limits bound how long the loop runs blind."""
        if not _isfinite(x_ref_m):
            self.latch("not_finite", f"reference position is {x_ref_m}", t_s, cycle)
            return True
        if not fresh:
            return self.fault is not None
        e = x_ref_m - x_m
        if abs(e) > self.cfg.following_error_m:
            if self._fe_since is None:
                self._fe_since = t_s
            if t_s - self._fe_since >= self.cfg.following_error_time_s:
                self.latch(
                    "following_error",
                    f"|x_ref - x| = {abs(e):.6g} m > following_error_m {self.cfg.following_error_m:g} m",
                    t_s,
                    cycle,
                )
                return True
        else:
            self._fe_since = None
        return self.fault is not None

    def set_actuator_limit(self, limit_n: float) -> None:
        """The largest force the actuator really applies [N] (a CiA 402 drive's max torque 0x6072): the hard
        clamp becomes min(``max_force_n``, limit_n), so the force written (and recorded) is the force applied
        and the saturation time counts at the real limit (inf or not > 0: ``max_force_n``). The position-jump
        bound keeps F_max = ``max_force_n`` (external forces may add to the actuator's)."""
        lim = float(limit_n)
        self._act_lim = lim if lim > 0.0 and math.isfinite(lim) else math.inf

    @property
    def force_limit_n(self) -> float:
        """The hard force clamp L [N]: min(``max_force_n``, the actuator's own limit)."""
        return min(self.cfg.max_force_n, self._act_lim)

    def limit_force(self, t_s: float, cycle: int, u_n: float, clamped: bool = False) -> float:
        """Clamp ``u_n`` to ±L, L = :attr:`force_limit_n` (``max_force_n``, or the actuator's limit when lower);
        latch ``not_finite`` / ``force_limit``. ``clamped``: the controller already clamped its output (its own
        force limit), which counts as saturated as well. Returns the force to write (0.0 when a fault is latched
        by this call)."""
        if not _isfinite(u_n):
            self.latch("not_finite", f"controller output is {u_n}", t_s, cycle)
            return 0.0
        lim = min(self.cfg.max_force_n, self._act_lim)
        inside = -lim <= u_n <= lim
        a = abs(u_n) if inside else lim  # the force written (unseen travel: F̄)
        self._u_last = a
        self._u_gap = max(self._u_gap, a)
        if inside and not clamped:
            self._sat_since = None
            return u_n
        if self._sat_since is None:
            self._sat_since = t_s
        elif t_s - self._sat_since >= self.cfg.force_saturation_time_s:
            what = f"±{lim:g} N" if not inside else f"the controller's limit ({abs(u_n):.4g} N)"
            self.latch(
                "force_limit",
                f"force clamped at {what} for {t_s - self._sat_since:.3f} s "
                f"(force_saturation_time_s {self.cfg.force_saturation_time_s:g} s)",
                t_s,
                cycle,
            )
            return 0.0
        return u_n if inside else lim if u_n > 0 else -lim
