"""Start-up / offline gain design and loop analysis (python-control, imported lazily inside functions).

Not real-time: call at start-up (before ``gc.freeze()``) or from ``stagectl tune``. Importing this module
is cheap; python-control is imported only by the functions that need it (``design_pid``, the loop
analysis, ``use_control=True``). The Kalman observer gain built by the controller at start-up uses
scipy's DARE solver only, so the loop process never imports python-control (docs/architecture.md §3).

PID rule ("loop shaping" for a rigid mass m [kg] with target crossover f_c [Hz], ω_c = 2π·f_c)::

    C(s) = Kd·s/(1 + s/ω_f) + Kp + Ki/s,   Kp = Kd·ω_c/3,   Ki = Kp·ω_c/10,   ω_f = 2π·min(5·f_c, 0.2/period_s)

i.e. the PD zero a factor 3 below crossover (≈ 70° of lead), the integral zero a decade below it, the
derivative filter 5× above; Kd is then scaled so that |L(e^{jω_c T})| = 1 exactly on the *discrete* loop
(ZOH plant, I/O delay, the PID as implemented). ``bandwidth_hz`` therefore is the open-loop crossover.
Seed stage (2 kg, 1 kHz, one sample of I/O delay) at 20 Hz: Kp ≈ 9.85e3 N/m, Ki ≈ 1.24e5 N/(m·s),
Kd ≈ 235 N·s/m, cut-off 100 Hz, phase margin ≈ 49°, gain margin ≈ 14.6 dB.

Loop analysis: discrete plant P(z) = ZOH{1/(m s² + c s)} at ``period_s`` times z^−n for n samples of
I/O delay, with the discrete PID exactly as implemented in :mod:`stagectl.control.pid` and, if given, the
Q-filter DOB of :mod:`stagectl.control.dob`. With the DOB, d̂ = H_u·u − H_y·y and the loop opened at the
plant input is ``L = P·(C + H_y)/(1 − H_u)``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from stagectl.control.pid import PidConfig

#: ratios of the PID rule: crossover / PD zero, crossover / integral zero, derivative filter / crossover
PD_RATIO = 3.0
INTEGRAL_RATIO = 10.0
DERIV_RATIO = 5.0


def design_pid(mass_kg: float, bandwidth_hz: float, period_s: float, delay_samples: int = 1,
               viscous_n_s_m: float = 0.0, **overrides: Any) -> PidConfig:
    """PID gains from mass and target crossover (rule in the module docstring; imports python-control)."""
    if not (mass_kg > 0 and bandwidth_hz > 0 and period_s > 0):
        raise ValueError("mass_kg, bandwidth_hz and period_s must be > 0")
    if bandwidth_hz >= 0.5 / period_s:
        raise ValueError(f"bandwidth_hz {bandwidth_hz:g} Hz must be below the Nyquist frequency {0.5 / period_s:g} Hz")
    wc = 2.0 * math.pi * bandwidth_hz
    cut = min(DERIV_RATIO * bandwidth_hz, 0.2 / period_s)
    unit = PidConfig(kp_n_m=wc / PD_RATIO, ki_n_m_s=wc / PD_RATIO * wc / INTEGRAL_RATIO, kd_n_s_m=1.0,
                     derivative_cutoff_hz=cut)
    L = plant_tf(mass_kg, period_s, delay_samples, viscous_n_s_m) * pid_tf(unit, period_s)
    k = 1.0 / abs(complex(L(np.exp(1j * wc * period_s))))
    kw: dict[str, Any] = dict(kp_n_m=unit.kp_n_m * k, ki_n_m_s=unit.ki_n_m_s * k, kd_n_s_m=k,
                              derivative_cutoff_hz=cut)
    kw.update(overrides)
    return PidConfig(**kw)


# ---------------------------------------------------------------------------------------------- Kalman


def _kalman_matrices(mass_kg: float, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    m = mass_kg
    A = np.array([[1.0, dt, -dt * dt / (2 * m)], [0.0, 1.0, -dt / m], [0.0, 0.0, 1.0]])
    B = np.array([[dt * dt / (2 * m)], [dt / m], [0.0]])
    C = np.array([[1.0, 0.0, 0.0]])
    return A, B, C


def kalman_gain_for_noise(mass_kg: float, dt: float, measurement_noise_m: float,
                          disturbance_noise_n_sqrt_s: float, *, use_control: bool = False
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Steady-state *filter-form* gain K (3,) and the a-priori covariance P (3, 3).

    Model of :mod:`stagectl.control.dob` (ZOH), process noise only on τ (variance q²·dt per step),
    measurement variance r². The a-priori P solves the filter DARE
    P = A·P·Aᵀ − A·P·Cᵀ(C·P·Cᵀ + R)⁻¹·C·P·Aᵀ + Q, and the filter-form gain for x⁺ = x⁻ + K(z − C·x⁻) is
    K = P·Cᵀ(C·P·Cᵀ + R)⁻¹.

    By default P comes from ``scipy.linalg.solve_discrete_are`` (light import, safe in the loop process:
    docs/architecture.md keeps python-control out of it). ``use_control=True`` uses ``control.dlqe`` instead (the
    tuning tool): dlqe returns the **predictor** gain L = A·P·Cᵀ(C·P·Cᵀ + R)⁻¹ for
    x[k+1] = A·x + B·u + L(y − C·x) together with the same a-priori P, so K is recomputed from P
    (docs/platform.md §6: plugging L into the filter form diverges).
    """
    A, _, C = _kalman_matrices(mass_kg, dt)
    Q = np.diag([0.0, 0.0, disturbance_noise_n_sqrt_s ** 2 * dt])
    R = np.array([[measurement_noise_m ** 2]])
    if use_control:
        import control

        _L, P, _E = control.dlqe(A, np.eye(3), C, Q, R)
        P = np.asarray(P)
    else:
        from scipy.linalg import solve_discrete_are

        P = solve_discrete_are(A.T, C.T, Q, R)
    S = float((C @ P @ C.T)[0, 0] + R[0, 0])
    K = (P @ C.T)[:, 0] / S
    return K, P


def observer_bandwidth_hz(K: np.ndarray, mass_kg: float, dt: float) -> float:
    """Geometric mean of |s_i|/2π of the filter error poles, s_i = ln(λ_i)/dt, λ_i = eig((I − K·C)·A)."""
    A, _, C = _kalman_matrices(mass_kg, dt)
    lam = np.linalg.eigvals((np.eye(3) - np.outer(K, C[0])) @ A)
    s = np.log(lam.astype(complex)) / dt
    return float(np.exp(np.mean(np.log(np.abs(s)))) / (2 * math.pi))


def kalman_noise_for_bandwidth(mass_kg: float, dt: float, bandwidth_hz: float, measurement_noise_m: float = 1e-9,
                               *, use_control: bool = False) -> float:
    """Disturbance noise intensity q [N/√s] giving :func:`observer_bandwidth_hz` = ``bandwidth_hz``.

    Continuous-time start: the steady-state filter of the chain τ -> v -> x is a 3rd-order Butterworth with
    radius ω = (q²/(m²·r²·dt))^(1/6), i.e. q = m·ω³·r·√dt; then Newton steps on log q (ω ∝ q^(1/3)) against
    the discrete poles (a few DARE solutions).
    """
    w = 2.0 * math.pi * bandwidth_hz
    log_q = math.log(mass_kg * w ** 3 * measurement_noise_m * math.sqrt(dt))
    for _ in range(12):
        K, _ = kalman_gain_for_noise(mass_kg, dt, measurement_noise_m, math.exp(log_q), use_control=use_control)
        err = math.log(bandwidth_hz / observer_bandwidth_hz(K, mass_kg, dt))
        if abs(err) < 1e-6:
            break
        log_q += 3.0 * err
    return math.exp(log_q)


def kalman_gain(mass_kg: float, dt: float, bandwidth_hz: float, measurement_noise_m: float = 1e-9,
                disturbance_noise_n_sqrt_s: float | None = None, *, use_control: bool = False
                ) -> tuple[float, float, float]:
    """Filter-form steady-state gain (k_x, k_v, k_τ) for the Kalman DOB.

    If ``disturbance_noise_n_sqrt_s`` is None it is chosen with :func:`kalman_noise_for_bandwidth`.
    """
    q = disturbance_noise_n_sqrt_s
    if q is None:
        q = kalman_noise_for_bandwidth(mass_kg, dt, bandwidth_hz, measurement_noise_m, use_control=use_control)
    K, _ = kalman_gain_for_noise(mass_kg, dt, measurement_noise_m, q, use_control=use_control)
    return float(K[0]), float(K[1]), float(K[2])


# ---------------------------------------------------------------------------------------------- analysis


@dataclass
class LoopAnalysis:
    """Margins of one loop (gain margin [dB], phase margin [deg], crossover frequencies [Hz])."""

    name: str
    gain_margin_db: float
    phase_margin_deg: float
    crossover_hz: float
    phase_crossover_hz: float
    stable: bool
    freq_hz: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    mag_db: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    phase_deg: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))

    def summary(self) -> dict[str, Any]:
        return {
            "gain_margin_db": self.gain_margin_db,
            "phase_margin_deg": self.phase_margin_deg,
            "crossover_hz": self.crossover_hz,
            "phase_crossover_hz": self.phase_crossover_hz,
            "closed_loop_stable": self.stable,
        }


def _zinv(dt: float, n: int = 1) -> Any:
    import control

    return control.tf([1.0], [1.0] + [0.0] * n, dt) if n else control.tf([1.0], [1.0], dt)


def pid_tf(pid: PidConfig, dt: float) -> Any:
    """Discrete PID of :mod:`stagectl.control.pid` (error -> force) as a transfer function in z."""
    import control

    b = math.exp(-2 * math.pi * pid.derivative_cutoff_hz * dt)
    z = control.tf([1.0, 0.0], [1.0], dt)
    integ = pid.ki_n_m_s * dt * z / (z - 1)
    deriv = pid.kd_n_s_m * (1 - b) / dt * (z - 1) / (z - b)
    return control.tf([pid.kp_n_m], [1.0], dt) + integ + deriv


def plant_tf(mass_kg: float, dt: float, delay_samples: int = 1, viscous_n_s_m: float = 0.0) -> Any:
    """ZOH-discretised rigid mass (with optional viscous damping) and ``delay_samples`` of I/O delay."""
    import control

    P = control.c2d(control.tf([1.0], [mass_kg, viscous_n_s_m, 0.0]), dt, "zoh")
    return P * _zinv(dt, delay_samples) if delay_samples else P


def qfilter_tfs(mass_kg: float, bandwidth_hz: float, dt: float, command_delay_samples: int = 0,
                velocity_cutoff_hz: float | None = None) -> tuple[Any, Any]:
    """(H_u, H_y) of the Q-filter DOB of :mod:`stagectl.control.dob`: d̂ = H_u·u − H_y·y.

    H_w = (1−α)z⁻¹/(1−αz⁻¹), K_v = m(1−α)/dt, ū = (1+z⁻¹)/2·z^−d·u, v̂ = F_v·(1−z⁻¹)/dt·y::

        H_u = H_w·(1+z⁻¹)/2·z^−d,        H_y = K_v·(1 − H_w)·F_v·(1−z⁻¹)/dt

    with the controller's velocity low-pass F_v = (1−β)/(1−βz⁻¹), β = exp(−2π·``velocity_cutoff_hz``·dt)
    (``controller.velocity_cutoff_hz``; F_v = 1 when None).
    """
    import control

    g = 2 * math.pi * bandwidth_hz
    a = math.exp(-g * dt)
    kv = mass_kg * (1 - a) / dt
    z = control.tf([1.0, 0.0], [1.0], dt)
    one = control.tf([1.0], [1.0], dt)
    Hw = (1 - a) / (z - a)  # (1-a) z^-1 / (1 - a z^-1)
    Hu = Hw * (z + 1) / (2 * z)
    if command_delay_samples:
        Hu = Hu * _zinv(dt, command_delay_samples)
    Hy = kv * (one - Hw) * (z - 1) / (z * dt)
    if velocity_cutoff_hz is not None:
        b = math.exp(-2 * math.pi * velocity_cutoff_hz * dt)
        Hy = Hy * (1 - b) * z / (z - b)
    return Hu, Hy


def kalman_tfs(mass_kg: float, dt: float, K: Any, command_delay_samples: int = 0) -> tuple[Any, Any]:
    """(H_u, H_y) of the steady-state Kalman DOB of :mod:`stagectl.control.dob`: d̂ = H_u·u − H_y·y.

    With F = (I − K·C)·A and G = (I − K·C)·B, the filter s⁺_k = F·s⁺_{k−1} + G·u_{k−1} + K·y_k gives
    (zI − F)·s⁺ = G·u + z·K·y, d̂ = e₃ᵀ·s⁺; so H_u = e₃ᵀ(zI − F)⁻¹G and
    −H_y = e₃ᵀ(zI − F)⁻¹·z·K = e₃ᵀ(zI − F)⁻¹·F·K + K₃.
    """
    import control

    A, B, C = _kalman_matrices(mass_kg, dt)
    Kv = np.asarray(K, dtype=float).reshape(3, 1)
    ImKC = np.eye(3) - Kv @ C
    F = ImKC @ A
    G = ImKC @ B
    e3 = np.array([[0.0, 0.0, 1.0]])
    Hu = control.ss(F, G, e3, np.zeros((1, 1)), dt)
    Hy = control.ss(F, -(F @ Kv), e3, -Kv[2:3, :], dt)
    if command_delay_samples:
        Hu = Hu * control.ss(_zinv(dt, command_delay_samples))
    return Hu, Hy


def analyse(name: str, L: Any, dt: float, n_points: int = 600) -> LoopAnalysis:
    """Margins, crossover and frequency response of an open loop L(z); closed-loop stability of 1/(1+L)."""
    import control

    f = np.logspace(-1, math.log10(0.5 / dt * 0.999), n_points)
    w = 2 * math.pi * f
    # one vectorised evaluation (python-control's per-point call retries its slycot import every time)
    resp = _freq_response(L, np.exp(1j * w * dt))
    mag = np.abs(resp)
    ph = np.unwrap(np.angle(resp))
    # margins from the dense response (robust against high-order numerics), checked against control.margin
    gm_db, pm_deg, wc_hz, wp_hz = _margins_from_response(f, mag, ph)
    # display convention: shift by whole turns so that the phase at the crossover lies in (-360°, 0°]
    ref = float(np.interp(wc_hz, f, ph)) if not math.isnan(wc_hz) else float(ph[0])
    ph = ph - 2 * math.pi * math.ceil(ref / (2 * math.pi))
    cl = control.feedback(L, 1)
    stable = bool(np.all(np.abs(control.poles(cl)) < 1.0))
    return LoopAnalysis(name, gm_db, pm_deg, wc_hz, wp_hz, stable, f, 20 * np.log10(mag), np.degrees(ph))


def _freq_response(L: Any, z: np.ndarray) -> np.ndarray:
    """L(z) at the points ``z`` (SISO). A state-space L is evaluated as C·(zI − A)⁻¹·B + D with one batched solve
    (python-control's own evaluation solves point by point: most of the time of a rest-gain search)."""
    import control

    if isinstance(L, control.StateSpace) and L.ninputs == 1 and L.noutputs == 1 and L.nstates > 0:
        A, B, C, D = (np.asarray(M, dtype=float) for M in (L.A, L.B, L.C, L.D))
        n = A.shape[0]
        M = z[:, None, None] * np.eye(n)[None, :, :] - A[None, :, :]
        X = np.linalg.solve(M, np.broadcast_to(B.astype(complex), (z.size, n, 1)))
        out: np.ndarray = (C @ X)[:, 0, 0] + D[0, 0]
        return out
    return np.asarray(L(z), dtype=complex).reshape(-1)


def _margins_from_response(f: np.ndarray, mag: np.ndarray, ph: np.ndarray) -> tuple[float, float, float, float]:
    pm, wc = math.inf, math.nan
    above = mag >= 1.0
    idx = np.nonzero(above[:-1] & ~above[1:])[0]
    if idx.size:
        i = int(idx[-1])
        t = (0.0 - math.log(mag[i])) / (math.log(mag[i + 1]) - math.log(mag[i]))
        wc = float(f[i] * (f[i + 1] / f[i]) ** t)
        p = ph[i] + t * (ph[i + 1] - ph[i])
        pm = float(math.degrees(p) + 180.0)
        pm = (pm + 180.0) % 360.0 - 180.0
    gm, wp = math.inf, math.nan
    # phase crossings of -180° (mod 360) above the gain crossover
    phd = np.degrees(ph)
    k = np.floor((phd + 180.0) / 360.0)
    cross = np.nonzero(np.diff(k) != 0)[0]
    for i in cross.tolist():
        if not math.isnan(wc) and f[i] < wc:
            continue
        gm_i = -20 * math.log10(max(mag[i], 1e-300))
        if gm_i < gm:
            gm, wp = float(gm_i), float(f[i])
    return gm, pm, wc, wp


def analyse_design(mass_kg: float, period_s: float, pid: PidConfig, delay_samples: int = 1,
                   dob_bandwidth_hz: float | None = None, dob_command_delay_samples: int = 0,
                   viscous_n_s_m: float = 0.0, dob_mass_kg: float | None = None,
                   dob_kind: str = "qfilter", kalman_k: Any = None,
                   velocity_cutoff_hz: float | None = None) -> list[LoopAnalysis]:
    """Margins of PID alone and (if ``dob_bandwidth_hz``) PID + DOB on the discrete plant.

    ``dob_kind`` ``qfilter`` (default) or ``kalman`` (then ``kalman_k``, the filter-form gain, is used, or
    designed for ``dob_bandwidth_hz``).
    """
    import control

    P = plant_tf(mass_kg, period_s, delay_samples, viscous_n_s_m)
    C = pid_tf(pid, period_s)
    out = [analyse("pid", control.ss(P) * control.ss(C), period_s)]
    if dob_bandwidth_hz:
        md = dob_mass_kg or mass_kg
        if dob_kind == "kalman":
            K = kalman_k if kalman_k is not None else kalman_gain(md, period_s, dob_bandwidth_hz)
            Hu, Hy = kalman_tfs(md, period_s, K, dob_command_delay_samples)
        else:
            Hu, Hy = qfilter_tfs(md, dob_bandwidth_hz, period_s, dob_command_delay_samples, velocity_cutoff_hz)
        out.append(analyse("pid+dob", dob_loop(P, C, Hu, Hy, period_s), period_s))
    return out


def analyse_rest(mass_kg: float, period_s: float, pid: PidConfig, delay_samples: int, dob_bandwidth_hz: float,
                 dob_command_delay_samples: int, stiffness_n_m: float, damping_n_s_m: float,
                 rest_spring_n_m: float, velocity_cutoff_hz: float | None = None, *,
                 dob_mass_kg: float | None = None, integrator_held: bool = True, kd_fraction: float = 1.0,
                 dob_bandwidth_fraction: float = 1.0, spring_sections: int = 1,
                 rest_integral_n_m_s: float = 0.0, free_spring_n_m: float | None = None) -> list[LoopAnalysis]:
    """Margins of the *rest* loop (:mod:`stagectl.control.controller`, "Rest spring"): PD (PID with its
    integrator held at rest, ``integrator_held``; False: the full PID, as a controller with
    ``hold_integrator_at_rest: false`` runs) + Q-filter DOB with nominal mass ``dob_mass_kg`` (None: the plant's
    ``mass_kg``; the controller's ``dob.nominal_mass_kg`` when it differs) + the rest spring
    C_s = k_v·(1−α)z/(z−α) (α = exp(−2π·bandwidth·T), the observer's low-pass; k_v = ``rest_spring_n_m`` =
    φ·min(θ, 1)·Σk of the controller's model, 0: off) on two plants of mass ``mass_kg`` [kg], both with the I/O delay.
    The controller's rest gains: K_d × ``kd_fraction`` (``rest_kd_fraction``), the observer at
    ``dob_bandwidth_hz`` × ``dob_bandwidth_fraction`` (``rest_dob_bandwidth_fraction``), and the spring's low-pass
    ``spring_sections`` (``rest_spring_section_count``) times, C_s = k_v·((1−α)z/(z−α))ⁿ (α at ``dob_bandwidth_hz``).
    The plants:

    * ``rest/stuck``: the stage stuck in pre-sliding, 1/(m·s² + c·s + k) (c = ``damping_n_s_m``, the friction's
      σ2 + Σσ1; k its initial stiffness Σk);
    * ``rest/free``: the free mass 1/(m·s²) (the stage slipping while the reference is at rest), with the spring
      ``free_spring_n_m`` (None: ``rest_spring_n_m``): the controller's spring until the stage is seen held,
      min(k_v, ``rest_spring_unconfirmed_kp_fraction``·K_p), which is all a free mass gets.

    The spring term enters the command like the PID's, and the residual-form observer does not see it (its input
    includes it), so L = P·(C_PD + C_s + H_y)/(1 − H_u).

    The rest integral (``controller.rest_integral_hz`` = f_r; K_r = ``rest_integral_n_m_s`` = 2π·f_r·Σk, its gain on
    the stiff side, the largest) moves the observer's estimate by K_r·e·T each period (``dob.shift``: the observer
    takes the force as applied and does not integrate it again), i.e. a term C_I = K_r·T·z/(z − 1) outside the
    observer's loop: L = P·(C_PD + C_s + H_y)/(1 − H_u) + P·C_I. Without an observer (``dob_bandwidth_hz`` <= 0:
    the controller then adds the rest integral's force to the PID's integrator, the same C_I) L = P·(C + C_I).
    """
    import control

    pid_r = dataclasses.replace(pid, kd_n_s_m=pid.kd_n_s_m * kd_fraction)
    observer = dob_bandwidth_hz > 0.0
    if not observer:  # C_I has the PID integrator's form: one integrator K_i + K_r (no double pole at z = 1)
        pid_r = dataclasses.replace(pid_r, ki_n_m_s=(0.0 if integrator_held else pid_r.ki_n_m_s) + rest_integral_n_m_s)
        integrator_held, rest_integral_n_m_s = False, 0.0
    C0 = pid_tf(dataclasses.replace(pid_r, ki_n_m_s=0.0) if integrator_held else pid_r, period_s)

    def with_spring(kv: float) -> Any:
        if kv <= 0.0:
            return C0
        a = math.exp(-2 * math.pi * dob_bandwidth_hz * period_s)
        z = control.tf([1.0, 0.0], [1.0], period_s)
        F = (1 - a) * z / (z - a)
        return C0 + kv * (F * F if spring_sections == 2 else F)

    C = with_spring(rest_spring_n_m)
    C_free = C if free_spring_n_m is None else with_spring(min(free_spring_n_m, rest_spring_n_m))
    md = dob_mass_kg if dob_mass_kg is not None else mass_kg
    if observer:
        Hu, Hy = qfilter_tfs(md, dob_bandwidth_hz * dob_bandwidth_fraction, period_s, dob_command_delay_samples,
                             velocity_cutoff_hz)
    stuck = control.c2d(control.tf([1.0], [mass_kg, damping_n_s_m, stiffness_n_m]), period_s, "zoh")
    if delay_samples:
        stuck = stuck * _zinv(period_s, delay_samples)
    free = plant_tf(mass_kg, period_s, delay_samples)
    def loop(P: Any, C: Any) -> Any:
        L = dob_loop(P, C, Hu, Hy, period_s) if observer else control.ss(P) * control.ss(C)
        if rest_integral_n_m_s > 0.0:
            z = control.tf([1.0, 0.0], [1.0], period_s)
            L = L + control.ss(P) * control.ss(rest_integral_n_m_s * period_s * z / (z - 1))
        return L

    return [analyse("rest/stuck", loop(stuck, C), period_s, 2000),
            analyse("rest/free", loop(free, C_free), period_s, 2000)]


def worst_over(summaries: list[dict[str, Any]]) -> tuple[int, dict[str, Any]]:
    """One loop's margins over a sweep (:meth:`LoopAnalysis.summary` per point, e.g. per feed-forward scale θ), worst
    case: the point with the lowest phase margin (an unstable one first), with the lowest gain margin of all points
    and ``closed_loop_stable`` only if every point is. Returns (that point's index, the summary)."""
    i = min(range(len(summaries)),
            key=lambda j: (summaries[j]["closed_loop_stable"], summaries[j]["phase_margin_deg"]))
    return i, {**summaries[i], "gain_margin_db": min(r["gain_margin_db"] for r in summaries),
               "closed_loop_stable": all(r["closed_loop_stable"] for r in summaries)}


#: the rest-loop gains :func:`design_rest_gains` searches: K_d's fraction at rest (tried largest first), the
#: observer's bandwidth fraction at rest, the rest spring's low-pass sections (``controller.rest_kd_fraction``,
#: ``rest_dob_bandwidth_fraction``, ``rest_spring_section_count``)
REST_KD_FRACTIONS = (1.0, 0.7, 0.5, 0.3, 0.2, 0.15, 0.1)
REST_DOB_BANDWIDTH_FRACTIONS = (1.0, 0.75, 0.6, 0.45, 0.35, 0.3, 0.25)
REST_SPRING_SECTIONS = (1, 2)


def design_rest_gains(mass_kg: float, period_s: float, pid: PidConfig, delay_samples: int, dob_bandwidth_hz: float,
                      dob_command_delay_samples: int, stiffness_n_m: float, damping_n_s_m: float,
                      rest_spring_n_m: float, velocity_cutoff_hz: float | None = None, *,
                      dob_mass_kg: float | None = None, integrator_held: bool = True,
                      thetas: tuple[float, ...] | list[float] = (1.0,), free_spring_cap_n_m: float | None = None,
                      rest_integral_n_m_s: float = 0.0, min_phase_margin_deg: float = 40.0,
                      min_gain_margin_db: float = 8.0) -> dict[str, Any]:
    """The rest loop's gains (K_d × κ_d, observer bandwidth × κ_g, n spring sections) for the moving loop ``pid`` +
    Q-filter observer (``dob_bandwidth_hz``, command delay ``dob_command_delay_samples``) on a stage of mass
    ``mass_kg`` [kg] with ``delay_samples`` periods of I/O delay, stuck on the pre-sliding stiffness
    ``stiffness_n_m`` [N/m] and damping ``damping_n_s_m`` [N s/m] or free, with the rest spring k_v =
    ``rest_spring_n_m`` [N/m] (× θ for each θ of ``thetas``: the spring follows the feed-forward's scale; the free
    mass gets min(θ·k_v, ``free_spring_cap_n_m``), None: θ·k_v, the controller's spring before the stage is seen held)
    and the rest integral θ·``rest_integral_n_m_s``.

    Both rest loops of :func:`analyse_rest`, ``rest/stuck`` and ``rest/free``, must meet PM ≥ ``min_phase_margin_deg``
    and GM ≥ ``min_gain_margin_db`` at every θ: a rest loop healthy only on the stuck stage relies on friction
    holding the stage (on ``config/hil-serial.yaml``'s two periods of delay K_d × 0.1 with the observer × 0.3 kept
    the stuck loop at PM 92° / GM 9.5 dB but left the free mass 11°). The K_d fractions of
    :data:`REST_KD_FRACTIONS` are tried from the largest (K_d's cut is what costs a start from rest; the most-margin
    points drop the stuck loop's crossover to a few Hz); at the first one with points that meet the floor the point
    with the most margin, min(PM/floor, GM/floor) over both loops, is chosen. Each point is screened at θ = 1 and
    analysed over the other θ only if it passes there.

    Returns ``gains`` (``kd_fraction``, ``dob_bandwidth_fraction``, ``spring_sections``; None when no point meets
    the floor), ``loops`` (the chosen point's ``rest/stuck`` and ``rest/free`` figures, worst over θ, with
    ``healthy``; None without a choice) and ``points`` (how many points were analysed)."""
    ths = sorted({float(t) for t in thetas}, key=lambda t: (t != 1.0, t))
    cap = math.inf if free_spring_cap_n_m is None else float(free_spring_cap_n_m)

    def healthy(w: dict[str, Any]) -> bool:
        return bool(w["closed_loop_stable"] and w["phase_margin_deg"] >= min_phase_margin_deg
                    and w["gain_margin_db"] >= min_gain_margin_db)

    def score(loops: dict[str, dict[str, Any]]) -> float:
        return min(min(float(w["phase_margin_deg"]) / min_phase_margin_deg,
                       float(w["gain_margin_db"]) / min_gain_margin_db) for w in loops.values())

    points = 0
    screen = _rest_screen(mass_kg, period_s, pid, delay_samples, dob_bandwidth_hz, dob_command_delay_samples,
                          stiffness_n_m, damping_n_s_m, velocity_cutoff_hz, dob_mass_kg, integrator_held)

    def evaluate(kd: float, g: float, n: int) -> dict[str, dict[str, Any]] | None:
        nonlocal points
        for th in ths:  # the dense numpy response first (no stability test), with a little slack
            for pm, gm in screen(kd, g, n, th * rest_spring_n_m, min(th * rest_spring_n_m, cap),
                                 th * rest_integral_n_m_s):
                if pm < min_phase_margin_deg - SCREEN_SLACK[0] or gm < min_gain_margin_db - SCREEN_SLACK[1]:
                    return None
        per: list[tuple[float, list[LoopAnalysis]]] = []
        for th in ths:
            points += 1
            a = analyse_rest(mass_kg, period_s, pid, delay_samples, dob_bandwidth_hz, dob_command_delay_samples,
                             stiffness_n_m, damping_n_s_m, th * rest_spring_n_m, velocity_cutoff_hz,
                             dob_mass_kg=dob_mass_kg, integrator_held=integrator_held, kd_fraction=kd,
                             dob_bandwidth_fraction=g, spring_sections=n,
                             rest_integral_n_m_s=th * rest_integral_n_m_s,
                             free_spring_n_m=min(th * rest_spring_n_m, cap))
            if not all(healthy(x.summary()) for x in a):
                return None
            per.append((th, a))
        out: dict[str, dict[str, Any]] = {}
        for j, a0 in enumerate(per[0][1]):
            i, w = worst_over([loops[j].summary() for _, loops in per])
            out[a0.name] = {**w, "theta": per[i][0], "healthy": healthy(w)}
        return out

    for kd in REST_KD_FRACTIONS:
        ok = [((kd, g, n), r) for g in REST_DOB_BANDWIDTH_FRACTIONS for n in REST_SPRING_SECTIONS
              if (r := evaluate(kd, g, n)) is not None]
        if ok:
            (kd_, g_, n_), loops = max(ok, key=lambda t: score(t[1]))
            return {"gains": {"kd_fraction": kd_, "dob_bandwidth_fraction": g_, "spring_sections": n_},
                    "loops": loops, "points": points}
    return {"gains": None, "loops": None, "points": points}


#: :func:`design_rest_gains` analyses a point fully only when its screening response is within this slack of the
#: floor ([deg], [dB])
SCREEN_SLACK = (2.0, 0.5)


def _rest_screen(mass_kg: float, period_s: float, pid: PidConfig, delay_samples: int, dob_bandwidth_hz: float,
                 dob_command_delay_samples: int, stiffness_n_m: float, damping_n_s_m: float,
                 velocity_cutoff_hz: float | None, dob_mass_kg: float | None, integrator_held: bool) -> Any:
    """A fast screen for :func:`design_rest_gains`: the two rest loops of :func:`analyse_rest` evaluated directly in
    numpy on its frequency grid, margins only (no closed-loop stability test). Returns f(κ_d, κ_g, n, k_v stuck,
    k_v free, K_r) -> [(PM, GM) stuck, (PM, GM) free]."""
    import control

    T = period_s
    f = np.logspace(-1, math.log10(0.5 / T * 0.999), 2000)
    z = np.exp(2j * math.pi * f * T)
    zd = z ** -delay_samples

    def tf_at(P: Any) -> np.ndarray:
        num, den = (np.asarray(v, dtype=float).ravel() for v in control.tfdata(P)[:2])
        return np.polyval(num, z) / np.polyval(den, z)

    stuck = tf_at(control.c2d(control.tf([1.0], [mass_kg, damping_n_s_m, stiffness_n_m]), T, "zoh")) * zd
    free = tf_at(control.c2d(control.tf([1.0], [mass_kg, 0.0, 0.0]), T, "zoh")) * zd
    b = math.exp(-2 * math.pi * pid.derivative_cutoff_hz * T)
    integ = pid.ki_n_m_s * T * z / (z - 1)
    a_s = math.exp(-2 * math.pi * dob_bandwidth_hz * T)
    F = (1 - a_s) * z / (z - a_s)
    md = dob_mass_kg if dob_mass_kg is not None else mass_kg
    observer = dob_bandwidth_hz > 0.0
    Fv = 1.0
    if velocity_cutoff_hz is not None:
        bv = math.exp(-2 * math.pi * velocity_cutoff_hz * T)
        Fv = (1 - bv) * z / (z - bv)
    c_int = T * z / (z - 1)

    def f_screen(kd: float, g: float, n: int, kv: float, kv_free: float, kr: float) -> list[tuple[float, float]]:
        C0 = pid.kp_n_m + pid.kd_n_s_m * kd * (1 - b) / T * (z - 1) / (z - b)
        if observer:
            a = math.exp(-2 * math.pi * dob_bandwidth_hz * g * T)
            Hw = (1 - a) / (z - a)
            Hu = Hw * (z + 1) / (2 * z) * z ** -dob_command_delay_samples
            Hy = md * (1 - a) / T * (1 - Hw) * (z - 1) / (z * T) * Fv
            if not integrator_held:
                C0 = C0 + integ
        else:
            C0 = C0 + (0.0 if integrator_held else integ) + kr * c_int
        out = []
        for P, k in ((stuck, kv), (free, kv_free)):
            C = C0 + (k * F ** n if k > 0.0 else 0.0)
            L = P * (C + Hy) / (1 - Hu) + (P * kr * c_int if kr > 0.0 else 0.0) if observer else P * C
            gm, pm, _, _ = _margins_from_response(f, np.abs(L), np.unwrap(np.angle(L)))
            out.append((pm, gm))
        return out

    return f_screen


def dob_loop(P: Any, C: Any, Hu: Any, Hy: Any, dt: float) -> Any:
    """``L = P·(C + H_y)/(1 − H_u)`` as a state-space interconnection.

    Forming this product as one polynomial ratio loses the roots clustered at z = 1 at short periods
    (10 kHz); the series/feedback state-space form keeps them.
    """
    import control

    one = control.ss(control.tf([1.0], [1.0], dt))
    CH = control.ss(C) + control.ss(Hy)
    return control.ss(P) * CH * control.feedback(one, control.ss(Hu), sign=1)


def bode_png(analyses: list[LoopAnalysis], path: str, title: str = "") -> None:
    """Write a Bode plot (magnitude and phase of each open loop) as PNG (Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(8, 6))
    for a in analyses:
        lab = f"{a.name}: PM {a.phase_margin_deg:.1f}°, GM {a.gain_margin_db:.1f} dB, fc {a.crossover_hz:.1f} Hz"
        ax1.semilogx(a.freq_hz, a.mag_db, label=lab)
        ax2.semilogx(a.freq_hz, a.phase_deg, label=a.name)
        if not math.isnan(a.crossover_hz):
            ax1.axvline(a.crossover_hz, ls=":", lw=0.8)
    ax1.axhline(0.0, color="k", lw=0.6)
    ax2.axhline(-180.0, color="k", lw=0.6)
    ax1.set_ylabel("|L| [dB]")
    ax2.set_ylabel("phase [deg]")
    ax2.set_xlabel("frequency [Hz]")
    ax1.legend(fontsize=8)
    ax1.grid(True, which="both", alpha=0.3)
    ax2.grid(True, which="both", alpha=0.3)
    ax1.set_title(title or "open loop at the plant input")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
