"""The learners' evidence gate after an irregular sample interval (a skipped slot, a stale sample): the observer was
not told the force the actuator applied in the slots it did not see and takes that force error for a disturbance,
which is no error of the model. So after a step whose dt is longer than IRREGULAR_DT_PERIODS·T the adaptation
(θ, β) waits ADAPT_SETTLED_TIME_CONSTANTS observer time constants, as after an inertia transient; a late wake-up's
jitter (dt < 1.5 T) does not stop it. Controller alone, sim.yaml settings, a stage that lags a 10 µm cosine's
descent by 20 nm (the observer sees a force error to adapt to)."""

from __future__ import annotations

import math
from pathlib import Path

from stagectl.control.controller import ADAPT_SETTLED_TIME_CONSTANTS, IRREGULAR_DT_PERIODS, StageController
from stagectl.control.trajectory import Cosine, TrajectoryGenerator

REPO = Path(__file__).resolve().parents[2]


def _thetas(dt_at: dict[int, float], n: int = 950) -> list[float]:
    from stagectl.config import load_app_config

    cfg = load_app_config(REPO / "config" / "sim.yaml")
    ctl = StageController(cfg.controller, cfg.timing)
    T = cfg.loop.period_s
    ctl.reset(0.0)
    gen = TrajectoryGenerator(0.0)
    gen.replace(Cosine(amplitude_m=10e-6, frequency_hz=1.0, cycles=1))
    out = []
    for k in range(n):
        dt = dt_at.get(k, T)
        ref = gen.step(dt)
        ctl.step(dt, ref.x_m - 20e-9 * (1 if ref.v_m_s >= 0 else -1) * min(1.0, k / 50), ref)
        out.append(ctl.ff_scale)
    return out


def test_adaptation_waits_after_an_irregular_interval_not_after_jitter() -> None:
    T = 1e-3
    k0 = 850  # sliding on the way back down (θ adapts from 0.75 s on)
    base = _thetas({})
    assert base[k0 + 1] != base[k0]  # the adaptation is under way here
    skipped = _thetas({k0: 2.0 * T})
    jitter = _thetas({k0: 1.2 * T, k0 + 1: 0.8 * T})
    assert IRREGULAR_DT_PERIODS * T > 1.2 * T
    from stagectl.config import load_app_config

    f_dob = load_app_config(REPO / "config" / "sim.yaml").controller.dob.bandwidth_hz
    wait = ADAPT_SETTLED_TIME_CONSTANTS / (2 * math.pi * f_dob)
    n_wait = int(wait / T)
    assert n_wait >= 4
    # after the skipped slot: θ held for the gate's wait, then adapting again
    assert all(skipped[k] == skipped[k0 - 1] for k in range(k0, k0 + n_wait - 1))
    assert skipped[k0 + n_wait + 3] != skipped[k0 + n_wait - 2]
    # jitter: no wait
    assert jitter[k0 + 1] != jitter[k0 - 1] and jitter[k0 + 2] != jitter[k0 + 1]
