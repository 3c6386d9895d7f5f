"""The rest spring's guard (controller docstring, "Rest spring"): on a stage that is not stuck at standstill the
spring is released bumplessly, so a low-friction stage holds as well as without it; simulated time."""

from __future__ import annotations

import copy
import dataclasses
import itertools
import json

import pytest

from stagectl.cli import main


@pytest.fixture(scope="module")
def seed(repo_root):
    from stagectl.config import load_app_config

    return load_app_config(repo_root / "config" / "sim.yaml")


def _low_friction(cfg, k_scale: float = 0.1, f_scale: float = 0.2):
    """``cfg`` with a plant whose friction is far below the controller's model: pre-sliding stiffness and
    micro-damping ×k_scale, Fs and Fc ×f_scale (the controller keeps the configured model)."""
    from stagectl.friction import build

    plant = cfg.sim.plant
    spec = dict(plant.friction.spec())
    spec["k_n_m"] = [k_scale * k for k in spec["k_n_m"]]
    spec["sigma1_n_s_m"] = [k_scale * c for c in spec["sigma1_n_s_m"]]
    spec["fs_n"] *= f_scale
    spec["fc_n"] *= f_scale
    return dataclasses.replace(cfg, sim=dataclasses.replace(
        cfg.sim, plant=dataclasses.replace(plant, friction=build(spec))))


def test_a_low_friction_stage_holds_with_the_rest_spring_on(seed):
    """Plant friction ×0.2, stiffness ×0.1 against the shipped controller: with the guard every 10 µm step settles
    (within 0.1 s of the controller without the spring: one burst of hunting before the release) and holds for 2 s without a limit cycle; the same spring without the guard (never
    released) hunts by hundreds of nm (the risk the guard removes)."""
    from stagectl.bench.control import steps_check

    low = _low_friction(seed)
    c = seed.controller
    assert c.rest_stiffness_fraction > 0.0
    on = steps_check(low, c, hold_s=2.0)
    off = steps_check(low, dataclasses.replace(c, rest_stiffness_fraction=0.0), hold_s=2.0)
    unguarded = steps_check(low, dataclasses.replace(c, rest_spring_release_m=2.0, rest_spring_rearm_m=1.0),
                            hold_s=2.0)
    assert on["fault"] is None and on["limit_cycle"] is False
    assert on["settled"] == 4 and on["max_late_excursion_m"] <= 10e-9
    # at most one burst of hunting before the release: settles within 0.1 s of the spring-less controller
    assert max(on["settle_s"]) <= max(off["settle_s"]) + 0.1
    assert unguarded["limit_cycle"] is True and unguarded["max_late_excursion_m"] > 100e-9


def _at_rest(ctl, dt, x, n):
    from stagectl.control.api import Reference

    cmd = None
    for _ in range(n):
        cmd = ctl.step(dt, x, Reference(0.0, 0.0, 0.0))
    return cmd


def test_hunting_releases_the_spring_a_stuck_approach_does_not(seed):
    """Released after x − x_r swung across ±rest_spring_rearm_m twice; a monotonic approach from 150 nm (a stuck
    stage pulled in by the spring) keeps it."""
    from stagectl.control.controller import StageController

    c = seed.controller
    dt = seed.loop.period_s
    band = c.rest_spring_rearm_m
    ctl = StageController(c, seed.timing)
    ctl.reset(0.0)
    for i in range(300):
        _at_rest(ctl, dt, 150e-9 * (1.0 - i / 300), 1)
    assert ctl._rs_armed and ctl._s_rest != 0.0
    ctl.reset(0.0)
    _at_rest(ctl, dt, 1.5 * band, 20)
    _at_rest(ctl, dt, -1.5 * band, 20)
    assert ctl._rs_armed  # one swing
    _at_rest(ctl, dt, 1.5 * band, 1)
    assert not ctl._rs_armed and ctl._s_rest == 0.0


def test_release_and_rearm_are_bumpless(seed):
    """At the release (|x − x_r| beyond rest_spring_release_m) the spring force s (tens of mN) goes into the
    observer: the command equals, to within one step of the spring's low-pass, that of the same controller
    keeping the spring. The re-arm (rest_spring_max_release_count 2, after rest_spring_rearm_s within the band) loads
    the observer with the spring's force first: at the re-arm sample the command is the one without the re-arm;
    the spring's force then builds in over several samples (the observer's time constant), no step."""
    from stagectl.control.controller import StageController

    # the full spring at once (the positions here are synthetic: no force to see the stage held by,
    # tests/control/test_rest_spring_held.py has that gate)
    c = dataclasses.replace(seed.controller, rest_spring_max_release_count=2, rest_spring_unconfirmed_kp_fraction=1e9)
    dt = seed.loop.period_s
    ctl = StageController(c, seed.timing)
    ctl.reset(0.0)
    _at_rest(ctl, dt, 190e-9, 200)
    s_prev = ctl._s_rest
    assert abs(s_prev) > 30e-3
    keep = copy.deepcopy(ctl)
    keep.cfg = dataclasses.replace(c, rest_spring_release_m=1.0)
    far = 1.2 * c.rest_spring_release_m
    u_rel = _at_rest(ctl, dt, far, 1).force_n
    u_keep = _at_rest(keep, dt, far, 1).force_n
    assert not ctl._rs_armed and ctl._s_rest == 0.0 and keep._rs_armed
    assert abs(u_rel - u_keep) < 0.05 * abs(s_prev)
    # back near the reference: re-armed after the dwell
    x_in = 0.6 * c.rest_spring_rearm_m
    n_dwell = round(c.rest_spring_rearm_s / dt)
    _at_rest(ctl, dt, x_in, n_dwell - 1)
    assert not ctl._rs_armed
    no_rearm = copy.deepcopy(ctl)
    no_rearm.cfg = dataclasses.replace(c, rest_spring_max_release_count=1)
    u_a = [_at_rest(ctl, dt, x_in, 1).force_n]
    u_b = [_at_rest(no_rearm, dt, x_in, 1).force_n]
    assert ctl._rs_armed and not no_rearm._rs_armed
    s_new = ctl._s_rest
    assert abs(s_new) > 5e-3
    assert u_a[0] == pytest.approx(u_b[0], abs=1e-9)
    for _ in range(5):
        u_a.append(_at_rest(ctl, dt, x_in, 1).force_n)
        u_b.append(_at_rest(no_rearm, dt, x_in, 1).force_n)
    diff = [a - b for a, b in zip(u_a, u_b, strict=True)]
    assert max(abs(d1 - d0) for d0, d1 in itertools.pairwise(diff)) < 0.5 * abs(s_new)


def test_tune_prints_the_rest_loop_margins_and_what_it_relies_on(repo_root, capsys, tmp_path):
    """``stagectl tune`` shows the configured rest loop (stuck and free plant) beside the moving loop, the same
    margins as design.analyse_rest: on the free mass with the spring a stage not seen held gets
    (``rest_spring_unconfirmed_kp_fraction``, 0 in config/sim.yaml: healthy); with the full spring there (the
    fraction raised) it says which case is below the floor (the free stage) and that it relies on a stuck stage."""
    from stagectl.config import load_app_config
    from stagectl.control.design import analyse_rest

    path = repo_root / "config" / "sim.yaml"
    args = ["tune", "--config", str(path), "--bandwidth-hz", "200"]  # refused design: no steps check (fast)
    main(args + ["--json"])
    rest = json.loads(capsys.readouterr().out)["configured"]["rest"]
    cfg = load_app_config(path)
    c = cfg.controller
    fr = cfg.sim.plant.friction
    th = rest["loops"]["rest/stuck"]["theta"]  # the worst θ of the sweep
    stuck, free = analyse_rest(2.0, cfg.loop.period_s, c.pid, cfg.io.delay_cycles, c.dob.bandwidth_hz,
                               c.dob.command_delay_samples, fr.stiffness_n_m, fr.damping_n_s_m,
                               th * rest["rest_spring_n_m"], c.velocity_cutoff_hz, kd_fraction=c.rest_kd_fraction,
                               dob_bandwidth_fraction=c.rest_dob_bandwidth_fraction,
                               spring_sections=c.rest_spring_section_count, free_spring_n_m=0.0)
    assert c.rest_spring_unconfirmed_kp_fraction == 0.0
    assert rest["rest_spring_n_m"] == pytest.approx(c.rest_stiffness_fraction * fr.stiffness_n_m)
    assert rest["loops"]["rest/stuck"]["phase_margin_deg"] == pytest.approx(stuck.phase_margin_deg)
    assert rest["loops"]["rest/free"]["closed_loop_stable"] is free.stable is True
    assert rest["loops"]["rest/free"]["healthy"] is True and rest["healthy"] is True and rest["relies_on"] is None
    # the full spring on the free mass too (the gate opened): the free stage is below the floor, tune says so
    import yaml

    from tests.support import shipped_config_mapping

    data = shipped_config_mapping("sim.yaml")
    data["controller"]["rest_spring_unconfirmed_kp_fraction"] = 1e9
    path = tmp_path / "full.yaml"
    path.write_text(yaml.safe_dump(data))
    args = ["tune", "--config", str(path), "--bandwidth-hz", "200"]
    main(args + ["--json"])
    rest = json.loads(capsys.readouterr().out)["configured"]["rest"]
    assert rest["loops"]["rest/free"]["closed_loop_stable"] is False
    assert rest["healthy"] is False and "stuck" in rest["relies_on"]
    main(args)
    out = capsys.readouterr().out
    assert "rest/stuck" in out and "rest/free" in out and "pid+dob" in out
    # config/sim.yaml's rest gains meet the floor on the stuck stage (not on a free one): tune says which case misses
    assert rest["loops"]["rest/stuck"]["healthy"] is True and rest["loops"]["rest/free"]["healthy"] is False
    assert ("the rest loop meets the PM 40 deg / GM 8 dB floor on the stuck stage; on a free stage (no friction "
            "holding it) it does not: it relies on the stage being stuck") in out
    assert "is below the PM 40 deg" not in out


def test_a_rearm_band_outside_the_release_distance_is_a_config_error():
    from stagectl.control.controller import controller_from_mapping
    from stagectl.errors import ConfigError

    with pytest.raises(ConfigError, match=r"rest_spring_rearm_m: 1e-05 m must be below rest_spring_release_m"):
        controller_from_mapping({"mass_kg": 2.0, "feedforward": {"kind": "none"}, "rest_spring_rearm_m": 1e-5,
                                 "rest_spring_release_m": 5e-6}, 1e-3)


def test_tune_analyses_the_rest_loop_actually_configured(tmp_path, capsys):
    """The rest loop of ``stagectl tune`` is the configured one: the observer's own nominal mass
    (``dob.nominal_mass_kg``, here 30 % above the plant's) and the full PID when the integrator is not held at
    rest (``hold_integrator_at_rest: false``); its margins are design.analyse_rest's for exactly those, and differ
    from the one-mass, integrator-held analysis."""
    import yaml

    from stagectl.config import load_app_config
    from stagectl.control.design import analyse_rest
    from tests.support import shipped_config_mapping

    data = shipped_config_mapping("sim.yaml")
    data["controller"]["dob"]["nominal_mass_kg"] = 2.6
    data["controller"]["hold_integrator_at_rest"] = False
    data["controller"]["feedforward"].update(adapt_bandwidth_hz=0.0, learn_moves_fraction=0.0)  # θ stays 1
    path = tmp_path / "rest.yaml"
    path.write_text(yaml.safe_dump(data))
    main(["tune", "--config", str(path), "--bandwidth-hz", "200", "--json"])  # refused design: no steps check
    rest = json.loads(capsys.readouterr().out)["configured"]["rest"]
    assert rest["mass_kg"] == 2.0 and rest["observer_mass_kg"] == 2.6 and rest["integrator_held"] is False
    cfg = load_app_config(path)
    c = cfg.controller
    fr = cfg.sim.plant.friction
    args = (2.0, cfg.loop.period_s, c.pid, cfg.io.delay_cycles, c.dob.bandwidth_hz, c.dob.command_delay_samples,
            fr.stiffness_n_m, fr.damping_n_s_m, rest["rest_spring_n_m"], c.velocity_cutoff_hz)
    gains = {"kd_fraction": c.rest_kd_fraction, "dob_bandwidth_fraction": c.rest_dob_bandwidth_fraction,
             "spring_sections": c.rest_spring_section_count}
    stuck, free = analyse_rest(*args, dob_mass_kg=2.6, integrator_held=False, free_spring_n_m=0.0, **gains)
    old_stuck, old_free = analyse_rest(*args, free_spring_n_m=0.0, **gains)
    got = rest["loops"]
    assert got["rest/stuck"]["phase_margin_deg"] == pytest.approx(stuck.phase_margin_deg)
    assert got["rest/free"]["phase_margin_deg"] == pytest.approx(free.phase_margin_deg)
    assert got["rest/stuck"]["gain_margin_db"] == pytest.approx(stuck.gain_margin_db)
    assert abs(stuck.phase_margin_deg - old_stuck.phase_margin_deg) > 0.5
    assert abs(free.gain_margin_db - old_free.gain_margin_db) > 0.1
    main(["tune", "--config", str(path), "--bandwidth-hz", "200"])
    assert "at standstill (integrator running, observer mass 2.6 kg" in capsys.readouterr().out
