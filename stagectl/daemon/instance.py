"""One daemon per runtime directory: an exclusive ``flock`` taken before anything else is touched.

A second ``stagectl daemon`` on the same runtime directory (or state directory) must not delete the first one's
control socket, rewrite its run marker or open the devices the first one drives. :class:`InstanceLock` takes
``flock(LOCK_EX | LOCK_NB)`` on ``<dir>/stagectl.lock`` for each directory, as the very first step of start-up
(before the configuration is even read); the loser exits 1 naming the holder's pid and touches nothing.

The lock is tied to the open file description, so it is released by the kernel when the process dies
however it dies (SIGKILL included): no stale lock to clean up. The file itself is never deleted (deleting a
lock file races with a third process opening it); it holds the holder's pid as text, for the message. The
loop process inherits the locked descriptor: when the daemon in the file is dead but the lock is still held,
its loop process is still stopping the drive, and a new daemon (systemd's restart) waits for it, bounded.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import time
from pathlib import Path

from stagectl.errors import StageError

__all__ = ["InstanceLock", "InstanceLockedError"]

log = logging.getLogger("stagectl.daemon")

LOCK_NAME = "stagectl.lock"


class InstanceLockedError(StageError):
    """Another daemon holds the lock on this runtime/state directory."""


class InstanceLock:
    """Exclusive locks on ``<dir>/stagectl.lock`` for every distinct directory given (see the module docstring)."""

    def __init__(self, *directories: Path | None, orphan_wait_s: float = 10.0) -> None:
        self.orphan_wait_s = orphan_wait_s
        seen: dict[Path, None] = {}
        for d in directories:
            if d is not None:
                seen.setdefault(Path(os.path.abspath(d)), None)
        self.paths = tuple(d / LOCK_NAME for d in seen)
        self._fds: list[int] = []

    @property
    def held(self) -> bool:
        return bool(self._fds) and len(self._fds) == len(self.paths)

    def acquire(self) -> None:
        """Take every lock or none. Raises InstanceLockedError (another daemon runs) or OSError (cannot create)."""
        try:
            for path in self.paths:
                path.parent.mkdir(parents=True, mode=0o750, exist_ok=True)
                fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o640)
                try:
                    _lock(fd, path, self.orphan_wait_s)
                except OSError as exc:
                    holder = _read_pid(fd)
                    os.close(fd)
                    if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                        raise InstanceLockedError(
                            f"another stagectl daemon{f' (pid {holder})' if holder else ''} holds {path}; "
                            f"not starting (nothing was touched: socket, run marker and devices are its own)"
                        ) from None
                    raise
                self._fds.append(fd)
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except BaseException:
            self.release()
            raise

    def release(self) -> None:
        """Drop the locks (idempotent). The files stay."""
        while self._fds:
            fd = self._fds.pop()
            try:
                os.close(fd)
            except OSError:
                pass


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _lock(fd: int, path: Path, orphan_wait_s: float) -> None:
    """``flock(LOCK_EX|LOCK_NB)``; if it is held but the pid written in the file is dead, the holder is that
    daemon's loop process still stopping the drive (it inherited the lock): wait for it, at most
    ``orphan_wait_s``. A live holder is refused at once. Raises OSError (EWOULDBLOCK) when still held."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return
    except OSError as exc:
        holder = _read_pid(fd)
        if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN) or holder is None or _alive(holder):
            raise
    log.warning("%s is held by the loop process of daemon %d, which has ended: waiting up to %.0f s for it to "
                "stop the drive", path, holder, orphan_wait_s)
    end = time.monotonic() + orphan_wait_s
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN) or time.monotonic() >= end:
                raise
        time.sleep(0.05)


def lock_pid(path: str | Path) -> int | None:
    """The pid the lock file ``path`` names (None: no file, unreadable, or no pid in it). Reads only: it takes no
    lock, so a client may look while a daemon starts."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        return _read_pid(fd)
    finally:
        os.close(fd)


def _read_pid(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        return int(text) if text.isdigit() else None
    except OSError:
        return None
