"""Hand-written ``sd_notify`` client (no dependency; docs/platform.md section 5).

systemd passes ``NOTIFY_SOCKET`` (a filesystem path, or ``@name`` for the Linux abstract namespace) to a
``Type=notify`` service; the service sends newline-separated ``KEY=VALUE`` assignments as one AF_UNIX
datagram each: ``READY=1``, ``STATUS=...``, ``WATCHDOG=1``, ``WATCHDOG=trigger``, ``STOPPING=1``,
``RELOADING=1``, ``MAINPID=N``.

The watchdog interval comes from ``WATCHDOG_USEC`` (microseconds), valid only if ``WATCHDOG_PID`` is absent
or equals our PID. The service must ping at least every ``WATCHDOG_USEC``; stagectl pings at half of it.

Every method **never blocks** (non-blocking socket: if the receiver's queue is full the datagram is dropped
and counted in ``errors``), **never raises**, and is a no-op (returning False) when ``NOTIFY_SOCKET`` is not set, so the
same code runs from a shell and under systemd. Not real-time critical, but cheap (one ``sendto``).
"""

from __future__ import annotations

import os
import socket
from collections.abc import Mapping


def watchdog_interval_s(environ: Mapping[str, str] | None = None, pid: int | None = None) -> float | None:
    """The systemd watchdog interval [s] from ``WATCHDOG_USEC``/``WATCHDOG_PID``, or None if not enabled.

    ``WATCHDOG_PID`` (when present) must equal ``pid`` (default: our PID); a malformed or non-positive
    ``WATCHDOG_USEC`` means "no watchdog".
    """
    env = os.environ if environ is None else environ
    usec = env.get("WATCHDOG_USEC")
    if not usec:
        return None
    wpid = env.get("WATCHDOG_PID")
    if wpid:
        try:
            if int(wpid) != (os.getpid() if pid is None else pid):
                return None
        except ValueError:
            return None
    try:
        value = int(usec)
    except ValueError:
        return None
    if value <= 0:
        return None
    return value / 1e6


class SdNotifier:
    """Sends ``sd_notify`` datagrams to ``$NOTIFY_SOCKET``.

    Parameters
    ----------
    address : str, optional
        Socket address; default: ``$NOTIFY_SOCKET`` read at construction. ``@name`` is the abstract
        namespace (sent as a leading NUL byte).

    Attributes
    ----------
    enabled : bool
        True if a notify socket was given.
    watchdog_s : float | None
        systemd watchdog interval [s] (``WATCHDOG_USEC``) or None.
    errors : int
        Number of failed sends (never raised; the last one is in ``last_error``).
    """

    def __init__(self, address: str | None = None, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        addr = env.get("NOTIFY_SOCKET", "") if address is None else address
        self._addr: str | bytes | None
        if not addr:
            self._addr = None
        elif addr.startswith("@"):
            self._addr = b"\0" + addr[1:].encode()
        elif addr.startswith("/"):
            self._addr = addr
        else:  # systemd only uses absolute paths or '@'; anything else is ignored like libsystemd does
            self._addr = None
        self.watchdog_s = watchdog_interval_s(env)
        self.errors = 0
        self.last_error = ""
        self._sock: socket.socket | None = None

    @property
    def enabled(self) -> bool:
        return self._addr is not None

    def notify(self, *assignments: str) -> bool:
        """Send ``KEY=VALUE`` lines as one datagram. Returns True if sent; never raises."""
        if self._addr is None:
            return False
        try:
            # one assignment per line; a newline inside a value would start a bogus assignment
            payload = "\n".join(a.replace("\n", " ") for a in assignments).encode("utf-8", "replace")
            if self._sock is None:
                # non-blocking: a receiver that does not read (its queue is full) must never stall the
                # supervisor; the datagram is dropped and counted instead
                self._sock = socket.socket(socket.AF_UNIX,
                                           socket.SOCK_DGRAM | socket.SOCK_CLOEXEC | socket.SOCK_NONBLOCK)
            self._sock.sendto(payload, self._addr)
            return True
        except Exception as exc:  # noqa: BLE001 - must never raise (a missing systemd is not our fault)
            self.errors += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            return False

    def ready(self, status: str | None = None) -> bool:
        """``READY=1`` (+ ``STATUS=``, ``MAINPID=``): start-up finished, the service is operational."""
        msgs = ["READY=1", f"MAINPID={os.getpid()}"]
        if status:
            msgs.append(f"STATUS={status}")
        return self.notify(*msgs)

    def status(self, text: str) -> bool:
        """``STATUS=text`` (shown by ``systemctl status``)."""
        return self.notify(f"STATUS={text}")

    def watchdog(self) -> bool:
        """``WATCHDOG=1``: the service is healthy (send only after a real health check)."""
        return self.notify("WATCHDOG=1")

    def watchdog_trigger(self) -> bool:
        """``WATCHDOG=trigger``: ask systemd to act as if the watchdog expired (internal fatal condition)."""
        return self.notify("WATCHDOG=trigger")

    def reloading(self) -> bool:
        return self.notify("RELOADING=1")

    def stopping(self, status: str | None = None) -> bool:
        """``STOPPING=1``: shutdown has begun."""
        msgs = ["STOPPING=1"]
        if status:
            msgs.append(f"STATUS={status}")
        return self.notify(*msgs)

    def close(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            except OSError:
                pass
            self._sock = None
