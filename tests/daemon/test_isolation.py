"""Availability and honesty of the service: one instance per directory, `stop` never locked out, a read-only
observer socket, health by I/O kind, telemetry losses counted and reported, no missed fault after a reset.

The service runs in-process on the rig (real ControlLoop on the real clock, PlantIO twin). Waits are on the
notify socket and control-socket replies; their timeouts are failure guards only, never the assertion.
"""

from __future__ import annotations

import json
import os
import socket
import stat
import subprocess
import sys
import threading

import pytest
import yaml

from stagectl.daemon.control import ControlClient
from stagectl.daemon.sdnotify import SdNotifier
from stagectl.daemon.service import StageService


def _cfg(path, tmp_path, *, telemetry=None, **daemon):
    tel = {"directory": str(tmp_path / "tel"), "flush_interval_s": 0.05, **(telemetry or {})}
    path.write_text(yaml.safe_dump({"controller": {"kp_n_m": 4e4, "kd_n_s_m": 400.0},
                                    "daemon": {"status_interval_s": 0.05, **daemon, "telemetry": tel}}))
    return path


class _Svc:
    """``StageService.run()`` in a thread; ``builds`` counts device builds."""

    def __init__(self, cfg, tmp_path, notify_path, loader, builder) -> None:
        self.builds = 0

        def build(app_cfg):
            self.builds += 1
            return builder(app_cfg)

        self.dut = StageService(cfg, tmp_path / "run", load_config=loader, build=build,
                                notifier=SdNotifier(str(notify_path)), state_dir=tmp_path / "state")
        self.code: list[int] = []
        self.thread = threading.Thread(target=lambda: self.code.append(self.dut.run()))
        self.thread.start()

    def alive(self) -> bool:
        return self.thread.is_alive()

    def stop(self) -> int | None:
        self.dut.request_stop()
        return self.join()

    def join(self) -> int | None:
        self.thread.join(30)
        return self.code[0] if self.code else None


def test_second_daemon_refuses_before_touching_anything(tmp_path, notify_socket, notify_cls, rig_loader,
                                                        rig_builder):
    cfg = _cfg(tmp_path / "s.yaml", tmp_path)
    first = _Svc(cfg, tmp_path, notify_socket.path, rig_loader, rig_builder)
    second_notify = notify_cls(tmp_path / "notify2.sock")
    try:
        notify_socket.wait_for("READY", "1", alive=first.alive)
        marker = tmp_path / "state" / "stagectl.running"
        before = marker.read_text()
        second = _Svc(cfg, tmp_path, second_notify.path, rig_loader, rig_builder)
        assert second.join() == 1
        assert second.builds == 0  # no device was opened
        msg = second_notify.wait_for("STATUS")
        assert "another stagectl daemon" in msg["STATUS"] and str(os.getpid()) in msg["STATUS"]
        assert marker.read_text() == before  # the first one's run marker untouched
        with ControlClient(tmp_path / "run" / "control.sock") as c:  # its socket still there and answering
            assert c.request({"request": "status"})["status"]["state"] == "active"
    finally:
        second_notify.close()
        assert first.stop() == 0


def test_stop_gets_through_32_half_open_clients_and_a_flood(tmp_path, notify_socket, rig_loader, rig_builder):
    cfg = _cfg(tmp_path / "s.yaml", tmp_path)
    svc = _Svc(cfg, tmp_path, notify_socket.path, rig_loader, rig_builder)
    path = str(tmp_path / "run" / "control.sock")
    half_open: list[socket.socket] = []
    done = threading.Event()
    flooded = [0]

    def flood() -> None:
        line = b'{"request": "status"}\n' * 64
        while not done.is_set():
            try:
                with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                    s.settimeout(5)
                    s.connect(path)
                    while not done.is_set():
                        s.sendall(line)
                        flooded[0] += 64
                        s.recv(65536)
            except OSError:
                continue  # evicted or dropped for not keeping up: come back

    try:
        notify_socket.wait_for("READY", "1", alive=svc.alive)
        for i in range(32):
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.connect(path)
            if i % 2:
                s.sendall(b'{"request": "sta')  # stalled mid-line
            half_open.append(s)
        flooders = [threading.Thread(target=flood, daemon=True) for _ in range(4)]
        for t in flooders:
            t.start()
        while flooded[0] < 2000:  # the flood is on before stop is sent
            notify_socket.wait_for("STATUS")
        with ControlClient(path) as c:
            assert c.request({"request": "move", "relative_m": 2e-4})["ok"]
            r = c.request({"request": "stop", "id": "halt"})
            assert r["ok"] and r["id"] == "halt" and "x_m" in r, r
            st = c.request({"request": "status"})["status"]
        assert st["state"] == "active" and st["loop"]["fault"] is None
        assert st["control"]["evicted"] >= 1
        # the loop ran in its own process (it owns the devices; the flood was served by this one)
        assert st["isolation"] == "process" and st["loop_pid"] != os.getpid() and st["pid"] == os.getpid()
    finally:
        done.set()
        for s in half_open:
            s.close()
        assert svc.stop() == 0


def test_observer_socket_is_read_only(tmp_path, notify_socket, rig_loader, rig_builder):
    cfg = _cfg(tmp_path / "s.yaml", tmp_path)
    svc = _Svc(cfg, tmp_path, notify_socket.path, rig_loader, rig_builder)
    obs = tmp_path / "run" / "observer.sock"
    try:
        notify_socket.wait_for("READY", "1", alive=svc.alive)
        assert stat.S_IMODE(os.stat(obs).st_mode) == 0o660
        with ControlClient(obs) as c:
            assert c.request({"request": "status"})["status"]["state"] == "active"
            assert c.request({"request": "gains"})["controller"]["kp_n_m"] == 4e4
            for kind in ("move", "stop", "reset", "record", "fault"):
                r = c.request({"request": kind, "target_m": 1e-4})
                assert r["ok"] is False and r["field"] == "request" and "read-only" in r["error"], r
        with ControlClient(tmp_path / "run" / "control.sock") as c:  # the control socket still commands
            assert c.request({"request": "move", "target_m": 1e-5})["ok"]
    finally:
        assert svc.stop() == 0
    assert not obs.exists()


def test_health_policy_follows_the_io(tmp_path, notify_socket, rig_loader, rig_builder):
    """The rig is a simulated plant: `auto` asks only that the loop cycles (liveness); real devices
    (simulated=False) keep the overrun limit; an explicit policy wins."""
    import dataclasses

    def real_builder(app_cfg):
        return dataclasses.replace(rig_builder(app_cfg), simulated=False)

    for builder, health, want in ((rig_builder, "auto", "liveness"), (real_builder, "auto", "realtime"),
                                  (rig_builder, "realtime", "realtime")):
        cfg = _cfg(tmp_path / "s.yaml", tmp_path, health=health)
        svc = _Svc(cfg, tmp_path, notify_socket.path, rig_loader, builder)
        try:
            ready = notify_socket.wait_for("READY", "1", alive=svc.alive)
            assert svc.dut.status()["health_policy"] == want
            assert ("health liveness" in ready["STATUS"]) == (want == "liveness")
            limit = svc.dut.watchdog.limit
            assert limit == (1.0 if want == "liveness" else svc.dut.asm.loop.cfg.healthy_overrun_fraction)
        finally:
            assert svc.stop() == 0


def test_watchdog_liveness_pings_through_overruns_realtime_withholds(notify_socket):
    from stagectl.daemon.watchdog import Watchdog
    from stagectl.runtime.status import LoopState, LoopStatus

    def st(cycle, overruns):
        return LoopStatus(state=LoopState.ACTIVE, fault=None, t_s=0.0, x_m=0.0, x_ref_m=0.0, e_m=0.0, u_n=0.0,
                          cycle=cycle, overruns=overruns, recent_overrun_fraction=0.0, period_s=1e-3, running=True,
                          healthy=True)

    live, strict = Watchdog(SdNotifier(str(notify_socket.path)), 1.0), Watchdog(SdNotifier(environ={}), 0.01)
    for k in range(1, 5):  # half the slots skipped (a loaded machine)
        live.check(st(1000 * k, 1000 * k))
        strict.check(st(1000 * k, 1000 * k))
    assert live.pings == 3 and not live.reason
    assert strict.pings == 0 and "overruns" in strict.reason
    st_stalled = st(4000, 4000)
    live.check(st_stalled)  # not advancing: withheld under either policy
    assert live.reason == "cycle counter not advancing"


def test_unwritable_telemetry_with_refuse_policy_does_not_start(tmp_path, notify_socket, rig_loader, rig_builder):
    blocker = tmp_path / "file"
    blocker.write_text("x")  # a file where a directory should be: not writable even as root
    cfg = _cfg(tmp_path / "s.yaml", tmp_path, telemetry={"directory": str(blocker / "tel"), "on_error": "refuse"})
    svc = _Svc(cfg, tmp_path, notify_socket.path, rig_loader, rig_builder)
    assert svc.join() == 1
    assert svc.builds == 0  # refused before any device was opened
    msg = notify_socket.wait_for("STATUS")
    while "not writable" not in msg["STATUS"]:
        msg = notify_socket.wait_for("STATUS")
    assert "on_error: refuse" in msg["STATUS"] and "file" in msg["STATUS"]


def test_fault_cleared_before_the_supervisor_looked_is_still_handled(tmp_path, notify_socket, rig_loader,
                                                                     rig_builder):
    cfg = _cfg(tmp_path / "s.yaml", tmp_path, allow_fault_injection=True, status_interval_s=0.5)
    svc = _Svc(cfg, tmp_path, notify_socket.path, rig_loader, rig_builder)
    try:
        notify_socket.wait_for("READY", "1", alive=svc.alive)
        with ControlClient(tmp_path / "run" / "control.sock") as c:
            assert c.request({"request": "fault", "kind": "emcy"})["ok"]
            while c.request({"request": "status"})["status"]["loop"]["faults"] < 1:  # latched (next cycle)
                pass
            r = c.request({"request": "reset"})  # well inside the supervisor's 0.5 s tick
            assert r["ok"] and r["state"] == "active" and r["cleared"]["name"] == "emcy", r
            st = c.request({"request": "status"})["status"]
            assert st["loop"]["faults"] == 1 and st["state"] == "active"
            while svc.dut.fault_flushes < 1:  # the supervisor handles it at its next tick
                notify_socket.wait_for("STATUS")
            assert svc.dut.fault_flushes == 1
    finally:
        assert svc.stop() == 0


_FULL_DISK = r"""
import json, resource, signal, sys, pathlib
import numpy as np
from stagectl.daemon.telemetry import TelemetryRing, TelemetryWriter, WriterSettings
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)        # write() then fails with EFBIG instead of killing us
resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[2]), int(sys.argv[2])))
ring = TelemetryRing(("t", "x", "u"), 4096)
w = TelemetryWriter(ring, WriterSettings(directory=pathlib.Path(sys.argv[1]), chunk_rows=7, retry_s=1e9))
produced = 0
for k in range(3000):
    ring.append((k * 1e-3, 1e-6 * k + 0.123456789, -3.25 + 1e-4 * k))
    produced += 1
    if k % 100 == 99:
        w._drain_all(sync=False)
w.stop()
print(json.dumps({"produced": produced, **w.status()}))
"""


def test_full_disk_loses_whole_rows_and_counts_every_one(tmp_path):
    """A file-size limit (RLIMIT_FSIZE, like a full disk: writes fail part-way) in a subprocess: the file ends
    on a complete row, its rows are exactly ``rows_written``, and written + lost + dropped = produced."""
    out = tmp_path / "tel"
    r = subprocess.run([sys.executable, "-c", _FULL_DISK, str(out), "20000"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    st = json.loads(r.stdout.strip().splitlines()[-1])
    files = sorted(out.glob("telemetry-*.csv"))
    assert files
    data_rows = 0
    for f in files:
        raw = f.read_bytes()
        assert raw.endswith(b"\n")  # never a truncated row
        lines = raw.decode().splitlines()
        assert lines[0] == "t,x,u"
        assert all(len(line.split(",")) == 3 for line in lines[1:])
        data_rows += len(lines) - 1
        assert f.stat().st_size <= 20000
    assert st["lost"] > 0 and "too large" in st["error"].lower()
    assert data_rows == st["rows_written"]
    assert st["rows_written"] + st["lost"] + st["dropped"] == st["produced"]


def test_reload_error_text_is_bounded(tmp_path):
    """A reload error (e.g. a YAML alias bomb's message) is shown in every status/gains reply: bounded."""
    from stagectl.daemon.reload import Reloader
    from stagectl.errors import ConfigError

    def load(path):
        raise ConfigError(["controller.pid: " + "x" * 50_000])

    dut = Reloader(load, tmp_path / "s.yaml", SdNotifier(environ={}), 1.0, lambda cfg: None, lambda: "")
    dut._reload(None, None)
    err = dut.status["error"]
    assert dut.status["ok"] is False and err.startswith("controller.pid: ") and len(err) < 2100
    assert "more characters" in err


def test_lock_held_by_a_dead_daemons_loop_process_is_waited_for_a_live_one_refused(tmp_path):
    """The loop process inherits the lock: a restart after the daemon died waits for it (bounded); a live
    holder is refused at once."""
    from stagectl.daemon.instance import InstanceLock, InstanceLockedError

    go_r, go_w = os.pipe()
    held_r, held_w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the "orphaned loop process": holds the lock until told to finish
        code = 1
        try:
            lock = InstanceLock(tmp_path)
            lock.acquire()
            os.write(held_w, b"h")
            os.read(go_r, 1)
            code = 0
        finally:
            os._exit(code)
    try:
        assert os.read(held_r, 1) == b"h"
        with pytest.raises(InstanceLockedError, match=str(pid)):  # its pid is alive: refused at once
            InstanceLock(tmp_path, orphan_wait_s=60).acquire()
        dead = subprocess.Popen([sys.executable, "-c", "pass"])
        dead.wait()
        (tmp_path / "stagectl.lock").write_text(f"{dead.pid}\n")  # the daemon named in the file is gone
        os.write(go_w, b"g")  # the loop process finishes stopping the drive
        dut = InstanceLock(tmp_path, orphan_wait_s=60)
        dut.acquire()  # waited for it instead of refusing
        assert dut.held
        dut.release()
    finally:
        os.write(go_w, b"g")
        os.waitpid(pid, 0)
        for fd in (go_r, go_w, held_r, held_w):
            os.close(fd)
