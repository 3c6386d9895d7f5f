"""Thread scheduling helpers for the daemon's non-real-time threads."""

from __future__ import annotations

import os

#: ``sched_getscheduler`` ORs this flag into the policy under systemd's ``CPUSchedulingResetOnFork=yes``
#: (Linux ``SCHED_RESET_ON_FORK``): FIFO then reads back as 0x40000001, not ``SCHED_FIFO`` (1)
SCHED_RESET_ON_FORK = 0x40000000


def is_realtime_policy(policy: int) -> bool:
    """True for SCHED_FIFO/SCHED_RR as ``sched_getscheduler`` returns it, with ``SCHED_RESET_ON_FORK`` masked."""
    return (policy & ~SCHED_RESET_ON_FORK) in (os.SCHED_FIFO, os.SCHED_RR)


def demote_to_normal_priority() -> None:
    """Run the *calling thread* at SCHED_OTHER if the process inherited SCHED_FIFO/RR.

    systemd's ``CPUSchedulingPolicy=fifo`` applies to the exec'd process, so every thread starts at FIFO;
    on Linux ``sched_setscheduler(0, ...)`` acts on the calling thread only, so helper threads (telemetry
    writer, control socket, logging) step down and never compete with the loop. The policy is decoded with
    ``SCHED_RESET_ON_FORK`` masked (the unit sets ``CPUSchedulingResetOnFork=yes``) and the flag is kept (a
    thread may drop it only with CAP_SYS_NICE). Never raises.
    """
    try:
        policy = os.sched_getscheduler(0)
        if is_realtime_policy(policy):
            # keep the flag: clearing SCHED_RESET_ON_FORK needs CAP_SYS_NICE, which the unit does not grant
            os.sched_setscheduler(0, os.SCHED_OTHER | (policy & SCHED_RESET_ON_FORK), os.sched_param(0))
    except (OSError, AttributeError):
        pass
