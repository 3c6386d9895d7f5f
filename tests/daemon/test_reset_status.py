"""Reset and status tell the truth: a reset is refused with the persisting cause, accepted once it is gone, and
``drive_enabled`` is false while the loop has the drive quick-stopped (in-process service on the rig)."""

from __future__ import annotations

import threading

import yaml

from stagectl.daemon.control import ControlClient
from stagectl.daemon.sdnotify import SdNotifier
from stagectl.daemon.service import StageService


class _Svc:
    def __init__(self, tmp_path, notify_path, loader, builder) -> None:
        cfg = tmp_path / "s.yaml"
        cfg.write_text(yaml.safe_dump({"controller": {"kp_n_m": 4e4, "kd_n_s_m": 400.0},
                                       "daemon": {"status_interval_s": 0.05, "allow_fault_injection": True,
                                                  "telemetry": {"directory": str(tmp_path / "tel")}}}))
        self.dut = StageService(cfg, tmp_path / "run", load_config=loader, build=builder,
                                notifier=SdNotifier(str(notify_path)), state_dir=tmp_path / "state")
        self.code: list[int] = []
        self.thread = threading.Thread(target=lambda: self.code.append(self.dut.run()))
        self.thread.start()

    def stop(self) -> int | None:
        self.dut.request_stop()
        self.thread.join(30)
        return self.code[0] if self.code else None


def _until_fault(c):
    while (st := c.request({"request": "status"})["status"])["loop"]["faults"] < 1:
        pass
    return st


def test_reset_refused_while_the_cause_persists_then_accepted(tmp_path, notify_socket, rig_loader, rig_builder):
    svc = _Svc(tmp_path, notify_socket.path, rig_loader, rig_builder)
    try:
        notify_socket.wait_for("READY", "1", alive=svc.thread.is_alive)
        with ControlClient(tmp_path / "run" / "control.sock") as c:
            assert c.request({"request": "fault", "kind": "heartbeat_lost", "persist": True})["ok"]
            st = _until_fault(c)
            assert st["state"] == "fault" and st["drive_enabled"] is False
            r = c.request({"request": "reset"})
            assert r["ok"] is False, r
            assert r["error"] == ("reset refused: cause still present: plant_io: heartbeat_lost: injected by test; "
                                  "the fault stays latched"), r
            st = c.request({"request": "status"})["status"]
            assert st["state"] == "fault" and st["loop"]["fault"]["name"] == "heartbeat_lost"
            assert c.request({"request": "fault", "kind": "cause_gone"})["ok"]
            r = c.request({"request": "reset"})
            assert r["ok"] and r["state"] == "active" and r["cleared"]["name"] == "heartbeat_lost", r
            st = c.request({"request": "status"})["status"]
            assert st["state"] == "active" and st["drive_enabled"] is True and st["drive"] == "enabled"
    finally:
        assert svc.stop() == 0


def test_drive_not_reported_enabled_while_quick_stopped(tmp_path, notify_socket, rig_loader, rig_builder):
    """A supervisor fault (not_finite) leaves the device enabled but quick-stopped: not "enabled"; the state
    is the loop's own at once (no supervisor tick in between)."""
    svc = _Svc(tmp_path, notify_socket.path, rig_loader, rig_builder)
    try:
        notify_socket.wait_for("READY", "1", alive=svc.thread.is_alive)
        with ControlClient(tmp_path / "run" / "control.sock") as c:
            assert c.request({"request": "status"})["status"]["drive_enabled"] is True
            assert c.request({"request": "fault", "kind": "nan"})["ok"]
            st = _until_fault(c)
            assert st["loop"]["fault"]["name"] == "not_finite"
            assert st["state"] == "fault" and st["drive"] == "quick_stopped" and st["drive_enabled"] is False
            r = c.request({"request": "reset"})
            assert r["ok"] and r["state"] == "active", r
            st = c.request({"request": "status"})["status"]
            assert st["state"] == "active" and st["drive_enabled"] is True
    finally:
        assert svc.stop() == 0
