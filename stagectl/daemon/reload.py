"""SIGHUP: reload the controller tuning with the full ``check-config`` validation, applied bumplessly.

The reload runs in its own thread (normal priority, like the supervisor that starts it): loading the YAML and
designing the new tuning (observer gain, feed-forward model) may take longer than the watchdog interval,
and the supervisor keeps pinging meanwhile. SIGHUPs arriving during a reload are served by one more reload
after it. The new ``controller`` section goes to the loop as a
:class:`~stagectl.runtime.requests.RetuneRequest` (swapped in at a cycle boundary), or is rejected (reason
logged and shown in ``status()["reload"]``) and the old tuning kept. Other sections need a restart.

Honesty rules:

* the new tuning is checked before it is sent: the closed loop (PID, or PID + observer when one is on) on the
  discrete rigid-mass plant at the loop period with the configuration's I/O delay
  (:func:`stagectl.control.design.analyse_design`, the model ``stagectl tune`` reports) must be stable with
  at least :data:`MIN_PHASE_MARGIN_DEG` and :data:`MIN_GAIN_MARGIN_DB`; else the reload is rejected naming
  the margins found. In-range gains can still make an unstable loop (kp ten times too high, say).
* edits of other sections (``safety:``, ``loop:``, ``io:``, ``sim:``...) are *not* applied: the reply says
  ``applied: ["controller"]`` and ``not_applied: [...]`` (they need a restart), and the configuration the
  daemon reports keeps the old sections. The warning is logged once per new set of pending edits; sections
  are compared by value (a model object read twice from the same file is the same), so an unchanged ``sim:``
  section never warns.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from stagectl.config.daemon import DaemonConfig
from stagectl.daemon.sdnotify import SdNotifier
from stagectl.daemon.remote import LoopLike
from stagectl.errors import short
from stagectl.runtime.requests import RetuneRequest

__all__ = ["MIN_GAIN_MARGIN_DB", "MIN_PHASE_MARGIN_DEG", "AppConfigLike", "ConfigLoader", "Reloader",
           "same_value", "sections_not_applied", "stability_problem", "with_controller_of"]

log = logging.getLogger("stagectl.daemon")


class AppConfigLike(Protocol):
    """What the daemon reads from the application configuration: its ``controller`` section."""

    @property
    def controller(self) -> object: ...


#: config_path -> (app config, daemon config); raises ConfigError (the check-config validation)
ConfigLoader = Callable[[Path], tuple[AppConfigLike, DaemonConfig]]


#: a reloaded tuning whose closed loop has less margin than this is rejected (the shipped sim.yaml has PM 42.2
#: deg / GM 8.9 dB with its observer; 10 deg / 2 dB is "rings for seconds, a small model error from unstable")
MIN_PHASE_MARGIN_DEG = 10.0
MIN_GAIN_MARGIN_DB = 2.0
_MAX_DEPTH = 12


def same_value(a: object, b: object, depth: int = 0) -> bool:
    """Structural equality of two configuration values: dataclasses field by field, containers element-wise,
    arrays by content, other objects (friction models) by type and attributes. Two loads of one file are equal
    (a model object has no ``__eq__``, so ``==`` would call them different)."""
    if a is b:
        return True
    if type(a) is not type(b) or depth > _MAX_DEPTH:
        return False
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        return all(same_value(getattr(a, f.name), getattr(b, f.name), depth + 1) for f in dataclasses.fields(a))
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(same_value(x, y, depth + 1) for x, y in zip(a, b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(same_value(a[k], b[k], depth + 1) for k in a)
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    try:
        eq = a == b
    except Exception:  # noqa: BLE001 - an exotic __eq__: compare the attributes below
        eq = NotImplemented
    if isinstance(eq, bool):
        if eq or not hasattr(a, "__dict__"):
            return eq
    elif hasattr(eq, "all"):  # numpy arrays
        return bool(getattr(a, "shape", None) == getattr(b, "shape", None) and eq.all())
    return hasattr(a, "__dict__") and same_value(vars(a), vars(b), depth + 1)


def sections_not_applied(old: object, new: object) -> list[str]:
    """The sections other than ``controller`` whose values differ between ``old`` and ``new`` (a reload does
    not apply them: they need a restart)."""
    if not (dataclasses.is_dataclass(old) and dataclasses.is_dataclass(new)) or type(old) is not type(new):
        return []
    return [f.name for f in dataclasses.fields(old)
            if f.name not in ("controller", "source", "path", "description")
            and not same_value(getattr(old, f.name), getattr(new, f.name, None))]


def with_controller_of(current: AppConfigLike, new: AppConfigLike) -> AppConfigLike:
    """``current`` with ``new``'s controller: what the daemon runs after a reload (the other sections of the
    running configuration stay until a restart)."""
    if dataclasses.is_dataclass(current) and type(current) is type(new):
        out: AppConfigLike = dataclasses.replace(current, controller=new.controller)
        return out
    return new


def stability_problem(app: object) -> str | None:
    """Why the controller of ``app`` must not be swapped in (None: stable with margins, or not an application
    configuration whose loop can be analysed, e.g. a test rig's).

    The loop analysed is the one in operation: PID + observer when ``controller.dob.kind`` is not ``none``,
    else PID alone, on the ZOH rigid mass ``controller_mass`` (else the simulated plant's) at ``loop.period_s``
    with ``controller.design_delay_samples`` cycles of I/O delay, else ``io.delay_cycles`` (plant I/O) or one cycle
    (drives), the delay ``stagectl tune`` designs for.
    """
    from stagectl.config.sections import AppConfig, IoKind

    if not isinstance(app, AppConfig):
        return None
    from stagectl.control import design
    from stagectl.control.controller import controller_mass

    ctl = app.controller
    mass = controller_mass(ctl, ctl.feedforward.model)
    if mass is None and app.sim is not None:
        mass = app.sim.plant.mass_kg
    if mass is None:
        return None
    T = app.loop.period_s
    if ctl.design_delay_samples is not None:  # the delay the tuning was designed for (as `tune` uses it)
        nd = int(ctl.design_delay_samples)
    else:
        nd = int(app.io.delay_cycles) if app.io.kind is IoKind.PLANT_IO else 1
    dob = ctl.dob
    m_dob = dob.nominal_mass_kg if dob.nominal_mass_kg is not None else mass
    try:
        K = None
        if dob.kind == "kalman":
            K = design.kalman_gain(m_dob, T, dob.bandwidth_hz, dob.measurement_noise_m,
                                   dob.disturbance_noise_n_sqrt_s)
        loop = design.analyse_design(mass, T, ctl.pid, nd, None if dob.kind == "none" else dob.bandwidth_hz,
                                     dob.command_delay_samples, dob_mass_kg=m_dob, dob_kind=dob.kind,
                                     kalman_k=K, velocity_cutoff_hz=ctl.velocity_cutoff_hz)[-1]
    except Exception as exc:  # noqa: BLE001 - gains so extreme the analysis fails: not a tuning to swap in
        return f"controller: the new tuning cannot be analysed ({type(exc).__name__}: {short(str(exc), 120)})"
    pm, gm = loop.phase_margin_deg, loop.gain_margin_db
    where = (f"{loop.name} loop, m = {mass:g} kg, T = {T * 1e3:g} ms, {nd} cycle(s) I/O delay: phase margin "
             f"{pm:.1f} deg, gain margin {gm:.1f} dB")
    if not loop.stable:
        return f"controller: the new tuning's closed loop is UNSTABLE ({where})"
    if not (pm >= MIN_PHASE_MARGIN_DEG and gm >= MIN_GAIN_MARGIN_DB):
        return (f"controller: the new tuning's margins are too thin ({where}; a reload needs >= "
                f"{MIN_PHASE_MARGIN_DEG:g} deg and >= {MIN_GAIN_MARGIN_DB:g} dB)")
    return None


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
        self._warned: list[str] = []  # the pending (not applied) sections last warned about
        self._thread: threading.Thread | None = None

    def request(self) -> None:
        """Note a SIGHUP (thread-safe; served at the supervisor's next tick)."""
        self.pending += 1

    def warm(self, current: AppConfigLike) -> None:
        """Analyse the running tuning once in a background thread (normal priority, daemon process only):
        imports python-control/scipy (seconds on a loaded machine) so the first SIGHUP is applied promptly,
        and logs a warning if the tuning in force has thin margins or an unstable loop."""

        def run() -> None:
            try:
                problem = stability_problem(current)
            except Exception as exc:  # noqa: BLE001 - a warm-up: a reload reports the same problem properly
                problem = f"cannot analyse the running tuning ({type(exc).__name__})"
            if problem is not None:
                log.warning("running tuning: %s", problem.removeprefix("controller: the new tuning's "))

        threading.Thread(target=run, name="stagectl-margins", daemon=True).start()

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
            problem = stability_problem(new_app)
            if problem is not None:
                raise ValueError(problem)
            pending = sections_not_applied(current, new_app)
            fut = loop.submit(RetuneRequest(new_app.controller))
            fut.result(timeout=max(2.0, self.reply_timeout_s))
        except concurrent.futures.TimeoutError:
            self._rejected(t, "the loop did not apply the new tuning in time; old tuning kept")
        except Exception as exc:  # noqa: BLE001 - ConfigError, ValueError from retune...
            self._rejected(t, str(exc))
        else:
            self.on_applied(with_controller_of(current, new_app))
            self.status = {"ok": True, "time": t, "error": None, "applied": ["controller"],
                           "not_applied": pending}
            if pending:
                self.status["note"] = (f"edits of {', '.join(pending)} NOT applied: they need a restart "
                                       "(systemctl restart stagectl)")
            log.info("reload: new controller tuning applied at a cycle boundary")
            if pending and pending != self._warned:
                log.warning("reload: %s", self.status["note"])
            self._warned = pending
        self.notify.ready(self.status_line())

    def _rejected(self, t: float, reason: str) -> None:
        if len(reason) > 2000:  # returned in every status/gains reply and logged: bounded
            reason = f"{reason[:2000]}... ({len(reason) - 2000} more characters)"
        self.status = {"ok": False, "time": t, "error": reason}
        log.error("reload rejected, old tuning kept:\n%s", reason)
