"""Settle move from ahead (``controller.settle.ahead_stiffness_fraction``): a move whose friction feed-forward was too
high ends with the stage *ahead* of its target, stuck on the stiff (pre-sliding) side of its friction. The
continuation back to the target carries the friction spring's force along it (docs/control.md §2.8).

Two closed loops in simulated time:

* a plain plant written here (the oracle: 2 kg on an elasto-plastic friction spring, k_p·z with |k_p·z| <= F_C,
  plus viscous damping; one period of I/O delay), driven by the real controller with the seed GMS model 20 % too
  high: the stage ends ~1 µm ahead; the continuation's force is the model's reversal stiffness times the planned
  travel, outside the observer, and it is handed to the observer without a step in the command;
* the bench's stage (``config/sim.yaml``'s GMS plant through the loop, ``steps_check``) with too-high models: the
  first 10 µm step settles to ±10 nm within 30 ms of the end of the commanded move, without a limit cycle; with
  the fraction 0 (the earlier controller) it does not.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest

PERIOD = 1e-3


class ElastoPlasticStage:
    """Oracle plant (not stagectl.sim): m·ẍ = u − k_p·z − SIGMA·v, the friction spring z following x and clipped
    to |k_p·z| <= F_C (slip); semi-implicit Euler in ``sub`` sub-steps per period; ``step(u)`` advances one period
    under the previous command (one cycle of I/O delay), latches ``u`` and returns the position [m]."""

    MASS, K_P, F_C, SIGMA = 2.0, 6.4e5, 0.9, 240.0  # [kg], [N/m], [N], [N·s/m]

    def __init__(self, sub: int = 50) -> None:
        self.x = self.v = self.z = self.u_applied = 0.0
        self.sub = sub
        self.h = PERIOD / sub

    def step(self, u_n: float) -> float:
        x, v, z, u, h = self.x, self.v, self.z, self.u_applied, self.h
        zmax = self.F_C / self.K_P
        for _ in range(self.sub):
            v += (u - self.K_P * z - self.SIGMA * v) / self.MASS * h
            dx = v * h
            x += dx
            z = min(zmax, max(-zmax, z + dx))
        self.x, self.v, self.z, self.u_applied = x, v, z, u_n
        return x


@pytest.fixture(scope="module")
def seed(repo_root: Any) -> Any:
    from stagectl.config import load_app_config

    return load_app_config(repo_root / "config" / "sim.yaml")


def _high(cfg: Any, k: float = 1.2, f: float = 1.2) -> Any:
    """The seed GMS with Σk ×k and F_s, F_c ×f (a model that is too high)."""
    from stagectl.friction import StageModel, build

    spec = dict(cfg.sim.plant.friction.spec())
    spec["k_n_m"] = [k * v for v in spec["k_n_m"]]
    spec["fs_n"] = f * float(spec["fs_n"])
    spec["fc_n"] = f * float(spec["fc_n"])
    return StageModel(friction=build(spec), effects=cfg.sim.plant.effects, mass_kg=cfg.sim.plant.mass_kg)


def _with(cfg: Any, fraction: float) -> Any:
    c = cfg.controller
    return dataclasses.replace(c, settle=dataclasses.replace(c.settle, ahead_stiffness_fraction=fraction))


def _run_plain(seed: Any, fraction: float, hold_s: float = 0.15, segments: tuple[Any, ...] = ()) -> dict[str, Any]:
    from stagectl.control.controller import StageController
    from stagectl.control.trajectory import Dwell, Move, Scenario, TrajectoryGenerator

    ctl = StageController(_with(seed, fraction), PERIOD, model=_high(seed))
    ctl.reset(0.0)
    gen = TrajectoryGenerator(0.0)
    segs = segments or (Move(by_m=10e-6, max_velocity_m_s=1e-3, max_acceleration_m_s2=0.05, max_jerk_m_s3=20.0),)
    sc = Scenario(name="one", segments=(*segs, Dwell(hold_s)), start_m=0.0)
    gen.load(sc)
    plant = ElastoPlasticStage()
    x = 0.0
    rows = []
    for _ in range(round(sc.duration_s(0.0) / PERIOD)):
        ref = gen.step(PERIOD)
        cmd = ctl.step(PERIOD, x, ref)
        rows.append((ref.x_m, ref.v_m_s, ref.a_m_s2, x, cmd.force_n, cmd.terms["u_dob"], ctl._sm.active,
                     ctl.ff_scale * ctl.ff.input_scale * ctl.ff.model.stiffness_n_m, ctl._u_k, ctl._ahead_pass))
        x = plant.step(cmd.force_n)
    a = np.array(rows, dtype=float)
    return {"xr": a[:, 0], "vr": a[:, 1], "ar": a[:, 2], "x": a[:, 3], "u": a[:, 4], "dob": a[:, 5],
            "active": a[:, 6].astype(bool), "k_rev": a[:, 7], "u_k": a[:, 8], "pass": a[:, 9]}


def test_ahead_on_a_plain_plant_force_along_the_travel_and_bumpless(seed: Any) -> None:
    on = _run_plain(seed, 1.0)
    off = _run_plain(seed, 0.0)
    rest = (on["vr"] == 0.0) & (on["ar"] == 0.0)
    k = int(np.flatnonzero(~rest)[-1] + 1)  # first sample at rest
    e0 = on["xr"][k] - on["x"][k]
    assert e0 < -3e-7, "the high model must leave the stage ahead (the case under test)"
    np.testing.assert_array_equal(on["u"][:k], off["u"][:k])  # the move itself is unchanged
    assert on["active"][k] and not off["active"].any() and not np.any(off["u_k"])
    # the samples of the first continuation (pass 1) and of the second, if any (pass 2), as recorded after each step
    p1 = np.flatnonzero(on["pass"] == 1)
    p2 = np.flatnonzero(on["pass"] == 2)
    assert p1[0] == k and np.all(np.diff(p1) == 1)
    last = int(p2[-1]) if p2.size else int(p1[-1])
    j = last + 1  # the first sample after the continuation: its force is handed to the observer
    assert on["pass"][j] == 0 and on["u_k"][j] == 0.0 and not np.any(on["u_k"][j:])
    # the first's force: the model's reversal stiffness θ·β·Σk times the planned travel, the whole way e₀ at its end
    k_rev = on["k_rev"][k]
    assert on["u_k"][k - 1] == 0.0 and on["u_k"][p1[-1]] == pytest.approx(k_rev * e0, rel=1e-9)
    move_min = seed.controller.settle.move_min_m
    if p2.size:  # the second, from the error left: its gain the first's × planned / measured travel, bounded
        assert p2[0] == p1[-1] + 1 and np.all(np.diff(p2) == 1)
        e1 = on["xr"][p2[0]] - on["x"][p2[0]]
        assert abs(e1) > 0.5 * move_min
        r = min(1.3, max(1 / 1.3, e0 / (e0 - e1))) if (e0 - e1) * e0 > 0 else 1.3
        assert on["u_k"][last] - on["u_k"][p1[-1]] == pytest.approx(k_rev * r * e1, rel=1e-9)
    # the observer does not take it up while it runs, and takes it over at the end without a step in u
    assert abs(on["dob"][j - 1] - on["dob"][k]) < 0.5 * abs(on["u_k"][j - 1])
    assert on["dob"][j] - on["dob"][j - 1] == pytest.approx(on["u_k"][j - 1], abs=0.1 * abs(on["u_k"][j - 1]))
    steps = np.abs(np.diff(on["u"][k - 1:j]))
    assert abs(on["u"][j] - on["u"][j - 1]) <= steps.max()
    # and the stage comes to rest at the target (±10 nm in the last 20 ms of the hold)
    e_on = np.abs(on["xr"] - on["x"])
    assert e_on[-20:].max() < 10e-9


def test_not_after_a_motion_that_reversed(seed: Any) -> None:
    # a motion that starts one way and comes to rest going the other (out and back without a stop): the stage ends
    # behind in its last direction, not ahead; no continuation from ahead, commands bit for bit as with it off
    from stagectl.control.trajectory import Move

    kw = {"max_velocity_m_s": 1e-3, "max_acceleration_m_s2": 0.05, "max_jerk_m_s3": 20.0}
    back = (Move(by_m=10e-6, **kw), Move(by_m=-10e-6, **kw))
    on, off = _run_plain(seed, 1.0, 0.05, back), _run_plain(seed, 0.0, 0.05, back)
    rest = (on["vr"] == 0.0) & (on["ar"] == 0.0)
    assert rest[1:].sum() > 40 and not rest[5:-60].all()
    np.testing.assert_array_equal(on["u"], off["u"])
    assert not np.any(on["u_k"])


@pytest.mark.parametrize("k, f", [(1.2, 1.2), (1.0, 1.15)])
def test_first_step_of_a_high_model_settles_within_30_ms(seed: Any, k: float, f: float) -> None:
    from stagectl.bench.control import steps_check

    model = _high(seed, k, f)
    on = steps_check(seed, _with(seed, 1.0), model=model, hold_s=0.3)
    off = steps_check(seed, _with(seed, 0.0), model=model, hold_s=0.3)
    assert on["at_move_end"][0]["e_m"] < -3e-7  # the first move ends ahead by more than the rest spring's range
    assert off["settle_s"][0] is not None and off["settle_s"][0] > 0.03  # the earlier controller misses
    assert on["settle_s"][0] is not None and on["settle_s"][0] <= 0.03 + 1e-9
    assert on["settled"] == 4 and not on["limit_cycle"] and on["fault"] is None
    assert on["max_late_excursion_m"] < 10e-9
