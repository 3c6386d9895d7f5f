"""A true actuation delay passes the rule that a delay must not move with the analysis filter
(docs/discovery.md §13).

Plain oracle, no stagectl simulator: the inverse dynamics of a smooth trajectory, with the recorded command
leading the applied force by the delay. (The rule's other side, a closed loop answering an unrecorded force
disturbance, was measured on the held-out generator's recordings; a small plain closed loop written here did
not reproduce that spurious delay, so it is not a test yet.)
"""

from __future__ import annotations

import numpy as np
import pytest

from stagectl.ident.discover import discover
from stagectl.ident.recording import Recording

M_KG, FC_N, FV_N_S_M = 4.0, 2.5, 60.0
FS_HZ = 2000.0


def _delayed(seed: int, duration_s: float, delay_s: float) -> Recording:
    rng = np.random.default_rng(seed)
    dt = 1.0 / FS_HZ
    n = int(duration_s * FS_HZ)
    t = np.arange(n) * dt
    f1 = rng.uniform(4.0, 6.0)

    def x_of(tt: np.ndarray) -> np.ndarray:
        return 2e-3 * np.sin(2 * np.pi * f1 * tt) + 0.5e-3 * np.sin(2 * np.pi * 2.7 * f1 * tt + 1.0)

    def force(tt: np.ndarray) -> np.ndarray:  # applied force of the exact trajectory
        xx = x_of(tt)
        vv = np.gradient(xx, dt)
        aa = np.gradient(vv, dt)
        return M_KG * aa + FC_N * np.tanh(vv / 1e-5) + FV_N_S_M * vv

    # commanded at t[k], held over [t[k], t[k+1]) and applied delay_s later: the held value is the applied
    # force at the middle of the interval it acts over (zero-order hold, docs/discovery.md §3)
    u = force(t + delay_s + 0.5 * dt) + 0.01 * rng.standard_normal(n)
    return Recording(t=t, x=x_of(t) + 2e-9 * rng.standard_normal(n), u=u, x_ref=x_of(t), source=f"delayed {seed}")


@pytest.mark.parametrize("delay_s", [0.6e-3, 2.2e-3])
def test_a_true_delay_stays_put_when_the_filter_changes(delay_s: float) -> None:
    res = discover(_delayed(23, 8.0, delay_s), _delayed(24, 5.0, delay_s), catalogue=("delay",), max_rounds=1)
    assert [e.name for e in res.effects] == ["delay"], res.rounds[0].candidates
    assert res.effects[0].parameters.delay_s == pytest.approx(delay_s, rel=0.1)
