"""Shared memory between the loop process and the daemon: preallocated, fixed-size, lock-free.

One :class:`multiprocessing.shared_memory.SharedMemory` block, created by the loop process once its stage
is built (the telemetry width is known then) and attached by the daemon, holds numpy views:

==============  ===========================================  ==================================================
view            shape / type                                 written by
==============  ===========================================  ==================================================
``ctl``         int64[16] counters                           see :data:`CTL` (each index has ONE writer)
``status``      float64[16] + ``fault_text`` uint8[512]      loop (seqlock ``ctl[STATUS_SEQ]``)
``cmd``         float64[CMD_SLOTS, 6] + ``blob`` bytes        daemon (producer) → loop (consumer)
``rep``         float64[REP_SLOTS, 2] + ``rep_text``          loop (producer) → daemon (consumer)
``late`` ...    float64/float64/int32[window] cycle stats     loop (CycleStats over shared buffers)
``tel``         float64[capacity, columns]                   loop → daemon's telemetry writer
==============  ===========================================  ==================================================

Every ring is single-producer/single-consumer: the producer writes the record, then publishes its head
counter; the consumer reads the record, then publishes its tail counter. A full ring refuses (counted) and
never overwrites unread data. Each counter has exactly one writer process, an aligned 8-byte store (atomic on
x86-64 and AArch64); the record-then-counter order relies on the stores becoming visible in program order,
which x86-64 (TSO) guarantees; docs/daemon.md says what a weaker memory model would need. No lock is ever
shared between the processes, so the daemon (its clients, reloads, logs, disk) can never make the loop wait.

The status snapshot uses a sequence lock: the loop makes ``STATUS_SEQ`` odd, writes, makes it even; a reader
retries while it is odd or changed under it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from multiprocessing import resource_tracker, shared_memory
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["CMD_SLOTS", "CTL", "REP_SLOTS", "LoopShm", "ShmLayout"]

#: ``ctl`` indices: (name, writer)
CTL = {
    "CMD_HEAD": 0,  # daemon
    "CMD_TAIL": 1,  # loop
    "REP_HEAD": 2,  # loop
    "REP_TAIL": 3,  # daemon
    "TEL_HEAD": 4,  # loop
    "TEL_TAIL": 5,  # daemon (writer thread)
    "TEL_DROPPED": 6,  # loop
    "TEL_BAD": 7,  # loop
    "STATUS_SEQ": 8,  # loop
    "STOP_REQ": 9,  # daemon: end the loop (the LoopHost stop event, across the process boundary)
    "PHASE": 10,  # loop: 0 built, 1 running, 2 ended
}
CMD_HEAD, CMD_TAIL, REP_HEAD, REP_TAIL = 0, 1, 2, 3
TEL_HEAD, TEL_TAIL, TEL_DROPPED, TEL_BAD, STATUS_SEQ, STOP_REQ, PHASE = 4, 5, 6, 7, 8, 9, 10

CMD_SLOTS = 64  #: queued requests (a full ring answers "busy"; `stop` has its own path, never queued behind)
REP_SLOTS = 64
CMD_WIDTH = 6  #: request id, kind, three numbers (NaN = absent), blob length
REP_TEXT = 2048  #: a reply's JSON text [bytes]; longer replies are cut and marked
BLOB_BYTES = 1 << 18  #: one pickled retune configuration or fault-injection argument set
FAULT_TEXT = 512

#: ``status`` indices
S_STATE, S_T, S_X, S_XREF, S_U, S_CYCLE, S_OVERRUNS, S_FAULTS, S_RUNNING, S_DRIVE, S_LATE_MAX, S_EXEC_MAX = range(12)
S_FAULT_T, S_FAULT_CYCLE, S_HAS_FAULT = 12, 13, 14
STATUS_WIDTH = 16


@dataclass(frozen=True)
class ShmLayout:
    """Sizes of the block (``columns``: telemetry width; ``tel_rows`` a power of two; ``window`` stats)."""

    columns: int
    tel_rows: int
    window: int

    def parts(self) -> list[tuple[str, Any, tuple[int, ...]]]:
        return [
            ("ctl", np.int64, (16,)),
            ("status", np.float64, (STATUS_WIDTH,)),
            ("cmd", np.float64, (CMD_SLOTS, CMD_WIDTH)),
            ("rep", np.float64, (REP_SLOTS, 2)),
            ("late", np.float64, (self.window,)),
            ("exec", np.float64, (self.window,)),
            ("tel", np.float64, (self.tel_rows, self.columns)),
            ("skip", np.int32, (self.window,)),
            ("fault_text", np.uint8, (FAULT_TEXT,)),
            ("rep_text", np.uint8, (REP_SLOTS, REP_TEXT)),
            ("blob", np.uint8, (BLOB_BYTES,)),
        ]

    def size(self) -> int:
        n = 0
        for _, dt, shape in self.parts():
            n += int(np.dtype(dt).itemsize * int(np.prod(shape)))
            n = (n + 63) & ~63
        return n


class LoopShm:
    """The block and its numpy views (see the module docstring). :meth:`create` in the loop process,
    :meth:`attach` in the daemon; :meth:`close` unmaps, :meth:`unlink` removes the name (idempotent)."""

    def __init__(self, shm: shared_memory.SharedMemory, layout: ShmLayout, owner: bool) -> None:
        self.shm = shm
        self.layout = layout
        self.owner = owner
        self.name = shm.name
        views: dict[str, npt.NDArray[Any]] = {}
        off = 0
        for name, dt, shape in layout.parts():
            count = int(np.prod(shape))
            views[name] = np.ndarray(shape, dtype=dt, buffer=shm.buf, offset=off)
            off += int(np.dtype(dt).itemsize * count)
            off = (off + 63) & ~63
        self.ctl: npt.NDArray[np.int64] = views["ctl"]
        self.status: npt.NDArray[np.float64] = views["status"]
        self.cmd: npt.NDArray[np.float64] = views["cmd"]
        self.rep: npt.NDArray[np.float64] = views["rep"]
        self.late: npt.NDArray[np.float64] = views["late"]
        self.exec: npt.NDArray[np.float64] = views["exec"]
        self.skip: npt.NDArray[np.int32] = views["skip"]
        self.tel: npt.NDArray[np.float64] = views["tel"]
        self.fault_text: npt.NDArray[np.uint8] = views["fault_text"]
        self.rep_text: npt.NDArray[np.uint8] = views["rep_text"]
        self.blob: npt.NDArray[np.uint8] = views["blob"]
        self._closed = False

    @classmethod
    def create(cls, layout: ShmLayout) -> LoopShm:
        """A new block (loop process). Its name is unlinked as soon as the daemon has attached
        (:meth:`unlink`), so no name outlives the pair of processes whatever way they end."""
        shm = shared_memory.SharedMemory(create=True, size=layout.size())
        _untrack(shm)
        out = cls(shm, layout, owner=True)
        out.ctl[:] = 0
        out.status[:] = np.nan
        out.status[S_STATE] = 0
        return out

    @classmethod
    def attach(cls, name: str, layout: ShmLayout) -> LoopShm:
        shm = shared_memory.SharedMemory(name=name, create=False)
        _untrack(shm)
        return cls(shm, layout, owner=False)

    # ------------------------------------------------------------------ text slots
    @staticmethod
    def put_text(dest: npt.NDArray[np.uint8], text: str) -> int:
        """UTF-8 ``text`` into ``dest`` (cut to fit, NUL-terminated when shorter); returns the bytes stored."""
        raw = text.encode("utf-8", "replace")[: dest.size - 1]
        n = len(raw)
        dest[:n] = np.frombuffer(raw, dtype=np.uint8)
        dest[n] = 0
        return n

    @staticmethod
    def get_text(src: npt.NDArray[np.uint8]) -> str:
        raw = src.tobytes()
        end = raw.find(b"\0")
        return raw[: end if end >= 0 else len(raw)].decode("utf-8", "replace")

    def put_reply(self, slot: int, req_id: int, ok: bool, payload: dict[str, Any]) -> None:
        """Reply record (loop side): id, ok, and the reply (or error) as JSON text, bounded to the slot."""
        text = json.dumps(payload, allow_nan=True, default=str, separators=(",", ":"))
        if len(text) >= REP_TEXT:
            ok = False
            text = json.dumps({"error": f"reply: {len(text)} bytes, longer than the {REP_TEXT}-byte slot",
                               "field": "reply"})
        self.rep[slot, 0] = req_id
        self.rep[slot, 1] = 1.0 if ok else 0.0
        self.put_text(self.rep_text[slot], text)

    def close(self) -> None:
        """Mark the block closed. It is deliberately never unmapped while this process runs: the numpy views
        (telemetry ring, statistics, status) are shared by several objects and threads, and touching an
        unmapped page is a segmentation fault. The mapping goes with the process; the name is unlinked
        early (:meth:`unlink`), so nothing outlives the processes."""
        self._closed = True

    def unlink(self) -> None:
        """Remove the block's name (idempotent): the mapping stays valid in both processes."""
        try:  # shm_unlink itself: SharedMemory.unlink would also tell a tracker that never knew the name
            shared_memory._posixshmem.shm_unlink(self.shm._name)  # type: ignore[attr-defined]
        except FileNotFoundError:
            pass


def _untrack(shm: shared_memory.SharedMemory) -> None:
    """Python < 3.13 registers every block with its resource tracker, which would unlink it (and warn) when
    *either* process exits: the pair manages the name itself (see :meth:`LoopShm.create`)."""
    try:
        resource_tracker.unregister(shm._name, "shared_memory")  # type: ignore[attr-defined]
    except Exception:  # noqa: BLE001 - no tracker running: nothing registered
        pass
