"""The drive's own force limit (CiA 402 max torque 0x6072) where the loop hands it over: to the controllers
commissioning verifies inside its one :class:`CommissionController`, and a limit of 0 N (a drive that gives no
force). Whole stage in simulated time: the real CiA 402 driver and the virtual drive over python-can's virtual
bus (as tests/canopen/test_drive_force_limit.py).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from support import drive_limit_config

from stagectl.app import build_stage
from stagectl.clock import SimClock
from stagectl.config import parse_app_config
from stagectl.control.trajectory import Move, Scenario

ROOT = Path(__file__).resolve().parents[2]
SIM_YAML = ROOT / "config" / "sim.yaml"
LIMIT_N = 1.5  # below the 2 N inertia + 0.9 N friction the fast move's acceleration asks for


def _cfg(**drive: object):
    return drive_limit_config(**drive)



def test_commissioning_hands_the_drive_limit_to_the_controllers_it_verifies() -> None:
    """Commissioning's loop drives one :class:`CommissionController`; its verification runs install the given and
    the commissioned controller (``make_controller``: the configuration's 10 N) in it with no clamp of their own
    (``set_closed``, limit inf). They must work at the drive's 1.5 N as under ``stagectl run``: with the limit
    hidden from them (main at 7b6f7d9) the observer took the withheld force for a disturbance, d̂ up to 8.5 N
    while the reference moved (test_drive_force_limit.py: the same with ``stagectl run``'s controller)."""
    from stagectl.app import make_controller
    from stagectl.commission.controllers import CommissionController

    cfg = _cfg(max_force_n=LIMIT_N)
    dob: list[tuple[float, float]] = []   # (x_ref, u_dob)
    with build_stage(cfg, clock=SimClock(), controller=CommissionController(make_controller(cfg))) as st:
        ctl = st.controller
        assert isinstance(ctl, CommissionController)
        i_dob = list(st.loop.columns).index("u_dob")

        class Sink:
            def append(self, row: tuple[float, ...]) -> None:
                dob.append((row[3], row[i_dob]))

        st.loop.add_sink(Sink())
        st.loop.run(duration_s=0.01)  # an earlier experiment: the loop's start hands the limit over
        dob.clear()
        verified = make_controller(cfg)   # as Commissioning._scenario_run builds it, after the loop's start
        assert verified.force_limit_n == 10.0
        ctl.set_closed(verified)
        st.load_scenario(Scenario("fast", (Move(by_m=1e-3, max_velocity_m_s=0.01, max_acceleration_m_s2=1.0,
                                                 max_jerk_m_s3=1e4),), settle_s=0.2))
        res = st.loop.run(duration_s=0.2)
        assert res.fault is None, res.fault
        assert verified.force_limit_n == pytest.approx(LIMIT_N)
    a = np.array(dob)
    moving = np.arange(len(a)) <= np.nonzero(np.diff(a[:, 0]) != 0.0)[0][-1] + 1   # (rows up to the last change of the reference)
    assert np.max(np.abs(a[moving, 1])) < 1.0



def test_a_drive_whose_max_torque_is_zero_is_named_at_start(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A drive whose 0x6072 reads 0 clamps every command to nothing. The loop says so at start, naming the object
    (main at 7b6f7d9 said nothing: a limit not > 0 was skipped as "no limit of its own")."""
    eds = (ROOT / "config" / "eds" / "stagectl_cia402.eds").read_text()
    head, _, tail = eds.partition("[6072]")
    body, sep, rest = tail.partition("\n\n")
    assert "DefaultValue=3000" in body
    (tmp_path / "zero.eds").write_text(head + "[6072]" + body.replace("DefaultValue=3000", "DefaultValue=0")
                                       + sep + rest)
    data = yaml.safe_load(SIM_YAML.read_text())
    data["io"]["kind"] = "embedded_canopen"
    data["sim"]["drive"]["eds_file"] = str(tmp_path / "zero.eds")
    data["sim"]["plant"]["actuator"]["max_force_n"] = math.inf  # (the virtual drive keeps the EDS's 0x6072)
    cfg = parse_app_config(data, SIM_YAML)
    with caplog.at_level(logging.WARNING), build_stage(cfg, clock=SimClock()) as st:
        assert st.actuator.drive_max_units == 0 and st.actuator.force_limit_n == 0.0
        st.loop.run(duration_s=0.005)
        st.loop.run(duration_s=0.005)
    warned = [r.getMessage() for r in caplog.records if "0x6072 = 0 units" in r.getMessage()]
    assert len(warned) == 1 and "gets no force" in warned[0], [r.getMessage() for r in caplog.records]
