"""Settle move: the end of a move re-planned once from the stage's measured state (two degrees of freedom).

A move that ends with the stage still *behind* the reference in the move's direction (on the soft side of its
friction: the friction feed-forward was too low during the move, so the stage lags; docs/control.md §2.4–2.5) by
more than ``settle.move_min_m`` gets one short continuation. At the first sample at rest, with the error
e₀ = x_r − x [m] and ė₀ = −v̂ [m/s] (v̂: the velocity estimate), a quintic

    c(τ) = e₀ + ė₀·τ + c₃τ³ + c₄τ⁴ + c₅τ⁵,   0 <= τ <= T
    c₃ = −(10e₀ + 6ė₀T)/T³,   c₄ = (15e₀ + 8ė₀T)/T⁴,   c₅ = −(6e₀ + 3ė₀T)/T⁵

takes c(0) = e₀, ċ(0) = ė₀, c̈(0) = 0 to c(T) = ċ(T) = c̈(T) = 0. T = ``settle.move_s``, or with
``settle.move_force_n`` = F the longer of that and √(10/√3·m·|e₀|/F), so that the quintic's peak inertial force
m·|c̈| is at most F for ė₀ = 0 (the controller chooses T; ė₀ is not counted and can raise the peak: 1.2·F at
ė₀T = 0.3·e₀). For T the controller tracks

* feedback (PID) reference  x_r − c,  v_r − ċ   (starts at the stage's own position and speed: no P or D step,
  so the PID no longer pushes the stage through the break-away and the overshoot that followed),
* inertia feed-forward       m·(a_r − c̈(τ + τ_a))   (with the inertia term's look-ahead),

while the friction feed-forward holds the model where the move left it (the observer, whose input is the applied
force, supplies the sliding friction of the short continuation). The reference itself, and so the settle time
measured from the end of the commanded move, the in-position detector, the learning from moves and the adaptation,
is unchanged: the continuation is not part of the move. While it runs the controller's rest logic (rest spring,
rest synchronisation, integrator hold) waits; it takes over at τ = T.

From ahead (the controller's ``settle.ahead_stiffness_fraction``; :attr:`SettleMove.stiff`): the same quintic
from a stage that ended *ahead* (stiff side), with the friction spring's force along c added by the controller
(:mod:`stagectl.control.controller`, "Settle move from ahead"). :attr:`SettleMove.last_direction` is the
reference's direction at its last moving sample: a motion that reversed without a stop is not called ahead from
its first direction (a speed of at most ``V_DIRECTION_MIN_M_S`` gives no direction).

Pure, scalar, real-time safe.
"""

from __future__ import annotations

#: a reference speed at most this [m/s] gives no direction (:attr:`SettleMove.last_direction`): a ``stop`` from
#: constant speed sampled a rounding step before its end gave v = −4·10⁻²⁰ m/s, a = −10⁻¹⁵ m/s², which called
#: the motion reversed and left a stage 5 µm ahead without its continuation (300 ms creeping back)
V_DIRECTION_MIN_M_S = 1e-12


class SettleMove:
    """The continuation quintic and the move bookkeeping (see module docstring)."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """No move under way, no continuation."""
        self.moving = False  # the reference moved at the last sample
        self.direction = 0.0  # +1 / −1: the direction of the move under way (or the last one) at its start
        self.last_direction = 0.0  # +1 / −1: the reference's direction at its last sample in motion
        self.active = False  # a continuation is running
        self.stiff = False  # the continuation started from ahead (the controller adds the spring force)
        self.e0 = 0.0  # e₀ [m] of the continuation under way (or the last one)
        self.tau_s = 0.0
        self.duration_s = 0.0
        self._k = (0.0, 0.0, 0.0, 0.0, 0.0)

    def observe(self, v_r: float, a_r: float) -> bool:
        """Track the reference's motion; True at the first sample at rest after a motion (a move's end)."""
        if v_r == 0.0 and a_r == 0.0:
            ended = self.moving
            self.moving = False
            return ended
        if not self.moving:
            self.moving = True
            s = v_r if v_r != 0.0 else a_r
            self.direction = 1.0 if s > 0.0 else -1.0
            self.last_direction = self.direction
        if abs(v_r) > V_DIRECTION_MIN_M_S:  # (not the rounding residue of a jerk-limited stop's last sample)
            self.last_direction = 1.0 if v_r > 0.0 else -1.0
        return False

    def start(self, e0_m: float, v0_m_s: float, duration_s: float) -> None:
        """Plan c from (e0_m, v0_m_s, 0) to rest at 0 over ``duration_s`` [s] (> 0)."""
        T = duration_s
        self.duration_s = T
        self.e0 = e0_m
        self.stiff = False
        self.tau_s = 0.0
        self.active = True
        self._k = (e0_m, v0_m_s, -(10.0 * e0_m + 6.0 * v0_m_s * T) / T**3,
                   (15.0 * e0_m + 8.0 * v0_m_s * T) / T**4, -(6.0 * e0_m + 3.0 * v0_m_s * T) / T**5)

    def sample(self, tau_s: float) -> tuple[float, float, float]:
        """(c [m], ċ [m/s], c̈ [m/s²]) at ``tau_s`` after the start; zero from T on."""
        if tau_s >= self.duration_s:
            return 0.0, 0.0, 0.0
        k0, k1, k3, k4, k5 = self._k
        t = tau_s
        c = k0 + t * (k1 + t * t * (k3 + t * (k4 + t * k5)))
        cd = k1 + t * t * (3.0 * k3 + t * (4.0 * k4 + t * 5.0 * k5))
        cdd = t * (6.0 * k3 + t * (12.0 * k4 + t * 20.0 * k5))
        return c, cd, cdd


def reversal_force(travel_m: float, stiffness_scale: float, elements: tuple[tuple[float, float], ...]) -> float:
    """The friction's force change along a reversal of ``travel_m`` [m] (signed; the result has its sign) [N], by
    Masing's rule for parallel elasto-slip elements (k_i [N/m], slip force W_i [N]) each starting at its slip limit
    on the other side::

        Δf(δ) = sgn(δ)·Σ min(s·k_i·|δ|, 2·W_i)        (s = ``stiffness_scale``; ``elements`` holds (k_i, 2·W_i))

    Linear (s·Σk·δ) up to the first element's slip, |δ| <= min 2·W_i/(s·k_i); at most 2·ΣW_i, the whole swing of
    the friction from one slip limit to the other, however far the travel. Pure, scalar, real-time safe."""
    d = abs(travel_m)
    f = 0.0
    for k, w2 in elements:
        f += min(stiffness_scale * k * d, w2)
    return f if travel_m >= 0.0 else -f


__all__ = ["SettleMove", "reversal_force"]
