"""In-position (settle) detector: pure, scalar, real-time safe.

The stage is *in position* when the reference is at rest (v_ref = a_ref = 0) and the tracking error has
stayed inside the window for the dwell time::

    in_position_k = at_rest_k  and  |e_j| <= tolerance_m  for every sample j with t_k − t_j < dwell_s

A sample outside the window, or any reference motion, clears it at once (and restarts the dwell). The
detector also times each move: ``settle_time_s`` is the time from the end of the commanded move (first
sample at rest) to the sample that declared in-position (``nan`` until the current move has settled).
YAML ``controller.settle``: ``tolerance_m`` [m], ``dwell_s`` [s]; ``move_s`` [s], ``move_force_n`` [N], ``move_min_m`` [m] and ``ahead_stiffness_fraction`` configure
the settle move of :mod:`stagectl.control.settle_move` (a controller element, not the detector's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from stagectl.schema import param


@dataclass(frozen=True)
class SettleConfig:
    """Settle-detector settings (YAML ``controller.settle``)."""

    tolerance_m: float = param(10e-9, unit="m", desc="in-position window: |x_ref − x| <= tolerance_m", gt=0.0)
    dwell_s: float = param(0.005, unit="s", desc="time the error must stay inside the window before the stage "
                           "is reported in position", ge=0.0)
    move_s: float = param(
        0.0, unit="s", desc="settle move (with an observer and feedforward kind: model): a move that ends with "
        "the stage behind the reference in its direction by more than move_min_m is continued from the stage's "
        "measured position and speed to the target by a quintic of this duration (the feedback's reference and "
        "the inertia feed-forward follow it; the reference is unchanged; 0: off; with move_force_n: the shortest "
        "duration)", ge=0.0, le=0.1)
    move_force_n: float | None = param(
        None, unit="N", desc="settle move: the inertial force m·|c̈| its quintic from rest may need at most (the "
        "stage's speed at the start is not counted); the duration "
        "is then the longer of move_s and sqrt(10/sqrt(3)·m·|e0|/move_force_n) for the error e0 at the end of "
        "the move, so a small error gets a short continuation, a large one a gentler one (None: always move_s)",
        gt=0.0)
    move_min_m: float | None = param(
        None, unit="m", desc="settle move: the least error behind the reference at the end of a move that starts "
        "one (None: controller.rest_spring_range_m, the range the rest spring covers)", gt=0.0)
    ahead_stiffness_fraction: float = param(
        0.0, desc="settle move from ahead (with move_s > 0): a move that ends with the stage ahead of the reference "
        "in its direction by more than move_min_m (on the stiff, pre-sliding side of its friction) gets the same "
        "continuation back to the target, and the friction spring's force along it, this fraction of the model's "
        "reversal stiffness theta·beta·sum(k) times the planned travel (beyond the first element's slip the "
        "model's Masing reversal curve, and never a friction outside the model's range), as feed-forward outside "
        "the observer; "
        "a stage still off by more than move_min_m/2 at its end gets a second one, its gain scaled by the "
        "travel the first made (0: off, the rest spring alone pulls the stage back)", ge=0.0, le=2.0)


@dataclass
class SettleState:
    """Diagnostics: in-position flag, time at rest [s], time inside the window [s], last settle time [s]."""

    in_position: bool = False
    at_rest_s: float = 0.0
    inside_s: float = 0.0
    settle_time_s: float = math.nan
    settled_moves: int = 0


class SettleDetector:
    """See module docstring. ``step`` is real-time safe (floats only)."""

    def __init__(self, cfg: SettleConfig | None = None) -> None:
        self.cfg = cfg if cfg is not None else SettleConfig()
        self.state = SettleState()

    def reset(self) -> None:
        """Forget the history (not in position; the next rest interval is timed from its start)."""
        self.state = SettleState()

    def step(self, dt: float, error_m: float, at_rest: bool) -> bool:
        """Feed one sample (period ``dt`` [s], error ``error_m`` [m], reference at rest); return in-position."""
        st = self.state
        if not at_rest:
            st.at_rest_s = 0.0
            st.inside_s = 0.0
            st.in_position = False
            st.settle_time_s = math.nan
            return False
        st.at_rest_s += dt
        if abs(error_m) <= self.cfg.tolerance_m:
            st.inside_s += dt
        else:
            st.inside_s = 0.0
            st.in_position = False
            return False
        # the sample that enters the window counts as the start of the dwell (inside_s = dt there)
        if not st.in_position and st.inside_s >= self.cfg.dwell_s - 1e-12:
            st.in_position = True
            if math.isnan(st.settle_time_s):
                st.settle_time_s = st.at_rest_s - st.inside_s
                st.settled_moves += 1
        return st.in_position
