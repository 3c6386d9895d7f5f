"""One error hierarchy for the whole project (docs/architecture.md section 4).

``StageError`` is the root. Subclasses also derive from the matching built-in where one fits,
so callers can catch either (``ConfigError`` is a ``ValueError``, ``DriverTimeoutError`` a
``TimeoutError``). Vendor exceptions (python-can, canopen, pyserial) are converted at the driver
boundary with ``raise ... from``.
"""

from __future__ import annotations

import reprlib
from collections.abc import Iterable

__all__ = ["ConfigError", "DataError", "DriveFault", "DriverError", "DriverIOError", "DriverInitError",
           "DriverTimeoutError", "StageError", "cut", "interrupt_exit_code", "interrupt_name", "set_interrupt_name", "short"]

#: what interrupted this process last: "Ctrl-C" (SIGINT) or "SIGTERM"; set by the CLI's signal handlers, read
#: where an interrupt is reported (a KeyboardInterrupt does not say which signal raised it)
_interrupt = ["Ctrl-C"]


def interrupt_name() -> str:
    """"Ctrl-C" or "SIGTERM": the signal behind the latest KeyboardInterrupt (see :mod:`stagectl.cli`)."""
    return _interrupt[0]


def interrupt_exit_code() -> int:
    """The exit code of an interrupted command: 130 after Ctrl-C, 143 after SIGTERM (128 + signal number)."""
    return 143 if _interrupt[0] == "SIGTERM" else 130


def set_interrupt_name(name: str) -> None:
    _interrupt[0] = name


#: the longest single problem line a ConfigError keeps, and how many lines it keeps (the rest are counted)
MAX_PROBLEM_CHARS = 400
MAX_PROBLEMS = 100

_REPR = reprlib.Repr()
_REPR.maxlevel = 3
_REPR.maxstring = 60
_REPR.maxother = 60
_REPR.maxlong = 40
for _attr in ("maxlist", "maxtuple", "maxdict", "maxset", "maxfrozenset", "maxdeque", "maxarray"):
    setattr(_REPR, _attr, 6)


def short(value: object, limit: int = 60) -> str:
    """A bounded ``repr`` of ``value`` for error messages: at most ``limit`` characters, whatever its size.

    Containers are shortened element-wise (``reprlib``: a few elements, 3 levels deep) so a huge or
    self-referencing value costs no more time than a small one; integers too long to print (Python refuses
    ``str`` of > 4300 digits) are described by their digit count; a value whose ``repr`` raises is named by
    its type. ``short("abc") == "'abc'"``, ``short(10**400) == "<integer of 401 digits>"``.
    """
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 128:
        digits = len(str(value)) if value.bit_length() < 13000 else int(value.bit_length() * 0.30103) + 1
        text = f"<integer of {digits - (value < 0)} digits>" if value.bit_length() < 13000 \
            else f"<integer of about {digits} digits>"
    elif isinstance(value, str):  # reprlib would cut any string at 60 characters, whatever the limit
        text = repr(value[:limit])
    else:
        try:
            text = _REPR.repr(value)
        except Exception:  # noqa: BLE001 - a hostile __repr__ must not replace the error being reported
            text = f"<{type(value).__name__}>"
    limit = max(limit, 8)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def cut(text: str, limit: int = 200) -> str:
    """``text`` (a message, a header) on one line and at most ``limit`` characters, unquoted."""
    text = " ".join(text.split())
    return text if len(text) <= limit else text[:max(limit, 8) - 3] + "..."


def _bounded(line: str) -> str:
    if len(line) <= MAX_PROBLEM_CHARS:
        return line
    return f"{line[:MAX_PROBLEM_CHARS]}... ({len(line) - MAX_PROBLEM_CHARS} more characters)"


class StageError(Exception):
    """Root of every error stagectl raises on purpose."""


class ConfigError(StageError, ValueError):
    """Invalid configuration. Carries *all* problems found, each prefixed with its key path.

    ``str(err)`` lists one problem per line, e.g.
    ``controller.pid.kp_n_m: must be > 0 (got -3 N/m)``.

    Bounded: each line is cut at :data:`MAX_PROBLEM_CHARS` characters, and the message (``str(err)``) shows the
    first :data:`MAX_PROBLEMS` lines and a line counting the rest (:meth:`shown`), so a hostile file cannot make
    an error text of megabytes. ``problems`` keeps every (cut) line, so that callers that collect the problems
    of several parts count them all.
    """

    def __init__(self, problems: str | Iterable[str]):
        if isinstance(problems, str):
            problems = [problems]
        self.problems: list[str] = [_bounded(str(line)) for line in problems]
        super().__init__("\n".join(self.shown()) if self.problems else "invalid configuration")

    def shown(self) -> list[str]:
        """The lines to print: the first MAX_PROBLEMS problems, then ``... and N more problems``."""
        more = len(self.problems) - MAX_PROBLEMS
        return self.problems if more <= 0 else [*self.problems[:MAX_PROBLEMS], f"... and {more} more problems"]


class DataError(StageError, ValueError):
    """A recording (CSV) cannot be used; the message names the row and column."""


class DriverError(StageError):
    """Base of all device/driver errors."""


class DriverInitError(DriverError):
    """Opening or configuring a device failed (bad port, SDO abort, no boot-up...)."""


class DriverIOError(DriverError, OSError):
    """Cyclic I/O failed (bus error, write failed, port closed)."""


class DriverTimeoutError(DriverError, TimeoutError):
    """A device did not answer within its time limit."""


class DriveFault(DriverError):
    """The drive reported a fault (CiA 402 FAULT state or EMCY). ``code`` is the CiA 301 error code."""

    def __init__(self, message: str, code: int = 0):
        self.code = int(code)
        super().__init__(f"{message} (error code 0x{self.code:04X})" if code else message)
