"""The loop process ends within its grace once its daemon is gone, even when it is stuck (loopproc backstop).

A stand-in daemon (a subprocess) forks a real loop process with ``spawn_loop_process`` on the rig of conftest,
starts its loop and is then SIGKILLed. The loop process gets SIGTERM from the kernel (``PR_SET_PDEATHSIG``)
and is stuck where no SIGTERM handler helps: in a ``close`` that never returns, or in a controller step that
blocks the loop thread. It must end anyway: faulthandler dumps its stacks (naming where it was stuck) and
exits. Every wait is on a pipe or a pidfd; the time-outs are failure guards, not timing checks.
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent

DAEMON = r"""
import dataclasses, sys, threading, time
sys.path[:0] = [sys.argv[2], sys.argv[1]]  # tests/daemon first: its conftest
from conftest import PDConfig, RigAppConfig, build_rig
from stagectl.daemon.loopproc import spawn_loop_process
from stagectl.runtime.shm import PHASE

where = sys.argv[3]

def build(cfg):
    asm = build_rig(cfg)
    if where == "step":  # the first controller step blocks the loop thread (for 60 s: longer than any guard)
        asm.loop.controller.hang.set()
    def hang_in_close():
        asm.close()
        threading.Event().wait()  # never returns; a SIGTERM handler runs and the wait goes on
    return dataclasses.replace(asm, close=hang_in_close if where == "close" else asm.close)

asm = spawn_loop_process(build, RigAppConfig(PDConfig()), telemetry_buffer_s=0.0, timeout_s=60.0,
                         stopping=lambda: False, end_grace_s=0.3)
remote = asm.loop
remote.conn.send({"go": True, "latch": None})
end = time.monotonic() + 60
while remote.shm.ctl[PHASE] != 1 and time.monotonic() < end:
    time.sleep(0.01)
print(remote.pid, flush=True)
sys.stdin.read()  # until SIGKILLed
"""


@pytest.mark.parametrize("where", ["close", "step"])
def test_stuck_loop_process_ends_after_its_daemon_is_killed(where):
    proc = subprocess.Popen([sys.executable, "-c", DAEMON, str(HERE.parent), str(HERE), where],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    pidfd = -1
    try:
        assert select.select([proc.stdout], [], [], 120)[0], "the stand-in daemon printed no loop pid"
        line = proc.stdout.readline()
        assert line.strip().isdigit(), proc.stderr.read() if proc.poll() is not None else line
        loop_pid = int(line)
        pidfd = os.pidfd_open(loop_pid)
        proc.kill()
        proc.wait(30)
        # nobody signals the loop process but the kernel (its parent died): it must end by itself
        assert select.select([pidfd], [], [], 60)[0], f"loop process {loop_pid} still alive"
        err = proc.stderr.read()  # the loop process held the pipe too: EOF now
    finally:
        if pidfd >= 0:
            if not select.select([pidfd], [], [], 0)[0]:
                signal.pidfd_send_signal(pidfd, signal.SIGKILL)  # leave no orphan behind a failed test
            os.close(pidfd)
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
    # it ended through the backstop's dump (not the kernel's SIGALRM), which names where it was stuck
    assert "Timeout (0:00:00.300000)!" in err, err[-3000:]
    assert ("in hang_in_close" if where == "close" else "in step") in err, err[-3000:]
