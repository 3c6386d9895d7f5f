"""The ``can:`` keys of a python-can interface: named ``__init__`` parameters, plus the options a bus class
takes through ``**kwargs`` (harvested from its module), only near-misses refused for such classes; the check
runs once, in the loader (opening a bus does not repeat it); vendor import noise stays out of check-config."""

from __future__ import annotations

import subprocess
import sys
import types
from pathlib import Path

import pytest
import yaml

from stagectl.drivers import canbus
from stagectl.drivers.canbus import bus_keys, bus_kwargs, can_key_problems

REPO = Path(__file__).resolve().parents[2]
MODEL = str(REPO / "config" / "models" / "kamenar2016_gms.yaml")


def _canopen_config(can: dict) -> dict:
    data = yaml.safe_load((REPO / "config" / "stage-canopen.yaml").read_text())
    data["controller"]["feedforward"]["model_file"] = MODEL
    data["io"]["drive"]["can"] = can
    return data


def _check_config(tmp_path: Path, data: dict) -> subprocess.CompletedProcess[str]:
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(data))
    return subprocess.run([sys.executable, "-m", "stagectl.cli", "check-config", str(p)], capture_output=True,
                          text=True, timeout=120)


@pytest.mark.parametrize("can", [
    {"interface": "kvaser", "channel": 0, "bitrate": 1000000, "single_handle": True, "accept_virtual": False},
    {"interface": "pcan", "channel": "PCAN_USBBUS1", "bitrate": 1000000, "auto_reset": True},
    {"interface": "slcan", "channel": "/dev/ttyACM0", "btr": "401c"},
    {"interface": "vector", "channel": 0, "bitrate": 1000000, "channel_index": 1},
])
def test_kwargs_options_of_vendor_interfaces_accepted(can):
    assert can_key_problems(can, path="io.drive.can") == []
    assert bus_kwargs(can, path="io.drive.can") == can  # what open_bus hands to can.Bus, unchanged


def test_kwargs_options_accepted_by_check_config_without_vendor_noise(tmp_path):
    data = _canopen_config({"interface": "kvaser", "channel": 0, "bitrate": 1000000, "single_handle": True,
                            "accept_virtual": False})
    r = _check_config(tmp_path, data)
    assert r.returncode == 0, r.stderr
    out = r.stdout + r.stderr
    assert "OK" in out and "Traceback" not in out
    assert "canlib is unavailable" not in out and "uptime library" not in out


@pytest.mark.parametrize("iface", ["socketcan", "socketcand", "virtual", "kvaser", "pcan"])
def test_typo_of_an_accepted_key_rejected_for_every_interface(iface):
    can = {"interface": iface, "channel": "can0", "host": "h", "port": 1, "bitrat": 1000000}
    if iface != "socketcand":
        del can["host"], can["port"]
    assert can_key_problems(can, path="io.drive.can") == [
        f"io.drive.can.bitrat: unknown key for interface {iface} (did you mean bitrate?)"]


def test_typo_of_a_harvested_kwargs_key_rejected(tmp_path):
    data = _canopen_config({"interface": "kvaser", "channel": 0, "single_handel": True})
    r = _check_config(tmp_path, data)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("stagectl: error:")]
    assert lines == ["stagectl: error: bad.yaml: io.drive.can.single_handel: unknown key for interface kvaser "
                     "(did you mean single_handle?)"]
    assert "canlib is unavailable" not in r.stdout + r.stderr


def test_unrelated_key_forwarded_for_a_kwargs_interface():
    # python-can hands keys it does not name to the interface: not a near-miss of anything, not refused
    assert can_key_problems({"interface": "socketcan", "channel": "can0", "ignore_rx_error_frames": True,
                             "zz_vendor_option": 1}) == []
    assert can_key_problems({"interface": "socketcan", "channel": "can0", 5: 1}) == [
        "can.5: unknown key for interface socketcan"]


class _StrictBus:
    def __init__(self, channel: str, bitrate: int = 500000) -> None:  # no **kwargs
        self.channel = channel


class _KwargsBus:
    def __init__(self, channel: str, **kwargs: object) -> None:
        self.polling = kwargs.get("polling_hz", 10)
        self.wide = "wide_mode" in kwargs


def test_strict_class_refuses_every_unknown_key_kwargs_class_harvests(monkeypatch):
    import can.interfaces

    mod = types.ModuleType("stagectl_test_fake_bus")
    mod._StrictBus = _StrictBus  # type: ignore[attr-defined]
    mod._KwargsBus = _KwargsBus  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, mod.__name__, mod)
    monkeypatch.setitem(can.interfaces.BACKENDS, "zz_strict", (mod.__name__, "_StrictBus"))
    monkeypatch.setitem(can.interfaces.BACKENDS, "zz_kwargs", (__name__, "_KwargsBus"))
    monkeypatch.setattr(can.interfaces, "VALID_INTERFACES",
                        can.interfaces.VALID_INTERFACES | {"zz_strict", "zz_kwargs"})
    canbus.bus_keys.cache_clear()
    try:
        strict = bus_keys("zz_strict")
        assert strict is not None and strict.strict and "bitrate" in strict.accepted
        assert can_key_problems({"interface": "zz_strict", "channel": "x", "other": 1}) == [
            "can.other: unknown key for interface zz_strict"]
        loose = bus_keys("zz_kwargs")
        assert loose is not None and not loose.strict
        assert {"polling_hz", "wide_mode"} <= loose.accepted
        assert can_key_problems({"interface": "zz_kwargs", "channel": "x", "other": 1, "wide_mode": 1}) == []
        assert can_key_problems({"interface": "zz_kwargs", "channel": "x", "poling_hz": 1}) == [
            "can.poling_hz: unknown key for interface zz_kwargs (did you mean polling_hz?)"]
    finally:
        canbus.bus_keys.cache_clear()


def test_open_bus_does_not_repeat_the_key_check():
    # the loader checked the keys; at run time a key python-can forwards must reach can.Bus
    kw = bus_kwargs({"interface": "virtual", "channel": "x", "zz_vendor_option": 1, "bitrat": 1})
    assert kw["zz_vendor_option"] == 1 and kw["bitrat"] == 1
    bus = canbus.open_bus({"interface": "virtual", "channel": "stagectl-test-can-keys", "preserve_timestamps": 1})
    canbus.close_bus(bus)


def test_can_check_runs_once(monkeypatch):
    import stagectl.config.checks as checks
    from stagectl.config import parse_app_config
    from stagectl.errors import ConfigError

    calls: list[str] = []
    real = checks.can_key_problems

    def counting(mapping, *, path="can"):
        calls.append(path)
        return real(mapping, path=path)

    monkeypatch.setattr(checks, "can_key_problems", counting)
    monkeypatch.setattr(canbus, "can_key_problems", counting)
    data = _canopen_config({"interface": "socketcan", "channel": "can0", "bitrat": 1})
    with pytest.raises(ConfigError) as ei:
        parse_app_config(data, REPO / "config" / "x.yaml")
    assert calls == ["io.drive.can"]
    assert ei.value.problems == ["x.yaml: io.drive.can.bitrat: unknown key for interface socketcan "
                                 "(did you mean bitrate?)"]


@pytest.mark.parametrize(("can", "line"), [
    ({"interface": "socketcand", "channel": "can0", "host": "127.0.0.1", "port": 70000},
     "io.drive.can.port: must be a TCP port, an integer 1..65535 (got 70000)"),
    ({"interface": "socketcand", "channel": "can0", "host": "127.0.0.1", "port": "29536"},
     "io.drive.can.port: must be a TCP port, an integer 1..65535 (got '29536')"),
    ({"interface": "socketcand", "channel": "can0", "host": "", "port": 29536},
     "io.drive.can.host: must be a host name or address (got '')"),
    ({"interface": "socketcan", "channel": "can0", "bitrate": "fast"},
     "io.drive.can.bitrate: must be a positive integer in bit/s (got 'fast')"),
    ({"interface": "pcan", "channel": "PCAN_USBBUS1", "bitrate": -500000},
     "io.drive.can.bitrate: must be a positive integer in bit/s (got -500000)"),
])
def test_bad_port_host_or_bitrate_is_refused_before_opening(can, line):
    """python-can would refuse a socketcand port only after a 10 s connect attempt, a text bitrate not at all."""
    with pytest.raises(canbus.ConfigError) as ei:
        bus_kwargs(can, path="io.drive.can")
    assert str(ei.value) == line


def test_check_config_names_a_bad_can_port(tmp_path):
    data = _canopen_config({"interface": "socketcand", "channel": "can0", "host": "127.0.0.1", "port": 70000})
    r = _check_config(tmp_path, data)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "io.drive.can.port: must be a TCP port, an integer 1..65535 (got 70000)" in r.stderr, r.stderr
