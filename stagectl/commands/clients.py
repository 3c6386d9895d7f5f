"""Operator commands that talk to a running daemon over its control socket (JSON lines).

::

    stagectl status [--watch [S]] [--json]      state, position, loop timing, telemetry, faults
    stagectl move (--to M | --by M) [--max-velocity M_S]
    stagectl stop [--json]                      decelerate and hold
    stagectl reset [--json]                     clear a latched fault (re-enables the drive)
    stagectl record start NAME | stop           capture telemetry to <telemetry dir>/NAME.csv
    stagectl gains [--json]                     the controller tuning in force
    stagectl ilc start|stop|status|save [--motion NAME]|load --motion NAME
                                                learning feed-forward of the repeated motion (ilc:)

Every command takes ``--socket PATH`` (default ``$STAGECTL_SOCKET``, else ``$RUNTIME_DIRECTORY/control.sock``,
else ``/run/stagectl/control.sock``); while a daemon is still starting on that directory (no socket yet), a
client waits for it, at most ``--timeout``. A refused request prints ``stagectl: error: <field>: <reason>`` and
exits with code 2; an unreachable daemon also exits 2 with the socket path in the message.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from collections.abc import Iterator
from typing import Any

import yaml

from stagectl.commands.args import number
from stagectl.daemon.control import ControlClient
from stagectl.daemon.paths import first_dir
from stagectl.errors import StageError
from stagectl.outputs import si
from stagectl.runtime.requests import IlcRequest, MoveRequest, ResetRequest, StopRequest

DEFAULT_SOCKET = "/run/stagectl/control.sock"


def default_socket() -> str:
    env = os.environ.get("STAGECTL_SOCKET")
    if env:
        return env
    rd = first_dir(os.environ, "RUNTIME_DIRECTORY")
    return str(rd / "control.sock") if rd is not None else DEFAULT_SOCKET


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--socket", metavar="PATH", default=None,
                   help=f"control socket of the daemon (default: $STAGECTL_SOCKET or {DEFAULT_SOCKET})")
    p.add_argument("--timeout", type=number("s", lo=0, lo_open=True, hi=3600), default=10.0, metavar="S",
                   help="reply timeout [s] (default 10)")


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("status", help="show the daemon's state, position, loop timing and telemetry")
    _common(p)
    p.add_argument("--watch", nargs="?", const=1.0, type=number("s", lo=0.01, hi=3600), metavar="S",
                   help="refresh every S seconds (default 1) until Ctrl-C")
    p.add_argument("--json", action="store_true", help="print the raw status as JSON")
    p.set_defaults(func=cmd_status)

    p = sub.add_parser("move", help="move the stage to an absolute position or by a distance (metres)")
    _common(p)
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--to", type=number("m"), metavar="M", help="absolute target [m]")
    g.add_argument("--by", type=number("m"), metavar="M", help="relative distance [m] from the current target")
    p.add_argument("--max-velocity", type=number("m/s", lo=0, lo_open=True), metavar="M_S",
                   help="velocity limit for this move [m/s]")
    p.set_defaults(func=cmd_move)

    p = sub.add_parser("stop", help="decelerate and hold position")
    _common(p)
    p.add_argument("--json", action="store_true", help="print the reply as JSON (default: YAML)")
    p.set_defaults(func=lambda a: _simple(a, StopRequest().to_json()))

    p = sub.add_parser("reset", help="clear a latched fault and re-enable the drive")
    _common(p)
    p.add_argument("--json", action="store_true", help="print the reply as JSON (default: YAML)")
    p.set_defaults(func=lambda a: _simple(a, ResetRequest().to_json()))

    p = sub.add_parser("record", help="start/stop capturing telemetry into a named CSV file")
    rs = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    ps = rs.add_parser("start", help="start capturing to <telemetry dir>/NAME.csv")
    _common(ps)
    ps.add_argument("name", metavar="NAME", help="file name (letters, digits, ._-; no directories)")
    pe = rs.add_parser("stop", help="stop the running capture and print its file and row count")
    _common(pe)
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("ilc", help="learning feed-forward of the repeated motion: start/stop learning, "
                                   "save/load the learned signal per motion, status")
    _common(p)
    p.add_argument("action", choices=("start", "stop", "status", "save", "load"),
                   help="start | stop learning (the learned force ramps in/out), status, save | load the "
                        "learned signal (<ilc.store_dir>/<motion>.npz)")
    p.add_argument("--motion", metavar="NAME", default=None,
                   help="motion name of the saved signal (save: default the running motion; load: required)")
    p.add_argument("--json", action="store_true", help="print the reply as JSON")
    p.set_defaults(func=cmd_ilc)

    p = sub.add_parser("gains", help="show the controller tuning in force")
    _common(p)
    p.add_argument("--json", action="store_true", help="print as JSON (default: YAML to paste into a config)")
    p.set_defaults(func=cmd_gains)


# ---------------------------------------------------------------------------------------------- plumbing
def _daemon_argv(pid: int) -> list[bytes] | None:
    """The command line of process ``pid`` if it is a ``stagectl daemon``, else None."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            argv = f.read().split(b"\0")
    except OSError:
        return None
    return argv if b"daemon" in argv and any(b"stagectl" in a for a in argv) else None


def _runtime_dir_of(pid: int, argv: list[bytes]) -> str | None:
    """The absolute ``--runtime-dir`` a daemon was started with (relative to its working directory)."""
    for k, a in enumerate(argv):
        value = argv[k + 1] if a == b"--runtime-dir" and k + 1 < len(argv) else (
            a.split(b"=", 1)[1] if a.startswith(b"--runtime-dir=") else None)
        if value:
            try:
                return os.path.normpath(os.path.join(os.readlink(f"/proc/{pid}/cwd"), os.fsdecode(value)))
            except OSError:
                return None
    return None


def _starting_daemon(path: str) -> int | None:
    """The pid of a live ``stagectl daemon`` on the directory of ``path`` that has not opened its socket yet
    (start-up takes seconds), else None: the pid its lock file names, or (before it has taken the lock) one
    started with that ``--runtime-dir``. Reads only: taking the lock, even shared, could make that daemon's
    own start-up fail."""
    from stagectl.daemon.instance import LOCK_NAME, lock_pid

    rdir = os.path.abspath(os.path.dirname(path) or ".")
    pid = lock_pid(os.path.join(rdir, LOCK_NAME))
    if pid is not None and _daemon_argv(pid) is not None:
        return pid
    try:
        pids = [int(d) for d in os.listdir("/proc") if d.isdigit()]
    except OSError:
        return None
    for pid in pids:
        argv = _daemon_argv(pid)
        if argv is not None and _runtime_dir_of(pid, argv) == rdir:
            return pid
    return None


def _wait_for_a_starting_daemon(path: str, timeout_s: float) -> None:
    """No socket yet, but a daemon is starting on that directory (``stagectl daemon … &`` and a client right
    after, as in the README): wait for its socket, at most ``timeout_s``, while that daemon lives."""
    if os.path.exists(path):
        return
    pid = _starting_daemon(path)
    if pid is None:
        return
    print(f"stagectl: waiting for the daemon (pid {pid}) to open {path}", file=sys.stderr, flush=True)
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not os.path.exists(path) and _starting_daemon(path) == pid:
        time.sleep(0.05)


@contextlib.contextmanager
def open_client(socket_path: str | None, timeout_s: float) -> Iterator[ControlClient]:
    """A connected client; an unreachable daemon or a broken connection is one :class:`StageError` line."""
    path = socket_path or default_socket()
    _wait_for_a_starting_daemon(path, timeout_s)
    try:
        with ControlClient(path, timeout_s=timeout_s) as c:
            yield c
    except FileNotFoundError:
        raise StageError(f"{path}: no control socket (is the daemon running? use --socket PATH)") from None
    except PermissionError:
        raise StageError(f"{path}: permission denied (is your user in the daemon's group?)") from None
    except ConnectionRefusedError:
        import stat

        try:
            mode = os.stat(path).st_mode
        except OSError:
            mode = 0
        if mode and not stat.S_ISSOCK(mode):
            kind = "a directory" if stat.S_ISDIR(mode) else "a file"
            raise StageError(f"{path}: not a control socket but {kind} (use --socket PATH)") from None
        raise StageError(f"{path}: no daemon listening (a socket left by a daemon that stopped? start it, or "
                         f"use --socket PATH)") from None
    except BrokenPipeError:
        if _stdout_broken():  # `stagectl scope --once | head`: the reader went away, not the daemon
            raise  # (cli.main ends quietly on it)
        raise StageError(f"{path}: the daemon closed the connection (broken pipe)") from None
    except (ConnectionError, TimeoutError, OSError) as exc:
        raise StageError(f"{path}: {exc}") from None


def _stdout_broken() -> bool:
    """Whether standard output is a pipe whose reader has gone (Linux reports POLLERR on such a write end)."""
    import select

    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(ev & select.POLLERR for _, ev in poller.poll(0))
    except (OSError, ValueError, AttributeError):
        return False
    return False


def _request(args: argparse.Namespace, req: dict[str, Any]) -> dict[str, Any]:
    with open_client(args.socket, args.timeout) as c:
        reply = c.request(req)
    if not reply.get("ok"):
        raise StageError(str(reply.get("error", "request refused")))
    return reply


def _simple(args: argparse.Namespace, req: dict[str, Any]) -> int:
    reply = _request(args, req)
    body = {k: v for k, v in reply.items() if k not in ("ok", "id")}
    if getattr(args, "json", False):
        print(json.dumps(body, indent=2))
    else:
        print(_yaml(body).rstrip() if body else "ok")
    return 0


def config_form(ctl: Any) -> Any:
    """The controller section as a config file writes it: keys left at their default (``None``: the config
    refuses an explicit ``null`` there) are dropped, and so is ``feedforward.model``, the model the daemon
    resolved from ``model_file``/``friction`` (an object, not a config key)."""
    def drop_nulls(node: Any) -> Any:
        if isinstance(node, dict):
            return {k: drop_nulls(v) for k, v in node.items() if v is not None}
        if isinstance(node, list):
            return [drop_nulls(v) for v in node]
        return node

    out = drop_nulls(ctl)
    if isinstance(out, dict) and isinstance(out.get("feedforward"), dict):
        out["feedforward"].pop("model", None)
    return out


def _yaml(obj: Any) -> str:
    """YAML a user can paste into a config (``null``/``true``, not Python's ``None``/``True``)."""
    return yaml.safe_dump(obj, sort_keys=False, default_flow_style=False, allow_unicode=True)


#: the move request's fields as the user typed them on the command line
MOVE_FLAGS = {"target_m": "--to", "relative_m": "--by", "max_velocity_m_s": "--max-velocity"}


def move_error_for_user(message: str) -> str:
    """A refused move's ``"<field>: reason"`` (the socket's convention) named by the user's option instead:
    ``relative_m: ...`` becomes ``move --by: ...``; other messages are returned unchanged."""
    for field, flag in MOVE_FLAGS.items():
        if message.startswith(field + ": "):
            return f"move {flag}: {message[len(field) + 2:]}"
    return message


# ---------------------------------------------------------------------------------------------- commands
def cmd_move(args: argparse.Namespace) -> int:
    # validated here (finite numbers, velocity > 0) before anything is sent; the daemon checks the limits
    try:
        req = MoveRequest(target_m=args.to, relative_m=args.by if args.to is None else None,
                          max_velocity_m_s=args.max_velocity)
        reply = _request(args, req.to_json())
    except StageError as exc:
        raise StageError(move_error_for_user(str(exc))) from None
    print(f"moving to {reply.get('target_m', float('nan')):.9g} m"
          + (f" ({reply['duration_s']:.4g} s)" if isinstance(reply.get("duration_s"), (int, float)) else ""))
    return 0


def cmd_record(args: argparse.Namespace) -> int:
    if args.action == "start":
        reply = _request(args, {"request": "record", "action": "start", "name": args.name})
        print(f"recording to {reply['recording']}")
    else:
        rec = _request(args, {"request": "record", "action": "stop"})["recording"] or {}
        err = f" (error: {rec['error']})" if rec.get("error") else ""
        print(f"recorded {rec.get('rows', 0)} rows to {rec.get('path')}{err}")
    return 0


def cmd_gains(args: argparse.Namespace) -> int:
    reply = _request(args, {"request": "gains"})
    ctl = config_form(reply.get("controller"))
    if args.json:
        json.dump({"controller": ctl, "reload": reply.get("reload")}, sys.stdout, indent=2)
        sys.stdout.write("\n")
        return 0
    # the controller section as YAML, ready to paste into a config
    print(_yaml({"controller": ctl}).rstrip())
    rl = reply.get("reload")
    if rl:
        print(f"# last reload: {'applied' if rl.get('ok') else 'REJECTED: ' + str(rl.get('error'))}")
        if rl.get("ok") and rl.get("note"):
            print(f"# {rl['note']}")
    return 0


def cmd_ilc(args: argparse.Namespace) -> int:
    req = IlcRequest(action=args.action, motion=args.motion)  # checked here before anything is sent
    reply = _request(args, req.to_json())
    body = {k: v for k, v in reply.items() if k not in ("ok", "id")}
    if args.json:
        print(json.dumps(body, indent=2))
        return 0
    for key in ("saved", "loaded"):
        if key in body:
            print(f"{key} {body[key]}")
    rms = body.get("rms_m") or []
    d = body.get("design") or {}
    print(f"motion {body.get('motion')}  learning {body.get('learning')}  applying {body.get('applying')}  "
          f"gain {_n(body.get('gain'))}  iteration {body.get('iteration')}"
          + (f"  FROZEN ({body['frozen']})" if body.get("frozen") else ""))
    if rms:
        print("rms per repetition  " + "  ".join(_m(v) for v in rms))
    if d:
        print(f"design  {d.get('learning')}  rho {_n(d.get('rho'))}  rho with model error {_n(d.get('rho_robust'))}  "
              f"monotonic {d.get('monotonic')}")
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    while True:
        st = _request(args, {"request": "status"})["status"]
        if args.json:
            print(json.dumps(st, indent=None if args.watch else 2), flush=True)
        else:
            if args.watch:
                print("\033[H\033[2J", end="")
            print(render_status(st), flush=True)
        if not args.watch:
            return 0
        try:
            time.sleep(max(0.05, args.watch))
        except KeyboardInterrupt:  # Ctrl-C ends a watch as asked (exit 0); SIGTERM exits 143 as every command
            from stagectl.errors import interrupt_name

            return 143 if interrupt_name() == "SIGTERM" else 0


def render_status(st: dict[str, Any]) -> str:
    """Human-readable status (SI units; positions also in mm for reading)."""
    loop = st.get("loop") or {}
    late = loop.get("lateness_us") or {}
    tel = st.get("telemetry") or {}
    lines = [
        f"state      {st.get('state')}   (loop {loop.get('state')}, drive "
        f"{st.get('drive') or ('enabled' if st.get('drive_enabled') else 'disabled')})",
        f"position   x = {_m(loop.get('x_m'))}   x_ref = {_m(loop.get('x_ref_m'))}   e = {_m(loop.get('e_m'))}"
        + ("" if loop.get("in_position") is None else
           f"   {'in position' if loop.get('in_position') else 'not in position'}"),
        f"force      u = {_n(loop.get('u_n'))} N",
        f"loop       cycle {loop.get('cycle')}   overruns {loop.get('overruns')}   lateness p50/p99/max "
        f"{_n(late.get('p50'))}/{_n(late.get('p99'))}/{_n(late.get('max'))} us",
    ]
    fault = loop.get("fault")
    if fault:
        lines.append(f"FAULT      {fault.get('name', fault) if isinstance(fault, dict) else fault}: "
                     f"{fault.get('cause', '') if isinstance(fault, dict) else ''}")
    if tel:
        rec = tel.get("recording")
        lines.append(f"telemetry  {tel.get('rows_written')} rows, dropped {tel.get('dropped')}, lost {tel.get('lost')}"
                     f"{', recording ' + str(rec.get('name')) if rec else ''}   {tel.get('file') or ''}")
        if tel.get("error"):
            lines.append(f"TELEMETRY ERROR  {tel['error']}")
    ilc = loop.get("ilc")
    if ilc:
        lines.append(f"learning   iteration {ilc.get('iteration')}   rms {_m(ilc.get('last_rms_m'))}   "
                     f"u_ilc {_n(ilc.get('u_ilc_n'))} N")
    rl = st.get("reload")
    if rl and not rl.get("ok"):
        lines.append(f"reload     REJECTED: {rl.get('error')}")
    elif rl and rl.get("note"):
        lines.append(f"reload     controller applied; {rl['note']}")
    wd = st.get("watchdog") or {}
    if wd.get("reason"):
        lines.append(f"watchdog   withheld: {wd['reason']}")
    return "\n".join(lines)


def _m(v: Any) -> str:
    """Metres in the unit that suits the value (nm, µm, mm, m), to 0.1 nm for sub-mm values."""
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return "-"
    return si(float(v), "m")


def _n(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, (int, float)) else "-"
