"""Issue 12 item 2 at standstill: the rest loop's gains (K_d's and the observer's fraction at rest, the spring's
low-pass sections) come from a design rule, :func:`stagectl.control.design.design_rest_gains`, that asks for the
PM 40° / GM 8 dB floor on the stuck stage *and* on the free mass, for the loop's delay, mass and stiffness; ``stagectl
tune`` keeps the configured rest gains when they meet it and suggests designed ones when they do not.

On main config/hil-serial.yaml (two periods of delay) carried K_d × 0.1, observer × 0.3: the stuck stage's rest loop
PM 92° / GM 9.5 dB, the free mass's PM 11.3° (its linear loop relied on friction holding the stage)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

CONFIG = Path(__file__).resolve().parents[2] / "config"
THETAS = (0.5, 0.75, 1.0)


def _healthy(s: dict) -> bool:
    return bool(s["closed_loop_stable"] and s["phase_margin_deg"] >= 40.0 and s["gain_margin_db"] >= 8.0)


def _loops(m, pid, nd, dbw, k, c, kv, gains):
    """Both rest loops at each θ, as tune analyses them (free mass: no spring before the stage is seen held)."""
    from stagectl.control.design import analyse_rest

    return [analyse_rest(m, 1e-3, pid, nd, dbw, nd, k, c, th * kv, free_spring_n_m=0.0, **gains) for th in THETAS]


def test_designed_rest_gains_meet_the_floor_on_the_stuck_and_the_free_stage_at_two_periods_of_delay():
    """Another stage than the shipped ones (1 kg, 2.5e5 N/m): the rule is a function of mass, stiffness and delay."""
    from stagectl.control.design import design_pid, design_rest_gains

    m, k, nd, bw = 1.0, 2.5e5, 2, 14.58
    pid = design_pid(m, bw, 1e-3, nd)
    dbw, c, kv = 5 * bw, 3.7e-4 * k, 0.5 * k
    # the rest gains hil-serial shipped on main: healthy on the stuck stage, not on the free mass
    old = _loops(m, pid, nd, dbw, k, c, kv, {"kd_fraction": 0.1, "dob_bandwidth_fraction": 0.3, "spring_sections": 2})
    assert all(_healthy(a[0].summary()) for a in old) and not all(_healthy(a[1].summary()) for a in old)
    r = design_rest_gains(m, 1e-3, pid, nd, dbw, nd, k, c, kv, thetas=THETAS, free_spring_cap_n_m=0.0)
    assert r["gains"] is not None, r
    for loops in _loops(m, pid, nd, dbw, k, c, kv, r["gains"]):  # checked independently of the search's screen
        for a in loops:
            assert _healthy(a.summary()), (r["gains"], a.name, a.summary())
    assert all(s["healthy"] for s in r["loops"].values())


def test_hil_serial_rest_loop_meets_the_floor_on_both_stages_and_tune_designs_rest_gains_when_thin():
    """config/hil-serial.yaml's shipped rest loop meets the floor on the stuck stage and on the free mass over the θ
    range (PM 11.3° on the free mass on main), and tune keeps its rest gains. With main's rest gains (K_d × 0.1,
    observer × 0.3) tune's suggestion carries rest gains of the design rule, healthy on both stages, in its YAML."""
    from stagectl.commands.tune import _rest_loops
    from stagectl.config import load_app_config

    app = load_app_config(str(CONFIG / "hil-serial.yaml"))
    ctl = app.controller
    T, nd, m = app.loop.period_s, 2, 2.0
    shipped = _rest_loops(app, ctl, m, m, T, nd, simulate=False)
    assert shipped is not None and shipped["rest_stiffness_fraction"] > 0.0
    for loop in ("rest/stuck", "rest/free"):
        assert _healthy(shipped["loops"][loop]), (loop, shipped["loops"][loop])
    from stagectl.commands.tune import _suggested_rest, _yaml_snippet

    kept = _suggested_rest(app, ctl, shipped, ctl.pid, ctl.dob.bandwidth_hz, nd, m, T)
    assert kept is not None and kept["source"] == "configured" and kept["healthy"]
    old = dataclasses.replace(ctl, rest_kd_fraction=0.1, rest_dob_bandwidth_fraction=0.3)
    rest = _rest_loops(app, old, m, m, T, nd, simulate=False)
    assert rest is not None and not rest["loops"]["rest/free"]["healthy"]
    rd = _suggested_rest(app, old, rest, old.pid, old.dob.bandwidth_hz, nd, m, T)
    assert rd is not None and rd["source"] == "designed", rd
    assert all(_healthy(s) for s in rd["loops"].values()), rd
    assert rd["configured_loops"]["rest/free"]["phase_margin_deg"] < 40.0
    snippet = _yaml_snippet(m, old.pid, old.dob.bandwidth_hz, nd, rd["gains"])
    assert f"rest_kd_fraction: {rd['gains']['kd_fraction']:g}" in snippet
    assert f"rest_spring_section_count: {rd['gains']['spring_sections']}" in snippet


def test_the_searchs_screen_is_the_loop_analyse_rest_analyses():
    """design_rest_gains screens each point with its own numpy copy of analyse_rest's two rest loops
    (design._rest_screen) and drops it unseen when the screen misses the floor by its slack: the copy must give
    the same margins, else the search silently skips points that meet the floor."""
    from stagectl.control.design import _rest_screen, analyse_rest, design_pid

    m, k, nd, bw = 1.0, 2.5e5, 2, 14.58
    pid = design_pid(m, bw, 1e-3, nd)
    dbw, c, kv = 5 * bw, 3.7e-4 * k, 0.5 * k
    screen = _rest_screen(m, 1e-3, pid, nd, dbw, nd, k, c, None, None, True)
    for kd, g, n in ((1.0, 1.0, 1), (0.3, 0.45, 2), (0.1, 0.25, 2)):
        got = screen(kd, g, n, kv, 0.0, 0.0)
        loops = analyse_rest(m, 1e-3, pid, nd, dbw, nd, k, c, kv, free_spring_n_m=0.0, kd_fraction=kd,
                             dob_bandwidth_fraction=g, spring_sections=n)
        for (pm, gm), a in zip(got, loops):
            s = a.summary()
            assert abs(pm - s["phase_margin_deg"]) < 0.1 or pm == s["phase_margin_deg"], (kd, g, n, a.name, pm, s)
            assert abs(gm - s["gain_margin_db"]) < 0.05 or gm == s["gain_margin_db"], (kd, g, n, a.name, gm, s)
