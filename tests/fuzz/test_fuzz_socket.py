"""Fuzz the control socket: random request lines to a running service (in process, the real ControlServer,
handlers and request parser, the real loop on a simulated mass; the rig of tests/daemon).

Invariants, per line: exactly one reply line, a JSON object with a boolean ``ok``; an error reply carries a
bounded ``error`` text (and a ``field`` when one is to blame); replies stay far below the reply limit. After
every input: the service still answers ``status`` with the loop cycling (active, or a latched fault that a
random but valid move caused), and a ``stop`` is accepted. Nothing escapes as a crash of the control thread.
"""

from __future__ import annotations

import importlib.util
import json
import sys
import threading
from pathlib import Path
from typing import Any

import yaml
from hypothesis import assume, given
from hypothesis import strategies as st

from stagectl.daemon.control import MAX_ERROR_CHARS, ControlClient
from stagectl.daemon.sdnotify import SdNotifier
from stagectl.daemon.service import StageService
from stagectl.runtime.requests import SOCKET_KINDS

sys.path.insert(0, str(Path(__file__).parent))
from fuzzing import fuzz  # noqa: E402

_spec = importlib.util.spec_from_file_location("daemon_rig", Path(__file__).parents[1] / "daemon" / "conftest.py")
assert _spec is not None and _spec.loader is not None
rig = sys.modules.setdefault("daemon_rig", importlib.util.module_from_spec(_spec))
if not hasattr(rig, "build_rig"):
    _spec.loader.exec_module(rig)

KINDS = [*SOCKET_KINDS, "status", "gains", "record", "fault", "", "STATUS", "move ", "retune", "shutdown"]
FIELDS = ["target_m", "relative_m", "max_velocity_m_s", "max_acceleration_m_s2", "action", "name", "kind",
          "id", "speed", "controller_config"]
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats(allow_nan=False, allow_infinity=False)
    | st.sampled_from([1e-3, -1e-3, 0.0, 1e300, 5e-324, 0.01, 1e-6, "start", "stop", "../x", "capture", "nan"])
    | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3),
    max_leaves=8,
)
REQUESTS = st.fixed_dictionaries({"request": st.sampled_from(KINDS) | st.text(max_size=12)},
                                 optional={f: JSON_VALUES for f in FIELDS})
LINES = st.one_of(
    REQUESTS.map(lambda r: json.dumps(r).encode()),
    st.binary(max_size=200).map(lambda b: b.replace(b"\n", b" ")),
    st.sampled_from([b"[" * 50_000, b"{\"request\": " + b"[" * 5000, b"null", b"1e999", b"\"status\"",
                     b"{\"request\": \"status\", \"id\": 1e999}", b"{\"request\": \"status\", \"id\": " + b"9" * 500 + b"}",
                     b"{\"request\": \"status\", \"id\": [1]}", b"\xff\xfe{}", b"{}" * 1000, b"{\"a\":" * 10 + b"1"]),
)


def _write_cfg(tmp_path: Path) -> Path:
    path = tmp_path / "stagectl.yaml"
    path.write_text(yaml.safe_dump({"controller": {"kp_n_m": 4e4, "kd_n_s_m": 400.0},
                                    "daemon": {"status_interval_s": 0.05, "isolation": "thread",
                                               "telemetry": {"directory": str(tmp_path / "tel")}}}))
    return path


def _one_reply(c: ControlClient) -> dict[str, Any]:
    reply = c.read_reply()
    assert isinstance(reply.get("ok"), bool), reply
    if not reply["ok"]:
        assert isinstance(reply.get("error"), str) and 0 < len(reply["error"]) <= MAX_ERROR_CHARS + 40, reply
    assert len(json.dumps(reply)) < 100_000
    return reply


def test_random_request_lines_get_one_defined_reply_each(tmp_path: Path) -> None:
    notify = rig.NotifySocket(tmp_path / "notify.sock")
    dut = StageService(_write_cfg(tmp_path), tmp_path / "run", load_config=rig.load_rig_config,
                       build=rig.build_rig, notifier=SdNotifier(str(notify.path)))
    result: dict[str, int] = {}
    thread = threading.Thread(target=lambda: result.setdefault("code", dut.run()))
    thread.start()
    try:
        notify.wait_for("READY", "1", alive=thread.is_alive)
        with ControlClient(tmp_path / "run" / "control.sock", timeout_s=30) as c:

            @fuzz(150)
            @given(st.lists(LINES, min_size=1, max_size=4))
            def run(lines: list[bytes]) -> None:
                assume(not any(b"subscribe" in line for line in lines))  # turns the connection into a stream
                for line in lines:
                    c.send_raw(line + b"\n")
                    if line.strip():  # a blank line is skipped, as in any JSON-lines protocol
                        _one_reply(c)
                st_ = c.request({"request": "status"})
                assert st_["ok"] and st_["status"]["state"] in ("active", "fault"), st_
                assert c.request({"request": "stop"})["ok"]

            run()
            st_ = c.request({"request": "status"})["status"]
            assert st_["control"]["alive"] and st_["loop"]["cycle"] > 0
    finally:
        dut.request_stop()
        thread.join(30)
        notify.close()
    assert result.get("code") == 0
