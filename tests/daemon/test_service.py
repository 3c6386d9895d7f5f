"""The service in-process on a real ControlLoop (real clock, PlantIO twin): lifecycle, sd_notify,
control requests, fault + reset, reload (bad then good tuning), recording, clean stop with flushed telemetry.

Waits are on the notify socket and on control-socket replies (timeouts are failure guards only).
"""

from __future__ import annotations

import csv
import threading
import time

import numpy as np
import pytest

from stagectl.daemon.control import ControlClient
from stagectl.daemon.sdnotify import SdNotifier
from stagectl.daemon.service import StageService
from stagectl.runtime.requests import ShutdownRequest


def _write_cfg(path, kp, tmp_path, telemetry_dir=None, **daemon):
    """The rig's YAML: controller gains, a ``daemon:`` section (status every 50 ms, the loop as a thread of the
    service so the tests can reach into it, + ``daemon``), telemetry
    into ``telemetry_dir`` (default ``tmp_path/tel``) flushed every 50 ms."""
    import yaml

    tel = {"directory": str(telemetry_dir or tmp_path / "tel"), "flush_interval_s": 0.05}
    path.write_text(yaml.safe_dump({"controller": {"kp_n_m": kp, "kd_n_s_m": 400.0},
                                    "daemon": {"status_interval_s": 0.05, "isolation": "thread", **daemon,
                                               "telemetry": tel}}))
    return path


class _Running:
    """``StageService.run()`` in a thread (it is the main thread of a real daemon), with the rig devices."""

    def __init__(self, cfg, tmp_path, notify_socket, loader, builder, state_dir=None) -> None:
        self.dut = StageService(cfg, tmp_path / "run", load_config=loader, build=builder,
                                notifier=SdNotifier(str(notify_socket.path)), state_dir=state_dir)
        self._result: dict = {}
        self.thread = threading.Thread(target=lambda: self._result.setdefault("code", self.dut.run()))
        self.thread.start()

    def alive(self) -> bool:
        return self.thread.is_alive()

    def stop(self) -> int | None:
        """SIGTERM's path; returns the exit code (None if run() did not return within the failure guard)."""
        self.dut.request_stop()
        return self.join()

    def join(self) -> int | None:
        self.thread.join(30)
        return self._result.get("code")


def test_service_lifecycle_end_to_end_in_process(tmp_path, notify_socket, rig_loader, rig_builder):
    cfg = _write_cfg(tmp_path / "stagectl.yaml", 4e4, tmp_path, allow_fault_injection=True)
    svc = _Running(cfg, tmp_path, notify_socket, rig_loader, rig_builder)
    dut = svc.dut
    try:
        ready = notify_socket.wait_for("READY", "1", alive=svc.alive)
        assert "active" in ready["STATUS"]
        notify_socket.wait_for("WATCHDOG", "1")  # the supervisor saw the cycle counter advance
        with ControlClient(tmp_path / "run" / "control.sock") as c:
            st = c.request({"request": "status"})["status"]
            assert st["state"] == "active" and st["drive_enabled"] is True
            # "healthy" is the loop's recent overrun fraction within the rig's 50 %: the in-process loop thread
            # shares its interpreter with the daemon and the test, and a loaded CI machine once pushed it over;
            # it must come back (30 s failure guard)
            end = time.monotonic() + 30
            while not st["loop"]["healthy"] and time.monotonic() < end:
                time.sleep(0.05)
                st = c.request({"request": "status"})["status"]
            assert st["loop"]["healthy"], st["loop"]
            r = c.request({"request": "move", "target_m": 1e-4, "id": 1})
            assert r["ok"] and r["target_m"] == 1e-4 and r["id"] == 1
            r = c.request({"request": "move", "target_m": 0.5})
            assert r["ok"] is False and r["field"] == "target_m"
            r = c.request({"request": "move", "target_m": "near"})
            assert r["ok"] is False and r["field"] == "target_m" and "m" in r["error"]
            r = c.request({"request": "move", "relative_m": 1e-5, "speed": 3})
            assert r["ok"] is False and r["field"] == "speed"
            assert c.request({"request": "record", "action": "start", "name": "../x"})["field"] == "name"
            r = c.request({"request": "record", "action": "stop", "id": 9})  # answered from a helper thread
            assert r["ok"] is False and r["field"] == "action" and r["id"] == 9
            rec = c.request({"request": "record", "action": "start", "name": "capture"})
            assert rec["ok"], rec
            assert c.request({"request": "stop"})["ok"]
            # ---------------------------------------------------------------- fault and reset
            r = c.request({"request": "fault", "kind": "emcy"})
            assert r["ok"], r
            msg = notify_socket.wait_for("STATUS")
            while not msg["STATUS"].startswith("fault"):
                msg = notify_socket.wait_for("STATUS")
            st = c.request({"request": "status"})["status"]
            assert st["state"] == "fault" and st["loop"]["fault"] and st["fault_flushes"] == 1
            assert c.request({"request": "move", "relative_m": 1e-5})["ok"] is False  # refused in fault
            r = c.request({"request": "reset"})
            assert r["ok"] and r["state"] == "active", r
            # ---------------------------------------------------------------- reload: bad, then good
            _write_cfg(cfg, -1.0, tmp_path, allow_fault_injection=True)
            dut.request_reload()
            notify_socket.wait_for("READY", "1")
            st = c.request({"request": "status"})["status"]
            assert st["reload"]["ok"] is False and "controller.kp_n_m" in st["reload"]["error"]
            assert c.request({"request": "gains"})["controller"]["kp_n_m"] == 4e4  # old tuning kept
            _write_cfg(cfg, 5e4, tmp_path, allow_fault_injection=True)
            dut.request_reload()
            notify_socket.wait_for("READY", "1")
            g = c.request({"request": "gains"})
            assert g["controller"]["kp_n_m"] == 5e4 and g["reload"]["ok"] is True
            assert dut.asm.loop.controller.cfg.kp_n_m == 5e4  # applied inside the loop
            info = c.request({"request": "record", "action": "stop"})["recording"]
            assert info["rows"] > 0 and info["error"] is None
    finally:
        code = svc.stop()
    assert code == 0
    notify_socket.wait_for("STOPPING", "1")
    final = notify_socket.wait_for("STATUS")
    while not final["STATUS"].startswith("stopped"):
        final = notify_socket.wait_for("STATUS")
    assert "drive disabled" in final["STATUS"] and "telemetry dropped 0" in final["STATUS"]
    assert dut.asm.loop.actuator.state.value == "configured" or dut.asm.loop.actuator.state.value == "closed"
    assert not (tmp_path / "run" / "control.sock").exists()
    # ---------------------------------------------------------------- telemetry complete
    cycles = dut.loop_result.cycles
    files = sorted((tmp_path / "tel").glob("telemetry-*.csv"))
    assert len(files) == 1
    with open(files[0], newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == list(dut.asm.loop.columns)
    data = np.array(rows[1:], dtype=float)
    assert len(data) == cycles  # every cycle of the run, nothing dropped or lost
    assert np.all(np.diff(data[:, 0]) > 0)
    with open(tmp_path / "tel" / "capture.csv", newline="") as fh:
        assert next(csv.reader(fh)) == list(dut.asm.loop.columns)


def test_unwritable_telemetry_directory_reported_while_loop_runs(tmp_path, notify_socket, rig_loader, rig_builder):
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("x")  # a file where the telemetry directory should be (fails even as root)
    cfg = _write_cfg(tmp_path / "stagectl.yaml", 4e4, tmp_path, telemetry_dir=blocker / "tel")
    svc = _Running(cfg, tmp_path, notify_socket, rig_loader, rig_builder)
    dut = svc.dut
    try:
        ready = notify_socket.wait_for("READY", "1", alive=svc.alive)
        assert "TELEMETRY NOT RECORDING" in ready["STATUS"] and "not-a-dir" in ready["STATUS"]  # READY says so
        with ControlClient(tmp_path / "run" / "control.sock") as c:
            st1 = c.request({"request": "status"})["status"]
            assert st1["state"] == "active" and "not-a-dir" in st1["telemetry"]["error"]
            notify_socket.wait_for("WATCHDOG", "1")
            notify_socket.wait_for("WATCHDOG", "1")
            st2 = c.request({"request": "status"})["status"]
            assert st2["loop"]["cycle"] > st1["loop"]["cycle"]  # the loop keeps running
            assert st2["telemetry"]["lost"] > 0 and st2["telemetry"]["dropped"] == 0
    finally:
        code = svc.stop()
    assert code == 0


def test_watchdog_withheld_while_the_loop_hangs(tmp_path, notify_socket, rig_loader, rig_builder):
    cfg = _write_cfg(tmp_path / "stagectl.yaml", 4e4, tmp_path)
    svc = _Running(cfg, tmp_path, notify_socket, rig_loader, rig_builder)
    dut = svc.dut
    try:
        notify_socket.wait_for("READY", "1", alive=svc.alive)
        notify_socket.wait_for("WATCHDOG", "1")
        ctl = dut.asm.loop.controller
        ctl.hang.set()  # the loop thread blocks inside the controller: cycle counter stops
        while "WATCHDOG WITHHELD: cycle counter not advancing" not in notify_socket.wait_for("STATUS")["STATUS"]:
            pass
        since = len(notify_socket.history)
        for _ in range(3):  # three more supervisor reports, and no WATCHDOG=1 among the datagrams
            notify_socket.wait_for("STATUS")
        assert not any("WATCHDOG" in m for m in notify_socket.history[since:])
        ctl.release.set()
        notify_socket.wait_for("WATCHDOG", "1")  # pings resume once the loop cycles again
        assert dut.status()["watchdog"]["withheld"] >= 3
    finally:
        dut.asm.loop.controller.release.set()
        code = svc.stop()
    assert code == 0


def test_health_window_fraction_over_time_not_since_start():
    from stagectl.daemon.service import HealthWindow

    dut = HealthWindow(window_s=10.0)
    dut.add(0.0, 0, 0)
    dut.add(1.0, 900, 100)  # a start-up stall: 100 of 1000 slots skipped
    assert dut.advancing() and dut.overrun_fraction() == 0.1
    for k in range(2, 13):  # then 11 s of clean cycling
        dut.add(float(k), 900 + 1000 * (k - 1), 100)
    assert dut.overrun_fraction() == 0.0  # the stall left the window
    dut.add(13.0, 900 + 11000, 100)  # no cycles in the last second: stalled
    assert not dut.advancing()


@pytest.mark.parametrize("key", ["target_m", "relative_m", "max_velocity_m_s"])
@pytest.mark.parametrize("value", [10**400, float("nan"), float("inf"), "1e-3", True, [1e-3]])
def test_move_numbers_checked_before_the_loop_with_the_field_named(tmp_path, rig_loader, rig_builder, key, value):
    """A 400-digit integer is valid JSON; float() of it raised OverflowError, a traceback in the log (audit)."""
    from stagectl.daemon.control import RequestError

    dut = StageService(tmp_path / "none.yaml", tmp_path / "run", load_config=rig_loader, build=rig_builder,
                       notifier=SdNotifier(environ={}))
    req = {"request": "move", key: value}
    if key == "max_velocity_m_s":
        req["target_m"] = 1e-4
    with pytest.raises(RequestError) as ei:
        dut.handle(req)
    assert ei.value.field == key


def test_no_ready_while_the_loop_is_not_healthy(tmp_path, notify_socket, rig_loader, rig_builder):
    """READY=1 only once the loop cycles: a loop stuck in its first step never gets READY, start-up fails (exit 1)
    with the reason in STATUS= after ``ready_timeout_s`` (here the behaviour under test, not a wait)."""
    def build_stuck(app_cfg):
        asm = rig_builder(app_cfg)
        asm.loop.controller.hang.set()  # the first controller step blocks: cycle counter never advances
        return asm

    cfg = _write_cfg(tmp_path / "stagectl.yaml", 4e4, tmp_path, ready_timeout_s=0.5, stop_timeout_s=10)
    svc = _Running(cfg, tmp_path, notify_socket, rig_loader, build_stuck)
    dut = svc.dut
    try:
        while True:
            msg = notify_socket.wait_for("STATUS", alive=svc.alive)
            assert not any("READY" in m for m in notify_socket.history), "READY=1 sent for a stuck loop"
            if msg["STATUS"].startswith("start-up"):
                break
        assert "loop not healthy within 0.5 s" in msg["STATUS"]
    finally:
        dut.asm.loop.controller.release.set()  # let the stuck step finish so the loop can stop
        code = svc.join()
    assert code == 1
    assert not any("READY" in m for m in notify_socket.history)
    assert dut.asm.loop.actuator.state.value != "enabled"


def test_watchdog_pinged_during_a_slow_reload(tmp_path, notify_socket, rig_loader, rig_builder):
    """Loading + designing a new tuning can outlast WatchdogSec (first use of a model compiles kernels): the
    reload runs beside the supervisor, whose health-checked pings go on. The reload here blocks until released."""
    entered, release = threading.Event(), threading.Event()
    calls = []

    def slow_loader(path):
        calls.append(path)
        if len(calls) > 1:  # the reload, not the start-up
            entered.set()
            assert release.wait(60)  # failure guard
        return rig_loader(path)

    cfg = _write_cfg(tmp_path / "stagectl.yaml", 4e4, tmp_path)
    svc = _Running(cfg, tmp_path, notify_socket, slow_loader, rig_builder)
    try:
        notify_socket.wait_for("READY", "1", alive=svc.alive)
        _write_cfg(cfg, 5e4, tmp_path)
        since = len(notify_socket.history)
        svc.dut.request_reload()
        assert entered.wait(30)
        notify_socket.wait_for("RELOADING", "1")
        for _ in range(3):  # pings while the reload is stuck in the loader
            notify_socket.wait_for("WATCHDOG", "1")
        assert not any("READY" in m for m in notify_socket.history[since:])  # the reload has not finished
        release.set()
        notify_socket.wait_for("READY", "1")  # reload finished
        assert svc.dut.asm.loop.controller.cfg.kp_n_m == 5e4
    finally:
        release.set()
        code = svc.stop()
    assert code == 0


# ---------------------------------------------------------------------------- unclean end of the previous run
def _stale_marker(directory, pid=4242):
    import json

    directory.mkdir(parents=True, exist_ok=True)
    marker = directory / "stagectl.running"
    marker.write_text(json.dumps({"pid": pid, "started_utc": "2026-01-02T03:04:05Z", "config": "x.yaml"}) + "\n")
    return marker


def test_restart_after_unclean_end_comes_up_latched_until_reset(tmp_path, notify_socket, rig_loader, rig_builder,
                                                                 caplog):
    """A marker left by a killed run: READY=1 (the service answers) but latched in fault unclean_shutdown with the
    drive not enabled; a stop without reset keeps the marker (the next start is latched again); `reset` enables
    the drive, the marker then records this run, and a clean stop removes it."""
    import json
    import logging
    import os

    state = tmp_path / "state"
    marker = _stale_marker(state)
    cfg = _write_cfg(tmp_path / "stagectl.yaml", 4e4, tmp_path)
    caplog.set_level(logging.WARNING, logger="stagectl.daemon")
    for attempt in range(2):
        caplog.clear()
        svc = _Running(cfg, tmp_path, notify_socket, rig_loader, rig_builder, state_dir=state)
        dut = svc.dut
        try:
            ready = notify_socket.wait_for("READY", "1", alive=svc.alive)
            assert ready["STATUS"].startswith("fault") and "unclean_shutdown" in ready["STATUS"]
            assert any("did not stop cleanly" in r.getMessage() and '"pid": 4242' in r.getMessage()
                       for r in caplog.records)
            notify_socket.wait_for("WATCHDOG", "1")  # latched, still cycling and supervised
            with ControlClient(tmp_path / "run" / "control.sock") as c:
                st = c.request({"request": "status"})["status"]
                assert st["state"] == "fault" and st["drive_enabled"] is False
                fault = st["loop"]["fault"]
                assert fault["name"] == "unclean_shutdown" and st["loop"]["state"] == "fault"
                assert "did not stop cleanly" in fault["cause"] and "pid 4242" in fault["cause"]
                assert "2026-01-02T03:04:05Z" in fault["cause"]
                assert c.request({"request": "move", "relative_m": 1e-5})["ok"] is False  # refused while latched
                if attempt == 1:
                    r = c.request({"request": "reset"})
                    assert r["ok"] and r["state"] == "active" and r["cleared"]["name"] == "unclean_shutdown", r
                    while not notify_socket.wait_for("STATUS")["STATUS"].startswith("active"):
                        pass
                    st = c.request({"request": "status"})["status"]
                    assert st["state"] == "active" and st["drive_enabled"] is True and st["loop"]["fault"] is None
                    assert c.request({"request": "move", "relative_m": 1e-5})["ok"]
                    assert json.loads(marker.read_text())["pid"] == os.getpid()  # now records this run
        finally:
            code = svc.stop()
        assert code == 0
        assert dut.asm.loop.actuator.state.value != "enabled"
        if attempt == 0:
            assert json.loads(marker.read_text())["pid"] == 4242  # not acknowledged: kept as it was
    assert not marker.exists()


def test_clean_stop_removes_the_marker_and_the_next_start_is_clean(tmp_path, notify_socket, rig_loader,
                                                                   rig_builder):
    """No --state-dir: the marker lives in the runtime directory while the drive may be enabled; SIGTERM's path
    removes it after disabling the drive and flushing telemetry, so the next start enables the drive."""
    import json
    import os

    marker = tmp_path / "run" / "stagectl.running"
    cfg = _write_cfg(tmp_path / "stagectl.yaml", 4e4, tmp_path)
    for _ in range(2):
        svc = _Running(cfg, tmp_path, notify_socket, rig_loader, rig_builder)
        try:
            ready = notify_socket.wait_for("READY", "1", alive=svc.alive)
            assert ready["STATUS"].startswith("active")
            assert svc.dut.status()["drive_enabled"] is True
            info = json.loads(marker.read_text())
            assert info["pid"] == os.getpid() and info["started_utc"].endswith("Z")
        finally:
            code = svc.stop()
        assert code == 0
        assert not marker.exists()


def test_start_up_failure_keeps_an_unacknowledged_marker(tmp_path, notify_socket, rig_loader, rig_builder):
    """Invalid configuration on a restart after a crash (exit 2): the marker stays, so a later start is latched."""
    marker = _stale_marker(tmp_path / "run")
    cfg = _write_cfg(tmp_path / "stagectl.yaml", -1.0, tmp_path)
    svc = _Running(cfg, tmp_path, notify_socket, rig_loader, rig_builder)
    assert svc.join() == 2
    assert marker.exists() and "4242" in marker.read_text()


def test_loop_ending_by_itself_keeps_the_marker(tmp_path, notify_socket, rig_loader, rig_builder):
    """The loop ends without a stop request (exit 1, a crash for systemd): drive disabled, but the marker stays and
    the restart comes up latched."""
    marker = tmp_path / "run" / "stagectl.running"
    cfg = _write_cfg(tmp_path / "stagectl.yaml", 4e4, tmp_path)
    svc = _Running(cfg, tmp_path, notify_socket, rig_loader, rig_builder)
    try:
        notify_socket.wait_for("READY", "1", alive=svc.alive)
        svc.dut.asm.loop.submit(ShutdownRequest()).result(timeout=30)
    finally:
        code = svc.join()
    assert code == 1 and marker.exists()
    assert svc.dut.asm.loop.actuator.state.value != "enabled"
    svc = _Running(cfg, tmp_path, notify_socket, rig_loader, rig_builder)
    try:
        ready = notify_socket.wait_for("READY", "1", alive=svc.alive)
        assert ready["STATUS"].startswith("fault") and "unclean_shutdown" in ready["STATUS"]
        assert svc.dut.status()["drive_enabled"] is False
    finally:
        assert svc.stop() == 0
    assert marker.exists()  # not reset: still latched next time
