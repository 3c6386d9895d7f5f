"""One loop host for ``stagectl run`` and the daemon: the loop in its own thread, its sinks, its end.

:class:`LoopHost` takes an already-built loop (anything shaped like :class:`HostedLoop`, i.e. a
:class:`~stagectl.loop.ControlLoop`) and owns:

* the loop thread (``stagectl-loop``; the loop applies its real-time settings inside it);
* the telemetry sinks it was given: added before the thread starts, removed when the loop has ended;
* stopping: :meth:`stop` only sets an event the loop polls once per cycle, so it is safe from a signal handler
  or any thread; the loop then writes zero force and disables the drive itself (its ``run`` always does);
* :meth:`halt_motion`: a bounded deceleration before stopping (the daemon's SIGTERM path);
* the outcome: :attr:`result` (:class:`~stagectl.runtime.status.LoopResult`) or :attr:`error`, and
  :meth:`end_reason` for a log line.

Typical use::

    host = LoopHost(loop, sinks=[recorder])
    host.start(duration_s=10.0)
    while host.wait(1.0) is False: print(loop.status().x_m)
    result = host.finish(timeout_s=10.0)        # stop, join, remove sinks, re-raise a loop error
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from typing import Protocol

from stagectl.runtime.inbox import Reply
from stagectl.runtime.protocols import TelemetrySink
from stagectl.runtime.requests import LoopRequest, StopRequest
from stagectl.runtime.status import LoopResult, LoopState, LoopStatus

__all__ = ["HostedLoop", "LoopHost"]

log = logging.getLogger("stagectl.loop")


class HostedLoop(Protocol):
    """What the host needs from the loop (:class:`stagectl.loop.ControlLoop` provides it)."""

    def run(self, *, cycles: int | None = None, duration_s: float | None = None,
            stop: threading.Event | None = None) -> LoopResult: ...

    def add_sink(self, sink: TelemetrySink) -> None: ...

    def remove_sink(self, sink: TelemetrySink) -> None: ...

    def status(self, timing: bool = True) -> LoopStatus: ...

    def submit(self, req: LoopRequest) -> Reply: ...


#: LoopHost.wait's longest uninterrupted wait [s]: how late a pending signal's handler may run
WAIT_SLICE_S = 0.05


class LoopHost:
    """Runs ``loop`` in a thread (see the module docstring).

    Parameters
    ----------
    loop : HostedLoop
    sinks : sequence of TelemetrySink
        Registered with the loop for the duration of the run.
    on_exit : callable, optional
        Called in the loop thread when ``run`` has returned or raised (e.g. to wake a supervisor).
    """

    def __init__(self, loop: HostedLoop, *, sinks: Sequence[TelemetrySink] = (),
                 on_exit: Callable[[], None] | None = None) -> None:
        self.loop = loop
        self.sinks = tuple(sinks)
        self.on_exit = on_exit
        self.result: LoopResult | None = None
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        # set when the loop thread's work is over. Not Thread.join/is_alive: on CPython 3.11 a KeyboardInterrupt
        # (Ctrl-C, or the CLI's SIGTERM) raised inside Thread.join releases the thread's state lock and marks a
        # live thread stopped, so a `run` interrupted while it waited closed the devices under a running loop.
        self._ended = threading.Event()
        self._sinks_removed = False

    # ------------------------------------------------------------------ start / state
    def start(self, *, cycles: int | None = None, duration_s: float | None = None) -> None:
        """Register the sinks and start the loop thread (once)."""
        if self._thread is not None:
            raise RuntimeError("LoopHost.start: the loop was already started")
        for s in self.sinks:
            self.loop.add_sink(s)
        self._thread = threading.Thread(target=self._main, args=(cycles, duration_s), name="stagectl-loop",
                                        daemon=True)
        self._thread.start()

    def _main(self, cycles: int | None, duration_s: float | None) -> None:
        try:
            self.result = self.loop.run(cycles=cycles, duration_s=duration_s, stop=self._stop)
        except BaseException as exc:  # reported by the host's owner (finish / end_reason)
            self.error = exc
            log.exception("control loop ended with an error")
        finally:
            try:
                if self.on_exit is not None:
                    self.on_exit()
            finally:
                self._ended.set()

    @property
    def started(self) -> bool:
        return self._thread is not None

    @property
    def alive(self) -> bool:
        """The loop thread is running."""
        return self._thread is not None and not self._ended.is_set()

    def end_reason(self) -> str:
        """Why the loop ended, for a log line (``"unknown"`` while it runs)."""
        if self.error is not None:
            return f"{type(self.error).__name__}: {self.error}"
        return f"ended by {self.result.ended_by}" if self.result is not None else "unknown"

    # ------------------------------------------------------------------ stop
    def stop(self) -> None:
        """Ask the loop to end after its current cycle. Safe from a signal handler and from any thread."""
        self._stop.set()

    def wait(self, timeout_s: float | None) -> bool:
        """Wait up to ``timeout_s`` for the loop thread to end; True if it has ended (or never started).

        Waits in slices of at most ``WAIT_SLICE_S``: a signal (Ctrl-C, SIGTERM) that arrives in the instant before
        the thread blocks in the lock does not interrupt that wait (CPython checks pending signals between
        bytecodes, not inside the lock's wait), so its handler ran only when the whole wait ended. Seen as a
        60 s stall under load: the handler's KeyboardInterrupt then came out of finish() after its time-out,
        with the loop still running."""
        if self._thread is None:
            return True
        end = None if timeout_s is None else time.monotonic() + max(0.0, timeout_s)
        while True:
            slice_s = WAIT_SLICE_S if end is None else min(WAIT_SLICE_S, max(0.0, end - time.monotonic()))
            if self._ended.wait(slice_s):
                return True
            if end is not None and time.monotonic() >= end:
                return False

    def halt_motion(self, until_mono: float) -> None:
        """Decelerate to a stop before disabling, bounded by ``time.monotonic()`` deadline ``until_mono``.

        Skipped (logged) when the loop refuses (in fault the drive is already stopped; not running).
        """
        try:
            res = self.loop.submit(StopRequest()).result(timeout=max(0.05, until_mono - time.monotonic()))
        except Exception as exc:  # noqa: BLE001 - fault/not running: the loop stops the drive anyway
            log.info("stop before shutdown skipped: %s", exc)
            return
        x_stop = float(res["x_m"])
        while time.monotonic() < until_mono:
            st = self.loop.status(timing=False)
            if st.state is not LoopState.ACTIVE or abs(st.x_ref_m - x_stop) <= 1e-12 + 1e-9 * abs(x_stop):
                return
            time.sleep(0.005)
        log.warning("stage still decelerating at shutdown; disabling anyway")

    def remove_sinks(self) -> None:
        """Unregister the sinks (idempotent); done by :meth:`finish`, or by the owner once the loop ended."""
        if not self._sinks_removed:
            self._sinks_removed = True
            for s in self.sinks:
                self.loop.remove_sink(s)

    def finish(self, timeout_s: float) -> LoopResult | None:
        """Stop the loop, wait up to ``timeout_s``, unregister the sinks; re-raise the loop's error here.

        Returns the result, or None if the thread did not end in time (the drive may then still be enabled:
        the caller must disable it itself). An interrupt (a second Ctrl-C, or the CLI's SIGTERM) raised while it
        waits does not cut the wait short: the caller's next step is closing the devices, which must not happen
        under a loop still running its last cycle; it is raised again once the loop has ended (or the time-out).
        """
        end = time.monotonic() + timeout_s
        interrupt: KeyboardInterrupt | None = None
        while True:
            try:  # (stop inside: an interrupt right after it is taken here too)
                self.stop()
                ended = self.wait(max(0.0, end - time.monotonic()))
                break
            except KeyboardInterrupt as exc:  # the loop is ending (stop is set): wait for it, then re-raise
                interrupt = exc
        if interrupt is not None:
            if ended:
                self.remove_sinks()
            raise interrupt
        if not ended:
            log.error("control loop did not stop within %.1f s", timeout_s)
            return None
        self.remove_sinks()
        if self.error is not None:
            raise self.error
        return self.result
