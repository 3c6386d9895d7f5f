"""Active quick stop: brake the stage to standstill on a velocity ramp before the drive is released.

CiA 402 quick-stop option codes (0x605A 1/2/5/6) decelerate on a ramp and only then disable the power
stage; a torque-mode drive whose force is simply released lets the stage coast on. For the faults where the
loop still has a valid position and the actuator still obeys (``following_error``, ``velocity_limit``,
``position_limit``: :data:`BRAKE_FAULTS`), the loop brakes itself, with this law, and then calls the
actuator's ``quick_stop()`` (CANopen: controlword QUICK STOP, zero torque). Faults where braking is unsafe
(no or invalid position, a device or drive fault, an exception in the cycle) keep the immediate reaction:
``quick_stop()`` at once, zero force.

Law, per fresh sample (time t [s] since the fault at t_f, measured sample interval Δt [s])::

    v̂      = v̂ + α·((x − x_prev)/Δt − v̂),   α = 1 − exp(−2π·f_v·Δt)     velocity estimate [m/s]
    v_r(t) = sign(v₀)·max(0, |v₀| − a·(t − t_f))                         velocity ramp to zero [m/s]
    a_r    = −sign(v₀)·a while |v_r| > 0, else 0                          [m/s²]
    u      = clamp( m·(a_r + K_v·(v_r − v̂)), ±F_max )                     [N]

with v₀ the velocity estimate at the fault, a the quick-stop deceleration (default 0.9·F_max/m, so the
velocity loop keeps a 10 % force reserve; friction only helps), K_v = 2π·``BRAKE_BANDWIDTH_HZ``. The stop
distance is v₀²/(2a) plus the distance covered during the detection and I/O delay (≈ v₀·2T).

Release (then ``quick_stop()``): the ramp has ended and |v̂| < ``standstill_m_s`` for
``STANDSTILL_SAMPLES`` fresh samples, or the ramp time plus ``EXTRA_TIME_S`` has passed, or no fresh sample
for ``stale_limit`` cycles, or the position is not finite. Meanwhile the law holds its last force for
``HOLD_STALE_CYCLES`` stale cycles, then applies 0 (a force held blind for a long gap on a loaded PC, up to
F_max, drove a stage that had already stopped on for hundreds of µm).
"""

from __future__ import annotations

import math

__all__ = ["BRAKE_FAULTS", "QuickStopBrake"]

#: faults after which the loop brakes actively (position valid, actuator obeying)
BRAKE_FAULTS = frozenset({"following_error", "velocity_limit", "position_limit"})
#: bandwidth of the brake's velocity loop [Hz]
BRAKE_BANDWIDTH_HZ = 30.0
#: low-pass of the brake's velocity estimate [Hz]
VELOCITY_FILTER_HZ = 200.0
#: consecutive fresh samples below the standstill velocity that end the brake
STANDSTILL_SAMPLES = 5
#: on stale samples the last force is held this many cycles, then the brake applies 0 until a fresh sample
HOLD_STALE_CYCLES = 2
#: the brake gives up this long after its ramp should have ended [s]
EXTRA_TIME_S = 0.1


class QuickStopBrake:
    """One braking manoeuvre (see module docstring). Loop thread only; ``step`` is real-time safe.

    Parameters
    ----------
    t_s, x_m, v_m_s : float
        Time [s], measured position [m] and velocity estimate [m/s] at the fault.
    mass_kg : float
        Moving mass [kg].
    max_force_n : float
        Force limit [N] (the safety clamp).
    deceleration_m_s2 : float
        Ramp deceleration a [m/s²] (> 0).
    standstill_m_s : float
        Velocity below which the stage counts as standing [m/s].
    stale_limit : int
        Consecutive stale cycles after which the brake gives up.
    """

    def __init__(self, t_s: float, x_m: float, v_m_s: float, *, mass_kg: float, max_force_n: float,
                 deceleration_m_s2: float, standstill_m_s: float, stale_limit: int) -> None:
        self.t0_s = t_s
        self.x0_m = x_m
        self.v0_m_s = v_m_s if math.isfinite(v_m_s) else 0.0
        self.mass_kg = mass_kg
        self.max_force_n = max_force_n
        self.a_m_s2 = deceleration_m_s2
        self.standstill_m_s = standstill_m_s
        self.stale_limit = stale_limit
        self.kv = 2.0 * math.pi * BRAKE_BANDWIDTH_HZ
        self.ramp_s = abs(self.v0_m_s) / deceleration_m_s2
        self.v_hat_m_s = self.v0_m_s
        self._x_prev = x_m
        self._t_prev = t_s
        self._still = 0
        self._stale = 0
        self.t_last_s = -math.inf  # time of the last step call
        self.u_n = 0.0
        self.done = False
        self.why = ""

    def v_ref(self, t_s: float) -> tuple[float, float]:
        """Ramp velocity [m/s] and acceleration [m/s²] at ``t_s``."""
        left = abs(self.v0_m_s) - self.a_m_s2 * (t_s - self.t0_s)
        if left <= 0.0:
            return 0.0, 0.0
        s = 1.0 if self.v0_m_s > 0 else -1.0
        return s * left, -s * self.a_m_s2

    def step(self, t_s: float, x_m: float, fresh: bool) -> float:
        """The brake force [N] for this cycle (its last force on a stale sample); sets ``done`` and ``why``
        when the stage is stopped or the brake must give up."""
        if self.done:
            return 0.0
        self.t_last_s = t_s
        if not math.isfinite(x_m):
            return self._finish("position not finite")
        if t_s - self.t0_s > self.ramp_s + EXTRA_TIME_S:
            return self._finish("time-out")
        if not fresh:
            self._stale += 1
            if self._stale >= self.stale_limit:
                return self._finish(f"no fresh position for {self._stale} cycles")
            if self._stale > HOLD_STALE_CYCLES:  # blind: no braking force is held (friction stops a coasting
                self.u_n = 0.0                     # stage; a held 10 N pushes it on for the whole gap)
            return self.u_n
        self._stale = 0
        dt = t_s - self._t_prev
        if dt > 0.0:
            alpha = 1.0 - math.exp(-2.0 * math.pi * VELOCITY_FILTER_HZ * dt)
            self.v_hat_m_s += alpha * ((x_m - self._x_prev) / dt - self.v_hat_m_s)
        self._x_prev, self._t_prev = x_m, t_s
        v_r, a_r = self.v_ref(t_s)
        if v_r == 0.0 and abs(self.v_hat_m_s) < self.standstill_m_s:
            self._still += 1
            if self._still >= STANDSTILL_SAMPLES:
                return self._finish("standstill")
        else:
            self._still = 0
        u = self.mass_kg * (a_r + self.kv * (v_r - self.v_hat_m_s))
        lim = self.max_force_n
        self.u_n = lim if u > lim else -lim if u < -lim else u
        return self.u_n

    def _finish(self, why: str) -> float:
        self.done = True
        self.why = why
        self.u_n = 0.0
        return 0.0
