"""The command-line limits of ``commission`` (``--max-stroke``, ``--max-force``, ``--max-velocity``)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from support import cli_in_process

from stagectl.commission.envelope import make_envelope
from stagectl.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]

_CFG = {"min_position_m": -0.005, "max_position_m": 0.005, "safety_force_n": 10.0, "controller_force_n": 10.0,
        "max_velocity_m_s": 0.02, "period_s": 0.001, "following_error_m": 1e-4}


@pytest.mark.parametrize(
    ("flag", "key", "value", "fragments"),
    [
        ("--max-stroke", "max_stroke_m", -1.0, ["--max-stroke", "> 0 m", "got -1"]),
        ("--max-force", "max_force_n", 0.0, ["--max-force", "> 0 N", "got 0"]),
        ("--max-velocity", "max_speed_m_s", math.inf, ["--max-velocity", "finite", "m/s", "got inf"]),
        ("--max-stroke", "max_stroke_m", math.nan, ["--max-stroke", "finite", " m ", "got nan"]),
        ("--max-force", "max_force_n", 11.0, ["--max-force", "exceeds", "can only lower"]),
    ],
)
def test_bad_limit_names_flag_unit_and_reason(flag: str, key: str, value: float, fragments: list[str]) -> None:
    with pytest.raises(ConfigError) as exc:
        make_envelope(**_CFG, **{key: value})
    msg = str(exc.value)
    assert msg.startswith(flag), msg
    for frag in fragments:
        assert frag in msg, msg


def test_limits_only_lower_the_envelope() -> None:
    env = make_envelope(**_CFG, max_stroke_m=0.002)
    assert env.stroke_m == pytest.approx(0.002)
    assert make_envelope(**_CFG).stroke_m > 0.002


def test_an_out_directory_holding_a_commissioning_is_refused_and_left_as_it_was(tmp_path: Path) -> None:
    """A previous commissioning's report and recordings are never overwritten: one line naming --out, exit 2,
    before any experiment runs (the daemon guard and the config are checked first, nothing is written)."""
    out = tmp_path / "c"
    (out / "recordings").mkdir(parents=True)
    (out / "report.json").write_text('{"status": "complete"}')
    r = cli_in_process(["commission", "--config", str(REPO / "config" / "sim.yaml"), "--out", str(out), "-q"])
    rc, err = r.returncode, r.stderr
    assert rc == 2 and err.count("\n") == 1 and "--out" in err and "already holds a commissioning" in err, err
    assert (out / "report.json").read_text() == '{"status": "complete"}'
    assert sorted(p.name for p in out.iterdir()) == ["recordings", "report.json"]
