"""StageController: closed loop on the seed stage (stagectl.sim StagePlant, simulated time), TV9 structure,
trend, bumpless reset/retune, terms and limiters, input checks."""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from control_harness import (  # noqa: E402
    controller_cfg,
    make_plant,
    mismatched,
    rms_after,
    run_closed_loop,
    seed_model,
)

from stagectl.control.api import Reference  # noqa: E402
from stagectl.control.controller import TERM_NAMES, ControllerConfig, StageController  # noqa: E402
from stagectl.control.trajectory import Cosine, Scenario  # noqa: E402
from stagectl.errors import ConfigError  # noqa: E402
from stagectl.schema import load  # noqa: E402

COSINE = Scenario(name="cos", segments=(Cosine(amplitude_m=10e-6, frequency_hz=1.0, cycles=2),))
# TV9 at 10 kHz: 1.5 periods, error evaluated over 0.5-1.5 s (keeps the test short)
COSINE_SHORT = Scenario(name="cos", segments=(Cosine(amplitude_m=10e-6, frequency_hz=1.0, cycles=1.5),))


class NaiveDob(StageController):
    """The *wrong* combination of docs/friction-models.md §6.2: the observer is fed the full command."""

    def step(self, dt, x_meas_m, ref):  # type: ignore[no-untyped-def]
        cmd = super().step(dt, x_meas_m, ref)
        self.state.u_obs_prev_n = cmd.force_n
        return cmd


def _pid_10k():
    # 10 kHz loop, PID designed for a 40 Hz crossover (design.design_pid(2 kg, 40 Hz, 100 µs, 1 sample delay))
    return {"kp_n_m": 3.95e4, "ki_n_m_s": 9.92e5, "kd_n_s_m": 471.0, "derivative_cutoff_hz": 200.0}


def test_tv9_residual_dob_beats_naive_by_more_than_100x_with_exact_gms():
    sm = seed_model()
    T = 1e-4
    sec = dict(pid=_pid_10k(), dob={"kind": "qfilter", "bandwidth_hz": 200.0, "command_delay_samples": 0})
    res = {}
    for name, cls in (("residual", StageController), ("naive", NaiveDob)):
        ctl = cls(controller_cfg(**sec), T, sm)
        res[name] = rms_after(run_closed_loop(ctl, make_plant(sm), COSINE_SHORT, T), 0.5)
    pid_only = StageController(controller_cfg(pid=_pid_10k(), dob={"kind": "none"}, feedforward={"kind": "none"}), T)
    res["pid"] = rms_after(run_closed_loop(pid_only, make_plant(sm), COSINE_SHORT, T), 0.5)
    dob_only = StageController(controller_cfg(pid=_pid_10k(), dob={"kind": "qfilter", "bandwidth_hz": 200.0,
                                                                   "command_delay_samples": 0},
                                              feedforward={"kind": "none"}), T)
    res["dob"] = rms_after(run_closed_loop(dob_only, make_plant(sm), COSINE_SHORT, T), 0.5)
    assert res["naive"] > 100 * res["residual"], res
    assert res["naive"] > res["pid"], res  # double compensation is even worse than no compensation
    assert res["pid"] > 10 * res["dob"], res  # TV9: DOB alone > 10x
    assert res["residual"] < 5e-9, res


def test_trend_pid_dob_mismatched_gms_10x_better_than_pid_at_1khz_with_io_delay():
    """Seed stage, 1 kHz, one cycle of I/O delay, 1 nm quantisation, 10 µm cosine: default gains."""
    sm = seed_model()
    T = 1e-3
    base = dict(dob={"kind": "none"}, feedforward={"kind": "none"})
    pid = StageController(controller_cfg(**base), T)
    e_pid = rms_after(run_closed_loop(pid, make_plant(sm, io_delay_s=T), COSINE, T), 1.0)
    full = dict(dob={"kind": "qfilter"}, feedforward={"kind": "model", "lookahead_s": 1.5 * T})
    ctl = StageController(controller_cfg(**full), T, mismatched(sm))
    e_full = rms_after(run_closed_loop(ctl, make_plant(sm, io_delay_s=T), COSINE, T), 1.0)
    assert e_pid > 10 * e_full, (e_pid, e_full)


def test_terms_add_up_and_force_limiter_is_reported():
    sm = seed_model()
    cfg = controller_cfg(max_force_n=0.5, dob={"kind": "qfilter", "bandwidth_hz": 40.0})
    dut = StageController(cfg, 1e-3, sm)
    dut.reset(0.0)
    cmd = dut.step(1e-3, 0.0, Reference(1e-7, 1e-4, 0.1))
    assert set(cmd.terms) == set(TERM_NAMES)
    t = cmd.terms
    assert t["u_pid"] == pytest.approx(t["u_p"] + t["u_i"] + t["u_d"])
    assert cmd.force_n == pytest.approx(t["u_pid"] + t["u_dob"] + t["u_ff"] + t["u_inertia"])
    assert t["u_inertia"] == pytest.approx(2.0 * 0.1)
    assert cmd.limited == ()
    cmd = dut.step(1e-3, 0.0, Reference(1e-3, 0.0, 0.0))  # 1 mm error -> clamp
    assert cmd.force_n == 0.5 and "force" in cmd.limited and "anti_windup" in cmd.limited


def test_reset_is_bumpless():
    cfg = controller_cfg(dob={"kind": "qfilter"}, feedforward={"kind": "none"}, pid={"kd_n_s_m": 0.0})
    dut = StageController(cfg, 1e-3)
    dut.reset(5e-6, u_n=0.35)  # the drive was holding 0.35 N at 5 µm
    cmd = dut.step(1e-3, 5e-6, Reference(5e-6))
    assert cmd.force_n == pytest.approx(0.35, abs=1e-9)


def _run_and_retune(new: ControllerConfig, old: ControllerConfig, sm, steps_before=700, steps_after=50):
    T = 1e-3
    plant = make_plant(sm, io_delay_s=T)
    dut = StageController(old, T, sm)
    from stagectl.control.trajectory import TrajectoryGenerator

    gen = TrajectoryGenerator(0.0)
    gen.load(COSINE)
    plant.reset(0.0)
    dut.reset(0.0)
    forces = []
    ref = gen.sample()
    for k in range(steps_before + steps_after):
        if k == steps_before:
            dut.request_retune(new)
        cmd = dut.step(T, plant.measure(), ref)
        forces.append(cmd.force_n)
        plant.step(cmd.force_n, T)
        ref = gen.step(T)
    f = np.array(forces)
    # the switch step and the steps after it: a transfer the observer undoes later shows up there (issue-5 audit:
    # a feed-forward change moved into the integrator was re-learnt by the DOB, +0.4 N over 5 ms)
    jump = np.max(np.abs(np.diff(f[steps_before - 1:])))
    typical = np.max(np.abs(np.diff(f[steps_before - 100:steps_before])))
    return jump, typical, dut


@pytest.mark.parametrize("change", ["gains", "dob_off", "dob_on", "ff_model", "kalman_gain", "dob_kind", "ff_drop",
                                    "ff_drop_kalman", "ff_drop_no_dob"])
def test_retune_is_bumpless_in_closed_loop(change):
    sm = seed_model()
    old = controller_cfg(dob={"kind": "qfilter", "bandwidth_hz": 40.0, "command_delay_samples": 1},
                         feedforward={"kind": "model", "lookahead_s": 1.5e-3})
    if change == "gains":
        new = controller_cfg(pid={"kp_n_m": 2e4, "ki_n_m_s": 3e5, "kd_n_s_m": 300.0},
                             dob={"kind": "qfilter", "bandwidth_hz": 25.0, "command_delay_samples": 1},
                             feedforward={"kind": "model", "lookahead_s": 1.5e-3})
    elif change == "dob_off":
        new = controller_cfg(dob={"kind": "none"}, feedforward={"kind": "model", "lookahead_s": 1.5e-3})
    elif change == "dob_on":
        old, new = (controller_cfg(dob={"kind": "none"}, feedforward={"kind": "model", "lookahead_s": 1.5e-3}), old)
    elif change == "kalman_gain":
        ff = {"kind": "model", "lookahead_s": 1.5e-3}
        old = controller_cfg(dob={"kind": "kalman", "bandwidth_hz": 30.0}, feedforward=ff)
        new = controller_cfg(dob={"kind": "kalman", "bandwidth_hz": 50.0}, feedforward=ff)
    elif change == "dob_kind":
        new = controller_cfg(dob={"kind": "kalman", "bandwidth_hz": 40.0}, feedforward={"kind": "model",
                                                                                     "lookahead_s": 1.5e-3})
    elif change.startswith("ff_drop"):  # the feed-forward loses ~0.4 N mid-motion: the DOB (or I) takes it over
        dob = {"ff_drop": {"kind": "qfilter", "bandwidth_hz": 40.0, "command_delay_samples": 1},
               "ff_drop_kalman": {"kind": "kalman", "bandwidth_hz": 40.0},
               "ff_drop_no_dob": {"kind": "none"}}[change]
        old = controller_cfg(dob=dob, feedforward={"kind": "model", "lookahead_s": 1.5e-3})
        new = controller_cfg(dob=dob, feedforward={"kind": "coulomb", "coulomb_n": 0.4, "lookahead_s": 1.5e-3})
    else:
        new = controller_cfg(dob={"kind": "qfilter", "bandwidth_hz": 40.0, "command_delay_samples": 1},
                             feedforward={"kind": "coulomb", "coulomb_n": 0.8, "lookahead_s": 1.5e-3})
    jump, typical, dut = _run_and_retune(new, old, sm)
    assert dut.cfg == new
    if change == "kalman_gain":
        from stagectl.control.design import observer_bandwidth_hz

        assert observer_bandwidth_hz(np.array(dut.dob.K), 2.0, 1e-3) == pytest.approx(50.0, rel=1e-3)
    assert jump <= 3 * typical + 1e-4, (jump, typical)


def test_retune_changes_the_law():
    sm = seed_model()
    old = controller_cfg(dob={"kind": "none"}, feedforward={"kind": "none"})
    new = controller_cfg(pid={"kp_n_m": 2e4}, dob={"kind": "none"}, feedforward={"kind": "none"})
    dut = StageController(old, 1e-3, sm)
    dut.reset(0.0)
    dut.retune(new)
    dut.step(1e-3, 0.0, Reference(1e-6))
    assert dut.pid.state.p_n == pytest.approx(2e4 * 1e-6)


def test_kalman_dob_in_the_loop():
    sm = seed_model()
    T = 1e-3
    cfg = controller_cfg(dob={"kind": "kalman", "bandwidth_hz": 40.0, "command_delay_samples": 1},
                         feedforward={"kind": "none"})
    dut = StageController(cfg, T)
    e = rms_after(run_closed_loop(dut, make_plant(sm, io_delay_s=T), COSINE, T), 1.0)
    pid = StageController(controller_cfg(dob={"kind": "none"}, feedforward={"kind": "none"}), T)
    e_pid = rms_after(run_closed_loop(pid, make_plant(sm, io_delay_s=T), COSINE, T), 1.0)
    assert e < e_pid / 1.5
    assert math.isfinite(dut.state.d_hat_n)


@pytest.mark.parametrize("dt", [0.0, -1e-3, math.nan, math.inf])
def test_bad_dt_raises(dt):
    dut = StageController(controller_cfg(feedforward={"kind": "none"}), 1e-3)
    with pytest.raises(ValueError, match="dt"):
        dut.step(dt, 0.0, Reference(0.0))


def test_nan_measurement_or_reference_raises():
    dut = StageController(controller_cfg(feedforward={"kind": "none"}), 1e-3)
    with pytest.raises(ValueError, match="x_meas_m"):
        dut.step(1e-3, math.nan, Reference(0.0))
    with pytest.raises(ValueError, match="reference"):
        dut.step(1e-3, 0.0, Reference(0.0, math.inf))


def test_config_errors_are_clear():
    with pytest.raises(ConfigError, match="kind 'model' needs"):
        StageController(controller_cfg(), 1e-3)
    with pytest.raises(ConfigError, match="controller.mass_kg"):
        StageController(load(ControllerConfig, {"feedforward": {"kind": "none"}}, "controller"), 1e-3)
    with pytest.raises(ConfigError) as ei:
        load(ControllerConfig, {"dob": {"kind": "luenberger", "bandwidth_hz": -1}, "pid": {"kp": 1},
                                "feedforward": {"friction": {"model": "nope"}}}, "controller")
    msg = str(ei.value)
    assert "controller.dob.kind" in msg and "controller.dob.bandwidth_hz" in msg
    assert "controller.pid.kp: unknown key" in msg and "controller.feedforward.friction.model" in msg


def test_model_file_and_inline_friction(tmp_path):
    from control_harness import SEED_MODEL

    from stagectl.config import ModelFiles
    from stagectl.control.controller import resolve_model

    def resolved(cfg: ControllerConfig, files: ModelFiles) -> ControllerConfig:
        """What the configuration loader does: the model file loaded once, handed over as feedforward.model."""
        problems: list[str] = []
        sm = files.load(cfg.feedforward.model_file, "controller.feedforward.model_file", problems)
        if problems:
            raise ConfigError(problems)
        ff = dataclasses.replace(cfg.feedforward, model=resolve_model(cfg, sm))
        return dataclasses.replace(cfg, feedforward=ff)

    cfg = load(ControllerConfig, {"feedforward": {"model_file": str(SEED_MODEL)}}, "controller")
    with pytest.raises(ConfigError, match="model_file.*not loaded"):
        StageController(cfg, 1e-3)  # the controller reads no file
    dut = StageController(resolved(cfg, ModelFiles(None)), 1e-3)
    assert dut.mass_kg == 2.0  # from the model file
    cfg2 = load(ControllerConfig, {"mass_kg": 3.0, "feedforward": {
        "friction": {"model": "gms", **{k: v for k, v in seed_model().friction.spec().items() if k != "model"}},
        "effects": {"offset": {"force_n": 0.1}}}}, "controller")
    dut2 = StageController(cfg2, 1e-3)
    dut2.reset(0.0)
    cmd = dut2.step(1e-3, 0.0, Reference(0.0))
    assert cmd.terms["u_ff"] == pytest.approx(0.1)
    rel = load(ControllerConfig, {"feedforward": {"model_file": "kamenar2016_gms.yaml"}}, "controller")
    assert StageController(resolved(rel, ModelFiles(SEED_MODEL.parent)), 1e-3).mass_kg == 2.0
    with pytest.raises(ConfigError, match="model_file"):
        resolved(load(ControllerConfig, {"mass_kg": 2.0, "feedforward": {"model_file": str(tmp_path / "x")}},
                      "controller"), ModelFiles(None))
