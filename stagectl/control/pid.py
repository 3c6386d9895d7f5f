"""PID position controller with filtered derivative, conditional-integration anti-windup (held through the
recovery from a clamp), back-calculation and clamp.

Continuous law (gains in physical units)::

    u_pid = Kp·e + Ki·∫e dt + Kd·ė_f,        e = x_ref − x_meas  [m]
    ė_f   = LPF_fc( ė )                      first-order low-pass, cut-off fc = derivative_cutoff_hz

Kp = ``kp_n_m`` [N/m], Ki = ``ki_n_m_s`` [N/(m·s)], Kd = ``kd_n_s_m`` [N·s/m].

Derivative (``derivative_on``):

* ``measurement`` (default): ė = v_ref − (x_k − x_{k−1})/dt. The reference enters only through its
  analytic velocity v_ref, so steps in x_ref do not kick the D term.
* ``error``: ė = (e_k − e_{k−1})/dt (a step in x_ref kicks the D term, filtered).

Discrete filter (exact for a constant input over dt), β = exp(−2π·fc·dt)::

    ė_f,k = β·ė_f,k−1 + (1 − β)·ė_k

Algorithm per step, in LinuxCNC ``pid`` order:

1. e = x_ref − x_meas; P = Kp·e; D = Kd·ė_f.
2. Anti-windup (conditional integration): the candidate total u* = P + I + D + u_other is computed with
   the old integral term I; the integral is advanced (I += Ki·e·dt) unless |u*| exceeds the output
   limit *and* sgn(u*) = sgn(e) (saturated in the direction of the error), or while it recovers from a clamp
   (below). I is then clamped to ±``integrator_limit_n``.

   Recovery: a clamp (step 3) leaves an error P and D work off (a lag the stage catches up once the force comes
   back, an excess it brakes off). Integrated, that transient left I standing once the error closed, and the
   stage ran ahead of the reference by e = −I/K_p until I unwound over T_i (a 1 mm move at 1 m/s² on a 1.5 N
   drive: 118 µm of lag, I ≈ 0.2 N, 15.5 µm ahead while cruising and 30 µm past the target; now never ahead
   and 11 µm past). After a clamp with error e₀, I is held while sgn(e) = sgn(e₀) and

       t_since_clamp < T_i = Kp/Ki,   and   not (the error has closed fast, then slowly),

   "fast" meaning |ė_f|·T_i > |e| with e·ė_f < 0. An error P alone cannot close (an unmodelled load: it settles
   at e = F/K_p) thus ends the hold as its closing slows, at the latest T_i of unclamped time after the first
   clamp (a clamp of the same sign during the hold does not restart it). A hold that ran out so (not by a sign
   change) is spent: clamps of its sign arm none until e changes sign or T_i passes without a clamp (a load at
   the clamp otherwise touched it every few cycles and froze I for good). A clamp in either direction arms it (a
   lag the force catches up, or an excess the brake takes off; not frozen for good either way: P grows until the
   output leaves the clamp, and the hold ends at T_i); a retune keeps a running hold, its T_i then the new gains'.
   A loop never clamped runs as without it.
3. u_pid = clamp(P + I + D, ±``max_force_n``); total u = clamp(u_pid + u_other, ±limit_n).
4. Back-calculation (for the next step): when a clamp cut the command, the excess
   x = P + I + D + u_other − u is taken out of I at the tracking rate, as far as I pushes the same way
   (I moves towards 0, never across it: the other terms' share is not I's)::

       I ← I − x·min(1, dt/T_t)   if x·I > 0,      T_t = √(T_i·T_d), T_i = Kp/Ki, T_d = Kd/Kp  (T_i if Kd = 0)

   then |I| <= min(``integrator_limit_n``, limit_n + |u_other|): I alone never needs more than the force
   clamp gives plus what the other terms take away (with |I| <= limit_n alone, a term opposing the needed
   force left a steady error: −9 N needed with +3 N of feed-forward took I = −12 N, 198 µm short at 10 N).
   Step 2 alone let I integrate on every cycle clamped *against* the error: with another term (an
   observer's estimate in an unstable loop) swinging across the clamp, I spiked to 31-38 N against a 10 N
   clamp (``tests/control/test_integrator_windup.py``). Slowed gains (Kp/s², Ki/s³, Kd/s) give s·T_t.

The integral is stored as a force [N] (I = Ki·∫e), so gains can change without a jump in I.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from stagectl.errors import short
from stagectl.schema import param


@dataclass(frozen=True)
class PidConfig:
    """PID gains in physical units (no period-dependent discrete gains).

    Defaults: ``design.design_pid(2 kg, 20 Hz, 1 ms, one sample of I/O delay)`` for the seed stage
    (crossover 20 Hz, phase margin 49°, gain margin 14.6 dB).
    """

    kp_n_m: float = param(9.85e3, unit="N/m", desc="proportional gain Kp", ge=0.0)
    ki_n_m_s: float = param(1.24e5, unit="N/(m*s)", desc="integral gain Ki", ge=0.0)
    kd_n_s_m: float = param(235.0, unit="N*s/m", desc="derivative gain Kd", ge=0.0)
    derivative_cutoff_hz: float = param(100.0, unit="Hz", desc="derivative low-pass cut-off fc", gt=0.0)
    derivative_on: str = param("measurement", desc="differentiate the measurement (with v_ref) or the error",
                               choices=("measurement", "error"))
    max_force_n: float = param(math.inf, unit="N", desc="clamp of the PID term alone (inf: none)", gt=0.0,
                               allow_inf=True)
    integrator_limit_n: float = param(math.inf, unit="N", desc="clamp of the integral term (inf: none)", gt=0.0,
                                      allow_inf=True)


@dataclass
class PidState:
    """Mutable state and diagnostics (forces in N)."""

    p_n: float = 0.0
    i_n: float = 0.0
    d_n: float = 0.0
    u_pid_n: float = 0.0
    u_n: float = 0.0
    error_m: float = 0.0
    deriv_m_s: float = 0.0  # filtered error derivative ė_f [m/s]
    last_meas_m: float = math.nan
    last_error_m: float = math.nan
    saturated: int = 0  # +1 / -1 when the total output was clamped, else 0
    integrating: bool = True  # False while anti-windup held the integrator this step
    recovering: int = 0  # sgn(e) at the last clamp while the error it left is a transient (no integration), else 0
    recovery_s: float = 0.0  # time since the last clamp while recovering [s]
    recovery_closed: bool = False  # the error has closed faster than T_i since the last clamp
    recovery_spent: int = 0  # sgn(e) of a recovery that ran out (T_i, slow closing): its clamps hold no more, else 0
    enabled: bool = True


_INF = math.inf


def check_dt(dt: float) -> None:
    """Raise ``ValueError`` unless ``dt`` > 0 and finite."""
    if not (dt > 0.0 and math.isfinite(dt)):
        raise ValueError(f"dt must be > 0 and finite (got {short(dt)} s)")


class Pid:
    """Discrete PID (see module docstring). ``step`` is real-time safe (floats only)."""

    def __init__(self, cfg: PidConfig):
        self.cfg = cfg
        self.state = PidState()
        self._dt = math.nan
        self._beta = 0.0
        #: set by the caller before ``step``: True holds the integral term this step (reported as not integrating)
        self.hold_integrator = False

    def _coeffs(self, dt: float) -> None:
        if dt != self._dt:
            self._dt = dt
            self._beta = math.exp(-2.0 * math.pi * self.cfg.derivative_cutoff_hz * dt)

    def reset(self) -> None:
        """Zero the integrator and derivative filter (enabled state is kept)."""
        en = self.state.enabled
        self.state = PidState(enabled=en)

    def disable(self) -> None:
        """Output 0 and reset the integrator (LinuxCNC ``enable = 0``)."""
        self.reset()
        self.state.enabled = False

    def enable(self, u_pid_now_n: float = 0.0, error_m: float = 0.0) -> None:
        """Bumpless enable: preload I so that the first output equals ``u_pid_now_n`` at ``error_m``."""
        self.state.enabled = True
        self.preload(u_pid_now_n, error_m)

    def preload(self, u_pid_target_n: float, error_m: float | None = None) -> None:
        """Set I so that P + I + D (with the current derivative) equals ``u_pid_target_n``."""
        st = self.state
        e = st.error_m if error_m is None else error_m
        st.i_n = u_pid_target_n - self.cfg.kp_n_m * e - self.cfg.kd_n_s_m * st.deriv_m_s
        lim = self.cfg.integrator_limit_n
        st.i_n = max(-lim, min(lim, st.i_n))
        st.u_pid_n = u_pid_target_n

    def retune(self, cfg: PidConfig) -> None:
        """New gains, bumpless: the PID term keeps its last value (I absorbs the gain change)."""
        u_prev = self.state.u_pid_n
        self.cfg = cfg
        self._dt = math.nan
        if self.state.enabled:
            self.preload(u_prev)

    def tracking_time_s(self) -> float:
        """Back-calculation time constant T_t [s] = √(T_i·T_d) (T_i = Kp/Ki, T_d = Kd/Kp), T_i without a D term
        (Åström & Hägglund); gains scaled for a slowed loop (Kp/s², Ki/s³, Kd/s) give s·T_t."""
        c = self.cfg
        if c.ki_n_m_s <= 0.0 or c.kp_n_m <= 0.0:
            return self._dt if self._dt == self._dt else 1e-3
        ti = c.kp_n_m / c.ki_n_m_s
        return math.sqrt(ti * c.kd_n_s_m / c.kp_n_m) if c.kd_n_s_m > 0.0 else ti

    def step(self, dt: float, x_ref_m: float, x_meas_m: float, v_ref_m_s: float = 0.0,
             u_other_n: float = 0.0, limit_n: float = math.inf) -> float:
        """One step; returns the total force clamp(u_pid + u_other, ±limit_n) [N]."""
        if not (dt > 0.0 and dt < _INF):
            check_dt(dt)
        if dt != self._dt:
            self._coeffs(dt)
        c = self.cfg
        st = self.state
        e = x_ref_m - x_meas_m
        if not st.enabled:
            st.error_m = e
            st.last_meas_m = x_meas_m
            st.last_error_m = e
            st.p_n = st.i_n = st.d_n = st.u_pid_n = 0.0
            u = max(-limit_n, min(limit_n, u_other_n))
            st.u_n = u
            return u
        # derivative input
        if c.derivative_on == "measurement":
            lm = st.last_meas_m
            de = 0.0 if lm != lm else v_ref_m_s - (x_meas_m - lm) / dt
        else:
            le = st.last_error_m
            de = 0.0 if le != le else (e - le) / dt
        b = self._beta
        deriv = b * st.deriv_m_s + (1.0 - b) * de
        st.deriv_m_s = deriv
        p = c.kp_n_m * e
        d = c.kd_n_s_m * deriv
        lim = limit_n  # (= min(limit_n, inf))
        mf = c.max_force_n
        hold = self.hold_integrator
        i_n = st.i_n
        # conditional integration (anti-windup)
        u_star = p + i_n + d + u_other_n
        pid_sat = abs(p + i_n + d) > mf
        sat_dir = (abs(u_star) > lim or pid_sat) and (u_star > 0.0) == (e > 0.0) and e != 0.0
        rec = st.recovering
        if rec:
            # recovery from a clamp: the error the clamp left (a lag the stage catches up, an excess it brakes
            # off) is a transient for P and D; integrating it left I standing past the reference (e = −I/K_p).
            # I waits while the error keeps its sign, for at most T_i = Kp/Ki after the clamp, and once the
            # error has closed faster than T_i (|ė_f|·T_i > |e|, e·ė_f < 0) until that closing slows: the rest
            # (a load P alone cannot hold) is integrated
            st.recovery_s += dt
            fast = abs(deriv) * c.kp_n_m > abs(e) * c.ki_n_m_s and e * deriv < 0.0
            if e * rec > 0.0 and st.recovery_s * c.ki_n_m_s < c.kp_n_m and (fast or not st.recovery_closed):
                sat_dir = True
                if fast:
                    st.recovery_closed = True
            else:
                if e * rec > 0.0:  # ran out (T_i, or the closing slowed) with the error's sign kept: spent
                    st.recovery_spent = rec
                    st.recovery_s = 0.0
                st.recovering = rec = 0
        elif st.recovery_spent:
            # a spent recovery: clamps of its sign arm no new hold until the error changes sign or T_i passes
            # without a clamp (a load near the clamp re-clamped every few cycles, re-arming the hold for good: I
            # stayed frozen and the stage sat e = F/K_p off target)
            st.recovery_s += dt
            if e * st.recovery_spent <= 0.0 or st.recovery_s * c.ki_n_m_s >= c.kp_n_m:
                st.recovery_spent = 0
        if sat_dir or hold:
            st.integrating = False
        else:
            st.integrating = True
            i_n += c.ki_n_m_s * e * dt
            il = c.integrator_limit_n
            if i_n > il:
                i_n = il
            elif i_n < -il:
                i_n = -il
        u_pid = p + i_n + d
        if u_pid > mf:
            u_pid = mf
        elif u_pid < -mf:
            u_pid = -mf
        u = u_pid + u_other_n
        if u > lim:
            u = lim
            sat = 1
        elif u < -lim:
            u = -lim
            sat = -1
        else:
            sat = 0
        st.saturated = sat
        if (sat or u_pid != p + i_n + d) and e != 0.0 and c.ki_n_m_s > 0.0:
            sg = 1 if e > 0.0 else -1
            if sg == st.recovery_spent:
                st.recovery_s = 0.0  # (time since the last clamp)
            elif sg == rec:
                # the same recovery clamped again: its T_i counts the unclamped time since its first clamp
                st.recovery_s -= dt
                st.recovery_closed = False
            else:
                st.recovering = sg
                st.recovery_s = 0.0
                st.recovery_closed = False
                st.recovery_spent = 0
        if (sat or u_pid != p + i_n + d) and c.ki_n_m_s > 0.0 and not hold:
            # back-calculation (next step's I): the part of the command the clamps cut off leaves I at 1/T_t,
            # as far as I pushes that way (I is unwound towards 0, never driven across it by the other terms)
            excess = p + i_n + d + u_other_n - u
            if excess * i_n > 0.0:
                back = excess * min(1.0, dt / self.tracking_time_s())
                i_n = max(0.0, i_n - back) if i_n > 0.0 else min(0.0, i_n - back)
        # I alone never needs more than the force clamp gives plus what the other terms take away (a term that
        # opposes the needed force: the clamp alone left a steady error, tests/control/test_integrator_windup.py)
        ib = lim + abs(u_other_n)
        il = c.integrator_limit_n
        if not ib < il:  # ib = min(il, ib) (the value min() returns, nan included)
            ib = il
        if i_n > ib:
            i_n = ib
        elif i_n < -ib:
            i_n = -ib
        st.i_n = i_n
        st.p_n, st.d_n, st.u_pid_n, st.u_n, st.error_m = p, d, u_pid, u, e
        st.last_meas_m = x_meas_m
        st.last_error_m = e
        return u
