"""SIGHUP: reload the controller tuning with the full ``check-config`` validation, applied bumplessly.

The reload runs in its own thread (normal priority, like the supervisor that starts it): loading the YAML and
designing the new tuning (observer gain, feed-forward model) may take longer than the watchdog interval,
and the supervisor keeps pinging meanwhile. SIGHUPs arriving during a reload are served by one more reload
after it. The new ``controller`` section goes to the loop as a
:class:`~stagectl.runtime.requests.RetuneRequest` (swapped in at a cycle boundary), or is rejected (reason
logged and shown in ``status()["reload"]``) and the old tuning kept. Other sections need a restart.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from stagectl.config.daemon import DaemonConfig
from stagectl.daemon.sdnotify import SdNotifier
from stagectl.daemon.remote import LoopLike
from stagectl.runtime.requests import RetuneRequest

__all__ = ["AppConfigLike", "ConfigLoader", "Reloader"]

log = logging.getLogger("stagectl.daemon")


class AppConfigLike(Protocol):
    """What the daemon reads from the application configuration: its ``controller`` section."""

    @property
    def controller(self) -> object: ...


#: config_path -> (app config, daemon config); raises ConfigError (the check-config validation)
ConfigLoader = Callable[[Path], tuple[AppConfigLike, DaemonConfig]]


def _differs_outside_controller(old: object, new: object) -> bool:
    if not (dataclasses.is_dataclass(old) and dataclasses.is_dataclass(new)):
        return False
    return any(f.name not in ("controller", "source", "path") and getattr(old, f.name) != getattr(new, f.name, None)
               for f in dataclasses.fields(old))


class Reloader:
    """Counts SIGHUPs and runs one reload thread at a time (see the module docstring).

    ``on_applied(new_app_cfg)`` runs in the reload thread once the loop has taken the new tuning;
    ``status_line()`` is the ``STATUS=`` text sent with ``READY=1`` after each reload.
    """

    def __init__(self, load_config: ConfigLoader, config_path: Path, notify: SdNotifier, reply_timeout_s: float,
                 on_applied: Callable[[AppConfigLike], None], status_line: Callable[[], str]) -> None:
        self.load_config = load_config
        self.config_path = config_path
        self.notify = notify
        self.reply_timeout_s = reply_timeout_s
        self.on_applied = on_applied
        self.status_line = status_line
        self.pending = 0
        self.status: dict[str, Any] | None = None
        self._thread: threading.Thread | None = None

    def request(self) -> None:
        """Note a SIGHUP (thread-safe; served at the supervisor's next tick)."""
        self.pending += 1

    def maybe_start(self, loop: LoopLike, current: AppConfigLike) -> None:
        """Supervisor tick: start a reload thread if one is pending and none runs."""
        if self.pending and not (self._thread and self._thread.is_alive()):
            self.pending = 0
            self._thread = threading.Thread(target=self._reload, args=(loop, current), name="stagectl-reload",
                                            daemon=True)
            self._thread.start()

    def _reload(self, loop: LoopLike, current: AppConfigLike) -> None:
        self.notify.reloading()
        t = time.time()
        try:
            new_app, _new_daemon = self.load_config(self.config_path)
            if _differs_outside_controller(current, new_app):
                log.warning("reload: only the controller section is applied at reload; other changes need a restart")
            fut = loop.submit(RetuneRequest(new_app.controller))
            fut.result(timeout=max(2.0, self.reply_timeout_s))
        except concurrent.futures.TimeoutError:
            self._rejected(t, "the loop did not apply the new tuning in time; old tuning kept")
        except Exception as exc:  # noqa: BLE001 - ConfigError, ValueError from retune...
            self._rejected(t, str(exc))
        else:
            self.on_applied(new_app)
            self.status = {"ok": True, "time": t, "error": None}
            log.info("reload: new controller tuning applied at a cycle boundary")
        self.notify.ready(self.status_line())

    def _rejected(self, t: float, reason: str) -> None:
        if len(reason) > 2000:  # returned in every status/gains reply and logged: bounded
            reason = f"{reason[:2000]}... ({len(reason) - 2000} more characters)"
        self.status = {"ok": False, "time": t, "error": reason}
        log.error("reload rejected, old tuning kept:\n%s", reason)
