"""The envelope every commissioning experiment stays inside, and the amplitudes derived from it.

All figures come from the configuration (``safety:``, ``controller.max_force_n``) and from the command line,
which may only *lower* them:

* travel window ``[x_lo, x_hi]``: the soft limits shrunk by ``MARGIN_FRACTION`` of their span on each side,
  then narrowed to ``--max-stroke`` around its centre ``x_c``; stroke ``S = x_hi − x_lo``;
* force ``F_max = FORCE_FRACTION · min(safety.max_force_n, controller.max_force_n, --max-force)``: below the
  safety clamp, so an experiment never runs into the force-saturation fault; what an experiment commands is
  also clamped at the drive's own limit once the stage is open (:func:`within_drive_limit`);
* velocity ``v_max = VELOCITY_FRACTION · min(safety.max_velocity_m_s, --max-velocity)``.

Everything else scales with ``S``, ``F_max`` and ``v_max`` (and later the measured mass), so a 2 kg nanometre
stage and a 50 kg ball-screw axis get experiments of their own size.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from stagectl.errors import ConfigError

MARGIN_FRACTION = 0.05
FORCE_FRACTION = 0.7
VELOCITY_FRACTION = 0.8


@dataclass(frozen=True)
class Envelope:
    """Limits of the experiments (SI units). Build with :func:`make_envelope`."""

    x_lo_m: float
    x_hi_m: float
    f_max_n: float
    v_max_m_s: float
    period_s: float
    following_error_m: float
    #: the force the opened drive can command [N] (:func:`within_drive_limit`; inf: not known or not lower)
    drive_limit_n: float = math.inf

    @property
    def f_cmd_n(self) -> float:
        """The largest force an experiment commands [N]: ``F_max``, or the drive's limit where that is lower."""
        return min(self.f_max_n, self.drive_limit_n)

    @property
    def stroke_m(self) -> float:
        return self.x_hi_m - self.x_lo_m

    @property
    def x_c_m(self) -> float:
        return 0.5 * (self.x_lo_m + self.x_hi_m)

    def as_dict(self) -> dict[str, float]:
        d = {"x_lo_m": self.x_lo_m, "x_hi_m": self.x_hi_m, "stroke_m": self.stroke_m, "x_c_m": self.x_c_m,
             "f_max_n": self.f_max_n, "v_max_m_s": self.v_max_m_s, "period_s": self.period_s}
        if math.isfinite(self.drive_limit_n):
            d["drive_limit_n"] = self.drive_limit_n
        return d


def _lower(name: str, given: float | None, configured: float, unit: str, key: str) -> float:
    if given is None:
        return configured
    if not math.isfinite(given):
        raise ConfigError(f"{name}: must be a finite number > 0 {unit} (got {given:g})")
    if not given > 0:
        raise ConfigError(f"{name}: must be > 0 {unit} (got {given:g})")
    if given > configured:
        raise ConfigError(f"{name}: {given:g} {unit} exceeds {key} {configured:g} {unit} (the command line can only "
                          "lower the configured limits)")
    return given


def within_drive_limit(env: Envelope, drive_limit_n: float | None) -> Envelope:
    """``env`` with ``drive_limit_n`` set where the opened drive commands less than ``F_max`` (CiA 402:
    ``io.drive.max_force_n`` and the drive's max torque 0x6072, which the driver reads at start-up and clamps
    every command to; e.g. a virtual drive given ``sim.drive.max_force_n: 3`` while the configuration allows
    10 N). The experiments' amplitudes still scale with ``F_max``; what
    they command is clamped at :attr:`Envelope.f_cmd_n`, so a recording's ``u`` is the force the drive applied.
    ``None``, a non-finite limit or one at or above ``F_max``: ``env`` unchanged."""
    if drive_limit_n is None or not (math.isfinite(drive_limit_n) and drive_limit_n > 0):
        return env
    if drive_limit_n >= env.f_max_n:
        return env
    return dataclasses.replace(env, drive_limit_n=drive_limit_n)


def make_envelope(*, min_position_m: float, max_position_m: float, safety_force_n: float, controller_force_n: float,
                  max_velocity_m_s: float, period_s: float, following_error_m: float,
                  max_stroke_m: float | None = None, max_force_n: float | None = None,
                  max_speed_m_s: float | None = None) -> Envelope:
    """The envelope of a configuration, lowered by the command-line limits (see the module docstring).

    Raises
    ------
    ConfigError
        A command-line limit that is not positive or exceeds the configured one (the message names the flag).
    """
    span = max_position_m - min_position_m
    if not span > 0:
        raise ConfigError(f"safety: min_position_m {min_position_m:g} m must be below max_position_m "
                          f"{max_position_m:g} m")
    lo = min_position_m + MARGIN_FRACTION * span
    hi = max_position_m - MARGIN_FRACTION * span
    stroke = _lower("--max-stroke", max_stroke_m, hi - lo, "m", "the soft-limit span (less margins)")
    c = 0.5 * (lo + hi)
    f_cfg = min(safety_force_n, controller_force_n)
    f = _lower("--max-force", max_force_n, f_cfg, "N", "min(safety.max_force_n, controller.max_force_n)")
    v = _lower("--max-velocity", max_speed_m_s, max_velocity_m_s, "m/s", "safety.max_velocity_m_s")
    return Envelope(c - 0.5 * stroke, c + 0.5 * stroke, FORCE_FRACTION * f, VELOCITY_FRACTION * v, period_s,
                    following_error_m)
