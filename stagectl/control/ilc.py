"""Iterative learning control (ILC): a feed-forward force learned from the error of repeated motions.

A motion the stage repeats (a scan line, a raster, a move sequence: one *repetition* of N samples at the loop
period T) is tracked with the same feedback every time, so its error repeats. ILC adds a learned force u_k(t)
[N] to the command and improves it after every repetition k from that repetition's error e_k(t) = x_ref − x
[m]::

    u_{k+1}(t) = W(t)·Q(z)·[ u_k(t) + s·L(z)·e_k(t) ]                               (1)

* ``u_k`` is the force *actually applied* in repetition k (ramps included), so switching on or off mid-way
  does not corrupt the update.
* ``L(z)`` is the learning filter [N/m], designed from the plant model (mass m, I/O delay d samples, the
  controller's PID and observer). ``learning: inverse`` (default)::

      L(z) = α·Ĝ(z)⁻¹,     Ĝ(z) = P(z) / ((1 − H_u(z)) + P(z)·(C(z) + H_y(z)))          (2)

  Ĝ is the *process sensitivity*: how a force added to the command moves the stage with the loop closed
  (P = ZOH rigid mass with d samples of delay, C = PID, H_u/H_y = the observer's input/output filters of
  :func:`stagectl.control.design.qfilter_tfs`; the learned force is part of the observer's input, like the
  inertia feed-forward, so the observer does not fight it). Above the loop's crossover Ĝ⁻¹ ≈ m·(z−1)²·z^(1+d)/T²:
  a second difference with a phase *lead* of λ = (1 + d)·T, which is why the error is used "ahead",
  e_k(t + λ). ``learning: lead`` is the classic scalar form L(z) = L·z^λ (gain ``gain_n_m``, lead ``lead_s``).
* ``Q(z)`` is a zero-phase low-pass (forward-backward Butterworth of order 1, i.e. |Q| = 1/(1 + (f/f_Q)²),
  cut-off ``q_cutoff_hz``): it keeps the learning out of the frequencies where the model is not trusted and
  makes the iteration robust.

* ``W(t)`` in [0, 1] is the learning window (``window: moving``, :func:`learning_window`): the learned force
  is applied only while the reference moves, plus ``window_tail_s`` after each stop, with raised-cosine edges.
  At rest the plant is the friction's pre-sliding spring (Σk ≈ 6.4e5 N/m on the seed stage) and the controller
  holds its PID integrator, so the free-mass loop model of (2) does not hold there; learning everywhere
  diverged on 10 µm steps with the shipped gains. W multiplies the force only, so ‖W·M‖ ≤ ‖M‖ = max(ρ of (3),
  1 in the unlearned DC bin) for M = Q·(1 − L·G): the windowed iteration never grows for the model
  (windowing the error too would lose that: W does not commute with L·G).
* ``s`` in [1/16, 1] is the divergence guard's gain factor: a repetition whose RMS exceeds the previous one's by
  ``guard_growth_fraction`` rolls the last update back and halves s; s recovers ×1.25 per repetition that does
  not grow. s·L keeps (3): |Q·(1 − s·c)| ≤ (1 − s)·Q + s·|Q·(1 − c)|. The guard covers what (3) cannot see
  (pre-sliding inside a move, a plant change).

The update runs once per repetition on the whole record, so L and Q may be non-causal. It is done in the
frequency domain on the repetition's DFT grid f_j = j/(N·T) (a repetition starts and ends at rest, so the
record is treated as one period). With the true process sensitivity G the error evolves as
e_{k+1} = Q·(1 − G·L)·e_k + (1 − Q)·(…) and the learned force converges **monotonically** (in the 2-norm, for
every start) when::

    ρ = max_j |Q(f_j)·(1 − L(f_j)·G(f_j))| < 1                                       (3)

:func:`design_ilc` evaluates (3) for the nominal model and for the mass ``mass_error_fraction`` off either
way (``robust``), and reports both. DC (f = 0) is not learned (L = 0): a constant force is the
integrator's job; that bin keeps ρ = Q(0) = 1 and u's mean never changes.

Units: forces N, errors m, L in N/m, frequencies Hz, times s.

The stateful part, :class:`IlcLearner`, is stepped by the loop once per cycle (``step``: real-time safe, floats
only) and runs (1) at a repetition boundary (one FFT pair of the repetition: ~0.1 ms for N = 3000). It is
bumpless (its output ramps in and out over ``ramp_s``), frozen on any fault (the repetition in progress is
dropped, learning stops until started again; the learned signal is kept), off by default.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stagectl.control.dob import DobConfig
from stagectl.control.pid import PidConfig
from stagectl.errors import ConfigError
from stagectl.schema import param

__all__ = [
    "ILC_COLUMNS",
    "IlcConfig",
    "IlcDesign",
    "IlcLearner",
    "IlcPlant",
    "Repetition",
    "design_ilc",
    "ilc_update",
    "learning_window",
    "process_sensitivity",
    "q_filter",
    "rms",
]

#: telemetry columns of the learner: learned force applied [N], completed updates, RMS error of the last
#: complete repetition [m]
ILC_COLUMNS = ("u_ilc", "ilc_iteration", "ilc_rms_m")

_NAME = re.compile(r"^[A-Za-z0-9._-]{1,64}$")


@dataclass(frozen=True)
class IlcConfig:
    """Iterative learning control settings (YAML ``ilc:``). Off by default."""

    enabled: bool = param(False, desc="attach the learner: telemetry columns and the ilc client commands")
    autostart: bool = param(False, desc="start learning the repeated motion (demo / scenario) at loop start")
    learning: str = param("inverse", desc="learning filter: inverse (alpha times the model's process "
                          "sensitivity inverse) or lead (scalar gain_n_m with phase lead lead_s)",
                          choices=("inverse", "lead"))
    alpha: float = param(1.0, desc="learning gain as a fraction of the model inverse (inverse), or of "
                         "1/|G| at q_cutoff_hz when gain_n_m is None (lead)", gt=0.0, le=1.0)
    gain_n_m: float | None = param(None, unit="N/m", desc="lead: scalar learning gain L (None: from alpha)",
                                   gt=0.0)
    lead_s: float | None = param(None, unit="s", desc="lead: phase lead λ (None: (1 + I/O delay) periods)",
                                 ge=0.0, le=0.1)
    q_cutoff_hz: float = param(300.0, unit="Hz", desc="zero-phase robustness filter Q cut-off f_Q", gt=0.0)
    ramp_s: float = param(0.2, unit="s", desc="ramp of the learned force when learning is switched on/off",
                          ge=0.0, le=10.0)
    max_force_n: float = param(2.0, unit="N", desc="clamp of the learned force", gt=0.0)
    mass_error_fraction: float = param(0.2, desc="convergence is also checked with the mass this much off",
                                       ge=0.0, lt=1.0)
    min_coverage_fraction: float = param(0.98, desc="a repetition with fewer valid samples is not learned from",
                                         gt=0.0, le=1.0)
    max_repetition_s: float = param(60.0, unit="s", desc="longest repetition learned", gt=0.0, le=600.0)
    window: str = param("moving", desc="where to learn: moving (only while the reference moves, plus "
                        "window_tail_s after each stop, smooth edges) or all (the whole repetition)",
                        choices=("moving", "all"))
    window_tail_s: float = param(0.03, unit="s", desc="the learning window stays open this long after the "
                                 "reference stops (the settling after a move)", ge=0.0, le=10.0)
    window_taper_s: float = param(0.02, unit="s", desc="raised-cosine edges of the learning window", ge=0.0,
                                  le=10.0)
    guard_growth_fraction: float = param(
        0.3, desc="divergence guard: a repetition whose RMS exceeds the previous one's by this fraction rolls the "
        "last update back and halves the learning gain (it recovers x1.25 per repetition that does not grow; "
        "0: off)", ge=0.0, le=10.0)
    store_dir: Path | None = param(None, desc="directory of saved learned signals <motion>.npz (relative to "
                                   "the config file; None: the current directory)")


@dataclass(frozen=True)
class IlcPlant:
    """What the design needs to know of the loop: mass [kg], period [s], I/O delay [samples], PID, observer."""

    mass_kg: float
    period_s: float
    delay_samples: int
    pid: PidConfig
    dob: DobConfig = field(default_factory=lambda: DobConfig(kind="none"))
    dob_mass_kg: float | None = None


@dataclass(frozen=True)
class IlcDesign:
    """A learning law for repetitions of ``n_samples`` samples (see module docstring, (1)–(3)).

    ``learn`` = L(f_j) [N/m] and ``q`` = Q(f_j) on the rfft grid ``freq_hz``; ``rho`` = max ρ of (3) with the
    nominal model, ``rho_robust`` the worst with the mass ±``mass_error_fraction`` off or half a sample more delay; ``rho_hz`` where the
    nominal maximum is.
    """

    n_samples: int
    period_s: float
    learning: str
    freq_hz: np.ndarray
    learn: np.ndarray
    q: np.ndarray
    max_force_n: float
    rho: float
    rho_hz: float
    rho_robust: float
    mass_error_fraction: float
    lead_samples: int

    @property
    def monotonic(self) -> bool:
        """Condition (3) holds for the nominal model and for the mass ± the error fraction."""
        return self.rho < 1.0 and self.rho_robust < 1.0

    def summary(self) -> dict[str, Any]:
        """JSON-ready report of the design and its convergence check."""
        hi = self.freq_hz > 0
        return {
            "learning": self.learning, "n_samples": self.n_samples, "repetition_s": self.n_samples * self.period_s,
            "lead_samples": self.lead_samples,
            "learning_gain_at_q_cutoff_n_m": float(np.abs(np.interp(
                float(self.freq_hz[hi][np.argmin(np.abs(self.q[hi] - 0.5))]), self.freq_hz, np.abs(self.learn)))),
            "rho": self.rho, "rho_at_hz": self.rho_hz, "rho_robust": self.rho_robust,
            "mass_error_fraction": self.mass_error_fraction, "monotonic": self.monotonic,
        }


# ------------------------------------------------------------------------------------------ pure functions


def q_filter(freq_hz: np.ndarray, cutoff_hz: float) -> np.ndarray:
    """Zero-phase low-pass Q(f) = 1/(1 + (f/f_Q)²): a first-order Butterworth run forwards and backwards
    (|B|², real, 0 < Q ≤ 1)."""
    return np.asarray(1.0 / (1.0 + (np.asarray(freq_hz, dtype=float) / cutoff_hz) ** 2))


def _freqresp(sys: Any, z: np.ndarray) -> np.ndarray:
    return np.asarray(sys(z), dtype=complex).reshape(-1)


def process_sensitivity(freq_hz: np.ndarray, plant: IlcPlant, mass_kg: float | None = None,
                        sampling_zero: bool = True, extra_delay_samples: float = 0.0) -> np.ndarray:
    """G(f) [m/N] of (2): position per force added to the command, loop closed (PID + observer as configured).

    ``mass_kg`` overrides the *true* mass of P (the controller and observer keep the plant's nominal one) and
    ``extra_delay_samples`` adds delay to P, for the robustness check. ``sampling_zero`` False replaces the ZOH
    zero's factor (z+1)/2 = cos(ωT/2)·e^(jωT/2) by its phase e^(jωT/2) alone: the learning filter (2) uses
    that, since inverting the zero at z = −1 would give L → ∞ towards the Nyquist frequency, where no model
    of the real actuator holds. f = 0 gives 0 (the integrator rejects a constant force).
    """
    T = plant.period_s
    f = np.asarray(freq_hz, dtype=float)
    out = np.zeros(f.shape, dtype=complex)
    pos = f > 0
    z = np.exp(2j * math.pi * f[pos] * T)
    m = plant.mass_kg if mass_kg is None else mass_kg
    # closed forms of design.plant_tf, design.pid_tf and design.qfilter_tfs (numpy only: no python-control in
    # the loop process); ZOH rigid mass T²(z+1)/(2m(z−1)²) with d samples of delay
    zoh_zero = (z + 1) / 2 if sampling_zero else np.exp(1j * math.pi * f[pos] * T)
    P = (T * T * zoh_zero / (m * (z - 1) ** 2) * z ** (-plant.delay_samples)
         * np.exp(-2j * math.pi * f[pos] * T * extra_delay_samples))
    pid = plant.pid
    b = math.exp(-2 * math.pi * pid.derivative_cutoff_hz * T)
    C = pid.kp_n_m + pid.ki_n_m_s * T * z / (z - 1) + pid.kd_n_s_m * (1 - b) / T * (z - 1) / (z - b)
    dob = plant.dob
    md = plant.dob_mass_kg or dob.nominal_mass_kg or plant.mass_kg
    if dob.kind == "none":
        Hu = np.zeros_like(z)
        Hy = np.zeros_like(z)
    elif dob.kind == "kalman":
        from stagectl.control import design

        K = design.kalman_gain(md, T, dob.bandwidth_hz, dob.measurement_noise_m)
        hu, hy = design.kalman_tfs(md, T, K, dob.command_delay_samples)
        Hu, Hy = _freqresp(hu, z), _freqresp(hy, z)
    else:
        a = math.exp(-2 * math.pi * dob.bandwidth_hz * T)
        kv = md * (1 - a) / T
        Hw = (1 - a) / (z - a)
        Hu = Hw * (z + 1) / (2 * z) * z ** (-dob.command_delay_samples)
        Hy = kv * (1 - Hw) * (z - 1) / (z * T)
    out[pos] = P / ((1.0 - Hu) + P * (C + Hy))
    return out


def design_ilc(cfg: IlcConfig, plant: IlcPlant, n_samples: int) -> IlcDesign:
    """The learning law (1) for repetitions of ``n_samples`` samples, with its convergence check (3) for the
    nominal model and (``rho_robust``) for the mass ±``mass_error_fraction`` off and half a sample more delay.

    Raises
    ------
    ConfigError
        ``n_samples`` < 8 or longer than ``ilc.max_repetition_s``.
    """
    T = plant.period_s
    if n_samples < 8 or n_samples * T > cfg.max_repetition_s:
        raise ConfigError(f"ilc: a repetition of {n_samples} samples ({n_samples * T:g} s) is outside "
                          f"[8 samples, ilc.max_repetition_s {cfg.max_repetition_s:g} s]")
    f = np.fft.rfftfreq(n_samples, T)
    G = process_sensitivity(f, plant)
    G_learn = process_sensitivity(f, plant, sampling_zero=False)
    pos = f > 0
    q = q_filter(f, cfg.q_cutoff_hz)
    learn = np.zeros(f.shape, dtype=complex)
    lead = int(round((1 + plant.delay_samples) if cfg.lead_s is None else cfg.lead_s / T))
    if cfg.learning == "inverse":
        learn[pos] = cfg.alpha / G_learn[pos]
    else:
        gain = cfg.gain_n_m
        if gain is None:
            g_c = process_sensitivity(np.array([cfg.q_cutoff_hz]), plant)[0]
            gain = cfg.alpha / max(abs(g_c), 1e-300)
        learn[pos] = gain * np.exp(2j * math.pi * f[pos] * T * lead)

    def worst(Gt: np.ndarray) -> tuple[float, float]:
        r = np.abs(q * (1.0 - learn * Gt))
        r[~pos] = 0.0
        i = int(np.argmax(r)) if r.size else 0
        return float(r[i]) if r.size else 0.0, float(f[i]) if r.size else 0.0

    rho, rho_hz = worst(G)
    e = cfg.mass_error_fraction
    rob = max([worst(process_sensitivity(f, plant, plant.mass_kg * (1 + s * e)))[0] for s in (-1.0, 1.0)]
              + [worst(process_sensitivity(f, plant, extra_delay_samples=0.5))[0]])
    return IlcDesign(n_samples, T, cfg.learning, f, learn, q, cfg.max_force_n, rho, rho_hz, rob, e, lead)


def learning_window(moving: np.ndarray, period_s: float, tail_s: float, taper_s: float) -> np.ndarray:
    """The learning window W(t) in [0, 1] of one repetition (circular: the repetition is one period).

    ``moving`` (bool per sample): the reference moves. W = 1 where it moves and for ``tail_s`` after each stop,
    with raised-cosine edges ``taper_s`` wide centred on the edges of that set; 0 at rest beyond. No motion at
    all gives W = 0.
    """
    m = np.asarray(moving, dtype=bool)
    n = m.size
    if not m.any():
        return np.zeros(n)
    tail = int(round(tail_s / period_s))
    open_ = m.copy()
    for lag in range(1, min(tail, n) + 1):  # stays open tail samples after every stop (circular)
        open_ |= np.roll(m, lag)
    w = int(round(taper_s / period_s))
    if w < 2:
        return open_.astype(float)
    h = np.hanning(w + 2)[1:-1]
    h /= h.sum()
    k = np.zeros(n)
    k[: h.size] = h
    k = np.roll(k, -(h.size // 2))  # centred kernel: the edges are smoothed symmetrically
    out = np.fft.irfft(np.fft.rfft(open_.astype(float)) * np.fft.rfft(k), n)
    return np.asarray(np.clip(out, 0.0, 1.0))


def ilc_update(u_applied: np.ndarray, e: np.ndarray, d: IlcDesign, window: np.ndarray | None = None,
               scale: float = 1.0) -> np.ndarray:
    """One learning step (1): u_{k+1} = clamp(W·Q·(u_k + s·L·e_k), ±max_force_n) [N] over one repetition.

    ``u_applied`` [N] and ``e`` [m] are the repetition's applied learned force and error (length
    ``d.n_samples``), evaluated on the DFT grid (the repetition taken as one period); ``window`` W (None: 1)
    is the learning window of :func:`learning_window` (applied to the force only: ||W·M|| ≤ ||M||, so the
    check (3) still bounds the iteration); ``scale`` s in (0, 1] the divergence guard's gain factor (s·L keeps
    (3): |Q·(1 − s·c)| ≤ (1 − s)·Q + s·|Q·(1 − c)|). Pure.
    """
    n = d.n_samples
    ea = np.asarray(e, dtype=float)
    U = np.fft.rfft(np.asarray(u_applied, dtype=float), n)
    E = np.fft.rfft(ea, n)
    u = np.fft.irfft(d.q * (U + scale * d.learn * E), n)
    if window is not None:
        u = window * u
    return np.asarray(np.clip(u, -d.max_force_n, d.max_force_n))


def rms(x: np.ndarray) -> float:
    """Root mean square of ``x`` (same unit)."""
    a = np.asarray(x, dtype=float)
    return float(math.sqrt(float(np.mean(a * a)))) if a.size else math.nan


# ------------------------------------------------------------------------------------------ learner


@dataclass(frozen=True)
class Repetition:
    """Where the loop is in a repeated motion: its name, which repetition (a counter that changes at every
    restart), time into it [s] and its length [s]."""

    motion: str
    index: int
    tau_s: float
    length_s: float


class IlcLearner:
    """Learns and applies the feed-forward of one repeated motion at a time (see module docstring).

    Parameters
    ----------
    cfg : IlcConfig
    plant : IlcPlant
        For the design (one per repetition length, made when a motion is first met, outside ``step`` only
        when learning is started by :meth:`request`; else at the first cycle of the motion).
    repetition : callable
        ``repetition() -> Repetition | None``: where the reference is in its repeated motion (None: no
        repeated motion running).
    base_dir : Path
        Where a relative ``store_dir`` is resolved.
    """

    columns = ILC_COLUMNS

    def __init__(self, cfg: IlcConfig, plant: IlcPlant, repetition: Callable[[], Repetition | None],
                 base_dir: Path | None = None) -> None:
        self.cfg = cfg
        self.plant = plant
        self.period_s = plant.period_s
        self._repetition = repetition
        self.base_dir = base_dir or Path.cwd()
        self.learning = False  # updates on (requested by start, cleared by stop and by a fault)
        self.applying = False  # output target: 1 (ramp in) or 0 (ramp out)
        self.gain = 0.0  # current ramp factor 0..1
        self.frozen: str | None = None
        self.motion: str | None = None
        self.design: IlcDesign | None = None
        self.u = np.zeros(0)
        self.iteration = 0
        self.rms_history: list[float] = []
        self.last_rms_m = math.nan
        self.skipped_repetitions = 0
        self._designs: dict[int, IlcDesign] = {}
        self._rep_index: int | None = None
        self._rec_e = np.zeros(0)
        self._rec_u = np.zeros(0)
        self._rec_ok = np.zeros(0, dtype=bool)
        self._rec_mv = np.zeros(0, dtype=bool)
        self.window: np.ndarray | None = None  # learning window of the current motion (window: moving)
        self.record_only = False  # record the RMS per repetition without learning (a baseline run)
        self.gain_scale = 1.0  # divergence guard: factor on L (halved on growth, recovers)
        self.guard_rollbacks = 0
        self._u_prev: np.ndarray | None = None  # the signal before the last update (for a roll-back)
        self._valid = False  # the repetition in progress started with learning on and is usable
        self._loaded = False  # the signal came from a file (kept when its length does not match a pass)
        self._u_out = 0.0
        self._ramp_step = 1.0
        self._tail_step = 0.0
        #: the learner takes part in this cycle's motion (set by :meth:`step`): a repeated motion runs while it
        #: learns (armed or recording, applying nothing yet in the first repetition) or applies a learned force
        #: (ramping in or out, or the tail after the motion ended). The controller does not adapt its own
        #: feed-forward model then (one learner at a time: ILC learns against a fixed feed-forward). A
        #: record-only baseline run is not active: it learns nothing and applies nothing.
        self.active = False

    # ------------------------------------------------------------------ setup
    def _design_for(self, n: int) -> IlcDesign:
        d = self._designs.get(n)
        if d is None:
            d = design_ilc(self.cfg, self.plant, n)
            self._designs[n] = d
        return d

    def _bind(self, rep: Repetition) -> None:
        """Take up motion ``rep.motion`` (a new motion resets the learned signal unless loaded for it)."""
        n = int(round(rep.length_s / self.period_s)) + 1
        if self.motion != rep.motion or not self._loaded:
            self._loaded = False
            self.motion = rep.motion
            self.design = self._design_for(n)
            self.u = np.zeros(n)
            self.window = None
            self.gain_scale = 1.0
            self._u_prev = None
            self.iteration = 0
            self.rms_history = []
            self.last_rms_m = math.nan
        self._rec_e = np.zeros(n)
        self._rec_u = np.zeros(n)
        self._rec_ok = np.zeros(n, dtype=bool)
        self._rec_mv = np.zeros(n, dtype=bool)

    # ------------------------------------------------------------------ per cycle
    def step(self, t_s: float, e_m: float, fresh: bool = True, moving: bool = True) -> float:
        """The learned force for this cycle [N] (ramp applied), recording the error ``e_m`` [m] of this cycle
        (``fresh`` False: a stale sample, not recorded) and whether the reference moves (``moving``: for the
        learning window). Runs the update (1) when a repetition ends."""
        rep = self._repetition()
        target = 1.0 if (self.applying and self.frozen is None) else 0.0
        if self.gain != target:
            s = self._ramp_step
            self.gain = min(target, self.gain + s) if target > self.gain else max(target, self.gain - s)
        if rep is None:  # no repeated motion (a move/stop took over): the learned force decays over ramp_s
            if self._rep_index is not None:
                self._rep_index = None
                self._valid = False
                self._tail_step = abs(self._u_out) * self._ramp_step_of_cfg()
            u_prev = self._u_out
            self._u_out = 0.0 if abs(u_prev) <= self._tail_step else u_prev - math.copysign(self._tail_step, u_prev)
            self.active = self._u_out != 0.0
            return self._u_out
        n_rep = int(round(rep.length_s / self.period_s)) + 1
        if rep.index != self._rep_index:
            if self._rep_index is not None and self._valid:
                self._finish()
            self._rep_index = rep.index
            if rep.motion != self.motion or (self.iteration == 0 and not self._loaded and n_rep != self.u.size):
                self._bind(rep)
            self._rec_ok[:] = False
            self._valid = (self.learning or self.record_only) and self.frozen is None and n_rep == self.u.size
        i = int(round(rep.tau_s / self.period_s))
        n = self.u.size
        if n_rep == n and 0 <= i < n:  # (a first pass with an approach move has another length: not ours)
            u = self.gain * float(self.u[i])
            if fresh and self._valid:
                self._rec_e[i] = e_m
                self._rec_u[i] = u
                self._rec_ok[i] = True
                self._rec_mv[i] = moving
        else:
            u = 0.0
        self._u_out = u
        self.active = (self.learning and self.frozen is None) or self.gain > 0.0 or u != 0.0
        return u

    def _finish(self) -> None:
        """A repetition ended: learn from it if it is complete enough (module docstring, (1))."""
        ok = self._rec_ok
        if not ok.any() or ok.mean() < self.cfg.min_coverage_fraction or self.design is None:
            self.skipped_repetitions += 1
            return
        idx = np.arange(ok.size)
        e = np.interp(idx, idx[ok], self._rec_e[ok])
        u = np.interp(idx, idx[ok], self._rec_u[ok])
        self.last_rms_m = rms(e)
        self.rms_history.append(self.last_rms_m)
        if len(self.rms_history) > 1000:
            del self.rms_history[0]
        if not (self.learning and self.frozen is None):
            return
        h = self.rms_history
        g = self.cfg.guard_growth_fraction
        if g > 0 and len(h) >= 2 and h[-1] > (1.0 + g) * h[-2]:
            if self._u_prev is not None:  # the last update made it worse (or the plant changed): roll it back
                self.u = self._u_prev
                self._u_prev = None
                self.gain_scale = max(self.gain_scale * 0.5, 1.0 / 16.0)
                self.guard_rollbacks += 1
                return  # the next repetition runs the previous signal again, then learns at the lower gain
        elif len(h) >= 2:
            self.gain_scale = min(1.0, self.gain_scale * 1.25)
        self._u_prev = self.u.copy()
        w = None
        if self.cfg.window == "moving":
            if self.window is None or self.window.size != ok.size:  # the reference repeats: made once
                self.window = learning_window(self._rec_mv | ~ok, self.period_s, self.cfg.window_tail_s,
                                              self.cfg.window_taper_s)
            w = self.window
        self.u = ilc_update(u, e, self.design, w, self.gain_scale)  # from what was applied (ramps included)
        self.iteration += 1

    # ------------------------------------------------------------------ control
    def prepare(self) -> None:
        """Design the law for the running repetition's length now (any thread; the loop thread then finds it
        made). Nothing when no repeated motion runs."""
        rep = self._repetition()
        if rep is not None:
            self._design_for(int(round(rep.length_s / self.period_s)) + 1)

    def request(self, action: str, motion: str | None = None) -> dict[str, Any]:
        """``start`` | ``stop`` | ``save`` | ``load`` | ``status`` (the ``ilc`` client request), at the loop's
        cycle boundary. ValueError ``"<field>: why"`` for a refused one."""
        if action == "start":
            return self.start()
        if action == "stop":
            return self.stop()
        if action == "save":
            return {**self.save(motion), **self.status()}
        if action == "load":
            if motion is None:
                raise ValueError("motion: load needs the motion name of the saved signal")
            return {**self.load(motion), **self.status()}
        if action == "status":
            return self.status()
        raise ValueError(f"action: must be start, stop, save, load or status (got {action!r})")

    def start(self) -> dict[str, Any]:
        """Learn (and apply, ramping in) from the next repetition boundary on; clears a freeze.

        Refused (ValueError) when the design of the running motion fails the monotonic-convergence check (3)."""
        rep = self._repetition()
        if rep is not None:
            d = self._design_for(int(round(rep.length_s / self.period_s)) + 1)
            if not d.monotonic:
                raise ValueError(f"action: the learning law fails the convergence check for {rep.motion!r} "
                                 f"(rho {d.rho:.3g}, with the mass off {d.rho_robust:.3g}; needs < 1): lower "
                                 f"ilc.alpha or ilc.q_cutoff_hz, or use learning: inverse")
        self.frozen = None
        self.learning = True
        self.applying = True
        self._set_ramp()
        return self.status()

    def stop(self, keep_applying: bool = False) -> dict[str, Any]:
        """Stop learning; the learned force ramps out (``keep_applying``: it stays applied, frozen)."""
        self.learning = False
        self._valid = False
        self.applying = keep_applying
        self._set_ramp()
        return self.status()

    def freeze(self, reason: str) -> None:
        """A fault: drop the repetition in progress, stop learning and applying (output 0 at once: the loop is
        in fault and the drive quick-stopped); the learned signal is kept."""
        self.frozen = reason
        self.learning = False
        self.applying = False
        self._valid = False
        self.gain = 0.0
        self._u_out = 0.0
        self.active = False

    def _ramp_step_of_cfg(self) -> float:
        return 1.0 if self.cfg.ramp_s <= 0 else min(1.0, self.period_s / self.cfg.ramp_s)

    def _set_ramp(self) -> None:
        self._ramp_step = self._ramp_step_of_cfg()

    # ------------------------------------------------------------------ store
    def path_for(self, motion: str) -> Path:
        """``store_dir/<motion>.npz`` (``motion``: letters, digits, '._-'); ValueError naming ``motion``."""
        if not _NAME.match(motion):
            raise ValueError(f"motion: must be 1-64 letters, digits or '._-' (got {motion!r})")
        d = self.cfg.store_dir
        base = self.base_dir if d is None else (d if d.is_absolute() else self.base_dir / d)
        return base / f"{motion}.npz"

    def save(self, motion: str | None = None) -> dict[str, Any]:
        """Write the learned signal of the current motion to ``store_dir/<motion>.npz``."""
        name = motion or self.motion
        if name is None or self.motion is None or not self.u.size:
            raise ValueError("motion: nothing learned yet (no repeated motion has run)")
        path = self.path_for(name)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez(tmp, u_n=self.u, period_s=self.period_s, iteration=self.iteration,
                 rms_m=np.asarray(self.rms_history, dtype=float), motion=str(self.motion))
        tmp.replace(path)
        return {"saved": str(path), "motion": self.motion, "samples": int(self.u.size), "iteration": self.iteration}

    def load(self, motion: str) -> dict[str, Any]:
        """Read ``store_dir/<motion>.npz`` (``motion``: the name it was saved under) as the learned signal of the
        motion it was learned on (applied when that motion runs and learning is started)."""
        path = self.path_for(motion)
        try:
            with np.load(path) as z:
                u = np.asarray(z["u_n"], dtype=float)
                period = float(z["period_s"])
                it = int(z["iteration"])
                hist = [float(v) for v in z["rms_m"]]
                learned_on = str(z["motion"]) if "motion" in z.files else motion
        except FileNotFoundError:
            raise ValueError(f"motion: no saved signal {path}") from None
        except (OSError, KeyError, ValueError) as exc:
            raise ValueError(f"motion: {path} is not a learned signal ({exc})") from None
        if abs(period - self.period_s) > 1e-12 or u.ndim != 1 or u.size < 8 or not np.all(np.isfinite(u)):
            raise ValueError(f"motion: {path} was learned at period {period:g} s with {u.size} samples; the loop "
                             f"runs at {self.period_s:g} s")
        self.motion = learned_on  # the motion it applies to (the file name is the label it was saved under)
        self.design = self._design_for(u.size)
        self.u = np.clip(u, -self.cfg.max_force_n, self.cfg.max_force_n)
        self.iteration = it
        self._rec_e = np.zeros(u.size)
        self._rec_u = np.zeros(u.size)
        self._rec_ok = np.zeros(u.size, dtype=bool)
        self._rec_mv = np.zeros(u.size, dtype=bool)
        self.window = None
        self.rms_history = hist
        self.gain_scale = 1.0
        self._u_prev = None
        self.last_rms_m = hist[-1] if hist else math.nan
        self._rep_index = None
        self._valid = False
        self._loaded = True
        return {"loaded": str(path), "motion": learned_on, "samples": int(u.size), "iteration": it}

    # ------------------------------------------------------------------ state
    def row(self) -> tuple[float, float, float]:
        """The telemetry values of :data:`ILC_COLUMNS` for this cycle."""
        return (self._u_out, float(self.iteration), self.last_rms_m)

    def status(self) -> dict[str, Any]:
        """Learning state: motion, iteration, RMS per iteration [m] (last 20), gain, frozen, convergence check."""
        d = self.design
        return {
            "motion": self.motion, "learning": self.learning, "applying": self.applying, "gain": self.gain,
            "frozen": self.frozen, "iteration": self.iteration, "last_rms_m": self.last_rms_m,
            "rms_m": list(self.rms_history[-20:]), "skipped_repetitions": self.skipped_repetitions,
            "gain_scale": self.gain_scale, "guard_rollbacks": self.guard_rollbacks,
            "window_fraction": float(np.mean(self.window)) if self.window is not None else None,
            "design": d.summary() if d is not None else None,
        }
