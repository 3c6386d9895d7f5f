"""Helper threads step down from the unit's SCHED_FIFO even when the policy reads back with SCHED_RESET_ON_FORK."""

from __future__ import annotations

import os
import threading

import pytest

from stagectl.daemon._sched import SCHED_RESET_ON_FORK, demote_to_normal_priority, is_realtime_policy


def test_policy_decoded_with_reset_on_fork_masked():
    assert SCHED_RESET_ON_FORK == 0x40000000
    # what sched_getscheduler returns under CPUSchedulingPolicy=fifo + CPUSchedulingResetOnFork=yes
    assert is_realtime_policy(0x40000001) and is_realtime_policy(os.SCHED_FIFO | SCHED_RESET_ON_FORK)
    assert is_realtime_policy(os.SCHED_RR | SCHED_RESET_ON_FORK) and is_realtime_policy(os.SCHED_FIFO)
    assert not is_realtime_policy(SCHED_RESET_ON_FORK) and not is_realtime_policy(os.SCHED_OTHER)
    assert not is_realtime_policy(os.SCHED_BATCH | SCHED_RESET_ON_FORK)


def _in_thread(fn):
    out: dict[str, object] = {}

    def run() -> None:
        try:
            out["value"] = fn()
        except BaseException as exc:  # noqa: BLE001
            out["error"] = exc

    t = threading.Thread(target=run)
    t.start()
    t.join(10)
    if "error" in out:
        raise out["error"]  # type: ignore[misc]
    return out["value"]


def test_demote_really_drops_a_fifo_reset_on_fork_thread():
    """A real thread at SCHED_FIFO | SCHED_RESET_ON_FORK (as systemd starts the service) ends at SCHED_OTHER."""

    def fifo_then_demote() -> tuple[int, int]:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO | SCHED_RESET_ON_FORK, os.sched_param(1))
        except (OSError, AttributeError) as exc:
            pytest.skip(f"cannot set SCHED_FIFO here ({exc})")
        before = os.sched_getscheduler(0)
        try:
            demote_to_normal_priority()
            return before, os.sched_getscheduler(0)
        finally:  # never leave a FIFO thread behind, whatever happened
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))

    before, after = _in_thread(fifo_then_demote)
    assert before == os.SCHED_FIFO | SCHED_RESET_ON_FORK  # the value the old check did not recognise
    assert after & ~SCHED_RESET_ON_FORK == os.SCHED_OTHER
    assert after & SCHED_RESET_ON_FORK  # the flag is kept (dropping it needs CAP_SYS_NICE)
