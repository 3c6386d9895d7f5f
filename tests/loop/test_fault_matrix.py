"""Fault matrix: every fault the loop can latch (the supervisor's :data:`~stagectl.safety.SAFETY_FAULTS` and every
device :class:`~stagectl.drivers.base.FaultKind`), injected in simulated time on the PlantIO twin, with

* its reaction time in cycles: latched within ``detect`` cycles of the cause appearing, and the force acting on
  the plant 0 N by the end of the cycle that latched it (the drive's quick stop, same cycle);
* the latch: still latched ``HOLD`` cycles later with the cause gone, motion refused;
* its log line: one ERROR record ``FAULT <name>: <cause>``;
* reset: refused (one line naming the cause, fault kept) while a cause that can persist is still present, and
  accepted once it is gone. Causes that are a motion state (following error, speed, saturation, a jump, an
  exception, an unclean end of the last run) cannot be "present" while the drive is stopped: their reset is
  accepted and the same check runs again from the next cycle.

A new fault kind without a row here fails :func:`test_matrix_covers_every_fault_kind`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import pytest

from stagectl.drivers.base import DeviceState, FaultKind
from stagectl.loop import LoopState, LoopStateError
from stagectl.runtime.requests import MoveRequest, ResetRequest
from stagectl.safety import SAFETY_FAULTS, Safety

SETTLE = 20  # the cause appears at the end of this cycle (acts from cycle SETTLE + 1)
HOLD = 5
MASS_KG = 1.0  # the loop tests' MassPlant


@dataclass
class Case:
    """How to cause a fault: ``cause(loop, io, plant, ctl)`` at the end of cycle SETTLE; ``detect``: cycles from the
    first affected one to the latch (inclusive, 1 = the same cycle); ``persist``: make the cause stay present
    (None: the cause is not a lasting condition); ``remove``: take it away; ``safety``: config overrides."""

    cause: Callable
    detect: int = 1
    persist: Callable | None = None
    remove: Callable = lambda lp, io, pl, c: io.remove_cause()
    refused: str = ""
    safety: dict = field(default_factory=dict)


def _device(kind: FaultKind) -> Case:
    return Case(cause=lambda lp, io, pl, c: io.inject_fault(kind, "cause present", persist=True),
                persist=lambda lp, io, pl, c: None, refused=f"plant_io: {kind.value}: cause present")


def _stop_pushing(lp, io, pl, c):
    pl.push_n, pl.v_m_s = 0.0, 0.0


MATRIX: dict[str, Case] = {
    "not_finite": Case(cause=lambda lp, io, pl, c: io.glitch(math.nan, cycles=-1), persist=lambda *a: None,
                       refused="not_finite: measured position is nan"),
    # stale_cycles = 3: the third stale read latches
    "stale_position": Case(cause=lambda lp, io, pl, c: io.drop_samples(-1), detect=3, persist=lambda *a: None,
                           refused="stale_position: still no fresh position"),
    "position_limit": Case(cause=lambda lp, io, pl, c: setattr(pl, "x_m", 0.0102), persist=lambda *a: None,
                           remove=lambda lp, io, pl, c: setattr(pl, "x_m", 0.0095),
                           refused="position_limit: x = 0.0102",
                           safety={"max_velocity_m_s": 100.0}),
    # 200 µm for 3 cycles; the physical bound is 0.05 m/s·1 ms + 50 N/1 kg·(1 ms)²/2 + 1 µm = 76 µm
    "position_jump": Case(cause=lambda lp, io, pl, c: io.glitch(pl.x_m + 200e-6, cycles=3)),
    # a reference at 3 mm/s (bypassing the request checks, as a faulty trajectory would) with a 1 mm/s limit: the
    # stage follows it (one cycle of actuation delay) and v̂ crosses the limit on its 3rd sample after that
    "velocity_limit": Case(cause=lambda lp, io, pl, c: lp.reference.move(lp.status(False).t_s, 1e-3, 3e-3),
                           detect=4, remove=_stop_pushing, safety={"max_velocity_m_s": 1e-3}),
    "following_error": Case(cause=lambda lp, io, pl, c: setattr(pl, "push_n", 40.0), detect=3, remove=_stop_pushing,
                            safety={"following_error_m": 5e-6}),
    # clamped for force_saturation_time_s = 3 ms: latched on the 4th clamped cycle
    "force_limit": Case(cause=lambda lp, io, pl, c: setattr(pl, "push_n", -30.0), detect=6, remove=_stop_pushing,
                        safety={"max_force_n": 10.0, "following_error_m": 1e-2, "force_saturation_time_s": 0.003,
                                "max_velocity_m_s": 10.0}),
    "loop_error": Case(cause=lambda lp, io, pl, c: setattr(c, "fail_next", True)),
    "unclean_shutdown": Case(cause=lambda lp, io, pl, c: None, detect=0),  # latched before the run: see below
    **{k.value: _device(k) for k in FaultKind},
}


def test_matrix_covers_every_fault_kind():
    known = set(SAFETY_FAULTS) | {k.value for k in FaultKind}
    assert set(MATRIX) == known, f"missing rows: {known - set(MATRIX)}, stale rows: {set(MATRIX) - known}"
    assert len(SAFETY_FAULTS) == len(set(SAFETY_FAULTS))
    assert not set(SAFETY_FAULTS) & {k.value for k in FaultKind}  # one name, one cause


class _Probe:
    """Per cycle: the force acting on the plant after the cycle's write [N]."""

    def __init__(self, io):
        self.io, self.applied = io, []

    def append(self, row):
        self.applied.append(self.io.applied_force_n)


def _reset(loop, cycles=3):
    fut = loop.submit(ResetRequest())
    loop.run(cycles=cycles)
    return fut


@pytest.mark.parametrize("name", sorted(MATRIX))
def test_fault_matrix(make, name, caplog):
    case = MATRIX[name]
    caplog.set_level(logging.ERROR, logger="stagectl.loop")
    loop, io, plant, ctl, clock = make(safety=case.safety)
    loop.safety = Safety(loop.safety.cfg, loop.period_s, mass_kg=MASS_KG)  # the position_jump bound needs m
    probe = _Probe(io)
    loop.add_sink(probe)
    if name == "unclean_shutdown":
        loop.latch_fault(name, "previous run did not stop cleanly")
        loop.run(cycles=SETTLE)
        st = loop.status()
        assert st.state is LoopState.FAULT and st.fault.name == name
        assert io.state is not DeviceState.ENABLED and all(f == 0.0 for f in probe.applied)  # never enabled
    else:
        loop.on_cycle = lambda: loop.cycle == SETTLE and case.cause(loop, io, plant, ctl)
        loop.submit(MoveRequest(target_m=20e-6, max_velocity_m_s=0.5e-3))
        loop.run(cycles=SETTLE + 1 + case.detect + HOLD)
        loop.on_cycle = None
        assert any(abs(f) > 1e-3 for f in probe.applied[:SETTLE])  # it was pushing before
        st = loop.status()
        # ---- latched, with its name, within its reaction time
        assert st.state is LoopState.FAULT and st.fault.name == name, st.fault
        first = SETTLE + 1
        assert first <= st.fault.cycle <= first + case.detect - 1, (st.fault.cycle, first, case.detect)
        # ---- the force on the plant is 0 N from the end of the latching cycle on
        after = probe.applied[st.fault.cycle:]
        assert after and all(f == 0.0 for f in after), probe.applied[st.fault.cycle - 2:]
        # ---- the log line names it and its cause
        lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR and "FAULT" in r.getMessage()]
        assert len(lines) == 1 and lines[0].startswith(f"FAULT {name}: {st.fault.cause}"), lines
    # ---- latched: motion refused, still in fault after HOLD more cycles
    mv = loop.submit(MoveRequest(relative_m=1e-6))
    loop.run(cycles=HOLD)
    with pytest.raises(LoopStateError, match="reset first"):
        mv.result(timeout=0)
    assert loop.status().state is LoopState.FAULT and loop.status().fault.name == name
    # ---- reset while the cause persists: refused, naming it; the fault stays
    if case.persist is not None:
        case.persist(loop, io, plant, ctl)
        with pytest.raises(LoopStateError) as ei:
            _reset(loop).result(timeout=0)
        msg = str(ei.value)
        assert msg.startswith("reset refused: cause still present: ") and case.refused in msg, msg
        assert "\n" not in msg and loop.status().fault.name == name
        assert all(f == 0.0 for f in probe.applied[-3:])
    # ---- cause gone: reset accepted, the stage is controlled again and follows a move
    case.remove(loop, io, plant, ctl)
    out = _reset(loop).result(timeout=0)
    assert out["state"] == "active" and out["cleared"]["name"] == name
    mv = loop.submit(MoveRequest(relative_m=5e-6, max_velocity_m_s=0.5e-3))
    loop.run(cycles=100)
    assert mv.result(timeout=0)["target_m"] == pytest.approx(loop.status().x_ref_m)
    assert loop.status().fault is None, loop.status().fault
