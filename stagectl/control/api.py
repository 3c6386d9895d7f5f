"""Types shared by the control laws and the loop.

Contract for every law (docs/architecture.md section 1.4): a frozen ``Config`` (fields declared with
``stagectl.schema.param``, physical units), a mutable ``State`` holding the diagnostic terms,
``step(dt, ...)`` that checks ``dt > 0`` and finite and never reads a clock or does I/O, and ``reset()``.

The loop sees one object, :class:`stagectl.control.controller.StageController`::

    ctl = StageController(config, period_s, model=None)   # derived gains/filters computed here, once
    ctl.reset(x_m)                                         # bumpless start at the measured position
    cmd = ctl.step(dt, x_meas_m, ref)                      # -> Command
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple


class Reference(NamedTuple):
    """Reference motion at one sample: position [m], velocity [m/s], acceleration [m/s²]."""

    x_m: float
    v_m_s: float = 0.0
    a_m_s2: float = 0.0


@dataclass(slots=True)
class Command:
    """Output of one control step.

    ``force_n`` is the force to command [N] (already clamped); ``terms`` holds the named contributions in
    newtons (``u_pid``, ``u_dob``, ``u_ff``, ``u_inertia`` ...) recorded in telemetry; ``limited`` names the
    limiters that were active this step (e.g. ``"force"``), kept apart from faults.
    """

    force_n: float
    terms: dict[str, float] = field(default_factory=dict)
    limited: tuple[str, ...] = ()
