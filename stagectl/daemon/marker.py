"""The run marker and the unclean-end latch.

``stagectl.running`` in the state directory (:attr:`ServicePaths.marker_dir`) exists while a run may have the
drive enabled: written (fsynced) before the loop thread may enable the drive, removed on a clean stop
(SIGTERM/SIGINT) once the drive is disabled and telemetry flushed, and after a start-up failure that left the
drive disabled; kept after a failure while running (the loop died). If it exists at start, the previous run
ended abnormally (SIGKILL, watchdog SIGABRT, crash, power loss): :class:`UncleanLatch` latches the loop in
fault ``unclean_shutdown`` before it starts, and only an explicit ``reset`` request enables the drive. The
old marker is kept until that reset, so a stop or a start-up failure before it does not lose the latch.
"""

from __future__ import annotations

import datetime
import json
import logging
import os
from pathlib import Path
from typing import Any, Protocol

from stagectl.runtime.status import FaultInfo, LoopStatus

__all__ = ["UNCLEAN_FAULT", "RunMarker", "UncleanLatch"]

log = logging.getLogger("stagectl.daemon")

UNCLEAN_FAULT = "unclean_shutdown"


def utc_now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


class RunMarker:
    """``<dir>/stagectl.running``: present while a run may have the drive enabled (see the module docstring).

    Content: one JSON object ``{"pid", "started_utc", "config"}``. Written atomically (temporary file, fsync,
    rename, fsync of the directory) so that it survives a power loss; removal is not fsynced (a marker that
    reappears after a power loss only latches once more: the safe side).
    """

    NAME = "stagectl.running"

    def __init__(self, directory: Path) -> None:
        self.path = Path(directory) / self.NAME

    def read(self) -> dict[str, Any] | None:
        """The marker's content, None if there is no marker. An unreadable or garbled marker still counts."""
        try:
            text = self.path.read_text(encoding="utf-8", errors="replace")
        except FileNotFoundError:
            return None
        except OSError as exc:
            return {"unreadable": f"{exc.strerror or exc}"}
        try:
            data = json.loads(text)
        except ValueError:
            data = None
        return data if isinstance(data, dict) else {"content": text[:200]}

    def write(self, config_path: Path) -> None:
        """Record this run (raises OSError: start-up must not go on without the marker)."""
        info = {"pid": os.getpid(), "started_utc": utc_now(), "config": str(config_path)}
        self.path.parent.mkdir(parents=True, mode=0o750, exist_ok=True)
        tmp = self.path.with_name(self.NAME + ".tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o640)
        try:
            os.write(fd, (json.dumps(info) + "\n").encode())
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, self.path)
        dfd = os.open(self.path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)


def unclean_cause(info: dict[str, Any]) -> str:
    """The ``unclean_shutdown`` fault's cause text from the old marker's content."""
    who = f"pid {info.get('pid', '?')}, started {info.get('started_utc', '?')}"
    if "pid" not in info:
        who = f"marker {json.dumps(info)}"
    return (f"the previous run ({who}) did not stop cleanly (killed, crashed, watchdog abort or power loss); "
            f"detected at start {utc_now()}; check the stage, then `stagectl reset` to enable the drive")


class Latchable(Protocol):
    def latch_fault(self, name: str, cause: str) -> FaultInfo: ...


class UncleanLatch:
    """The marker's life over one run of the service (read at start, armed before the loop, settled at stop)."""

    def __init__(self, marker: RunMarker, config_path: Path) -> None:
        self.marker = marker
        self.config_path = config_path
        self.inherited: dict[str, Any] | None = None  # the previous run's marker, until `reset` acknowledges it
        self.latched = False

    def read(self) -> None:
        """At start: look for the previous run's marker (logged)."""
        self.inherited = self.marker.read()
        if self.inherited is not None:
            log.warning("previous run did not stop cleanly (marker %s: %s): starting LATCHED in fault %s, "
                        "drive not enabled until `stagectl reset`", self.marker.path, json.dumps(self.inherited),
                        UNCLEAN_FAULT)

    def arm(self, loop: Latchable) -> None:
        """Before the loop thread starts: latch ``unclean_shutdown`` (old marker kept), else write the marker."""
        if self.inherited is not None:
            loop.latch_fault(UNCLEAN_FAULT, unclean_cause(self.inherited))
            self.latched = True
        else:
            self.marker.write(self.config_path)

    @staticmethod
    def is_latched(st: LoopStatus) -> bool:
        """The loop holds the ``unclean_shutdown`` fault."""
        return st.fault is not None and st.fault.name == UNCLEAN_FAULT

    def pending(self, st: LoopStatus | None) -> bool:
        """The previous run's unclean end is not acknowledged yet: no ``reset`` has cleared the latch (or the
        latch was never applied, e.g. start-up failed before it). ``st``: the loop's status, if it exists."""
        if self.inherited is None:
            return False
        if not self.latched or st is None:
            return True
        return self.is_latched(st)

    def track(self, st: LoopStatus) -> None:
        """After the ``reset`` that cleared ``unclean_shutdown``: the marker now stands for this run."""
        if self.inherited is None or not self.latched or self.pending(st):
            return
        try:
            self.marker.write(self.config_path)
        except OSError as exc:  # the old marker is still there: a crash still latches the next start
            log.error("cannot rewrite the run marker %s: %s", self.marker.path, exc.strerror or exc)
            return
        log.warning("fault %s cleared by reset; marker %s now records this run", UNCLEAN_FAULT, self.marker.path)
        self.inherited = None

    def settle(self, *, failed_while_running: bool, loop_alive: bool, drive_enabled: bool, drive: str,
               st: LoopStatus | None) -> None:
        """At stop: remove the marker if this stop is clean for the drive (a stop request or a failed start-up,
        the loop has ended, the drive is not enabled, no inherited latch left); otherwise keep it, logged."""
        path = self.marker.path
        if failed_while_running:
            log.error("run marker %s kept: the service failed while running; the next start is latched", path)
        elif loop_alive:
            log.error("run marker %s kept: the control loop did not stop", path)
        elif drive_enabled:
            log.error("run marker %s kept: the drive is still enabled (%s)", path, drive)
        elif self.pending(st):
            log.warning("run marker %s kept: fault %s was not cleared by reset; the next start is latched too",
                        path, UNCLEAN_FAULT)
        else:
            try:
                self.marker.remove()
            except OSError as exc:
                log.error("cannot remove the run marker %s: %s (the next start will be latched)", path,
                          exc.strerror or exc)
