"""What the loop runs during a commissioning experiment.

The loop (:class:`~stagectl.loop.ControlLoop`) is the one ``stagectl run`` uses: same drivers, same safety
supervisor (soft limits, velocity, force clamp, following error, device faults). Commissioning hands it one
controller object, :class:`CommissionController`, whose *mode* changes between experiments (never during one):

* ``probe``: the open-loop sanity probe (:class:`SanityProbe`), a force state machine;
* ``closed``: a :class:`~stagectl.control.controller.StageController` (the commissioning tuning, the given
  configuration's, or the new one) plus an optional known force excitation ``d[n]`` (the FRF multisine),
  added to its output: ``u = C(x, ref) + d[n]``. ``n`` counts controller steps, so ``d`` is periodic in samples.

During the probe the reference follows the measured position (:class:`FollowMeasured`): a following-error
check is meaningless without a position controller. The probe bounds its own excursion (a few per cent of
the stroke) and its speed (half the velocity limit); soft limits, velocity and force limits stay active.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from stagectl.control.api import Command, Reference
from stagectl.control.controller import TERM_NAMES, StageController

FloatArray = npt.NDArray[np.float64]

#: telemetry terms of the commissioning controller: the closed-loop terms plus the excitation [N]
TERMS = (*TERM_NAMES, "u_exc")


class FollowMeasured:
    """Reference source that stands where the stage was last measured (the open-loop probe's reference)."""

    def __init__(self) -> None:
        self.x_m = 0.0

    def sample(self, t_s: float) -> Reference:
        return Reference(self.x_m)

    def hold(self, t_s: float, x_m: float) -> None:
        self.x_m = x_m

    def move(self, t_s: float, target_m: float, max_velocity_m_s: float | None) -> float:
        return 0.0

    def stop(self, t_s: float) -> float:
        return self.x_m

    @property
    def target_m(self) -> float:
        return self.x_m


@dataclass
class ProbeDirection:
    """What the probe saw in one direction (``sign`` +1/−1)."""

    sign: int
    outcome: str = "pending"          # ok | no_motion | wrong_sign | pending
    breakaway_n: float = math.nan     # |u| when the displacement first exceeded d_detect
    f1_n: float = math.nan
    f2_n: float = math.nan
    t1: list[float] = field(default_factory=list)
    x1: list[float] = field(default_factory=list)
    t2: list[float] = field(default_factory=list)
    x2: list[float] = field(default_factory=list)
    max_reverse_m: float = 0.0


class SanityProbe:
    """Open-loop force probe, per direction ``s = +1`` then ``−1`` (see ``docs/commissioning.md`` §1)::

        RAMP   u = s·f_lim·τ/t_ramp       until s·(x − x_start) ≥ d_detect   (breakaway force F_b = |u|)
                                           or τ ≥ t_ramp (no motion) or −s·(x − x_start) ≥ d_detect (wrong sign)
        ACC1   u = s·F1, F1 = min(1.5·F_b, f_lim)   until d_acc more, v ≥ v_stop/3 or t_acc
        ACC2   u = s·F2, F2 = min(2.5·F_b, f_lim)   until 3·d_acc more, v ≥ v_stop or t_acc
        BRAKE  u = −s·F2                   until the velocity (5-sample difference) reverses, or t_acc
        REST   u = 0                       for t_rest

    ACC1/ACC2 positions are kept: with a rigid mass and a friction force that does not depend on the force,
    ``a_i = (F_i − F_friction)/m``, so ``m = (F2 − F1)/(a2 − a1)`` does not depend on the friction.
    """

    def __init__(self, *, f_lim_n: float, d_detect_m: float, d_acc_m: float, v_stop_m_s: float,
                 t_ramp_s: float = 2.0, t_acc_s: float = 0.5, t_rest_s: float = 0.3) -> None:
        self.f_lim = f_lim_n
        self.d_detect = d_detect_m
        self.d_acc = d_acc_m
        self.v_stop = v_stop_m_s
        self.t_ramp = t_ramp_s
        self.t_acc = t_acc_s
        self.t_rest = t_rest_s
        self.dirs = [ProbeDirection(+1), ProbeDirection(-1)]
        self._i = 0
        self._phase = "RAMP"
        self._tau = 0.0
        self._x0 = math.nan
        self._xp = math.nan
        self._hist: list[float] = []
        self.done = False

    def reset(self, x_m: float) -> None:
        self._x0 = x_m
        self._xp = x_m
        self._hist = [x_m]

    def _next(self, phase: str, x: float) -> None:
        self._phase = phase
        self._tau = 0.0
        self._xp = x

    def step(self, dt: float, x: float) -> float:
        """Force [N] for this cycle."""
        if self.done:
            return 0.0
        self._hist.append(x)
        if len(self._hist) > 6:
            del self._hist[0]
        v = (self._hist[-1] - self._hist[0]) / (dt * max(len(self._hist) - 1, 1))
        d = self.dirs[self._i]
        s = d.sign
        self._tau += dt
        ph = self._phase
        if ph == "RAMP":
            if math.isnan(self._x0):
                self._x0 = x
            disp = s * (x - self._x0)
            d.max_reverse_m = max(d.max_reverse_m, -disp)
            if -disp >= self.d_detect:
                d.outcome = "wrong_sign"
                return self._finish()
            if disp >= self.d_detect:
                u_now = self.f_lim * min(self._tau / self.t_ramp, 1.0)
                d.breakaway_n = u_now
                d.f1_n = min(1.5 * u_now, self.f_lim)
                d.f2_n = min(2.5 * u_now, self.f_lim)
                self._next("ACC1", x)
                return s * d.f1_n
            if self._tau >= self.t_ramp:
                d.outcome = "no_motion"
                return self._finish()
            return s * self.f_lim * self._tau / self.t_ramp
        if ph in ("ACC1", "ACC2"):
            tl, xl = (d.t1, d.x1) if ph == "ACC1" else (d.t2, d.x2)
            tl.append(self._tau)
            xl.append(x)
            span = self.d_acc if ph == "ACC1" else 3.0 * self.d_acc
            v_end = self.v_stop / 3.0 if ph == "ACC1" else self.v_stop
            if s * (x - self._xp) >= span or s * v >= v_end or self._tau >= self.t_acc:
                if ph == "ACC1" and d.f2_n > 1.2 * d.f1_n:
                    self._next("ACC2", x)
                    return s * d.f2_n
                self._next("BRAKE", x)
                return -s * d.f2_n
            return s * (d.f1_n if ph == "ACC1" else d.f2_n)
        if ph == "BRAKE":
            if s * v <= 0.0 or self._tau >= self.t_acc:
                self._next("REST", x)
                return 0.0
            return -s * d.f2_n
        # REST
        if self._tau >= self.t_rest:
            d.outcome = "ok"
            if self._i + 1 < len(self.dirs):
                self._i += 1
                self._next("RAMP", x)
                self._x0 = x
                return 0.0
            return self._finish()
        return 0.0

    def _finish(self) -> float:
        self.done = True
        return 0.0


class CommissionController:
    """The one controller object the loop drives during commissioning (see the module docstring)."""

    term_names = TERMS

    def __init__(self, inner: StageController) -> None:
        self.inner: StageController = inner
        self.probe: SanityProbe | None = None
        self.follow: FollowMeasured | None = None
        self.excitation: FloatArray | None = None   # one period of d[n] [N]
        self.n = 0
        self.limit_n = math.inf
        self.on_probe_done: Callable[[], None] | None = None

    def set_closed(self, inner: StageController, excitation: FloatArray | None = None,
                   limit_n: float = math.inf) -> None:
        """Closed loop with ``inner`` (+ the ``excitation`` samples), the sum clamped to ±``limit_n``."""
        self.inner = inner
        self.limit_n = limit_n
        self.probe = None
        self.follow = None
        self.excitation = excitation
        self.n = 0

    def set_probe(self, probe: SanityProbe, follow: FollowMeasured) -> None:
        self.probe = probe
        self.follow = follow
        self.excitation = None

    def reset(self, x_m: float) -> None:
        self.n = 0
        self.inner.reset(x_m)
        if self.probe is not None:
            self.probe.reset(x_m)
        if self.follow is not None:
            self.follow.x_m = x_m

    def retune(self, cfg: object) -> None:
        self.inner.retune(cfg)  # type: ignore[arg-type]

    def step(self, dt: float, x_meas_m: float, ref: Reference) -> Command:
        if self.probe is not None:
            u = self.probe.step(dt, x_meas_m)
            if self.follow is not None:
                self.follow.x_m = x_meas_m
            return Command(u, {"u_exc": u})
        cmd = self.inner.step(dt, x_meas_m, ref)
        if self.excitation is not None:
            d = float(self.excitation[self.n]) if self.n < self.excitation.shape[0] else 0.0
            self.n += 1
            terms = dict(cmd.terms)
            terms["u_exc"] = d
            u = min(max(cmd.force_n + d, -self.limit_n), self.limit_n)
            return Command(u, terms, cmd.limited)
        return cmd


def multisine(n_samples: int, bins: npt.NDArray[np.int64], amplitude_n: float) -> FloatArray:
    """One period (``n_samples``) of ``Σ_i A·cos(2π·k_i·n/N + φ_i)`` with Schroeder phases
    ``φ_i = −π·i·(i+1)/n_lines`` (low crest factor), ``A = amplitude_n`` per line [N]."""
    n = np.arange(n_samples)
    nl = bins.shape[0]
    out = np.zeros(n_samples)
    for i, k in enumerate(bins.tolist()):
        out += amplitude_n * np.cos(2 * np.pi * k * n / n_samples - np.pi * i * (i + 1) / nl)
    return out


def log_bins(n_samples: int, k_min: int, k_max: int, n_lines: int) -> npt.NDArray[np.int64]:
    """About ``n_lines`` distinct integer frequency bins, log-spaced between ``k_min`` and ``k_max``."""
    b = np.unique(np.round(np.logspace(math.log10(k_min), math.log10(k_max), n_lines)).astype(np.int64))
    return b[(b >= 1) & (b < n_samples // 2)]
