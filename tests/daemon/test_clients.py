"""`stagectl status` rendering (the request path is covered end to end in test_end_to_end)."""

from __future__ import annotations

from stagectl.commands.clients import render_status


def test_render_status_shows_fault_telemetry_error_reload_and_watchdog():
    st = {
        "state": "fault", "drive_enabled": False,
        "loop": {"state": "fault", "x_m": -1e-13, "x_ref_m": 1.5e-3, "e_m": 1.5e-3, "u_n": 0.0, "cycle": 10,
                 "overruns": 2, "lateness_us": {"p50": 30.0, "p99": 400.0, "max": 900.0},
                 "fault": {"name": "following_error", "cause": "|e| 60 um > 50 um"}},
        "telemetry": {"rows_written": 9, "dropped": 0, "lost": 3, "recording": None, "file": None,
                      "error": "/var/lib/stagectl/telemetry: No space left on device"},
        "reload": {"ok": False, "error": "controller.pid.kp_n_m: must be > 0"},
        "watchdog": {"reason": "cycle counter not advancing"},
    }
    out = render_status(st)
    assert "x = -0.0001 nm" in out and "-0.0000" not in out  # each value in its own unit, never "-0"
    assert "x_ref = 1.5000 mm" in out
    assert "FAULT      following_error: |e| 60 um > 50 um" in out
    assert "TELEMETRY ERROR  /var/lib/stagectl/telemetry: No space left on device" in out
    assert "reload     REJECTED: controller.pid.kp_n_m" in out
    assert "watchdog   withheld: cycle counter not advancing" in out
    assert "drive disabled" in out


def test_render_status_tolerates_a_daemon_still_starting():
    out = render_status({"state": "configured", "loop": {}, "telemetry": None})
    assert out.startswith("state      configured") and "x = -" in out
