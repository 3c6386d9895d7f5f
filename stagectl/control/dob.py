"""Disturbance observers (DOB): Q-filter form and steady-state Kalman form.

Plant and nominal model (docs/friction-models.md §6.1)::

    m·ẍ = u − F_f − d               lumped disturbance  τ = u − m_n·ẍ  = F_f + d + (m − m_n)·ẍ
    u   = u_c + d̂                   the estimate is fed back (added to the command)

**Residual form (§6.2).** The observer input ``u_obs`` must be the applied command *minus the friction
model feed-forward* u_ff (the model is part of the nominal plant); then d̂ = Q·(τ − F̂) and the closed loop
sees only (1 − Q)(F_f − F̂). Feeding the full u double-compensates. The controller does this; the observer
only sees ``u_obs``. The inertia feed-forward m·a_ref is *not* subtracted (it really accelerates the mass).

Q-filter form (``kind: qfilter``), Q = g/(s+g), g = 2π·``bandwidth_hz``, velocity-based (§6.1) and
discretised with α = exp(−g·dt)::

    w_{k+1} = α·w_k + (1 − α)·(ū_k + K_v·v̂_k),       d̂_k = w_k − K_v·v̂_k
    K_v = m_n·(1 − α)/dt   (→ m_n·g as dt → 0),       ū_k = (u_obs,k + u_obs,k−1)/2

with v̂ the backward-difference velocity estimate [m/s] from the controller and dt the measured sample
interval (when dt changes, w is re-based by ΔK_v·v̂ so that d̂ is continuous). The two discrete choices make
the estimate exact for a rigid mass under a zero-order-hold force (d̂ = LPF(τ), no bias): with §6.1's
literal K_v = m_n·g and ū = u_obs the estimate is biased by −m_n·a·g·dt/2 under a constant acceleration a
(1.6 % of m·a at 50 Hz and 10 kHz).

**Irregular sampling** (a PC without a real-time kernel: late wake-ups, skipped slots, stale samples). Given the
loop period T (``period_s``, from :func:`make_dob`), every sample is one step of the filter designed for T —
α_T, K_v,T, whatever the measured interval dt — and v̂ is the measured Δx/dt. The observer's response to
the encoder's noise n is a second difference, −K_v·(v̂_k − v̂_{k−1}) with v̂ ∋ (n_k − n_{k−1})/dt_k: it leaves
no net force impulse only while K_v is the same at consecutive steps. With α, K_v following dt, each sample's
noise left one — a low-frequency force noise the stage integrates: the 10 µm cosine's error RMS with a
U(0, 0.2T) wake-up jitter alone was 1.39× the clean run's, with a slot skipped at 10 % of the wake-ups 2.4×
(``stagectl bench timing``, plant_io, seed 1); with T's coefficients 1.14× and 1.6×. (The exact form for
unequal intervals — the ramp-weighted impulses over the mid-to-mid span (dt_k + dt_{k−1})/2 — is worse still,
5.4× on the jitter: its weights vary more.) What T's coefficients get wrong is the signal's part: over the
span h = (dt_k + dt_{k−1})/2 the net force m·a changes v̂ by a·h, the filter expects a·T; that part is taken
off with the reference's acceleration a_r (the stage follows it)::

    w_{k+1} += K_v,T·a_r·(h − f·T)          (only when dt_k or dt_{k−1} ≠ T, or h̄ ≠ T; f below, 1 at T)

On time (dt = T at every step) the filter is the one above, to the bit. A loop slowed down to s·T
(``StageController.set_timing_scale``) gives the observer ``period_s`` = P = s·T, and its bandwidth g/s: a retune
designs α_P, K_v,P at once, whatever the last interval was (before, it kept the old period's until an interval
differed from the last one: a slowed-down observer on on-time samples ran with T's, with P's after any late one).
But the loop's level lags its samples (it steps down only when its mean interval falls 10 % below it): a loop at
s = 3 may sample at T for a while, and a P-step per sample then runs the filter 3× faster than designed with K_v
a third of the one the samples need (an effective mass m_n/3; the stuck-stage limit of the controller could not
hold the estimate, tests/control/test_stuck_dob.py). So, with h̄ the mean span (h̄ += 0.1·(h − h̄) per sample;
h̄ = P on time), a sample takes the part f of a step::

    f = h̄/P if h̄ < 0.75·P else 1,    1 − a = (1 − α_P)·f,    K_v = K_v,P

exact for a rigid mass at h = h̄ (K_v·Δv̂ = (1 − a)·m·Δv̂/h); K_v stays P's (no noise impulse). Below 0.75·P the
loop's level is lagging (it keeps a level while its mean interval is >= 0.9 of it); above, as for the loop at T,
one step per sample. f = min(1, h̄/P) also in the loop's own range cost the plant_io cosine 2–10 % (seeds 2–6,
``stagectl bench timing --stages plant_io --seed N``; in quiet stretches h̄ dips below T); f = h/P per sample
(K_v kept, the decay following each span) tracked the 10 µm cosine with 50 % of the slots skipped (s = 1.5) at
7.3× the clean run against 4.4× (seeds 1–6 mean).
``step_fraction`` holds f for the filters matched to the observer (``StageController._dob_decay``).

Kalman form (``kind: kalman``), augmented state s = [x, v, τ] (m, m/s, N)::

    ẋ = v,  v̇ = (u_obs − τ)/m_n,  τ̇ = w  (random walk)       measurement z = x_meas + noise

ZOH-discretised (A, B), steady-state *filter-form* gain K designed once at construction
(``design.kalman_gain``: the a-priori DARE solution with scipy; ``stagectl tune`` cross-checks it with
python-control's ``dlqe``, whose predictor gain L = A·K must not be used in filter form). Per step (pure Python, ~1 µs)::

    s⁻ = A·s⁺ + B·u_obs,k−1,        s⁺ = s⁻ + K·(z_k − x⁻),        d̂_k = τ⁺

If the disturbance noise is not given, it is chosen so that the observer's error poles have a geometric
mean |s| of 2π·``bandwidth_hz`` (a 3rd-order Butterworth-like observer has all poles at that radius).

``command_delay_samples`` delays u_obs by that many extra samples to match an I/O delay of the actuator path.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

from stagectl.control.design import kalman_gain
from stagectl.control.pid import check_dt
from stagectl.schema import param


@dataclass(frozen=True)
class DobConfig:
    """Disturbance observer settings (YAML ``controller.dob``).

    Defaults (Q-filter, 100 Hz, command delay 1) with the default PID on the seed stage at 1 kHz with one
    cycle of I/O delay: phase margin 42°, gain margin 8.9 dB (``stagectl tune``); 60° / 12 dB without the
    I/O delay.
    """

    kind: str = param("qfilter", desc="observer form", choices=("none", "qfilter", "kalman"))
    bandwidth_hz: float = param(100.0, unit="Hz", desc="observer bandwidth g/2π", gt=0.0)
    nominal_mass_kg: float | None = param(None, unit="kg", desc="nominal mass m_n (None: controller mass_kg)",
                                          gt=0.0)
    command_delay_samples: int = param(1, unit="samples", desc="delay of the observer's command input (match "
                                       "the actuator path's I/O delay in periods)", ge=0, le=8)
    max_estimate_n: float = param(math.inf, unit="N", desc="clamp of the estimate d̂ (inf: none)", gt=0.0,
                                  allow_inf=True)
    measurement_noise_m: float = param(1e-9, unit="m", desc="kalman: position noise std (incl. quantisation)",
                                       gt=0.0)
    disturbance_noise_n_sqrt_s: float | None = param(
        None, unit="N/sqrt(s)", desc="kalman: disturbance random-walk intensity (None: from bandwidth_hz)", gt=0.0)


@dataclass
class DobState:
    """Diagnostics: estimate d̂ [N], filter state, Kalman estimates."""

    d_hat_n: float = 0.0
    w_n: float = 0.0  # Q-filter state
    x_hat_m: float = math.nan  # Kalman position estimate
    v_hat_m_s: float = 0.0  # Kalman velocity estimate (or last v̂ input for the Q-filter)
    tau_hat_n: float = 0.0
    u_obs_n: float = 0.0  # last command input (residual form)


#: gain of the mean span h̄ += c·(h − h̄) per sample (QFilterDob, "Irregular sampling")
H_MEAN_GAIN = 0.1
#: below this fraction of the period P the mean span h̄ is a loop level lagging its samples: a sample takes the part
#: h̄/P of a step (above it, one step: the loop keeps its level while its mean interval is >= 0.9 of it)
H_MEAN_LAG = 0.75


class QFilterDob:
    """Velocity-based Q-filter DOB (see module docstring). ``step`` is real-time safe."""

    def __init__(self, cfg: DobConfig, mass_kg: float, period_s: float | None = None):
        self.cfg = cfg
        self.mass_kg = mass_kg if cfg.nominal_mass_kg is None else cfg.nominal_mass_kg
        self.state = DobState()
        #: the loop period T [s]: every sample is then stepped with T's coefficients (module docstring,
        #: "Irregular sampling"); None: with its own interval's
        self.period_s = period_s
        self._dt = math.nan
        self._dt_last = 1e-3
        self._c_dt = math.nan  # the interval α and K_v were computed for [s]
        self._dt_meas = math.nan  # the previous step's measured interval [s]
        self._alpha = 0.0
        self._kv = 0.0
        self._h_mean = math.nan if period_s is None else period_s  # the mean span h̄ [s]
        #: the part f of one step of P's filter the last sample took: its decay was 1 − (1 − α_P)·f (1 on time
        #: and for a span h >= P; h/P for a shorter one: module docstring, "Irregular sampling")
        self.step_fraction = 1.0
        self._g = 2.0 * math.pi * cfg.bandwidth_hz
        self._delay: deque[float] = deque([0.0] * cfg.command_delay_samples)
        self._have_prev = False
        self._u_last = 0.0

    def _coeffs(self, dt: float) -> None:
        self._dt = self._dt_last = self._c_dt = dt
        self._alpha = math.exp(-self._g * dt)
        self._kv = self.mass_kg * (1.0 - self._alpha) / dt

    def reset(self, x_m: float = 0.0, d_hat_n: float = 0.0) -> None:
        """Estimate ``d_hat_n`` [N] at ``x_m`` [m], no history. The mean span h̄ is kept: like the loop's timing
        scale (which a reset keeps), it describes the sampling, not the estimate (a slowed-down loop that samples
        faster after a reset still takes partial steps at once)."""
        self.state = DobState(d_hat_n=d_hat_n, w_n=d_hat_n, x_hat_m=x_m)
        self._delay = deque([0.0] * self.cfg.command_delay_samples)
        self._have_prev = False
        self._u_last = 0.0
        self._dt_meas = math.nan
        self.step_fraction = 1.0

    def retune(self, cfg: DobConfig, mass_kg: float) -> None:
        """New bandwidth/mass, bumpless: w is re-set so that d̂ keeps its value."""
        st = self.state
        self.cfg = cfg
        self.mass_kg = mass_kg if cfg.nominal_mass_kg is None else cfg.nominal_mass_kg
        self._g = 2.0 * math.pi * cfg.bandwidth_hz
        self._dt = math.nan
        # (with a period set, its coefficients, whatever the last interval was: a retune after ``period_s``
        # changed, set_timing_scale, must not keep the old period's until an interval differs from the last one)
        self._coeffs(self._dt_last if self.period_s is None else self.period_s)
        st.w_n = st.d_hat_n + self._kv * st.v_hat_m_s
        old = list(self._delay)
        n = cfg.command_delay_samples
        self._delay = deque((old + [st.u_obs_n] * n)[:n] if n else [])

    def shift(self, delta_n: float) -> None:
        """Move the estimate and the command history by ``delta_n`` [N] (bumpless feed-forward change).

        The observer input is u_obs = u − u_ff; when the friction feed-forward drops by Δ, the same command
        gives u_obs + Δ and the residual the observer must carry grows by Δ: d̂, w, the held input and the
        delayed inputs all move by Δ, so the estimate is already at its new steady state (no transient).
        """
        st = self.state
        st.d_hat_n += delta_n
        st.w_n += delta_n
        st.u_obs_n += delta_n
        self._u_last += delta_n
        if self._delay:  # (an empty history stays as it is)
            self._delay = deque(u + delta_n for u in self._delay)

    def step(self, dt: float, x_meas_m: float, v_hat_m_s: float, u_obs_prev_n: float,
             a_ref_m_s2: float = 0.0) -> float:
        """Advance with the previous step's observer input ``u_obs_prev_n`` [N]; return d̂_k [N].

        ``u_obs_prev_n`` is the command applied after the previous step minus that step's friction
        feed-forward. ``v_hat_m_s`` is the velocity estimate at this step (Δx/dt over the measured interval
        ``dt`` [s]). With ``period_s`` P set, a step whose interval is not P (a late wake-up, a skipped slot, a
        step after stale samples) keeps P's coefficients (all of a step, or the part f = h̄/P of one while h̄ < 0.75·P), and the velocity
        change the reference's acceleration ``a_ref_m_s2`` [m/s²] makes in the span beyond f·P is taken off
        (module docstring, "Irregular sampling").
        """
        if not (dt > 0.0 and dt < math.inf):
            check_dt(dt)
        st = self.state
        t_nom = self.period_s
        dt_meas_prev = self._dt_meas
        self._dt_meas = dt
        if dt != self._dt or (t_nom is not None and self._c_dt != t_nom):
            kv_old = self._kv
            if t_nom is None:
                self._coeffs(dt)
            else:  # every sample one step of the filter designed for P (or the part h/P of one: below)
                if self._c_dt != t_nom:
                    self._coeffs(t_nom)
                self._dt = dt
            if self._have_prev:  # new coefficients (a new interval, a retune): re-base w so that the estimate
                st.w_n += (self._kv - kv_old) * st.v_hat_m_s  # d̂ = w − K_v·v̂ does not jump with K_v
        u_in = u_obs_prev_n
        if self._delay:
            self._delay.append(u_obs_prev_n)
            u_in = self._delay.popleft()
        kv = self._kv
        if self._have_prev:
            a = self._alpha
            f = 1.0  # the part of one step of P's filter this sample takes
            excess = 0.0  # the span beyond f·P [s]
            if t_nom is not None and (dt != t_nom or dt_meas_prev != t_nom or self._h_mean != t_nom):
                # the mid-to-mid span h = (dt_k + dt_{k−1})/2 the velocity change accrued over, not P
                h = 0.5 * (dt + (t_nom if math.isnan(dt_meas_prev) else dt_meas_prev))
                hm = self._h_mean if self._h_mean == self._h_mean else t_nom  # (period_s set after construction)
                hm = hm + H_MEAN_GAIN * (h - hm)
                if abs(hm - t_nom) <= 1e-9 * t_nom:
                    hm = t_nom
                self._h_mean = hm
                if hm < H_MEAN_LAG * t_nom:  # the part f = h̄/P of a step: 1 − a = (1 − α_P)·f
                    f = hm / t_nom
                    a = 1.0 - (1.0 - a) * f
                excess = h - f * t_nom
            self.step_fraction = f
            st.w_n = a * st.w_n + (1.0 - a) * (0.5 * (u_in + self._u_last) + kv * st.v_hat_m_s)
            if excess != 0.0 and a_ref_m_s2 != 0.0:
                st.w_n += kv * a_ref_m_s2 * excess
        else:
            st.w_n = st.d_hat_n + kv * v_hat_m_s
            self._have_prev = True
        self._u_last = u_in
        d = st.w_n - kv * v_hat_m_s
        lim = self.cfg.max_estimate_n
        if not d < lim:  # d = max(−lim, min(lim, d)), nan included (→ lim), without the two calls
            d = lim
        if not d > -lim:
            d = -lim
        st.v_hat_m_s = v_hat_m_s
        st.u_obs_n = u_obs_prev_n
        st.x_hat_m = x_meas_m
        st.d_hat_n = st.tau_hat_n = d
        return d


class KalmanDob:
    """Steady-state Kalman DOB on [x, v, τ] (see module docstring). ``step`` is real-time safe.

    The gain is designed for ``period_s`` at construction (:func:`stagectl.control.design.kalman_gain`,
    scipy imported lazily). A step's ``dt`` (the loop's measured sample interval) is rounded to a tenth of
    ``period_s``; a rounded interval not seen before is designed once (not real-time safe: the first
    skipped cycle of each length costs a design) and cached, so sampling jitter never redesigns.
    """

    def __init__(self, cfg: DobConfig, mass_kg: float, period_s: float):
        check_dt(period_s)
        self.cfg = cfg
        self.mass_kg = mass_kg if cfg.nominal_mass_kg is None else cfg.nominal_mass_kg
        self.state = DobState()
        self._delay: deque[float] = deque([0.0] * cfg.command_delay_samples)
        self._period_s = period_s
        self._gains: dict[float, Any] = {}
        self._design(period_s)

    def _design(self, dt: float) -> None:
        m = self.mass_kg
        self._dt = dt
        K = self._gains.get(dt)
        if K is None:
            K = self._gains[dt] = kalman_gain(m, dt, self.cfg.bandwidth_hz, self.cfg.measurement_noise_m,
                                              self.cfg.disturbance_noise_n_sqrt_s)
        self.K = K
        # A = [[1, dt, -dt²/2m], [0, 1, -dt/m], [0, 0, 1]],  B = [dt²/2m, dt/m, 0]
        self._a02 = -dt * dt / (2.0 * m)
        self._a12 = -dt / m
        self._b0 = dt * dt / (2.0 * m)
        self._b1 = dt / m

    def reset(self, x_m: float = 0.0, d_hat_n: float = 0.0) -> None:
        self.state = DobState(d_hat_n=d_hat_n, tau_hat_n=d_hat_n, x_hat_m=x_m)
        self._delay = deque([0.0] * self.cfg.command_delay_samples)

    def retune(self, cfg: DobConfig, mass_kg: float) -> None:
        """New gain (redesigned now); the state [x, v, τ] is kept, so d̂ does not jump."""
        self.cfg = cfg
        self.mass_kg = mass_kg if cfg.nominal_mass_kg is None else cfg.nominal_mass_kg
        self._gains = {}
        self._design(self._dt)
        n = cfg.command_delay_samples
        old = list(self._delay)
        self._delay = deque((old + [self.state.u_obs_n] * n)[:n] if n else [])

    def take_over(self, old: KalmanDob) -> None:
        """Continue from ``old``'s running estimate [x, v, τ] and command history (bumpless gain swap)."""
        self.state = old.state
        n = self.cfg.command_delay_samples
        hist = list(old._delay)
        self._delay = deque((hist + [old.state.u_obs_n] * n)[:n] if n else [])

    def shift(self, delta_n: float) -> None:
        """Move τ̂ and the command history by ``delta_n`` [N] (bumpless feed-forward change; see QFilterDob)."""
        st = self.state
        st.tau_hat_n += delta_n
        st.d_hat_n += delta_n
        st.u_obs_n += delta_n
        if self._delay:  # (an empty history stays as it is)
            self._delay = deque(u + delta_n for u in self._delay)

    def step(self, dt: float, x_meas_m: float, v_hat_m_s: float, u_obs_prev_n: float,
             a_ref_m_s2: float = 0.0) -> float:
        """Predict with the previous observer input, correct with ``x_meas_m``; return d̂ = τ⁺ [N].

        ``v_hat_m_s`` and ``a_ref_m_s2`` are unused (the filter estimates v itself, over the interval ``dt``);
        kept for a common signature.
        """
        check_dt(dt)
        q = self._period_s * max(1, round(10.0 * dt / self._period_s)) / 10.0
        if q != self._dt:
            self._design(q)
        dt = q
        st = self.state
        u_in = u_obs_prev_n
        if self._delay:
            self._delay.append(u_obs_prev_n)
            u_in = self._delay.popleft()
        x, v, tau = st.x_hat_m, st.v_hat_m_s, st.tau_hat_n
        if math.isnan(x):
            x = x_meas_m
        # predict
        xp = x + dt * v + self._a02 * tau + self._b0 * u_in
        vp = v + self._a12 * tau + self._b1 * u_in
        # correct
        r = x_meas_m - xp
        k0, k1, k2 = self.K
        st.x_hat_m = xp + k0 * r
        st.v_hat_m_s = vp + k1 * r
        tau = tau + k2 * r
        lim = self.cfg.max_estimate_n
        tau = max(-lim, min(lim, tau))
        st.tau_hat_n = st.d_hat_n = tau
        st.u_obs_n = u_obs_prev_n
        return tau


Dob = QFilterDob | KalmanDob


def make_dob(cfg: DobConfig, mass_kg: float, period_s: float) -> Dob | None:
    """Build the observer selected by ``cfg.kind`` (None for ``none``)."""
    if cfg.kind == "none":
        return None
    if cfg.kind == "qfilter":
        return QFilterDob(cfg, mass_kg, period_s)
    return KalmanDob(cfg, mass_kg, period_s)
