"""One error hierarchy for the whole project (docs/architecture.md section 4).

``StageError`` is the root. Subclasses also derive from the matching built-in where one fits,
so callers can catch either (``ConfigError`` is a ``ValueError``, ``DriverTimeoutError`` a
``TimeoutError``). Vendor exceptions (python-can, canopen, pyserial) are converted at the driver
boundary with ``raise ... from``.
"""

from __future__ import annotations

from collections.abc import Iterable


class StageError(Exception):
    """Root of every error stagectl raises on purpose."""


class ConfigError(StageError, ValueError):
    """Invalid configuration. Carries *all* problems found, each prefixed with its key path.

    ``str(err)`` lists one problem per line, e.g.
    ``controller.pid.kp_n_m: must be > 0 (got -3 N/m)``.
    """

    def __init__(self, problems: str | Iterable[str]):
        if isinstance(problems, str):
            problems = [problems]
        self.problems: list[str] = list(problems)
        super().__init__("\n".join(self.problems) if self.problems else "invalid configuration")


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
