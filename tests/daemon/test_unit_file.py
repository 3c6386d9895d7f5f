"""systemd/stagectl.service (and its drop-ins socketcand.conf, simulated.conf): `systemd-analyze verify` silent,
security exposure <= 1.5 (measured with systemd 252: 1.3 alone, 1.4 with socketcand.conf, 0.4 with
simulated.conf), RT options intact without capabilities (the resource limits allow them).

`systemd-analyze verify` fails when ExecStart's binary does not exist, and /usr/local/bin/stagectl does not
exist on a build machine, so the tests verify a temporary copy whose ExecStart points at this checkout's
installed entry point (the same program, another path). Every other line is verified unchanged.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

UNIT = Path(__file__).resolve().parents[2] / "systemd" / "stagectl.service"
DROPINS = ("socketcand", "simulated")
ANALYZE = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze not installed (CI installs systemd)")


def _entry_point() -> str:
    exe = Path(sys.executable).parent / "stagectl"
    return str(exe) if exe.exists() else shutil.which("stagectl") or "/bin/true"


@pytest.fixture
def unit_copy(tmp_path) -> Path:
    text = UNIT.read_text()
    assert "ExecStart=/usr/local/bin/stagectl daemon --config /etc/stagectl/stagectl.yaml" in text
    dst = tmp_path / "stagectl.service"
    dst.write_text(text.replace("/usr/local/bin/stagectl", _entry_point()))
    return dst


def _with_dropin(unit_copy: Path, dropin: str | None) -> Path:
    """The unit with a drop-in's lines appended (later assignments in one file merge exactly as a drop-in's)."""
    if dropin is None:
        return unit_copy
    dst = unit_copy.with_name(f"stagectl-{dropin}.service")
    dst.write_text(unit_copy.read_text() + "\n" + (UNIT.parent / f"{dropin}.conf").read_text())
    return dst


@needs_analyze
@pytest.mark.parametrize("dropin", [None, *DROPINS])
def test_verify_prints_nothing(unit_copy, dropin):
    # verify exits 0 on parse warnings (unknown key, bad value): any output at all is a failure
    r = subprocess.run([ANALYZE, "verify", str(_with_dropin(unit_copy, dropin))], capture_output=True, text=True,
                       timeout=60)
    assert (r.returncode, r.stdout, r.stderr) == (0, "", "")


@needs_analyze
def test_verify_would_catch_a_typo(tmp_path, unit_copy):
    bad = tmp_path / "typo" / "stagectl.service"
    bad.parent.mkdir()
    bad.write_text(unit_copy.read_text().replace("WatchdogSec=", "WatchdogSecs="))
    r = subprocess.run([ANALYZE, "verify", str(bad)], capture_output=True, text=True, timeout=60)
    assert "WatchdogSecs" in r.stderr  # the check above is not vacuous


@needs_analyze
@pytest.mark.parametrize("dropin,limit", [(None, 1.5), ("socketcand", 1.5), ("simulated", 0.5)])
def test_security_exposure(unit_copy, dropin, limit):
    r = subprocess.run([ANALYZE, "security", "--offline=true", str(_with_dropin(unit_copy, dropin))],
                       capture_output=True, text=True, timeout=60)
    m = re.search(r"Overall exposure level for \S+: (\d+(?:\.\d+)?)", r.stdout + r.stderr)
    assert m, r.stdout[-2000:] + r.stderr
    assert float(m.group(1)) <= limit


def _settings(path: Path = UNIT) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in path.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith(("#", "[")) and "=" in line:
            k, v = line.split("=", 1)
            out.setdefault(k, []).append(v)
    return out


def test_unit_keeps_what_the_loop_needs():
    s = _settings()
    assert s["Type"] == ["notify"] and s["NotifyAccess"] == ["main"]
    assert s["Restart"] == ["on-failure"] and s["WatchdogSec"]
    assert s["ExecReload"] == ["/bin/kill -HUP $MAINPID"]
    assert s["CPUSchedulingPolicy"] == ["fifo"] and s["LimitMEMLOCK"] == ["infinity"]
    # no capabilities: SCHED_FIFO up to LimitRTPRIO and mlockall up to LimitMEMLOCK are allowed unprivileged,
    # so the limit must cover the unit's priority and every shipped configuration's fifo_priority
    assert "AmbientCapabilities" not in s and s["CapabilityBoundingSet"] == [""]
    rtprio = int(s["LimitRTPRIO"][0])
    assert rtprio >= int(s["CPUSchedulingPriority"][0])
    for cfg in sorted((UNIT.parents[1] / "config").glob("*.yaml")):
        prio = (((yaml.safe_load(cfg.read_text()) or {}).get("loop") or {}).get("realtime") or {}).get("fifo_priority")
        assert prio is None or prio <= rtprio, (cfg.name, prio)
    assert s["RestrictAddressFamilies"] == ["AF_UNIX AF_CAN AF_NETLINK"]  # SocketCAN, no Internet sockets
    for key in ("User", "Group", "RuntimeDirectory", "StateDirectory", "LogsDirectory", "ConfigurationDirectory"):
        assert s[key] == ["stagectl"], key
    assert s["PrivateUsers"] == ["yes"] and s["PrivateMounts"] == ["yes"] and s["DevicePolicy"] == ["closed"]
    # docs/platform.md section 5: these break a real-time Python daemon on SocketCAN
    assert s.get("RestrictRealtime", ["no"]) == ["no"]
    assert "PrivateDevices" not in s and "PrivateNetwork" not in s
    # numba's JIT needs writable+executable memory: off, and the file says why
    assert s["MemoryDenyWriteExecute"] == ["no"]
    text = UNIT.read_text()
    assert re.search(r"MemoryDenyWriteExecute=yes: numba .*writable and executable", text.replace("\n#", ""))
    # the loop's syscalls stay allowed: sched_setscheduler/affinity (in @system-service's @resources)
    allow, deny = s["SystemCallFilter"][0], s["SystemCallFilter"][1:]
    assert allow == "@system-service" and all(d.startswith("~") for d in deny)
    denied = {w for d in deny for w in d[1:].split()}
    assert not {"sched_setscheduler", "sched_setaffinity", "sched_setparam", "setpriority", "@resources"} & denied


def test_dropins_say_what_they_change():
    tcp = _settings(UNIT.parent / "socketcand.conf")
    assert tcp["RestrictAddressFamilies"] == ["", "AF_UNIX AF_INET AF_INET6"] and tcp["IPAddressAllow"]
    sim = _settings(UNIT.parent / "simulated.conf")
    assert sim["PrivateNetwork"] == ["yes"] and sim["PrivateDevices"] == ["yes"]
    assert sim["RestrictAddressFamilies"] == ["", "AF_UNIX"]


@needs_analyze
def test_denied_syscalls_are_in_resources_and_the_scheduler_ones_are_not():
    """What the deny list takes away is really part of @system-service (via @resources), and what the loop
    needs from @resources is still in it."""
    r = subprocess.run([ANALYZE, "syscall-filter", "@resources"], capture_output=True, text=True, timeout=60, check=False)
    resources = {ln.strip() for ln in r.stdout.splitlines()[1:] if ln.strip() and not ln.strip().startswith("#")}
    deny = {w for line in _settings()["SystemCallFilter"][1:] for w in line.lstrip("~").split()
            if not w.startswith("@")}
    assert deny and deny <= resources
    assert {"sched_setscheduler", "sched_setaffinity"} <= resources - deny


def test_daemon_stops_within_the_units_stop_timeout():
    """SIGTERM → exit 0 within TimeoutStopSec: the daemon's own stop budget (halt, disable, flush) must fit in it,
    with room for the Python interpreter's exit; the watchdog is pinged at most every WatchdogSec/2."""
    from stagectl.config.daemon import DaemonConfig

    s = _settings()

    def seconds(v: str) -> float:
        m = re.fullmatch(r"(\d+(?:\.\d+)?)\s*(ms|s|min)?", v.strip())
        assert m, v
        return float(m.group(1)) * {"ms": 1e-3, "s": 1.0, "min": 60.0, None: 1.0}[m.group(2)]

    assert DaemonConfig().stop_timeout_s + 5.0 <= seconds(s["TimeoutStopSec"][0])
    assert s["KillMode"] == ["mixed"]  # SIGTERM to the daemon only; SIGKILL to everything after the timeout
    assert seconds(s["WatchdogSec"][0]) >= 2 * 0.5  # the supervisor checks health every <= 0.5 s


def test_documentation_path_is_where_the_readme_install_puts_the_readme():
    """Documentation= names the file pip installs: data files go under the environment's prefix, which is the
    venv of the README's "Installing on a stage PC" (not /usr/local, where only the stagectl link lives)."""
    import tomllib

    root = UNIT.parents[1]
    prefix = re.search(r"python3\.11 -m venv (/\S+) && \1/bin/pip install", (root / "README.md").read_text())
    assert prefix, "README: the stage PC install into a venv"
    data = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["data-files"]
    assert "README.md" in data["share/doc/stagectl"]
    doc = re.search(r"^Documentation=file://(\S+)$", UNIT.read_text(), re.M)
    assert doc and doc.group(1) == f"{prefix.group(1)}/share/doc/stagectl/README.md"
