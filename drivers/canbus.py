"""CAN bus helpers shared by the CANopen drivers (and the virtual devices).

* :func:`can_key_problems` checks the ``can:`` keys against what the chosen python-can interface accepts
  (:func:`bus_keys`: its bus class's ``__init__`` parameters, the keys its module reads from ``**kwargs``,
  python-can's common keys), with a did-you-mean hint. The configuration loader runs it once; opening the
  bus does not repeat it.
* :func:`open_bus` opens a :class:`can.BusABC` from the YAML ``can:`` mapping, which is passed to
  ``can.Bus(**mapping)`` unchanged (so ``socketcan``, ``pcan``, ``kvaser``, ``virtual``, ``socketcand`` all
  work), except that ``tcp_tune`` is forced on for ``socketcand`` (docs/platform.md §1.2: without it Nagle
  plus delayed ACK stall two back-to-back frames for ~44 ms), and that ``virtual`` with only the keys
  :class:`~stagectl.drivers.inproc.InprocBus` implements opens that lighter bus on the same python-can
  channel (it interoperates with stock ``virtual`` buses there). Vendor errors become
  :class:`~stagectl.errors.DriverInitError`.
  For ``socketcand`` the server is probed first (:func:`probe_socketcand`): python-can's client retries a
  refused connection for 10 s, warning on each try, where a wrong port should be one line at once.
* :func:`quiet_can_loggers` silences python-can's socketcand client, which logs a WARNING on every TCP
  read that splits a frame.
* :func:`close_bus` shuts a bus down and never raises (used from ``close()`` paths).
* :data:`OPEN_BUSES` tracks the buses opened here so tests can fail on a leaked bus.
* :class:`CanopenNode` is the CANopen plumbing shared by the CiA 402 and CiA 406 drivers: bus, canopen
  ``Network`` with one ``RemoteNode``, and the Notifier that runs only while SDO configuration needs it.

Error frames: python-can reports controller errors as ``Message(is_error_frame=True)`` whose
``arbitration_id`` carries the SocketCAN error class (``CAN_ERR_*``); :func:`error_frame_is_bus_off`
tells bus-off (``CAN_ERR_BUSOFF = 0x40``) from other bus errors.
"""

from __future__ import annotations

import difflib
import functools
import importlib
import inspect
import logging
import re
import socket
import threading
import time
import typing
import weakref
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from stagectl.drivers.inproc import INPROC_KEYS, InprocBus
from stagectl.errors import ConfigError, DriverError, DriverInitError, short

#: SocketCAN error class bits (linux/can/error.h) carried in an error frame's arbitration id
CAN_ERR_BUSOFF = 0x00000040
CAN_ERR_RESTARTED = 0x00000100

#: every bus opened by :func:`open_bus` that has not been closed through :func:`close_bus`
OPEN_BUSES: weakref.WeakSet[can.BusABC] = weakref.WeakSet()
_open_lock = threading.Lock()
_open_names: dict[int, str] = {}


def quiet_can_loggers() -> None:
    """Silence per-read warnings of the socketcand client (it warns on every split TCP read)."""
    logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)
    logging.getLogger("can.interfaces.socketcand").setLevel(logging.ERROR)


#: keys ``can.Bus`` itself or python-can's configuration handling (``can.util``) accepts for every interface
COMMON_BUS_KEYS = frozenset({
    "interface", "channel", "config_context", "ignore_config", "can_filters", "receive_own_messages",
    "bitrate", "data_bitrate", "fd", "timing", "state",
})


def _timing_keys() -> frozenset[str]:
    """Bit-timing keys python-can turns into a ``BitTiming`` / ``BitTimingFd`` (``can.util._dict2timing``)."""
    from can import typechecking

    keys: set[str] = set()
    for td in (typechecking.BitTimingDict, typechecking.BitTimingFdDict):
        keys.update(typing.get_type_hints(td))
    return frozenset(keys)


#: how a bus module reads an option its ``__init__`` takes through ``**kwargs``: ``kwargs.get("x"``,
#: ``kwargs.pop("x"``, ``kwargs.setdefault("x"``, ``kwargs["x"]`` and ``"x" in kwargs`` / ``"x" not in kwargs``
_KWARGS_READ = re.compile(
    r"""\bkwargs\s*(?:\.\s*(?:get|pop|setdefault)\s*\(\s*|\[\s*)(?P<q1>["'])(?P<k1>\w+)(?P=q1)"""
    r"""|(?P<q2>["'])(?P<k2>\w+)(?P=q2)\s+(?:not\s+)?in\s+kwargs\b""")

#: similarity (difflib ratio) from which an unknown key of a bus that forwards ``**kwargs`` counts as a typo of
#: an accepted key (``bitrat`` -> ``bitrate`` 0.92, ``hots`` -> ``host`` 0.75) and is refused
NEAR_MISS = 0.75


@contextmanager
def _quiet_can_logging() -> Iterator[None]:
    """Mute python-can's loggers (``can`` and its children) for the duration: importing a vendor interface
    module logs a WARNING when the vendor library is missing (``Kvaser canlib is unavailable.``), which is noise
    in ``check-config`` output (the bus is not opened there). Levels are restored afterwards."""
    names = ["can", *(n for n in logging.root.manager.loggerDict if n.startswith("can."))]
    loggers = [logging.getLogger(n) for n in names]
    saved = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        for lg, level in zip(loggers, saved):
            lg.setLevel(level)


@dataclass(frozen=True)
class BusKeys:
    """The ``can:`` keys one python-can interface accepts (:func:`bus_keys`)."""

    accepted: frozenset[str]
    #: False when the bus class's ``__init__`` takes ``**kwargs``: python-can forwards keys it does not know,
    #: so only a near-miss of an accepted key (a likely typo) is refused
    strict: bool


@functools.lru_cache(maxsize=None)
def bus_keys(interface: str) -> BusKeys | None:
    """The keys the python-can ``interface`` accepts: the named parameters of its bus class's ``__init__``
    (found through ``can.interfaces.BACKENDS``), the common keys and the bit-timing keys; for a class whose
    ``__init__`` takes ``**kwargs``, also every key its module reads from ``kwargs`` (``kwargs.get("x")`` and
    the like, e.g. kvaser's ``single_handle``, slcan's ``btr``). None when the interface is unknown or its module
    cannot be imported here (then nothing is checked)."""
    from can.interfaces import BACKENDS

    where = BACKENDS.get(interface)
    if where is None:
        return None
    module_name, cls_name = where
    try:
        with _quiet_can_logging():
            module = importlib.import_module(module_name)
        cls = getattr(module, cls_name)
        params = list(inspect.signature(cls.__init__).parameters.values())
    except Exception:  # noqa: BLE001 - vendor libraries missing on this machine: the bus would not open either
        return None
    named = {p.name for p in params if p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL) and p.name != "self"}
    forwards = any(p.kind is p.VAR_KEYWORD for p in params)
    if forwards:
        try:
            source = inspect.getsource(inspect.getmodule(cls) or module)
        except (OSError, TypeError):  # no source installed: the named parameters only
            source = ""
        for m in _KWARGS_READ.finditer(source):
            named.add(m.group("k1") or m.group("k2"))
    return BusKeys(frozenset(named) | COMMON_BUS_KEYS | _timing_keys(), strict=not forwards)


def accepted_bus_keys(interface: str) -> frozenset[str] | None:
    """The ``can:`` keys the python-can ``interface`` accepts (:func:`bus_keys`); None when unknown."""
    keys = bus_keys(interface)
    return keys.accepted if keys is not None else None


def can_key_problems(mapping: Mapping[str, Any], *, path: str = "can") -> list[str]:
    """Unknown keys (and an unknown ``interface``) of a ``can:`` mapping, one line each with a did-you-mean,
    e.g. ``io.drive.can.bitrat: unknown key for interface socketcan (did you mean bitrate?)``.

    For an interface whose bus class takes ``**kwargs`` (python-can forwards unknown keys) a key it does not
    name is refused only when it is a near-miss (:data:`NEAR_MISS`) of an accepted key."""
    from can.interfaces import VALID_INTERFACES

    iface = mapping.get("interface")
    if not isinstance(iface, str) or not iface:
        return []
    if iface not in VALID_INTERFACES:
        close = difflib.get_close_matches(iface, sorted(VALID_INTERFACES), n=1, cutoff=0.6)
        hint = f"did you mean {close[0]}?" if close else f"known: {', '.join(sorted(VALID_INTERFACES))}"
        return [f"{path}.interface: unknown python-can interface {short(iface)} ({hint})"]
    keys = bus_keys(iface)
    if keys is None:
        return []
    problems = []
    for key in mapping:
        if isinstance(key, str) and key in keys.accepted:
            continue
        if not isinstance(key, str) or keys.strict:
            close = difflib.get_close_matches(str(key), sorted(keys.accepted), n=1, cutoff=0.6)
            hint = f" (did you mean {close[0]}?)" if close else ""
        else:
            close = difflib.get_close_matches(key, sorted(keys.accepted), n=1, cutoff=NEAR_MISS)
            if not close:
                continue  # forwarded by python-can to the interface
            hint = f" (did you mean {close[0]}?)"
        problems.append(f"{path}.{key}: unknown key for interface {iface}{hint}")
    return problems


def bus_kwargs(mapping: Mapping[str, Any], *, path: str = "can") -> dict[str, Any]:
    """The keyword arguments for ``can.Bus`` from the ``can:`` mapping (its keys were checked against the
    interface by the configuration loader, :func:`can_key_problems`; they are passed on unchanged).

    Raises
    ------
    ConfigError
        If ``interface`` or ``channel`` is missing, or a socketcand mapping lacks ``host``/``port``.
    """
    kw = dict(mapping)
    problems: list[str] = []
    iface = kw.get("interface")
    if not isinstance(iface, str) or not iface:
        problems.append(f"{path}.interface: required (e.g. socketcan, pcan, virtual, socketcand)")
    if "channel" not in kw:
        problems.append(f"{path}.channel: required (e.g. can0, or a virtual channel name)")
    if iface == "socketcand":
        for key in ("host", "port"):
            if key not in kw:
                problems.append(f"{path}.{key}: required for interface socketcand")
        kw["tcp_tune"] = True  # mandatory: Nagle stalls otherwise (docs/platform.md §1.2)
        host = kw.get("host")
        if "host" in kw and (not isinstance(host, str) or not host.strip()):
            problems.append(f"{path}.host: must be a host name or address (got {short(host)})")
    # values python-can would only refuse at open time (after a 10 s connect attempt for a socketcand port),
    # or not at all (a bitrate typed as text reaches the adapter's driver)
    port = kw.get("port")
    if "port" in kw and (isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535):
        problems.append(f"{path}.port: must be a TCP port, an integer 1..65535 (got {short(port)})")
    rate = kw.get("bitrate")
    if "bitrate" in kw and (isinstance(rate, bool) or not isinstance(rate, int) or rate <= 0):
        problems.append(f"{path}.bitrate: must be a positive integer in bit/s (got {short(rate)})")
    if problems:
        raise ConfigError(problems)
    return kw


def open_bus(mapping: Mapping[str, Any], *, path: str = "can") -> can.BusABC:
    """Open ``can.Bus(**mapping)``; python-can / OS errors become :class:`DriverInitError`.

    Raises
    ------
    ConfigError
        Bad mapping (see :func:`bus_kwargs`).
    DriverInitError
        The interface could not be opened (unknown interface, no such device, connection refused).
    """
    kw = bus_kwargs(mapping, path=path)
    if kw.get("interface") == "socketcand":
        quiet_can_loggers()
        probe_socketcand(str(kw["host"]), int(kw["port"]), path=path)
    try:
        bus: can.BusABC
        if kw.get("interface") == "virtual" and kw.keys() <= INPROC_KEYS:
            bus = InprocBus(**kw)  # the same channels as python-can's virtual bus, less work per frame
        else:
            bus = can.Bus(**kw)
    except (can.CanError, OSError, ValueError, TypeError, ImportError, TimeoutError) as exc:
        where = ", ".join(f"{k}={v!r}" for k, v in kw.items() if k in ("interface", "channel", "host", "port"))
        raise DriverInitError(f"{path}: cannot open CAN bus ({where}): {exc}") from exc
    with _open_lock:
        OPEN_BUSES.add(bus)
        _open_names[id(bus)] = str(kw.get("channel"))
    return bus


#: how long :func:`probe_socketcand` waits for a socketcand server to accept [s] (a server just started)
SOCKETCAND_PROBE_S = 2.0


def probe_socketcand(host: str, port: int, *, path: str = "can", wait_s: float | None = None) -> None:
    """Connect to ``host:port`` and close again, retrying a refused connection for up to ``wait_s`` [s].

    Raises :class:`DriverInitError` (one line: host, port, the OS's reason) when nothing accepts in that time
    (``wait_s`` None: :data:`SOCKETCAND_PROBE_S`).
    python-can's socketcand client would spin on the refused port for 10 s, logging each attempt.
    """
    wait_s = SOCKETCAND_PROBE_S if wait_s is None else wait_s
    deadline = time.monotonic() + wait_s
    while True:
        try:
            with socket.create_connection((host, port), timeout=max(wait_s, 0.1)) as sock:
                _expect_greeting(sock, host, port, path)
                return
        except DriverInitError:
            raise
        except socket.gaierror as exc:  # the name does not resolve: nothing to connect to, not a refusal
            raise DriverInitError(f"{path}: cannot open CAN bus (interface='socketcand', host={host!r}, "
                                  f"port={port}): host name not found ({exc.strerror or exc}); check the host "
                                  "(an address such as 127.0.0.1, or a name this machine resolves)") from exc
        except OSError as exc:
            if time.monotonic() >= deadline or not isinstance(exc, ConnectionRefusedError):
                raise DriverInitError(f"{path}: cannot open CAN bus (interface='socketcand', host={host!r}, "
                                      f"port={port}): nothing accepts a connection there ({exc.strerror or exc}); "
                                      f"is the socketcand server (or `stagectl sim-plant`) running on that port?"
                                      ) from exc
            time.sleep(0.05)


#: how long :func:`probe_socketcand` waits for the server's ``< hi >`` once connected [s]
SOCKETCAND_GREETING_S = 5.0


def _expect_greeting(sock: socket.socket, host: str, port: int, path: str) -> None:
    """Read the ``< hi >`` a socketcand server sends on every new connection. python-can's client waits for it
    without a time-out: a port held by something else that never speaks (or a hung server) blocked the start
    for ever. One line instead, naming what was (not) said."""
    sock.settimeout(SOCKETCAND_GREETING_S)
    got = b""
    deadline = time.monotonic() + SOCKETCAND_GREETING_S
    where = f"{path}: socketcand at {host}:{port}"
    while b">" not in got and len(got) < 256:
        try:
            chunk = sock.recv(256 - len(got))
        except TimeoutError:
            chunk = None
        except OSError as exc:
            raise DriverInitError(f"{where}: connection lost before its greeting ({exc.strerror or exc})") from exc
        if chunk == b"":
            raise DriverInitError(f"{where}: closed the connection without its greeting '< hi >'")
        if chunk is None or time.monotonic() >= deadline:
            raise DriverInitError(f"{where}: no greeting '< hi >' within {SOCKETCAND_GREETING_S:g} s; is that "
                                  "port a socketcand server (or `stagectl sim-plant`), and is it running?")
        got += chunk
    if got.split(b">", 1)[0].split() != [b"<", b"hi"]:
        raise DriverInitError(f"{where}: not a socketcand server (it said {short(got.decode('latin-1'))} instead of "
                              "'< hi >')")


def close_bus(bus: can.BusABC | None) -> None:
    """Shut ``bus`` down; never raises (logs instead), safe to call twice."""
    if bus is None:
        return
    with _open_lock:
        OPEN_BUSES.discard(bus)
        _open_names.pop(id(bus), None)
    try:
        bus.shutdown()
    except Exception:  # noqa: BLE001 - close paths must not raise
        logging.getLogger(__name__).debug("bus shutdown failed", exc_info=True)


def open_bus_names() -> list[str]:
    """Channels of the buses opened by :func:`open_bus` and not yet closed (for leak checks)."""
    with _open_lock:
        return [_open_names.get(id(b), "?") for b in list(OPEN_BUSES)]


def error_frame_is_bus_off(msg: can.Message) -> bool:
    """True if the error frame reports bus-off (SocketCAN ``CAN_ERR_BUSOFF`` class bit)."""
    return bool(msg.arbitration_id & CAN_ERR_BUSOFF)


def link_closed(bus: can.BusABC) -> bool:
    """True when a socketcand bus's TCP connection was closed by the server (EOF pending on the socket).

    python-can's socketcand client then returns from ``recv`` at once, forever: a loop that waits for a frame
    would spin. Other interfaces: always False. Costs one non-blocking ``recv(MSG_PEEK)``; call it only after a
    missed frame.
    """
    import socket

    sock = getattr(bus, "_SocketCanDaemonBus__socket", None)
    if not isinstance(sock, socket.socket):
        return False
    try:
        return sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
    except (BlockingIOError, InterruptedError):
        return False
    except OSError:
        return True


@contextmanager
def pumping(pump: Callable[[], object] | None, name: str) -> Iterator[None]:
    """Lock-step helper: while the caller blocks (e.g. on SDO), run ``pump()`` from a helper thread.

    No-op when ``pump`` is None (real devices or a simulation running in its own thread).
    """
    if pump is None:
        yield
        return
    done = threading.Event()
    errors: list[BaseException] = []

    def run() -> None:
        while not done.is_set():
            try:
                pump()
            except BaseException as exc:  # noqa: BLE001 - re-raised in the caller
                errors.append(exc)
                return
            done.wait(0.0002)

    t = threading.Thread(target=run, name=f"{name}-sdo-pump", daemon=True)
    t.start()
    try:
        yield
    finally:
        done.set()
        t.join(2.0)
    if errors:
        raise DriverError(f"{name}: simulated peer failed while configuring: {errors[0]}") from errors[0]


def lockstep_sdo_reader(sdo: Any, bus: can.BusABC, listeners: list[can.Listener],
                        pump: Callable[[], object]) -> Callable[[], bytes]:
    """Lock-step replacement for canopen's ``SdoClient.read_response`` (installed per client instance).

    canopen waits for an SDO answer on a queue that a Notifier thread fills, for ``RESPONSE_TIMEOUT`` of wall
    time; with a simulated peer served by ``pump()`` from yet another thread, a loaded machine that left those
    threads unscheduled for that long aborted the transfer (0x05040000) although the peer would have answered.
    Here the waiting thread does it all in order: ``pump()`` (the peer handles the request and answers), then
    every frame on the bus goes to canopen's listeners, as the Notifier would pass it. An in-process peer has
    answered after the first round, so the outcome never depends on the wall clock. Only when a round brought
    no answer (a peer in another process, or none) does it wait for frames, pumping again, for
    ``RESPONSE_TIMEOUT`` as canopen would.
    """
    from canopen.sdo.client import SdoClient
    from canopen.sdo.exceptions import SdoCommunicationError

    canopen_read: Callable[[Any], bytes] = SdoClient.read_response

    def dispatch(msg: can.Message | None) -> None:
        while msg is not None:
            for listener in listeners:
                listener(msg)
            msg = bus.recv(0.0)

    def read_response() -> bytes:
        deadline: float | None = None
        while True:
            pump()
            dispatch(bus.recv(0.0))
            if not sdo.responses.empty():
                return canopen_read(sdo)  # returns at once (raises SdoAbortedError on an abort)
            now = time.monotonic()
            if deadline is None:
                deadline = now + sdo.RESPONSE_TIMEOUT
            elif now >= deadline:
                raise SdoCommunicationError("No SDO response received")
            dispatch(bus.recv(min(0.002, deadline - now)))

    return read_response


class CanopenNode:
    """Mixin for drivers of one CANopen node: bus + canopen ``Network`` + ``RemoteNode`` (SDO), and a
    ``can.Notifier`` that runs only while canopen has to receive (configuration over SDO); during cyclic
    operation it is stopped and the loop thread reads the bus itself ("pump mode", docs/platform.md §0.2)."""

    name: str
    _bus: can.BusABC | None = None
    _network: Any = None
    _node: Any = None
    _notifier: can.Notifier | None = None

    def _open_canopen(self, can_cfg: Mapping[str, Any], path: str, node_id: int, eds: Path,
                      sdo_timeout_s: float) -> None:
        """Open the bus and the node, start the Notifier; errors become :class:`DriverInitError`."""
        import canopen

        self._bus = open_bus(can_cfg, path=path)
        try:
            self._network = canopen.Network(self._bus)
            self._node = canopen.RemoteNode(node_id, str(eds))
            self._network.add_node(self._node)
            self._node.sdo.RESPONSE_TIMEOUT = sdo_timeout_s
            self._start_notifier()
        except Exception as exc:
            self._teardown()
            if isinstance(exc, (OSError, ValueError, KeyError)):
                raise DriverInitError(f"{self.name}: cannot load EDS {eds}: {exc}") from exc
            raise DriverInitError(f"{self.name}: cannot start CANopen network: {exc}") from exc

    def _start_notifier(self) -> None:
        """Let canopen receive: a Notifier thread, or in lock-step (a ``pump`` was set before ``open``) the
        SDO client's waiting thread itself (:func:`lockstep_sdo_reader`, no wall-clock race)."""
        if self._notifier is None and self._bus is not None and self._network is not None:
            pump: Callable[[], object] | None = getattr(self, "_pump", None)
            if pump is not None:
                if "read_response" not in vars(self._node.sdo):
                    self._node.sdo.read_response = lockstep_sdo_reader(self._node.sdo, self._bus,
                                                                       self._network.listeners, pump)
                return
            self._notifier = can.Notifier(self._bus, self._network.listeners, 0.05)

    @property
    def _sdo_lockstep(self) -> bool:
        """True while the SDO client serves the simulated peer itself (then no helper thread may pump)."""
        return self._node is not None and "read_response" in vars(self._node.sdo)

    def _stop_notifier(self) -> None:
        """Stop the Notifier and wait for its thread to end (at most ~0.5 s).

        A Ctrl-C (KeyboardInterrupt) that arrives while ``Notifier.stop`` joins the thread is re-raised only
        after the thread has ended: raised at once, it left the thread reading a bus that the caller's
        clean-up then closed, and python-can printed the thread's exception with a traceback over the one
        "interrupted" line (or the interpreter's exit cut it off half way)."""
        if self._node is not None:
            vars(self._node.sdo).pop("read_response", None)  # lock-step reader: canopen's own again
        notifier, self._notifier = self._notifier, None
        if notifier is None:
            return
        try:
            notifier.stop(0.5)
        except Exception:  # noqa: BLE001 - close paths must not raise
            logging.getLogger(__name__).debug("notifier stop failed", exc_info=True)
        except BaseException:  # KeyboardInterrupt / SystemExit half way through the join: finish it, then raise
            for _ in range(3):  # a further Ctrl-C during this join: join again (the first one is raised anyway)
                try:
                    notifier.stop(0.5)  # idempotent: the thread is already told to stop; join and unregister
                    break
                except KeyboardInterrupt:
                    continue
                except Exception:  # noqa: BLE001 - close paths must not raise
                    break
            raise

    def _teardown(self) -> None:
        """Stop the Notifier and close the bus; never raises (but passes a Ctrl-C on, bus closed)."""
        try:
            self._stop_notifier()
        finally:
            close_bus(self._bus)
            self._bus = None
            self._network = None
            self._node = None
