"""The in-process bus against python-can's stock ``virtual`` bus on the same channel: frames both ways, in order,
as independent copies; blocking and polling receive; software filters; own frames; shutdown."""

from __future__ import annotations

import itertools
import threading

import can
import pytest
from can.interfaces.virtual import VirtualBus
from stagectl.drivers import canbus
from stagectl.drivers.inproc import InprocBus

_n = itertools.count()


@pytest.fixture
def channel():
    return f"inproc-test-{next(_n)}-{id(object()):x}"


@pytest.fixture
def buses():
    opened = []

    def make(cls, channel, **kw):
        b = cls(channel=channel, **kw)
        opened.append(b)
        return b

    yield make
    for b in opened:
        b.shutdown()


def test_open_bus_gives_the_inproc_bus_for_a_plain_virtual_mapping_and_the_stock_one_otherwise(channel):
    a = canbus.open_bus({"interface": "virtual", "channel": channel})
    b = canbus.open_bus({"interface": "virtual", "channel": channel, "rx_queue_size": 4})
    try:
        assert type(a) is InprocBus and type(b) is VirtualBus
        a.send(can.Message(arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False))
        got = b.recv(1.0)
        assert got is not None and got.arbitration_id == 0x181 and bytes(got.data) == b"\x01\x02"
    finally:
        canbus.close_bus(a)
        canbus.close_bus(b)


@pytest.mark.parametrize("sender_cls, receiver_cls", [(InprocBus, VirtualBus), (VirtualBus, InprocBus),
                                                      (InprocBus, InprocBus)])
def test_frames_arrive_in_order_as_independent_copies_with_the_stock_fields(buses, channel, sender_cls,
                                                                           receiver_cls):
    tx = buses(sender_cls, channel)
    rx = buses(receiver_cls, channel)
    msg = can.Message(arbitration_id=0x201, data=bytearray(b"\x0f\x00\x05\x00"), is_extended_id=False)
    tx.send(msg)
    msg.data[2] = 6  # the sender reuses its frame (pdo_codec): the copy on the bus must not change
    tx.send(msg)
    tx.send(can.Message(arbitration_id=0x18FF0001, data=b"", is_extended_id=True))
    got = [rx.recv(1.0) for _ in range(3)]
    assert rx.recv(0.0) is None and tx.recv(0.0) is None  # nothing else, and no own frame by default
    assert [bytes(m.data) for m in got] == [b"\x0f\x00\x05\x00", b"\x0f\x00\x06\x00", b""]
    assert [(m.arbitration_id, m.is_extended_id, m.dlc) for m in got] == [(0x201, False, 4), (0x201, False, 4),
                                                                          (0x18FF0001, True, 0)]
    assert all(m.is_rx and m.channel == channel and m.timestamp > 0 for m in got)
    assert got[0] is not msg and got[0].data is not msg.data


def test_a_blocked_receiver_wakes_when_another_thread_sends(buses, channel):
    rx = buses(InprocBus, channel)
    tx = buses(InprocBus, channel)
    got: list[can.Message | None] = []
    waiting = threading.Event()

    def reader() -> None:
        waiting.set()
        got.append(rx.recv(30.0))  # a lost wake-up would hang here for the full 30 s

    t = threading.Thread(target=reader)
    t.start()
    waiting.wait(5.0)
    tx.send(can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False))
    t.join(30.0)
    assert not t.is_alive() and got and got[0] is not None and got[0].arbitration_id == 0x701


def test_recv_with_a_timeout_returns_none_when_nothing_comes(buses, channel):
    rx = buses(InprocBus, channel)
    assert rx.recv(0.01) is None and rx.recv(0.0) is None


def test_filters_and_own_frames(buses, channel):
    rx = buses(InprocBus, channel, can_filters=[{"can_id": 0x181, "can_mask": 0x7FF, "extended": False}])
    own = buses(InprocBus, channel, receive_own_messages=True)
    for cid in (0x701, 0x181, 0x281):
        own.send(can.Message(arbitration_id=cid, data=b"\x00", is_extended_id=False))
    assert rx.recv(0.1).arbitration_id == 0x181 and rx.recv(0.0) is None
    echoed = [own.recv(0.1) for _ in range(3)]
    assert [m.arbitration_id for m in echoed] == [0x701, 0x181, 0x281] and not any(m.is_rx for m in echoed)


def test_a_closed_bus_leaves_the_channel_and_refuses_io(channel):
    a = InprocBus(channel=channel)
    b = InprocBus(channel=channel)
    a.shutdown()
    b.send(can.Message(arbitration_id=0x80, is_extended_id=False))  # nobody listens: delivered to no one
    with pytest.raises(can.CanOperationError):
        a.send(can.Message(arbitration_id=0x80, is_extended_id=False))
    with pytest.raises(can.CanOperationError):
        a.recv(0.0)
    b.shutdown()
    from can.interfaces.virtual import channels

    assert channel not in channels


def test_shutdown_wakes_a_reader_blocked_for_ever(channel):
    """A reader blocked in ``recv(None)`` when its bus shuts down gets ``CanOperationError`` (it used to be
    woken and go back to waiting for ever)."""
    import os

    rx = InprocBus(channel=channel)
    out: list[object] = []

    def reader() -> None:
        try:
            out.append(rx.recv(None))
        except can.CanOperationError as exc:
            out.append(exc)

    t = threading.Thread(target=reader, daemon=True)
    t.start()
    while rx.queue.waiting == 0 and t.is_alive():  # until the reader blocks in the queue's wait
        os.sched_yield()
    rx.shutdown()
    t.join(30.0)  # a failure guard: the reader returns at once
    assert not t.is_alive() and len(out) == 1 and isinstance(out[0], can.CanOperationError), out


def test_a_signal_nobody_waited_for_does_not_end_a_later_wait_early(buses, channel):
    """Every send signals the receive queue's wake-up lock; frames taken by polling leave that signal pending.
    A later blocking receive must still wait its time-out (not return None at once) and take a frame sent
    meanwhile."""
    import time

    rx = buses(InprocBus, channel)
    tx = buses(InprocBus, channel)
    for i in range(3):
        tx.send(can.Message(arbitration_id=0x180 + i, is_extended_id=False))
    got = [rx.recv(0.0) for _ in range(3)]
    assert [m.arbitration_id for m in got if m is not None] == [0x180, 0x181, 0x182]
    t0 = time.monotonic()
    assert rx.recv(0.02) is None
    assert time.monotonic() - t0 >= 0.02  # a lower bound only: the wait was not cut short by the stale signal
    threading.Timer(0.01, lambda: tx.send(can.Message(arbitration_id=0x201, is_extended_id=False))).start()
    got = rx.recv(30.0)
    assert got is not None and got.arbitration_id == 0x201


def test_two_blocked_readers_of_one_bus_both_get_a_frame(buses, channel):
    """Two threads blocked in ``recv`` on the same bus: two frames sent back to back wake both (a reader that
    leaves frames behind passes the wake-up on)."""
    import os

    rx = buses(InprocBus, channel)
    tx = buses(InprocBus, channel)
    got: list[int] = []

    def reader() -> None:
        m = rx.recv(30.0)  # a lost wake-up would hang here for the full 30 s
        got.append(-1 if m is None else m.arbitration_id)

    threads = [threading.Thread(target=reader) for _ in range(2)]
    for t in threads:
        t.start()
    while rx.queue.waiting < 2 and all(t.is_alive() for t in threads):  # until both block in the wait
        os.sched_yield()
    tx.send(can.Message(arbitration_id=0x181, is_extended_id=False))
    tx.send(can.Message(arbitration_id=0x182, is_extended_id=False))
    for t in threads:
        t.join(10.0)  # (a reader left without its wake-up would sit out its 30 s time-out)
    assert not any(t.is_alive() for t in threads) and sorted(got) == [0x181, 0x182]
