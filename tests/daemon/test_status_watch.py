"""`stagectl status --watch`: Ctrl-C ends the watch as asked (exit 0); a SIGTERM exits 143 as every other
foreground command does (README, *CLI*; it exited 0, review16). The service runs in-process on the rig; the
signal is raised inside the watch's second sleep, so nothing waits on the wall clock."""

from __future__ import annotations

import signal

import pytest
import yaml

from stagectl import cli
from stagectl.commands import clients
from stagectl.daemon.sdnotify import SdNotifier
from stagectl.daemon.service import StageService


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 0), (signal.SIGTERM, 143)])
def test_a_watch_ends_with_0_on_ctrl_c_and_143_on_sigterm(tmp_path, notify_socket, rig_loader, rig_builder,
                                                         monkeypatch, capsys, sig, code):
    import threading

    cfg = tmp_path / "s.yaml"
    cfg.write_text(yaml.safe_dump({"controller": {"kp_n_m": 4e4, "kd_n_s_m": 400.0},
                                   "daemon": {"status_interval_s": 0.05,
                                              "telemetry": {"directory": str(tmp_path / "tel")}}}))
    svc = StageService(cfg, tmp_path / "run", load_config=rig_loader, build=rig_builder,
                       notifier=SdNotifier(str(notify_socket.path)), state_dir=tmp_path / "state")
    codes: list[int] = []
    th = threading.Thread(target=lambda: codes.append(svc.run()))
    th.start()
    try:
        notify_socket.wait_for("READY", "1", alive=th.is_alive)
        seen = [0]
        real_sleep = clients.time.sleep

        def sleep(s):  # the watch's sleep between two statuses, in the main thread only (the service sleeps too)
            if threading.current_thread() is threading.main_thread():
                seen[0] += 1
                if seen[0] == 2:
                    signal.raise_signal(sig)  # the handler runs here: the interrupt comes out of the sleep
            return real_sleep(s)

        monkeypatch.setattr(clients.time, "sleep", sleep)
        before = signal.getsignal(signal.SIGTERM)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # as in a fresh process: the CLI installs its own
        try:
            rc = cli.main(["status", "--watch", "0.05", "--socket", str(tmp_path / "run" / "control.sock")])
        finally:
            signal.signal(signal.SIGTERM, before)
        assert seen[0] == 2 and rc == code
        assert "Traceback" not in capsys.readouterr().err
    finally:
        svc.request_stop()
        th.join(30)
    assert codes == [0]
