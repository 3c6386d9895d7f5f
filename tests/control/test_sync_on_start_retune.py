"""The start-edge synchronisation (``feedforward.rest_sync_on_start``) and the rest spring's stiffness test at the
edges review26 found (controller state across a retune; the first standstill after reset).

Both drive :class:`StageController` directly on fixed samples (no plant): milliseconds of CPU.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]


def _cfg() -> Any:
    from stagectl.config import load_app_config

    return load_app_config(REPO / "config" / "sim.yaml")


def _move_after_retune(c0: Any, c1: Any) -> tuple[float, float, float]:
    """Stage held 40 nm off its reference at rest for 30 periods (the observer takes up a force, the stop
    synchronisation runs and has not finished), a retune to ``c1``, then the first sample of a move: the command,
    d̂ and the model's force."""
    from stagectl.control.controller import StageController
    from stagectl.control.reference import Reference

    app = _cfg()
    ctl = StageController(c0, app.timing)
    t = app.loop.period_s
    ctl.reset(0.0)
    for _ in range(30):
        ctl.step(t, 40e-9, Reference(0.0, 0.0, 0.0))
    ctl.retune(c1)
    cmd = ctl.step(t, 40e-9, Reference(1e-9, 1e-4, 0.1))
    return cmd.force_n, ctl.state.d_hat_n, ctl.state.u_ff_n


def test_a_retune_that_turns_the_start_edge_sync_off_is_obeyed_on_the_next_move() -> None:
    # the full rest spring at once (fixed samples: no force to see the stage held by)
    c = dataclasses.replace(_cfg().controller, rest_spring_unconfirmed_kp_fraction=1e9)
    assert c.feedforward.rest_sync_on_start and c.feedforward.rest_sync_hz > 0.0 and c.dob.kind != "none"
    off = dataclasses.replace(c, feedforward=dataclasses.replace(c.feedforward, rest_sync_on_start=False))
    on_then_off = _move_after_retune(c, off)
    off_all_along = _move_after_retune(off, dataclasses.replace(off))
    on_all_along = _move_after_retune(c, dataclasses.replace(c))
    # the start-edge sync acts in this case (the test can tell it) ...
    assert abs(on_all_along[2] - off_all_along[2]) > 1e-3, (on_all_along, off_all_along)
    # ... and once switched off it does not run (before: the standstill's armed sync ran on the move anyway)
    assert on_then_off == off_all_along, (on_then_off, off_all_along)


def test_the_stiffness_test_judges_a_later_branch_in_the_first_standstill() -> None:
    """No move since reset: the first branch runs from the arming point (judged held on a stiff contact); the
    stage then turns back on a soft one and that branch is judged too (before: the direction was never found
    while x_f crept by less than REST_HELD_MIN_TRAVEL_M per sample, so no later reversal was seen)."""
    from stagectl.control.controller import StageController

    app = _cfg()
    c = app.controller
    ctl = StageController(c, app.timing)
    ctl.reset(0.0)
    ks = ctl._k_ps
    kv = c.rest_stiffness_fraction * ks
    assert ks > 0.0 and c.rest_spring_held_fraction > 0.0
    ctl._h_age_s = 1.0  # past the witness's start-up after the reset (REST_HELD_WARMUP_TIME_CONSTANTS)

    def feed(xf: float, f: float) -> bool:
        ctl._h_xf, ctl._h_f = xf, f
        return ctl._not_held(kv, 0.0)

    out = [feed(i * 1e-9, ks * i * 1e-9) for i in range(31)]  # out 30 nm on a contact of stiffness Σk: held
    assert not any(out) and abs(ctl.rest_spring_held_n_m - ks) < 1e-6 * ks
    back = [feed(i * 1e-9, ks * 30e-9) for i in range(29, -1, -1)]  # back 30 nm, no force change: not held
    assert any(back) and ctl.rest_spring_held_n_m < 0.01 * ks


def test_a_spring_switched_on_after_moves_does_not_judge_the_run_in_as_a_branch() -> None:
    """A controller run without the rest spring moves, stops, and a retune switches the spring on: the stage has
    moved since reset, so a creep in without turning back (here 30 nm with no force change, what the stiffness
    test would call "not held") is not judged (before: the moves went unseen with the spring off, and the creep
    was judged as the first branch after a reset at rest)."""
    from stagectl.control.controller import StageController
    from stagectl.control.reference import Reference

    app = _cfg()
    c = app.controller
    assert c.rest_stiffness_fraction > 0.0 and c.rest_spring_held_fraction > 0.0
    ctl = StageController(dataclasses.replace(c, rest_stiffness_fraction=0.0), app.timing)
    t = app.loop.period_s
    ctl.reset(0.0)
    for i in range(20):  # a short move, then rest
        ctl.step(t, i * 1e-9, Reference(i * 1e-9, 1e-6, 0.0))
    for _ in range(5):
        ctl.step(t, 20e-9, Reference(20e-9, 0.0, 0.0))
    ctl.retune(c)
    kv = c.rest_stiffness_fraction * ctl._k_ps
    out = []
    for i in range(31):
        ctl._h_xf, ctl._h_f = 20e-9 - i * 1e-9, 0.0
        out.append(ctl._not_held(kv, 0.0))
    assert not any(out)
