"""Ctrl-C while a CANopen driver stops canopen's Notifier (end of ``configure``, or ``close``): the interrupt
goes on, but only after the Notifier's thread has ended, so closing the bus afterwards cannot make python-can
print "Exception in thread ..." with a traceback over the one "interrupted" line.

Real python-can Notifier on a virtual bus, a real SIGINT to this process; the moment is made deterministic by
holding the Notifier's thread inside a frame until the SIGINT handler (Python's own behaviour: raise
KeyboardInterrupt) has run in the joining main thread.
"""

from __future__ import annotations

import itertools
import os
import signal
import threading

import can
import canopen
import pytest

from stagectl.drivers.canbus import CanopenNode, close_bus, open_bus

_ids = itertools.count()


def test_ctrl_c_while_the_notifier_stops_ends_its_thread_before_the_interrupt_goes_on() -> None:
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signal handlers need the main thread")
    channel = f"notifier-int-{os.getpid()}-{next(_ids)}"
    peer = open_bus({"interface": "virtual", "channel": channel})
    node = CanopenNode()
    node.name = "test"
    bus = node._bus = open_bus({"interface": "virtual", "channel": channel})
    node._network = canopen.Network(bus)
    in_frame, release = threading.Event(), threading.Event()

    def slow_listener(msg: can.Message) -> None:  # the thread is busy with a frame when the stop comes
        in_frame.set()
        release.wait(10.0)  # bound only for a broken test; released by the SIGINT handler

    node._network.listeners.append(slow_listener)
    node._start_notifier()
    notifier = node._notifier
    assert notifier is not None
    thread = next(t for t in notifier._readers if isinstance(t, threading.Thread))
    peer.send(can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False))
    assert in_frame.wait(10.0)

    def on_sigint(signum: int, frame: object) -> None:  # Python's default (raise KeyboardInterrupt), and
        release.set()  # only then let the Notifier's thread leave its frame
        raise KeyboardInterrupt

    def ctrl_c_once_stopping() -> None:
        while not notifier._stopped:  # Notifier.stop() has begun (it sets _stopped, then joins)
            threading.Event().wait(0.0005)
        os.kill(os.getpid(), signal.SIGINT)

    thread_errors: list[BaseException | None] = []
    old_hook = threading.excepthook
    threading.excepthook = lambda a: thread_errors.append(a.exc_value)
    old_handler = signal.signal(signal.SIGINT, on_sigint)
    try:
        sender = threading.Thread(target=ctrl_c_once_stopping, daemon=True)
        sender.start()
        with pytest.raises(KeyboardInterrupt):
            node._teardown()  # what close() runs: stop the Notifier, close the bus
        # the interrupt came out only after the thread ended, and the bus was closed after that
        assert not thread.is_alive()
        assert node._notifier is None and node._bus is None
        sender.join(10.0)
    finally:
        signal.signal(signal.SIGINT, old_handler)
        threading.excepthook = old_hook
        release.set()
        close_bus(peer)
    assert thread_errors == []
    assert can.Notifier.find_instances(bus) == ()  # unregistered: a new Notifier may start on such a bus
