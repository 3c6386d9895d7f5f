"""A segment that ends moving (``sine``, a cosine of fractional cycles) followed by a ``dwell``, by a scenario's
``settle_s`` or by another rest-start segment: the reference stops at once where the segment ended, exactly as
when that segment is the last one (the hold after the queue). On main this raised
``ValueError("dwell must start at rest")`` from ``TrajectoryGenerator.step``."""

from __future__ import annotations

import math

import pytest

from stagectl.control.api import Reference
from stagectl.control.trajectory import Cosine, Dwell, Move, Scenario, Sine, TrajectoryGenerator, Triangle

DT = 1e-3


def _run(segments: tuple, settle_s: float = 0.0) -> list[tuple[str, Reference]]:
    gen = TrajectoryGenerator(0.0)
    sc = Scenario(name="t", segments=segments, settle_s=settle_s)
    n = round(sc.duration_s() / DT) + 5
    gen.load(sc)
    rows = []
    for _ in range(n):
        ref = gen.step(DT)
        rows.append((gen.state.segment, ref))
    return rows


@pytest.mark.parametrize("moving", [Sine(amplitude_m=1e-6, frequency_hz=2.0, cycles=1.3),
                                    Cosine(amplitude_m=-10e-6, frequency_hz=1.0, cycles=0.25)])
@pytest.mark.parametrize("after", ["dwell", "settle"])
def test_dwell_after_a_moving_end_holds_the_reached_position(moving: Sine | Cosine, after: str) -> None:
    alone = _run((moving,))  # the segment as the last one: the generator's own hold after it
    tail = (moving, Dwell(0.1)) if after == "dwell" else (moving,)
    rows = _run(tail, settle_s=0.1 if after == "settle" else 0.0)
    held_alone = [r for s, r in alone if s == "hold"]
    held = [r for s, r in rows if s == "dwell"]
    assert held and held_alone
    moving_rows = [r for s, r in rows if s in ("sine", "cosine")]
    assert abs(moving_rows[-1].v_m_s) > 1e-6  # it really was moving one sample before the dwell
    # the dwell holds exactly the position the hold after the segment holds, at rest
    assert all(r == held_alone[0] for r in held)
    assert held_alone[0].v_m_s == 0.0 and held_alone[0].a_m_s2 == 0.0
    assert rows[-1][1] == held_alone[0]
    # and the duration is the segment's plus the dwell's
    sc = Scenario(name="t", segments=tail, settle_s=0.1 if after == "settle" else 0.0)
    assert sc.duration_s() == pytest.approx(moving.cycles / moving.frequency_hz + 0.1)


def test_rest_start_segments_after_a_moving_end_start_from_the_reached_position() -> None:
    sine = Sine(amplitude_m=1e-6, frequency_hz=2.0, cycles=0.75)  # ends at x = −1 µm, v = 0, a ≠ 0 ... and at
    sine2 = Sine(amplitude_m=1e-6, frequency_hz=2.0, cycles=0.5)  # x = 0 moving at −2πfA
    cos = Cosine(amplitude_m=2e-6, frequency_hz=2.0, cycles=1)
    tri = Triangle(span_m=50e-6, velocity_m_s=1e-3, max_acceleration_m_s2=0.1, max_jerk_m_s3=100.0)
    gen = TrajectoryGenerator(0.0)
    gen.load(Scenario(name="t", segments=(sine, sine2, cos, sine2, tri, Move(by_m=1e-6))))
    x_end = gen.final_reference().x_m
    seen: dict[str, Reference] = {}
    prev = gen.sample()
    for _ in range(round(gen.remaining_s() / DT) + 3):
        seg0 = gen.state.segment
        ref = gen.step(DT)
        if gen.state.segment != seg0 and gen.state.segment in ("cosine", "triangle"):
            seen[gen.state.segment] = prev
        assert math.isfinite(ref.x_m)
        prev = ref
    assert gen.done and gen.sample().x_m == pytest.approx(x_end, abs=1e-15)
    assert set(seen) == {"cosine", "triangle"}
