"""Real small objects to run the service in-process: a rigid-mass plant behind PlantIO, a PD law, a ramp
reference, the real ControlLoop on the real monotonic clock (not mocks: the same interfaces as the product).
"""

from __future__ import annotations

import math
import socket
import threading
from dataclasses import dataclass
from pathlib import Path

import pytest

from support import RampReference
from stagectl.control.api import Command, Reference
from stagectl.errors import ConfigError


class MassPlant:
    """m·a = u − c·v (semi-implicit Euler), position quantised to 1 nm."""

    def __init__(self, mass_kg: float = 1.0, c_n_s_m: float = 5.0) -> None:
        self.m, self.c = mass_kg, c_n_s_m
        self.x_m = 0.0
        self.v_m_s = 0.0
        self.resolution_m = 1e-9

    def step(self, u_n: float, dt_s: float) -> None:
        n = max(1, math.ceil(dt_s / 1e-4))
        h = dt_s / n
        for _ in range(n):
            self.v_m_s += (u_n - self.c * self.v_m_s) / self.m * h
            self.x_m += self.v_m_s * h

    def measure(self) -> float:
        return round(self.x_m / 1e-9) * 1e-9

    def measure_counts(self) -> int:
        return round(self.x_m / 1e-9)


@dataclass(frozen=True)
class PDConfig:
    kp_n_m: float = 4e4
    kd_n_s_m: float = 400.0


@dataclass(frozen=True)
class RigAppConfig:
    controller: PDConfig


class PD:
    term_names = ("u_pid", "u_inertia")

    def __init__(self, cfg: PDConfig) -> None:
        self.cfg = cfg
        self.x_prev = 0.0
        self.hang = threading.Event()  # set: the next step blocks (a hung loop) until `release` is set
        self.release = threading.Event()

    def reset(self, x_m: float) -> None:
        self.x_prev = x_m

    def retune(self, cfg: PDConfig) -> None:
        self.cfg = cfg

    def step(self, dt: float, x: float, ref: Reference) -> Command:
        if self.hang.is_set():
            self.release.wait(60)
            self.hang.clear()
        v = (x - self.x_prev) / dt
        self.x_prev = x
        u = self.cfg.kp_n_m * (ref.x_m - x) + self.cfg.kd_n_s_m * (ref.v_m_s - v)
        return Command(u + ref.a_m_s2, {"u_pid": u, "u_inertia": ref.a_m_s2})


def load_rig_config(path: Path):
    """The rig's 'check-config': YAML with a controller section and an optional daemon section."""
    from stagectl.config.daemon import load_daemon_config
    from stagectl.schema import load_yaml_file

    raw = load_yaml_file(path) or {}
    ctl = raw.get("controller") or {}
    problems = []
    for key in ctl:
        if key not in ("kp_n_m", "kd_n_s_m"):
            problems.append(f"controller.{key}: unknown key")
    for key in ("kp_n_m", "kd_n_s_m"):
        if key in ctl and not (isinstance(ctl[key], (int, float)) and ctl[key] > 0):
            problems.append(f"controller.{key}: must be > 0 (got {ctl[key]!r})")
    if problems:
        raise ConfigError(problems)
    return RigAppConfig(PDConfig(**ctl)), load_daemon_config(raw.get("daemon"))


def build_rig(app_cfg):
    from stagectl.clock import MonotonicClock
    from stagectl.daemon.service import Assembly
    from stagectl.loop import ControlLoop, LoopConfig
    from stagectl.safety import Safety, SafetyConfig
    from stagectl.sim.direct import PlantIO

    clock = MonotonicClock()
    period = 1e-3
    # the plant advances exactly one period per SYNC (no clock): stepped by the wall clock, a loop held off the
    # CPU on a loaded machine saw the plant jump by the time it lost, with its command held, and its PD went
    # unstable (a velocity_limit fault at load 13); the loop itself still runs on the wall clock
    io = PlantIO(MassPlant(), period, delay_cycles=1)
    io.open()
    io.configure()
    safety = Safety(SafetyConfig(min_position_m=-0.01, max_position_m=0.01, following_error_m=1e-3,
                                 max_force_n=50.0, max_velocity_m_s=0.05, stale_cycles=3), period)
    loop = ControlLoop(clock=clock, sensor=io, actuator=io, controller=PD(app_cfg.controller), reference=RampReference(v_default=2e-3),
                       safety=safety, cfg=LoopConfig(period_s=period, healthy_overrun_fraction=0.5), realtime=False)

    def inject(kind: str, **kw):
        import math

        from stagectl.drivers.base import FaultKind

        if kind == "cause_gone":  # a persisting injected fault's cause goes away
            io.remove_cause()
        elif kind == "nan":  # the next sample is NaN: the supervisor's not_finite, the drive stays enabled
            io.glitch(math.nan)
        else:
            io.inject_fault(FaultKind(kind), detail="injected by test", persist=bool(kw.get("persist")))
        return {}

    return Assembly(loop=loop, close=io.close, controller_config=app_cfg.controller, simulated=True,
                    inject_fault=inject, describe={"plant": "mass"})


class NotifySocket:
    """A bound AF_UNIX datagram socket standing in for systemd's notify socket.

    A reader thread drains it continuously, like systemd does: the kernel queues only
    ``net.unix.max_dgram_qlen`` (often 10) datagrams for an unread socket, and the daemon's non-blocking
    sender drops what does not fit, so a test that reads only when it waits would lose e.g. ``STOPPING=1``
    behind a backlog of ``STATUS=`` updates.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.messages: list[dict[str, str]] = []  # received, not yet consumed by wait_for
        self.history: list[dict[str, str]] = []  # everything received, in order
        self._cv = threading.Condition()
        self._closed = False
        self._reader = threading.Thread(target=self._read, name="notify-reader", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while True:
            try:
                data = self.sock.recv(65536).decode()
            except OSError:
                return
            if not data and self._closed:
                return
            msg = dict(line.split("=", 1) for line in data.split("\n") if "=" in line)
            with self._cv:
                self.messages.append(msg)
                self.history.append(msg)
                self._cv.notify_all()

    def wait_for(self, key: str, value: str | None = None, timeout: float = 30.0, alive=None) -> dict[str, str]:
        """Oldest unconsumed datagram containing KEY (=VALUE); the ones before it are consumed too. ``timeout``
        is only a failure guard; ``alive()`` returning False (e.g. the daemon process exited) ends the wait at
        once with TimeoutError."""
        import time

        end = time.monotonic() + timeout
        with self._cv:
            while True:
                for i, m in enumerate(self.messages):
                    if key in m and (value is None or m[key] == value):
                        del self.messages[: i + 1]
                        return m
                self.messages.clear()
                left = end - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no {key}={value or '*'} within {timeout} s")
                if alive is not None and not alive():
                    raise TimeoutError(f"no {key}={value or '*'}: the process exited")
                self._cv.wait(min(left, 0.5))

    def close(self) -> None:
        self._closed = True
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()
        self._reader.join(5)


@pytest.fixture
def notify_socket(tmp_path):
    ns = NotifySocket(tmp_path / "notify.sock")
    yield ns
    ns.close()


@pytest.fixture
def rig_loader():
    return load_rig_config


@pytest.fixture
def rig_builder():
    return build_rig


@pytest.fixture
def notify_cls():
    return NotifySocket
