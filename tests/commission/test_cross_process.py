"""``stagectl commission`` across processes: the plant runs in ``stagectl sim-plant --lockstep`` (its own process,
a hidden model the commissioning configuration does not contain), the commissioning connects over socketcand
(loopback TCP) with a configuration that has no ``sim:`` section.

Lock-step across processes: each SYNC the commissioning sends advances the sim-plant's plant by one period and
the drive waits for its answer, so the run is deterministic and faster than real time (no wall-clock waits;
the timeouts below are failure guards). Marked slow: the complete commissioning (about 90 s of plant time,
21 s of it the pre-sliding loops; some 90 000 SYNC round trips) is most of the test's CPU time.
"""

from __future__ import annotations

import json
import selectors
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

sys.path.insert(0, str(Path(__file__).parent))
from support import stop_process

from commission_stage import assert_identified, controller_and_safety_yaml

from stagectl.cli import main
from stagectl.config import load_app_config
from stagectl.ident.recording import load_recording

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = ROOT / "config" / "models" / "kamenar2016_gms.yaml"
#: the hidden plant: mass +30 %, Coulomb +44 %, viscous +40 % against the shipped model, plus cogging
HIDDEN = {"mass_kg": 2.6, "fc_n": 1.15, "fs_n": 1.3, "viscous_n_s_m": 14.0,
          "cogging": {"amplitude_n": 0.15, "wavelength_m": 0.0005}}

pytestmark = pytest.mark.slow


def plant_yaml(faults: str = "") -> str:
    return textwrap.dedent(f"""
    sim:
      plant:
        model_file: {SHIPPED}
        mass_kg: {HIDDEN['mass_kg']}
        friction: {{fc_n: {HIDDEN['fc_n']}, fs_n: {HIDDEN['fs_n']}, viscous_n_s_m: {HIDDEN['viscous_n_s_m']}}}
        effects: {{cogging: {{amplitude_n: 0.15, wavelength_m: 0.0005}}}}
        sensor: {{resolution_m: 1.0e-9, noise_std_m: 0.5e-9}}
        actuator: {{max_force_n: 200.0}}
        seed: 3
      drive: {{node_id: 1, resolution_m: 1.0e-9, force_per_unit_n: 0.001}}
      transport: {{kind: socketcand, host: 127.0.0.1, port: 0}}
    """) + faults


def commission_yaml(port: int) -> str:
    """The commissioning side: no sim: section; the controller says the shipped (wrong) model."""
    return textwrap.dedent(f"""
    description: commissioning across processes (hidden plant in a sim-plant process)
    loop: {{period_s: 0.001}}
    io:
      kind: canopen
      sensor: drive
      drive:
        node_id: 1
        can: {{interface: socketcand, host: 127.0.0.1, port: {port}, channel: can0}}
        resolution_m: 1.0e-9
        force_per_unit_n: 0.001
        max_force_n: 10.0
        heartbeat_producer_s: 0.05
        heartbeat_timeout_s: 0.5
        controller_heartbeat_s: 0.02
        drive_consumer_timeout_s: 0.5
        sdo_timeout_s: 5.0
    """) + controller_and_safety_yaml()


def start_plant(path: Path) -> tuple[subprocess.Popen[str], dict[str, Any]]:
    proc = subprocess.Popen([sys.executable, "-m", "stagectl.cli", "sim-plant", "--config", str(path), "--lockstep"],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    assert proc.stdout is not None
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    if not sel.select(60.0):
        stop_process(proc, 5.0)
        raise AssertionError("sim-plant printed no ready line within 60 s")
    info = json.loads(proc.stdout.readline())
    assert info["ready"] and info["lockstep"] is True
    return proc, info


def commission(tmp: Path, name: str, faults: str = "", extra: tuple[str, ...] = ()) -> tuple[int, Path]:
    plant = tmp / f"{name}-plant.yaml"
    plant.write_text(plant_yaml(faults))
    proc, info = start_plant(plant)
    try:
        cfg = tmp / f"{name}.yaml"
        cfg.write_text(commission_yaml(info["can"]["port"]))
        assert "sim" not in yaml.safe_load(cfg.read_text())
        out = tmp / name
        rc = main(["commission", "--config", str(cfg), "--out", str(out), "--lockstep", "--no-plots",
                   "--max-stroke", "0.002", *extra])
        assert proc.poll() is None, "the sim-plant process died during the commissioning"
    finally:
        stop_process(proc, 10.0)
    assert proc.returncode == 0
    return rc, out


@pytest.fixture(scope="module")
def commissioned(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[int, Path]]:
    yield commission(tmp_path_factory.mktemp("xproc"), "out")


def test_identifies_the_hidden_plant_across_processes(commissioned: tuple[int, Path]) -> None:
    rc, out = commissioned
    assert rc == 0
    rep = json.loads((out / "report.json").read_text())
    assert_identified(rep, HIDDEN)
    assert main(["check-config", "-q", str(out / "stage.yaml")]) == 0
    ch = rep["gains"]["chosen"]
    assert ch["measured"]["phase_margin_deg"] >= 40 and ch["measured"]["gain_margin_db"] >= 8


def _on_hidden_plant(out: Path, name: str, controller: dict[str, Any]) -> Path:
    """A plant_io configuration: the hidden plant (embedded, lock-step) under ``controller``."""
    data = yaml.safe_load((out / "stage.yaml").read_text())
    plant = yaml.safe_load(plant_yaml())["sim"]
    del plant["drive"], plant["transport"]
    data["io"] = {"kind": "plant_io", "sensor": "drive", "delay_cycles": 1}
    data["sim"] = plant
    data["controller"] = controller
    path = out / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def against_exact(commissioned: tuple[int, Path]) -> dict[str, dict[str, dict[str, Any]]]:
    """DIR/stage.yaml's controller and the same gains given the exact hidden model (mass, friction, cogging),
    both on the hidden plant, through the verification's protocol (approach move, then the scenario)."""
    from stagectl.commission.sequence import simulate_verification

    _rc, out = commissioned
    ctl = yaml.safe_load((out / "stage.yaml").read_text())["controller"]
    ctl["feedforward"]["model_file"] = str(out / ctl["feedforward"]["model_file"])
    exact_model = yaml.safe_load(SHIPPED.read_text())
    exact_model["mass_kg"] = HIDDEN["mass_kg"]
    exact_model["friction"].update(fc_n=HIDDEN["fc_n"], fs_n=HIDDEN["fs_n"], viscous_n_s_m=HIDDEN["viscous_n_s_m"])
    exact_model["effects"] = {"cogging": HIDDEN["cogging"]}
    (out / "exact.yaml").write_text(yaml.safe_dump(exact_model))
    # the same total look-ahead: the commissioned feed-forward adds its model's effects.delay (when discover
    # named one) to lookahead_s; the exact model has none
    comm_delay = float((yaml.safe_load(Path(ctl["feedforward"]["model_file"]).read_text()).get("effects") or {})
                       .get("delay", {}).get("delay_s", 0.0))
    exact = dict(ctl, mass_kg=HIDDEN["mass_kg"],
                 feedforward=dict(ctl["feedforward"], model_file=str(out / "exact.yaml"),
                                  lookahead_s=float(ctl["feedforward"]["lookahead_s"]) + comm_delay))
    res = {}
    for name, c in (("new", ctl), ("exact", exact)):
        res[name] = simulate_verification(load_app_config(_on_hidden_plant(out, f"check-{name}", c)), 0.002, 10e-9)
    (out / "against_exact.json").write_text(json.dumps(res, default=str))
    return res


def test_commissioned_controller_tracks_within_2x_of_the_exact_model_one(
        against_exact: dict[str, dict[str, dict[str, Any]]]) -> None:
    """The issue's tracking criterion: DIR/stage.yaml's controller within 2x of the same gains given the exact
    hidden model on the cosine (pre-sliding: the identified GMS elements) and the triangle (sliding), and
    the 10 um steps within 4x and settling as often as with the exact model. Measured: cosine 2.36 / 1.62 nm,
    triangle 109 / 105 nm, steps 60.5 / 63.7 nm with 4/4 settled each (docs/commissioning.md)."""
    new, ex = against_exact["new"], against_exact["exact"]
    for sc in ("cosine", "triangle"):
        assert new[sc]["rms_error_m"] <= 2.0 * ex[sc]["rms_error_m"], (sc, new[sc], ex[sc])
    assert new["steps"]["rms_error_m"] <= 4.0 * ex["steps"]["rms_error_m"], (new["steps"], ex["steps"])
    assert new["steps"]["moves_settled"] >= min(1, ex["steps"]["moves_settled"]), (new["steps"], ex["steps"])


def test_issue_criterion_all_10um_steps_settle(against_exact: dict[str, dict[str, dict[str, Any]]]) -> None:
    """The issue's settling criterion: every 10 um step of DIR/stage.yaml's controller settles within +-10 nm on
    the hidden plant. It did not (2 of 4, as with the exact model and the same gains) until the commissioning
    offered the rest spring, checked on the twin before it is advised (docs/commissioning.md, *gains*)."""
    new = against_exact["new"]
    assert new["steps"]["moves_settled"] == new["steps"]["moves"], new["steps"]


def test_fault_mid_sequence_leaves_the_drive_disabled_and_recordings_readable(
        commissioned: tuple[int, Path], tmp_path: Path) -> None:
    """A drive fault scripted in the sim-plant process (sim.faults, device time = SYNC count) during the
    constant-velocity passes: the sequence aborts, the drive is left disabled, the recordings are readable."""
    _rc, out = commissioned
    rep = json.loads((out / "report.json").read_text())
    # the plant's time at the middle of friction_cv, from the complete (deterministic) run
    t = 0.0
    for e in rep["experiments"]:
        if e["name"] == "friction_cv":
            t += 0.5 * e["duration_s"]
            break
        t += e["duration_s"]
    faults = f"  faults:\n    - {{kind: drive_fault, at_time_s: {t:.3f}, code: 0x2310}}\n"
    rc, out2 = commission(tmp_path, "fault", faults, ("--no-verify",))
    assert rc == 1
    rep2 = json.loads((out2 / "report.json").read_text())
    assert rep2["status"] == "aborted" and rep2["aborted"]["experiment"] == "friction_cv"
    assert rep2["aborted"]["drive_state_after"] != "enabled"
    assert rep2["experiments"][-1]["fault"] is not None
    for name in ("sanity", "frf", "friction_cv"):
        rec = load_recording(out2 / "recordings" / f"{name}.csv", min_rows=100)
        assert rec.t[-1] > rec.t[0]
    assert not (out2 / "stage.yaml").exists()
