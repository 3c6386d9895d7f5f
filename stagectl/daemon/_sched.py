"""Thread scheduling helpers for the daemon's non-real-time threads."""

from __future__ import annotations

import os


def demote_to_normal_priority() -> None:
    """Run the *calling thread* at SCHED_OTHER if the process inherited SCHED_FIFO/RR.

    systemd's ``CPUSchedulingPolicy=fifo`` applies to the exec'd process, so every thread starts at FIFO;
    on Linux ``sched_setscheduler(0, ...)`` acts on the calling thread only, so helper threads (telemetry
    writer, control socket, logging) step down and never compete with the loop. Never raises.
    """
    try:
        if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError):
        pass
