"""Service paths from the command line and systemd's environment, read in one place."""

from __future__ import annotations

from pathlib import Path

from stagectl.daemon.paths import ServicePaths


def test_explicit_directories_win_over_the_environment():
    env = {"RUNTIME_DIRECTORY": "/run/a:/run/b", "STATE_DIRECTORY": "/var/lib/s1:/var/lib/s2"}
    dut = ServicePaths.from_env("c.yaml", "/tmp/rt", "/tmp/st", environ=env)
    assert dut == ServicePaths(Path("c.yaml"), Path("/tmp/rt"), Path("/tmp/st"))
    dut = ServicePaths.from_env("c.yaml", environ=env)  # the first entry of systemd's lists
    assert dut.runtime_dir == Path("/run/a") and dut.state_dir == Path("/var/lib/s1")
    assert dut.marker_dir == Path("/var/lib/s1") and dut.telemetry_dir(None) == Path("/var/lib/s1/telemetry")
    assert dut.telemetry_dir("/data/tel") == Path("/data/tel")


def test_defaults_without_systemd():
    dut = ServicePaths.from_env("c.yaml", environ={"STATE_DIRECTORY": ""})
    assert dut.runtime_dir == Path("/run/stagectl") and dut.state_dir is None
    assert dut.marker_dir == Path("/run/stagectl") and dut.telemetry_dir(None) == Path("/run/stagectl/telemetry")


def test_bench_telemetry_is_a_bench_kind_with_the_old_options():
    import argparse

    from stagectl.bench import telemetry
    from stagectl.commands import bench

    p = argparse.ArgumentParser()
    bench.add_parser(p.add_subparsers())
    args = p.parse_args(["bench", "telemetry", "--duration-s", "2", "--rate-hz", "500", "--columns", "9", "--json"])
    assert (args.duration_s, args.rate_hz, args.columns, args.json, args.daemon) == (2.0, 500.0, 9, True, None)
    ok = {"dropped": 0, "lost": 0, "rows_in_files": 10, "rows_produced": 10}
    assert telemetry.exit_code(ok) == 0 and telemetry.exit_code({**ok, "lost": 1}) == 1
    assert telemetry.exit_code({"complete": False, "dropped_at_end": 0, "lost_at_end": 0, "exit_code": 0}) == 1
