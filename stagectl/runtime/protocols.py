"""What the loop needs from the objects it drives (structural types; the real ones live in ``control/``)."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from stagectl.control.api import Command, Reference

__all__ = ["Controller", "HoldsOnStale", "Learner", "NamesTerms", "PreparesRetune", "ReferenceSource", "RunsScenarios",
           "ScalesWithTiming", "TakesLearnedForce", "TelemetrySink"]


class Controller(Protocol):
    """What the loop needs from :class:`stagectl.control.controller.StageController`.

    A controller may also offer ``request_retune(cfg)`` (prepare in the caller's thread, swap at its next
    step) and ``term_names`` (its telemetry terms); the loop uses them when present.
    """

    def reset(self, x_m: float) -> None: ...

    def step(self, dt: float, x_meas_m: float, ref: Reference) -> Command: ...

    def retune(self, cfg: Any) -> None: ...


@runtime_checkable
class PreparesRetune(Protocol):
    """A controller that designs a new tuning in the caller's thread and swaps it in at its next step
    (:class:`~stagectl.control.controller.StageController`); bad tunings raise in ``request_retune``."""

    def request_retune(self, cfg: Any) -> None: ...


@runtime_checkable
class PacesDevice(Protocol):
    """A SYNC producer that tells whether its device is behind (``loop.pace_cycles``, device time only:
    :meth:`stagectl.drivers.cia402.Cia402Drive.behind`): True = do not start a cycle in this slot."""

    def behind(self, unanswered: int, slots: int) -> bool: ...


@runtime_checkable
class TakesLearnedForce(Protocol):
    """A controller with the learned feed-forward input: ``step(..., u_learn_n)`` adds it to the command as an
    applied force (the observer counts it as applied, so it does not fight it)."""

    accepts_learned_force: bool

    def step(self, dt: float, x_meas_m: float, ref: Reference, u_learn_n: float = 0.0,
             learn_active: bool = False) -> Command: ...


class Learner(Protocol):
    """The loop's learning hook (:class:`stagectl.control.ilc.IlcLearner`): stepped once per active cycle
    before the controller, frozen on a fault, driven by ``ilc`` requests at the cycle boundary. ``active``: it
    learns from or applies a force to this cycle's motion (the controller then keeps its own model still)."""

    active: bool

    @property
    def columns(self) -> tuple[str, ...]: ...

    def step(self, t_s: float, e_m: float, fresh: bool = True, moving: bool = True) -> float: ...

    def row(self) -> tuple[float, ...]: ...

    def freeze(self, reason: str) -> None: ...

    def request(self, action: str, motion: str | None) -> dict[str, Any]: ...

    def prepare(self) -> None: ...

    def status(self) -> dict[str, Any]: ...


@runtime_checkable
class RunsScenarios(Protocol):
    """A reference source that can start a named motion, repeated (:class:`~stagectl.control.reference.
    TrajectoryReference`): what ``ilc start`` with a motion name runs."""

    def run_scenario(self, t_s: float, name: str) -> float: ...


@runtime_checkable
class KnowsStop(Protocol):
    """A reference source that knows where the reference next comes to rest without reversing first
    (:meth:`~stagectl.control.trajectory.TrajectoryGenerator.stop_m`; NaN: a reversal may come first)."""

    def stop_m(self) -> float: ...


@runtime_checkable
class UsesStop(Protocol):
    """A controller whose friction feed-forward keeps its look-ahead on the reference's travel to that rest
    (:func:`stagectl.control.friction_ff.bounded_ahead`), told each cycle before its step or hold."""

    def set_reference_stop(self, x_m: float) -> None: ...


@runtime_checkable
class HoldsOnStale(Protocol):
    """A controller with a stale-cycle step (:meth:`StageController.hold`): feedback held, feed-forward
    along the reference. Without it the loop holds the last force."""

    def hold(self, dt: float, ref: Reference) -> Command: ...


@runtime_checkable
class PredictsNextForce(Protocol):
    """A controller that predicts the force of the period after its last command (for an actuator's command
    schedule, :meth:`ForceActuator.write_schedule`): the increment û_{k+1} − u_k [N] of its last step or hold.
    (Its observer is not told when the actuator used it: it takes the force error for a disturbance.)"""

    def next_force_increment_n(self) -> float: ...


@runtime_checkable
class ScalesWithTiming(Protocol):
    """A controller whose feedback can be slowed down by a factor (the effective sample interval over T)."""

    def set_timing_scale(self, scale: float) -> None: ...


@runtime_checkable
class NamesTerms(Protocol):
    """A controller that names its telemetry terms (the loop's telemetry columns after the base ones)."""

    term_names: tuple[str, ...]


class ReferenceSource(Protocol):
    """A reference generator the loop samples once per cycle."""

    def sample(self, t_s: float) -> Reference: ...

    def hold(self, t_s: float, x_m: float) -> None:
        """Stand still at ``x_m`` from ``t_s`` on (start, reset)."""

    def move(self, t_s: float, target_m: float, max_velocity_m_s: float | None) -> float:
        """Start a move at ``t_s`` to ``target_m``; returns its duration [s]."""

    def stop(self, t_s: float) -> float:
        """Decelerate and hold; returns the position where it will stand [m]."""

    @property
    def target_m(self) -> float:
        """The position the reference is heading to (or holding) [m]."""


class TelemetrySink(Protocol):
    """``append(row)`` is called in the loop thread once per cycle; it must not block."""

    def append(self, row: tuple[float, ...]) -> None: ...
