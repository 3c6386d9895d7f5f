"""Daemon logging: journald priority prefixes, queued (non-blocking) handler, rate-limited warnings."""

from __future__ import annotations

import io
import logging
import queue

from stagectl.daemon.logging import DaemonLogging, DroppingQueueHandler, JournalFormatter, RateLimitFilter


def _record(level: int, msg: str, name: str = "stagectl.loop") -> logging.LogRecord:
    return logging.LogRecord(name, level, __file__, 1, msg, (), None)


def test_priority_prefix_on_every_line():
    f = JournalFormatter(prefix=True)
    assert f.format(_record(logging.ERROR, "boom\nsecond line")) == "<3>stagectl.loop: boom\n<3>second line"
    assert f.format(_record(logging.WARNING, "w")).startswith("<4>")
    assert f.format(_record(logging.INFO, "i")).startswith("<6>")
    assert f.format(_record(logging.DEBUG, "d")).startswith("<7>")
    assert f.format(_record(logging.CRITICAL, "c")).startswith("<2>")


def test_rate_limit_per_template_with_suppressed_count():
    now = [0.0]
    dut = RateLimitFilter(interval_s=10.0, burst=1, clock=lambda: now[0])
    passed = [dut.filter(_record(logging.WARNING, "overrun %d")) for _ in range(5)]
    assert passed == [True, False, False, False, False]
    assert dut.filter(_record(logging.WARNING, "other message"))  # another template is independent
    assert dut.filter(_record(logging.ERROR, "overrun %d"))  # errors are never suppressed
    now[0] = 10.5
    r = _record(logging.WARNING, "overrun %d")
    assert dut.filter(r) and "(4 similar messages suppressed)" in r.msg


def test_full_queue_drops_and_counts_instead_of_blocking():
    q: queue.Queue = queue.Queue(maxsize=2)
    dut = DroppingQueueHandler(q)
    for i in range(5):
        dut.handle(_record(logging.INFO, f"m{i}"))
    assert q.qsize() == 2 and dut.dropped == 3


def test_daemon_logging_writes_prefixed_lines_and_restores():
    buf = io.StringIO()
    root = logging.getLogger()
    before = list(root.handlers)
    dut = DaemonLogging(logging.INFO, stream=buf, journal=True)
    logging.getLogger("stagectl.daemon").info("ready")
    logging.getLogger("stagectl.daemon").debug("not shown")
    dut.close()  # flushes the queue
    assert buf.getvalue() == "<6>stagectl.daemon: ready\n"
    assert root.handlers == before


def test_close_with_a_timeout_returns_while_the_writer_is_blocked_on_a_full_stream():
    """The loop process closes its logging with a time-out: a writer blocked on a full stderr (a stalled journal,
    a pipe nobody reads) must not keep it alive (stagectl.daemon.loopproc)."""
    import fcntl
    import os

    r, w = os.pipe()
    try:
        fcntl.fcntl(w, fcntl.F_SETFL, os.O_NONBLOCK)
        try:
            while True:
                os.write(w, b"x" * 65536)
        except BlockingIOError:
            pass  # the pipe is full
        fcntl.fcntl(w, fcntl.F_SETFL, 0)  # writes block again
        stream = open(w, "w", closefd=False)
        logs = DaemonLogging(logging.INFO, stream=stream, journal=True)
        writer = logs.listener._thread
        try:
            logging.getLogger("stagectl.test").error("this write blocks")
            logs.close(timeout_s=0.2)  # returns (the writer is not waited for beyond the time-out)
            assert writer is not None and writer.is_alive()  # still blocked in its write: close did not wait
            assert logging.getLogger().handlers == logs._old_handlers  # handlers restored all the same
        finally:
            while writer is not None and writer.is_alive():  # unblock and end it (the sentinel is queued)
                os.read(r, 1 << 20)
                writer.join(0.05)
    finally:
        os.close(r)
        os.close(w)
