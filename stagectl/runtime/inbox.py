"""The loop's request inbox: typed requests queued by any thread, served in the loop thread at a cycle
boundary, each answered through its own :class:`concurrent.futures.Future`."""

from __future__ import annotations

import concurrent.futures
import queue
from collections.abc import Callable
from typing import Any

from stagectl.runtime.requests import LoopRequest

__all__ = ["Reply", "RequestInbox"]

#: the future a requester waits on: the loop's reply dict, or the exception the request raised
Reply = concurrent.futures.Future[dict[str, Any]]


class RequestInbox:
    """Thread-safe queue of ``(request, prepared, future)``; ``prepared`` marks a retune already designed in
    the caller's thread."""

    def __init__(self) -> None:
        self._q: queue.SimpleQueue[tuple[LoopRequest, bool, Reply]] = queue.SimpleQueue()

    def put(self, req: LoopRequest, prepared: bool = False) -> Reply:
        """Queue ``req`` (any thread); returns its future."""
        fut: Reply = concurrent.futures.Future()
        self._q.put((req, prepared, fut))
        return fut

    def serve(self, execute: Callable[[LoopRequest, bool, float, float], dict[str, Any]], t_s: float, x_m: float
              ) -> None:
        """``execute(request, prepared, t_s, x_m)`` for every queued request (loop thread, at loop time ``t_s``
        with the cycle's measured position ``x_m``); a raised exception goes onto the request's future.

        The usual case, an empty inbox, costs one ``empty()`` call (no ``queue.Empty`` raised and caught every
        cycle: ~0.5 µs); the loop thread is the only consumer, so a request queued right after the check is
        served at the next cycle boundary."""
        if self._q.empty():
            return
        while True:
            try:
                req, prepared, fut = self._q.get_nowait()
            except queue.Empty:
                return
            if not fut.set_running_or_notify_cancel():
                continue
            try:
                fut.set_result(execute(req, prepared, t_s, x_m))
            except BaseException as exc:  # noqa: BLE001 - handed to the requester
                fut.set_exception(exc)

    def fail_pending(self, error: Callable[[], BaseException]) -> None:
        """Fail every request still queued with a fresh ``error()`` (when ``run`` returns)."""
        while True:
            try:
                _, _, fut = self._q.get_nowait()
            except queue.Empty:
                return
            if fut.set_running_or_notify_cancel():
                fut.set_exception(error())
