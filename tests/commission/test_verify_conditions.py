"""Step 6 of issue 11: the verification runs "before" and "after" under the same conditions, and under the ones
:func:`~stagectl.commission.sequence.simulate_verification` (the twins, the tests) gives a fresh stage.

The oracle: one controller verified on both sides must give the same figure on both, whatever ran before, and the
figure a fresh simulated stage gives it. config/sim.yaml's controller learns from moves (feed-forward adaptation
and learning from moves), so it is the one a protocol that lets it learn from the verification's own lead, or from
the stage's friction memory of the previous experiment, gets wrong. Plain lock-step (simulated time): a 1 mm move
and back leaves the stage off the centre with a pre-sliding memory (as the slow passes leave it), then the
verification's cosine with the shipped controller as "before" and as "after". The sensor's noise is off here: with
it (0.5 nm rms) the same controller's 2 nm cosine scatters by 8 % (sd) from run to run; without it, by 2 %.

With main's protocol at d7bf33f (a 10 mm/s positioning move to the centre less the approach in the scenario's run,
no wipe, one controller object for the before and one for the after scenarios) this read 2.06 nm before and 5.77 nm
after for the one controller, against 1.91 nm on a fresh stage (the quick start's "before" cosine: 6.02 nm against
2.30 nm on a fresh stage); now 1.8-1.9 nm on both sides.
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import pytest

CONFIG = Path(__file__).resolve().parents[2] / "config" / "sim.yaml"


@pytest.fixture(scope="module")
def figures() -> dict[str, float]:
    from stagectl.app import build_stage, make_controller
    from stagectl.clock import SimClock
    from stagectl.commission import sequence as sq
    from stagectl.commission.controllers import CommissionController
    from stagectl.config import load_app_config
    from stagectl.control.trajectory import Dwell, Move

    shipped = load_app_config(str(CONFIG))
    assert shipped.sim is not None
    plant = shipped.sim.plant
    cfg = dataclasses.replace(shipped, sim=dataclasses.replace(shipped.sim, plant=dataclasses.replace(
        plant, sensor=dataclasses.replace(plant.sensor, noise_std_m=0.0))))
    assert cfg.controller.feedforward.learn_moves_fraction > 0 and cfg.controller.feedforward.adapt_bandwidth_hz > 0
    with tempfile.TemporaryDirectory() as d:
        com = sq.Commissioning(cfg, Path(d), sq.Options(plots=False), lambda res: cfg)
        env = com.env
        xc = env.x_c_m
        with build_stage(cfg, clock=SimClock(), controller=CommissionController(make_controller(cfg))) as st:
            # the stage's history: out by 1 mm and back, stopping 2 µm short of the centre
            prof = {"max_velocity_m_s": 2.7e-3, "max_acceleration_m_s2": 0.1, "max_jerk_m_s3": 10.0}
            com._closed(st, "history", "history", make_controller(cfg),
                        [Move(to_m=xc + 1e-3, **prof), Dwell(0.1), Move(to_m=xc - 2e-6, **prof)], {})
            com._verify(st, cfg, xc, scenarios=("cosine",))
        names = [e.name for e in com.res.experiments]
    fresh = sq.simulate_verification(cfg, env.stroke_m, 10e-9)["cosine"]
    v = com.res.verification["cosine"]
    return {"before": v["before"]["rms_error_m"], "after": v["after"]["rms_error_m"],
            "fresh": fresh["rms_error_m"], "names": names}  # type: ignore[dict-item]


def test_each_scenario_runs_after_its_own_wipe(figures):
    assert figures["names"] == ["history", "wipe_before_cosine", "verify_before_cosine", "wipe_after_cosine",
                                "verify_after_cosine"]


def test_one_controller_gives_one_figure_before_and_after(figures):
    """Within 20 %: the learners' state after the wipe and lead differs by a few 0.1 % between the two sides, and
    the exact model's 10 µm cosine is that sensitive (β x1.002: 1.69 -> 2.22 nm; docs/control.md §2.3): main at
    7fe9636 read 1.98 / 1.81 nm, with the adaptation's reversal gate 1.89 / 2.15 nm. The protocol error this
    guards against read 2.06 / 5.77 nm."""
    b, a = figures["before"], figures["after"]
    assert abs(b - a) <= 0.2 * min(a, b), (b, a)


def test_the_stage_figure_is_the_fresh_stage_figure(figures):
    for side in ("before", "after"):
        assert abs(figures[side] - figures["fresh"]) <= 0.15 * figures["fresh"], (side, figures)
