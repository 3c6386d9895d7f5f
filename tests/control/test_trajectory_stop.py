"""``TrajectoryGenerator.stop_m``: where the reference next comes to rest without reversing first (NaN when a
turn may come first), checked against the sampled reference itself: whenever it is finite, the reference travels
monotonically to it and rests there (v = 0); whenever a turn lies ahead before any rest, it is NaN."""

from __future__ import annotations

import numpy as np
import pytest

from stagectl.control.trajectory import Cosine, Dwell, Move, Sine, TrajectoryGenerator, Triangle

DT = 1e-5  # fine enough that a rest between two samples is within 1e-12 m of one
LIM = {"max_acceleration_m_s2": 0.1, "max_jerk_m_s3": 100.0}
CASES = {
    "moves": [Move(by_m=10e-6, **LIM), Dwell(0.01), Move(by_m=-4e-6, **LIM), Move(by_m=3e-6, **LIM)],
    "triangle": [Triangle(span_m=30e-6, velocity_m_s=0.3e-3, max_acceleration_m_s2=0.02, max_jerk_m_s3=1.0,
                          cycles=2), Dwell(0.01)],
    "cosine": [Cosine(amplitude_m=-4e-6, frequency_hz=5.0, cycles=2), Dwell(0.01)],
    "sine_then_dwell": [Sine(amplitude_m=1e-6, frequency_hz=5.0, cycles=1.3), Dwell(0.01)],
    "sine_then_move": [Sine(amplitude_m=1e-6, frequency_hz=5.0, cycles=1.3), Move(by_m=2e-6, **LIM)],
    # two moving segments back to back: the junction is a turn (v = 0, a ≠ 0), not a rest (on main stop_m was
    # the junction from the first cosine's last turn on, holding the look-ahead back there)
    "cosine_into_cosine": [Cosine(amplitude_m=-4e-6, frequency_hz=5.0, cycles=1),
                           Cosine(amplitude_m=-4e-6, frequency_hz=5.0, cycles=1), Dwell(0.01)],
    "cosine_then_move": [Cosine(amplitude_m=-4e-6, frequency_hz=5.0, cycles=1), Move(by_m=2e-6, **LIM)],
    "cosine_on_in_the_same_direction": [Cosine(amplitude_m=-4e-6, frequency_hz=5.0, cycles=1),
                                        Cosine(amplitude_m=4e-6, frequency_hz=5.0, cycles=1), Dwell(0.01)],
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_stop_m_is_where_the_reference_rests_without_turning(name: str) -> None:
    gen = TrajectoryGenerator(1e-3)
    gen.replace(CASES[name])
    rows = [(*gen.sample(), gen.stop_m())]
    while not gen.done:
        rows.append((*gen.step(DT), gen.stop_m()))
    for _ in range(3):
        rows.append((*gen.step(DT), gen.stop_m()))
    a = np.array(rows)
    x, v, stop = a[:, 0], a[:, 1], a[:, 3]
    v_scale = np.abs(v).max()
    finite = np.flatnonzero(np.isfinite(stop))
    assert finite.size > 0
    for k in finite[::37]:
        # the reference's own future: it reaches stop_m (first sample within 1e-12 m) ...
        near = np.flatnonzero(np.abs(x[k + 1:] - stop[k]) <= 1e-12)
        assert near.size, (k, x[k], stop[k])
        i = k + 1 + near[0]
        # ... at rest (v within 0.1 % of the motion's peak: a rest between two samples, or a cosine's end) ...
        assert abs(v[i]) <= 1e-3 * v_scale, (k, i, v[i])
        # ... without turning on the way
        d = np.diff(x[k:i + 1])
        assert (d >= -1e-18).all() or (d <= 1e-18).all(), (k, i)
    if name in ("triangle", "cosine", "cosine_into_cosine", "cosine_on_in_the_same_direction"):  # NaN up to the last turn
        turns = np.flatnonzero(v[:-2] * v[2:] < 0.0)
        assert turns.size and np.isnan(stop[: turns[-1]]).all()
    if name == "sine_then_move":  # a moving end with a move after it: not known (the move's stop is not bound)
        assert np.isnan(stop[int((1.3 / 5.0 - 0.01) / DT)])
    if name == "cosine_then_move":  # the move's stop phases from a ≠ 0 turn at once: NaN up to the junction (0.2 s)
        assert np.isnan(stop[: int(0.2 / DT) - 2]).all() and np.isfinite(stop[int(0.2 / DT) + 2])


@pytest.mark.parametrize("repeat", [True, False])
def test_a_repeated_cosine_without_settle_turns_at_its_restart(repeat: bool) -> None:
    """A scenario repeated back to back (``settle_s`` 0) restarts its cosine where the last one ended: a turn
    (v = 0, a ≠ 0), so ``stop_m`` is NaN from the cosine's last turn on, as for a cosine straight into a cosine
    (on main: the restart point, the look-ahead held back there). Run once, it rests at its end."""
    from stagectl.control.reference import TrajectoryReference
    from stagectl.control.trajectory import Scenario

    src = TrajectoryReference()
    src.set_scenario(Scenario(name="c", segments=(Cosine(amplitude_m=-4e-6, frequency_hz=5.0, cycles=1),)),
                     repeat=repeat)
    src.hold(0.0, 1e-3)
    T = 1e-4
    rows = []
    for k in range(1, int(0.35 / T)):
        ref = src.sample(k * T)
        rows.append((ref.x_m, ref.v_m_s, src.stop_m()))
    a = np.array(rows)
    after_turn = a[int(0.11 / T):int(0.19 / T)]  # between the first cosine's turn (0.1 s) and its end (0.2 s)
    if repeat:
        assert np.isnan(after_turn[:, 2]).all()
        assert (a[int(0.2 / T) + 5:, 1] != 0.0).any()  # (it did restart)
    else:
        assert (after_turn[:, 2] == 1e-3).all()
