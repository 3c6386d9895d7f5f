"""Typed loop requests, validated once on construction.

A request is a frozen dataclass; building it checks everything that can be checked without the loop
(types, finite numbers, exactly one of ``target_m``/``relative_m``, velocity > 0) and raises
:class:`RequestError` naming the field and its unit. The same classes serve three places:

* the CLI (``stagectl move``) builds a :class:`MoveRequest` before sending it, so a bad argument never
  leaves the process;
* the daemon parses each JSON line into one (:func:`parse_request`);
* the loop accepts them (:meth:`stagectl.loop.ControlLoop.submit`) and adds the checks only it can make:
  target against the soft limits and velocity against the limit (:meth:`MoveRequest.check_limits`), and in
  the loop thread a relative target against the limits (:meth:`MotionLimits.check_position`).

JSON form (control socket)::

    {"request": "move", "target_m": 0.001}            {"request": "move", "relative_m": -1e-4,
    {"request": "stop"}   {"request": "reset"}          "max_velocity_m_s": 0.002}
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Self, cast

from stagectl.errors import StageError, short

__all__ = [
    "ILC_ACTIONS",
    "SOCKET_KINDS",
    "IlcRequest",
    "LoopRequest",
    "MotionLimits",
    "MoveRequest",
    "RequestError",
    "ResetRequest",
    "RetuneRequest",
    "ShutdownRequest",
    "SocketRequest",
    "StopRequest",
    "parse_request",
]


class RequestError(StageError, ValueError):
    """A refused request; ``field`` names the offending key (``request``, ``target_m``, ...).

    The message starts with ``"<field>: "`` (the loop's and the control socket's convention).
    """

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        super().__init__(f"{field}: {message}")


def _number(field: str, value: object, unit: str) -> float:
    """``value`` as a finite float; RequestError naming ``field`` and ``unit`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise RequestError(field, f"expected a number in {unit}, got {short(value)}")
    try:
        v = float(value)
    except OverflowError:  # an integer literal with hundreds of digits (valid JSON)
        raise RequestError(field, f"must be finite ({unit}); got an integer too large for a float") from None
    if not math.isfinite(v):
        raise RequestError(field, f"must be finite ({unit}), got {short(value)}")
    return v


def _optional(field: str, value: object, unit: str) -> float | None:
    return None if value is None else _number(field, value, unit)


def check_fields(kind: str, fields: Mapping[str, object], allowed: tuple[str, ...]) -> None:
    """RequestError naming the first key of ``fields`` not in ``allowed`` (with the allowed ones)."""
    for key in fields:
        if key not in allowed:
            raise RequestError(key, f"unknown field for {short(kind)} "
                                    f"(allowed: {', '.join(sorted(allowed)) or 'none'})")


@dataclass(frozen=True)
class MotionLimits:
    """The limits a move is checked against (from the safety section): soft limits [m], velocity [m/s].

    A move is planned at most at ``move_velocity_m_s`` = ``move_velocity_fraction`` × ``max_velocity_m_s``: a
    reference at exactly the limit is crossed by the tracking overshoot and trips ``velocity_limit`` mid-move.
    """

    min_position_m: float
    max_position_m: float
    max_velocity_m_s: float
    move_velocity_fraction: float = 1.0

    @property
    def move_velocity_m_s(self) -> float:
        """The fastest planned move [m/s]."""
        return self.move_velocity_fraction * self.max_velocity_m_s

    def check_position(self, x_m: float, field: str) -> float:
        """``x_m`` inside the soft limits, else RequestError naming ``field``."""
        if not (self.min_position_m <= x_m <= self.max_position_m):
            raise RequestError(field, f"{x_m:g} m outside soft limits [{self.min_position_m:g}, "
                                      f"{self.max_position_m:g}] m")
        return x_m

    def check_relative(self, current_m: float, relative_m: float) -> float:
        """The target ``current_m + relative_m`` [m] inside the soft limits, else RequestError naming
        ``relative_m`` with the distance the user gave, where it would end and the limits."""
        x_m = current_m + relative_m
        if not (self.min_position_m <= x_m <= self.max_position_m):
            raise RequestError("relative_m", f"{relative_m:g} m from the current target {current_m:.9g} m ends at "
                                             f"{x_m:.9g} m, outside soft limits [{self.min_position_m:g}, "
                                             f"{self.max_position_m:g}] m")
        return x_m


@dataclass(frozen=True)
class MoveRequest:
    """Move to ``target_m`` [m] or by ``relative_m`` [m] (relative to the current move's target), optionally
    at most ``max_velocity_m_s`` [m/s]. Exactly one of ``target_m`` and ``relative_m``.

    Loop reply: ``{"target_m", "duration_s"}``.
    """

    KIND: ClassVar[str] = "move"
    FIELDS: ClassVar[tuple[str, ...]] = ("target_m", "relative_m", "max_velocity_m_s")

    target_m: float | None = None
    relative_m: float | None = None
    max_velocity_m_s: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "target_m", _optional("target_m", self.target_m, "m"))
        object.__setattr__(self, "relative_m", _optional("relative_m", self.relative_m, "m"))
        v = _optional("max_velocity_m_s", self.max_velocity_m_s, "m/s")
        if (self.target_m is None) == (self.relative_m is None):
            raise RequestError("target_m", "give exactly one of target_m (absolute, m) or relative_m (m)")
        if v is not None and not v > 0.0:
            raise RequestError("max_velocity_m_s", f"must be > 0 m/s (got {v:g} m/s)")
        object.__setattr__(self, "max_velocity_m_s", v)

    @classmethod
    def from_fields(cls, fields: Mapping[str, object]) -> MoveRequest:
        """From a mapping (keyword arguments, a JSON object without its envelope); unknown keys refused."""
        check_fields(cls.KIND, fields, cls.FIELDS)
        return cls(**cast("dict[str, Any]", dict(fields)))  # __post_init__ checks every value once

    def check_limits(self, limits: MotionLimits) -> None:
        """The checks that need the stage's limits: an absolute target inside the soft limits, the velocity at
        most the planned fraction of the limit (:attr:`MotionLimits.move_velocity_m_s`). RequestError naming
        the field."""
        if self.target_m is not None:
            limits.check_position(self.target_m, "target_m")
        v = self.max_velocity_m_s
        if v is not None and v > limits.move_velocity_m_s:
            raise RequestError("max_velocity_m_s", f"must be > 0 and <= {limits.move_velocity_m_s:.6g} m/s "
                               f"(safety.move_velocity_fraction {limits.move_velocity_fraction:g} of "
                               f"max_velocity_m_s {limits.max_velocity_m_s:g} m/s, room for tracking overshoot "
                               f"below the velocity_limit fault) (got {v:g} m/s)")

    def to_json(self) -> dict[str, object]:
        """The control-socket line (without ``id``)."""
        out: dict[str, object] = {"request": self.KIND}
        for name in self.FIELDS:
            value = getattr(self, name)
            if value is not None:
                out[name] = value
        return out


class _NoFieldRequest:
    """A request without fields: parsed from a line that carries none, sent as ``{"request": KIND}``."""

    KIND: ClassVar[str]
    FIELDS: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def from_fields(cls, fields: Mapping[str, object]) -> Self:
        check_fields(cls.KIND, fields, cls.FIELDS)
        return cls()

    def to_json(self) -> dict[str, object]:
        return {"request": self.KIND}


@dataclass(frozen=True)
class StopRequest(_NoFieldRequest):
    """Decelerate and hold. Loop reply: ``{"x_m"}`` (where the stage will stand)."""

    KIND: ClassVar[str] = "stop"


@dataclass(frozen=True)
class ResetRequest(_NoFieldRequest):
    """Clear a latched fault, re-enable the drive, restart bumplessly at the measured position (a no-op when no
    fault is latched). Loop reply: ``{"state", "cleared"}``."""

    KIND: ClassVar[str] = "reset"


@dataclass(frozen=True)
class RetuneRequest:
    """Swap in a new controller tuning (bumpless; the controller's job). Loop reply: ``{"retuned": True}``.

    ``controller_config`` is the controller's own typed configuration (``ControllerConfig`` for
    :class:`~stagectl.control.controller.StageController`); the loop does not look inside it.
    """

    KIND: ClassVar[str] = "retune"
    FIELDS: ClassVar[tuple[str, ...]] = ("controller_config",)

    controller_config: object

    @classmethod
    def from_fields(cls, fields: Mapping[str, object]) -> RetuneRequest:
        check_fields(cls.KIND, fields, cls.FIELDS)
        return cls(controller_config=fields.get("controller_config"))

    def __post_init__(self) -> None:
        if self.controller_config is None:
            raise RequestError("controller_config", "required for retune")


@dataclass(frozen=True)
class ShutdownRequest(_NoFieldRequest):
    """End :meth:`~stagectl.loop.ControlLoop.run` after this cycle. Loop reply: ``{"cycles"}``."""

    KIND: ClassVar[str] = "shutdown"


ILC_ACTIONS = ("start", "stop", "save", "load", "status")


@dataclass(frozen=True)
class IlcRequest:
    """Learning feed-forward (``ilc:``): ``action`` start | stop | save | load | status; ``motion`` names the
    saved signal for save (default: the running motion's name) and load. Loop reply: the learner's status
    (``motion``, ``iteration``, ``rms_m`` per repetition, ...), plus ``saved``/``loaded`` paths."""

    KIND: ClassVar[str] = "ilc"
    FIELDS: ClassVar[tuple[str, ...]] = ("action", "motion")

    action: str = "status"
    motion: str | None = None

    def __post_init__(self) -> None:
        if self.action not in ILC_ACTIONS:
            raise RequestError("action", f"must be one of {', '.join(ILC_ACTIONS)} (got {self.action!r})")
        if self.motion is not None and not isinstance(self.motion, str):
            raise RequestError("motion", f"must be a name of letters, digits, '._-' (got {self.motion!r})")
        if self.action == "load" and self.motion is None:
            raise RequestError("motion", "load needs the motion name of the saved signal")

    @classmethod
    def from_fields(cls, fields: Mapping[str, object]) -> IlcRequest:
        check_fields(cls.KIND, fields, cls.FIELDS)
        return cls(**cast("dict[str, Any]", dict(fields)))

    def to_json(self) -> dict[str, object]:
        out: dict[str, object] = {"request": self.KIND, "action": self.action}
        if self.motion is not None:
            out["motion"] = self.motion
        return out


LoopRequest = MoveRequest | StopRequest | ResetRequest | RetuneRequest | ShutdownRequest | IlcRequest
#: a loop request a control-socket client may send (retune comes from SIGHUP, shutdown from SIGTERM)
SocketRequest = MoveRequest | StopRequest | ResetRequest | IlcRequest


#: the requests a control-socket client may send, by kind (retune comes from SIGHUP, shutdown from SIGTERM)
SOCKET_REQUESTS: dict[str, type[SocketRequest]] = {r.KIND: r for r in (MoveRequest, StopRequest, ResetRequest,
                                                                       IlcRequest)}
#: kinds a control-socket client may send
SOCKET_KINDS = tuple(SOCKET_REQUESTS)


def parse_request(kind: str, line: Mapping[str, object], envelope: tuple[str, ...] = ("request", "id")
                  ) -> SocketRequest:
    """A control-socket request of a loop kind (``move``, ``stop``, ``reset``) from its decoded JSON object.

    ``envelope`` keys (``request``, ``id``) are the socket's own. Raises RequestError: unknown kind (field
    ``request``), unknown key (field = the key, with the allowed ones), bad values (field and unit).
    """
    cls = SOCKET_REQUESTS.get(kind)
    if cls is None:
        raise RequestError("request", f"unknown request {short(kind)}; one of {', '.join(SOCKET_KINDS)}")
    return cls.from_fields({k: v for k, v in line.items() if k not in envelope})
