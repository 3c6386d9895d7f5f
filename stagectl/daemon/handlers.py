"""Control-socket request handlers: one function per request kind.

Each handler takes the service (:class:`ServiceView`) and the decoded JSON object and returns a reply dict,
or a Future resolving to one (a loop request is answered once the loop has executed it). Bad input raises
:class:`~stagectl.runtime.requests.RequestError` naming the field; the server turns it into an error reply.
Handlers run in the control thread and never block.

===========  ====================================================================================
``status``   everything an operator needs (``StageService.status``)
``move``     :class:`~stagectl.runtime.requests.MoveRequest` (``target_m`` | ``relative_m``, ``max_velocity_m_s``)
``stop``     :class:`~stagectl.runtime.requests.StopRequest`
``reset``    :class:`~stagectl.runtime.requests.ResetRequest`
``gains``    the controller tuning in force and the last reload's outcome
``record``   ``action: start`` + ``name`` / ``action: stop``: a named telemetry recording
``subscribe`` the live telemetry stream of ``stagectl scope`` (:mod:`stagectl.daemon.stream`)
``fault``    debug: inject a fault into a *simulated* plant (``daemon.allow_fault_injection``)
===========  ====================================================================================
"""

from __future__ import annotations

import concurrent.futures
import threading
from collections.abc import Callable, Mapping
from typing import Any, Protocol

from stagectl.config.daemon import DaemonConfig
from stagectl.daemon.lifecycle import Assembly
from stagectl.daemon.paths import ServicePaths
from stagectl.daemon.reload import Reloader
from stagectl.daemon.stream import handle_subscribe
from stagectl.daemon.telemetry import TelemetryWriter
from stagectl.daemon.remote import LoopLike
from stagectl.errors import short
from stagectl.outputs import plain
from stagectl.runtime.requests import SOCKET_KINDS, RequestError, check_fields, parse_request

__all__ = ["HANDLERS", "READ_ONLY_REQUESTS", "ServiceView", "dispatch", "dispatch_observer"]

Reply = dict[str, Any]
ReplyOrFuture = Reply | concurrent.futures.Future[Reply]


class ServiceView(Protocol):
    """What the handlers need from :class:`~stagectl.daemon.service.StageService`."""

    cfg: DaemonConfig
    asm: Assembly | None
    writer: TelemetryWriter | None

    reloader: Reloader
    paths: ServicePaths

    def status(self) -> dict[str, Any]: ...

    def need_loop(self) -> LoopLike: ...


def _only(req: Mapping[str, object], *allowed: str) -> None:
    """The request line carries no key but the envelope (``request``, ``id``) and ``allowed``."""
    check_fields(str(req.get("request")), {k: v for k, v in req.items() if k not in ("request", "id")}, allowed)


#: the longest text a status/gains reply carries in one field (reload errors, fault causes, telemetry errors)
MAX_REPLY_TEXT = 2000


def bounded_texts(value: Any, limit: int = MAX_REPLY_TEXT) -> Any:
    """``value`` (plain JSON data) with every string longer than ``limit`` cut and marked, so a status or
    gains reply stays far below the reply size limit whatever an error message held."""
    if isinstance(value, str):
        if len(value) <= limit:
            return value
        return f"{value[:limit]}... ({len(value) - limit} more characters)"
    if isinstance(value, Mapping):
        return {k: bounded_texts(v, limit) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [bounded_texts(v, limit) for v in value]
    return value


def handle_status(svc: ServiceView, req: Mapping[str, object]) -> ReplyOrFuture:
    _only(req)
    return {"status": bounded_texts(svc.status())}


def handle_loop_request(svc: ServiceView, req: Mapping[str, object]) -> ReplyOrFuture:
    """``move``, ``stop``, ``reset``: parsed (and validated) first, then handed to the loop."""
    typed = parse_request(str(req.get("request")), req)
    # the loop's own future: the reply is made plain JSON when it is encoded, in the control thread (never in
    # the loop thread), and a reply timeout cancels it, so a request still queued then is never executed
    return svc.need_loop().submit(typed)


def handle_gains(svc: ServiceView, req: Mapping[str, object]) -> ReplyOrFuture:
    _only(req)
    ctl = plain(svc.asm.controller_config if svc.asm else None, json=True)
    ff = ctl.get("feedforward") if isinstance(ctl, dict) else None
    if isinstance(ff, dict) and isinstance(ff.get("model_file"), str):
        # the config names it relative to its own folder: absolute, so the section pasted elsewhere still works
        ff["model_file"] = str((svc.paths.config.parent / ff["model_file"]).resolve())
    return {"controller": ctl, "reload": bounded_texts(svc.reloader.status)}


def handle_record(svc: ServiceView, req: Mapping[str, object]) -> ReplyOrFuture:
    _only(req, "action", "name")
    writer = svc.writer
    if writer is None:
        raise RequestError("request", "telemetry is disabled (daemon.telemetry.enabled: false)")
    action = req.get("action")
    if action == "start":
        name = req.get("name")
        if not isinstance(name, str):
            raise RequestError("name", "must be a plain file name of letters, digits, '._-' "
                                       f"(got {short(name)})")
        try:
            path = writer.record_start(name)
        except OSError as exc:
            raise RequestError("name", f"cannot create the recording: {exc.strerror or exc}") from None
        return {"recording": str(path)}
    if action == "stop":
        # waits for the writer to drain and fsync: off the control thread, so other clients are served
        fut: concurrent.futures.Future[Reply] = concurrent.futures.Future()

        def stop_recording() -> None:
            try:
                fut.set_result({"recording": writer.record_stop()})
            except Exception as exc:  # noqa: BLE001 - "action: no recording is running" -> error reply
                fut.set_exception(exc)

        threading.Thread(target=stop_recording, name="stagectl-record-stop", daemon=True).start()
        return fut
    raise RequestError("action", f"must be start or stop (got {short(action)})")


def handle_fault(svc: ServiceView, req: Mapping[str, object]) -> ReplyOrFuture:
    """Debug: inject a fault into the *simulated* plant (``daemon.allow_fault_injection`` and sim only)."""
    asm = svc.asm
    if asm is None or asm.inject_fault is None or not (svc.cfg.allow_fault_injection and asm.simulated):
        raise RequestError("request", "fault injection is only available on a simulated plant with "
                                      "daemon.allow_fault_injection: true")
    kw = {k: v for k, v in req.items() if k not in ("request", "id")}
    kind = kw.pop("kind", None)
    if not isinstance(kind, str):
        raise RequestError("kind", "name the fault to inject")
    res = asm.inject_fault(kind, **kw)
    if isinstance(res, concurrent.futures.Future):  # the loop process injects it at its next cycle boundary
        fut: concurrent.futures.Future[Reply] = res
        return fut
    return {"injected": kind, **(res if isinstance(res, dict) else {})}


HANDLERS: dict[str, Callable[[ServiceView, Mapping[str, object]], ReplyOrFuture]] = {
    "status": handle_status,
    **{kind: handle_loop_request for kind in SOCKET_KINDS},
    "record": handle_record,
    "gains": handle_gains,
    "fault": handle_fault,
    "subscribe": handle_subscribe,
}


#: requests that work but are not advertised in error messages (fault injection on a simulated plant)
DEBUG_REQUESTS = ("fault",)


#: what the read-only observer socket serves (kinds not registered in HANDLERS are skipped)
READ_ONLY_REQUESTS = ("status", "gains", "subscribe")


def dispatch_observer(svc: ServiceView, req: Mapping[str, object]) -> ReplyOrFuture:
    """Route one request from the observer socket: only :data:`READ_ONLY_REQUESTS`; anything that could move,
    reset, record or inject is refused naming the field ``request``."""
    kind = req.get("request")
    allowed = [k for k in READ_ONLY_REQUESTS if k in HANDLERS]
    if kind not in allowed:
        shown = kind if isinstance(kind, str) and len(kind) <= 40 else "that"
        raise RequestError("request", f"{shown!r} is not allowed on the read-only observer socket; one of "
                                      f"{', '.join(allowed)} (use the control socket to command the stage)")
    return dispatch(svc, req)


def dispatch(svc: ServiceView, req: Mapping[str, object]) -> ReplyOrFuture:
    """Route one request to its handler (control thread; never blocks)."""
    kind = req.get("request")
    known = "one of " + ", ".join(k for k in HANDLERS if k not in DEBUG_REQUESTS)
    if not isinstance(kind, str):
        raise RequestError("request", f"missing; {known}")
    fn = HANDLERS.get(kind)
    if fn is None:
        raise RequestError("request", f"unknown request {kind[:40]!r}; {known}")
    return fn(svc, req)
