"""Assembly end to end in simulated time: PlantIO and the real CiA 402 driver against the virtual drive
(lock-step, python-can virtual bus), simulate outputs, safety with injected CANopen faults, teardown."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from stagectl.app import build_stage
from stagectl.clock import SimClock
from stagectl.commands.simulate import simulate
from stagectl.config import parse_app_config
from stagectl.drivers.base import DeviceState
from stagectl.loop import LoopState
from stagectl.recorder import Recorder
from stagectl.runtime.requests import MoveRequest, ResetRequest, RetuneRequest

REPO = Path(__file__).resolve().parents[2]
SIM_YAML = REPO / "config" / "sim.yaml"


def sim_cfg(**io):
    data = yaml.safe_load(SIM_YAML.read_text())
    data["io"].update(io)
    return parse_app_config(data, SIM_YAML)  # relative model paths resolve next to config/sim.yaml


@pytest.fixture(scope="module")
def plant_io_cfg():
    return sim_cfg(kind="plant_io")


@pytest.fixture(scope="module")
def canopen_cfg():
    return sim_cfg(kind="embedded_canopen")


def test_simulate_writes_csv_summary_and_plot(plant_io_cfg, tmp_path):
    s = simulate(plant_io_cfg, "steps", 0.6, tmp_path, plots=True)
    header = (tmp_path / "telemetry.csv").read_text().splitlines()[0].split(",")
    assert header[:7] == ["t", "x", "u", "x_ref", "v_ref", "a_ref", "e"]
    assert {"u_pid", "u_dob", "u_ff", "u_inertia"} <= set(header)
    data = np.loadtxt(tmp_path / "telemetry.csv", delimiter=",", skiprows=1)
    assert data.shape == (600, len(header))
    assert np.all(np.diff(data[:, 0]) > 0)
    summary = json.loads((tmp_path / "summary.json").read_text())
    for key in ("rms_error_m", "max_error_m", "settling_time_s", "fault", "loop"):
        assert key in summary
    assert summary["fault"] is None and s["loop"]["cycles"] == 600
    assert (tmp_path / "tracking.png").stat().st_size > 10_000
    # the stage really moved by the first 10 um step and tracks it
    assert data[-1, 3] == pytest.approx(10e-6, abs=1e-12)
    assert abs(data[-1, 1] - 10e-6) < 0.5e-6


def test_same_loop_code_through_virtual_canopen_drive(plant_io_cfg, canopen_cfg):
    """Lock-step: the real CiA 402 driver against the virtual drive; the trajectory matches PlantIO's."""
    out = {}
    for name, cfg in (("plant_io", plant_io_cfg), ("canopen", canopen_cfg)):
        with build_stage(cfg, clock=SimClock()) as stage:
            rec = Recorder(stage.loop.columns, 1000)
            stage.loop.add_sink(rec)
            stage.load_scenario("cosine")
            res = stage.loop.run(duration_s=0.5)
            assert res.fault is None and res.overruns == 0
            if name == "canopen":
                assert stage.world is not None and stage.actuator.state is DeviceState.CONFIGURED
            out[name] = rec
    xa, xb = out["plant_io"].col("x"), out["canopen"].col("x")
    assert xa.size == xb.size == 500
    assert np.max(np.abs(xa - xb)) < 0.2e-6  # same plant, same timing; force quantised to 10 mN on the bus
    assert np.max(np.abs(out["canopen"].col("e"))) < 1e-6


@pytest.mark.parametrize("kind,expect", [("drive_fault", "drive_fault"), ("heartbeat_stop", "heartbeat_lost"),
                                         ("drop_tpdo", "missed_frame")])
def test_canopen_faults_stop_the_drive_and_latch(canopen_cfg, kind, expect):
    with build_stage(canopen_cfg, clock=SimClock()) as stage:
        loop, world = stage.loop, stage.world
        probe = []
        loop.add_sink(type("P", (), {"append": lambda self, row: probe.append(world.drive.force_n)})())
        loop.submit(MoveRequest(target_m=5e-6))
        loop.on_cycle = lambda: loop.cycle == 100 and world.inject_fault(kind, at_cycle=None)
        loop.run(cycles=100 + int(0.5 / canopen_cfg.loop.period_s))
        st = loop.status()
        assert st.state is LoopState.FAULT
        assert st.fault.name in (expect, "emcy"), st.fault
        k = st.fault.cycle
        assert k >= 100
        # the drive's force: zero, or, after a quick stop (0x605A = 3, the default), its braking on the current
        # limit until the stage stands, then zero
        lim = world.drive.max_torque_units * world.drive.cfg.force_per_unit_n
        assert all(abs(f) <= lim + 1e-9 for f in probe[k + 3:]) and probe[-1] == 0.0, probe[k - 2:k + 6]
        assert all(f == 0.0 for f in probe[k + 3:]) or world.drive.brake_periods > 0
        assert world.drive.state.name != "OPERATION_ENABLED"
    assert stage.actuator.state is DeviceState.CLOSED


def test_canopen_fault_reset_re_enables(canopen_cfg):
    with build_stage(canopen_cfg, clock=SimClock()) as stage:
        loop, world = stage.loop, stage.world
        loop.on_cycle = lambda: loop.cycle == 50 and world.inject_fault("drive_fault")
        loop.run(cycles=80)
        assert loop.status().fault.name in ("drive_fault", "emcy")
        world.clear_faults()
        loop.on_cycle = None
        fut = loop.submit(ResetRequest())
        mv = None
        loop.run(cycles=5)
        assert fut.result(timeout=0)["state"] == "active"
        mv = loop.submit(MoveRequest(relative_m=2e-6))
        loop.run(cycles=400)
        assert mv.result(timeout=0)["target_m"] == pytest.approx(loop.status().x_ref_m)
        assert loop.status().fault is None


def test_stage_exit_disables_the_drive_after_an_exception(canopen_cfg):
    with pytest.raises(RuntimeError, match="boom"):
        with build_stage(canopen_cfg, clock=SimClock()) as stage:
            stage.loop.run(cycles=10)
            drive = stage.actuator
            raise RuntimeError("boom")
    assert drive.state is DeviceState.CLOSED
    assert stage.world.drive.force_n == 0.0


def test_run_command_smoke(tmp_path, capsys):
    """`stagectl run` real time for a fraction of a second (in-process, loop in its own thread): asserts on
    the outputs only, never on timing."""
    from stagectl.cli import main

    rc = main(["run", "--config", str(SIM_YAML), "--duration", "0.3", "--out", str(tmp_path), "--no-plots"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    summary = json.loads(out.out.strip().splitlines()[-1])
    assert summary["command"] == "run" and summary["fault"] is None
    assert summary["loop"]["ended_by"] == "duration"
    assert "stagectl run: sim.yaml" in out.err
    rows = (tmp_path / "telemetry.csv").read_text().splitlines()
    assert rows[0].startswith("t,x,u,x_ref,v_ref,a_ref,e")
    assert len(rows) > 10
    assert json.loads((tmp_path / "summary.json").read_text())["scenario"] == "demo"


def test_run_quiet_says_nothing_but_warnings(tmp_path, capsys):
    """`run -q` (scripts): no start, progress or outputs line on stderr; the summary on stdout names the
    directory."""
    from stagectl.cli import main

    rc = main(["run", "--config", str(SIM_YAML), "--duration", "0.1", "--out", str(tmp_path), "--no-plots", "-q"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "stagectl run:" not in out.err, out.err
    assert json.loads(out.out.strip().splitlines()[-1])["out"] == str(tmp_path)


def test_stop_decelerates_and_holds_without_going_back():
    from stagectl.control.reference import TrajectoryReference

    ref = TrajectoryReference()
    ref.hold(0.0, 0.0)
    assert ref.move(0.0, 100e-6, 1e-3) > 0.1
    t = 0.0
    for _ in range(30):
        t += 1e-3
        before = ref.sample(t)
    assert before.v_m_s > 0
    end = ref.stop(t)
    assert end > before.x_m and ref.target_m == end
    path = []
    for _ in range(300):
        t += 1e-3
        path.append(ref.sample(t))
    assert min(r.v_m_s for r in path) >= 0.0  # decelerates, never reverses
    assert path[-1] == (end, 0.0, 0.0)
    assert max(r.x_m for r in path) <= end + 1e-15


def test_retune_with_the_stage_controller(plant_io_cfg):
    """A good tuning is designed in the requesting thread and swapped in at the next step; a bad one raises
    at the request (the loop keeps its old tuning)."""
    import dataclasses

    from stagectl.errors import ConfigError

    with build_stage(plant_io_cfg, clock=SimClock()) as stage:
        loop, ctl = stage.loop, stage.controller
        old = ctl.cfg
        new = dataclasses.replace(old, pid=dataclasses.replace(old.pid, kp_n_m=old.pid.kp_n_m * 0.5))
        # a model file the configuration loader did not resolve (the controller itself reads no file)
        bad = dataclasses.replace(old, feedforward=dataclasses.replace(old.feedforward, model_file=Path("nope.yaml"),
                                                                       model=None))
        with pytest.raises(ConfigError, match="nope.yaml"):
            loop.submit(RetuneRequest(controller_config=bad))
        fut = loop.submit(RetuneRequest(controller_config=new))
        loop.run(cycles=5)
        assert fut.result(timeout=0) == {"retuned": True}
        assert ctl.cfg.pid.kp_n_m == pytest.approx(old.pid.kp_n_m * 0.5)
        assert loop.status().fault is None


def test_a_controller_hunting_at_its_own_clamp_latches_force_limit(tmp_path):
    """controller.mass_kg 2000 (grams typed as kg) on the 2 kg stage: the real controller hunts at ±10 N, its own
    clamp, which equals safety.max_force_n, so the safety never saw a force outside its limit; it ran so for
    ever (±10 N, 12 µm error, below the following-error window). Its ``limited`` flag now keeps the saturation
    clock running: force_limit after force_saturation_time_s."""
    data = yaml.safe_load(SIM_YAML.read_text())
    data["io"]["kind"] = "plant_io"
    data["controller"]["mass_kg"] = 2000.0
    s = simulate(parse_app_config(data, SIM_YAML), "cosine", 0.8, tmp_path, plots=False)
    assert s["fault"] is not None and s["fault"]["name"] == "force_limit", s["fault"]
    assert "controller's limit" in s["fault"]["cause"]
    assert s["fault"]["t_s"] == pytest.approx(data["safety"]["force_saturation_time_s"], abs=0.05)


def test_a_retune_plans_moves_on_its_own_mass_and_force_limit(plant_io_cfg):
    """Moves are planned within safety.move_force_fraction of the usable force on the controller's mass
    (ForceBudget). A retune (the daemon's SIGHUP reload) that changes controller.mass_kg and max_force_n is
    swapped in at the controller's next step; the budget follows it there, not only at the next reset."""
    import dataclasses

    with build_stage(plant_io_cfg, clock=SimClock()) as stage:
        loop, ctl, gen = stage.loop, stage.controller, stage.reference.gen
        loop.run(cycles=3)
        frac = plant_io_cfg.safety.move_force_fraction
        before = gen.force_budget
        assert before is not None and before.mass_kg == pytest.approx(ctl.mass_kg)
        old = ctl.cfg
        new = dataclasses.replace(old, mass_kg=2.0 * ctl.mass_kg, max_force_n=0.5 * ctl.force_limit_n)
        fut = loop.submit(RetuneRequest(controller_config=new))
        loop.run(cycles=3)
        assert fut.result(timeout=0) == {"retuned": True} and ctl.mass_kg == pytest.approx(2.0 * before.mass_kg)
        after = gen.force_budget
        assert after is not None
        assert after.mass_kg == pytest.approx(ctl.mass_kg)
        assert after.force_n == pytest.approx(frac * min(ctl.force_limit_n, stage.safety.force_limit_n))
        assert after.force_n == pytest.approx(0.5 * before.force_n)
