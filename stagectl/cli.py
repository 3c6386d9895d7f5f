"""``stagectl`` command-line entry point.

Every subcommand lives in ``stagectl.commands.<module>`` and registers itself through
``add_parser(subparsers)``, setting ``func(args) -> int`` as its handler. Errors the user can fix
(:class:`~stagectl.errors.StageError`: bad config, bad data, device errors) are printed as
``stagectl: error: ...`` (one line per problem) with exit code 2 and never as a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import re
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn

#: command modules, in the order they appear in ``--help``
COMMAND_MODULES = (
    "run",
    "simulate",
    "check_config",
    "tune",
    "sim_plant",
    "daemon",
    "clients",
    "model",
    "identify",
    "discover",
    "bench",
    "scope",
    "plot",
    "commission",
    "warm",
)

#: command names that live in a module of another name (the rest: name with '-' as '_')
COMMAND_ALIASES = {name: "clients" for name in ("status", "move", "stop", "reset", "record", "gains", "ilc")}


#: sphinx/rst markup in the command modules' docstrings, shown plain in ``--help``
_MARKUP = re.compile(r"``([^`]+)``|:(?:mod|func|class|meth|attr|data):`~?([^`]+)`")


class StageArgumentParser(argparse.ArgumentParser):
    """argparse with two fixes every subcommand inherits: ``--by -1e-5`` is a value, not an unknown
    option (argparse's own negative-number rule knows no exponent), and descriptions lose their rst markup."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        desc = kwargs.get("description")
        if isinstance(desc, str):
            kwargs["description"] = _MARKUP.sub(lambda m: m.group(1) or m.group(2), desc)
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self._negative_number_matcher = re.compile(r"^-(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?$|^-inf$")

    def error(self, message: str) -> NoReturn:
        """A bad argument is one ``stagectl: error: <command>: ...`` line (no usage block), exit 2."""
        cmd = self.prog.split(" ", 1)[1] if " " in self.prog else ""
        self.exit(2, f"stagectl: error: {cmd + ': ' if cmd else ''}{message} (see: {self.prog} --help)\n")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The full parser, or with ``only`` (a module of :data:`COMMAND_MODULES`) just that command's, so a
    command does not pay for importing every other one (``bench`` pulls in numpy/numba: ~0.4 s)."""
    from stagectl import __version__

    parser = StageArgumentParser(
        prog="stagectl",
        description="Friction-compensating controller for precision linear stages (SI units throughout).",
    )
    parser.add_argument("--version", action="version", version=f"stagectl {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES if only is None else (only,):
        mod = importlib.import_module(f"stagectl.commands.{name}")
        mod.add_parser(sub)
    return parser


def one_blas_thread() -> None:
    """One BLAS thread unless the user set otherwise (before numpy is first imported, which the parser does
    not do). stagectl's matrices are small (<= ~30 columns in the regressions, a few states in the designs):
    a BLAS worker pool only competes for the cores with the control loop, and a busy-waiting pool thread in
    the loop process would take CPU from it. On this 2-core machine discover on EMPS took 16.7 s with
    OpenBLAS' default threads and 3.6 s with one."""
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def _end_progress_line() -> None:
    """On a terminal a progress line (stagectl.commands.progress) may be standing without its newline: clear
    it, so the error or interrupt message starts its own line."""
    try:
        if sys.stderr.isatty():
            sys.stderr.write("\r\033[K")
    except (OSError, ValueError):
        pass


def _remove_created_if_empty() -> None:
    """A command refused (bad data found after its ``--out`` directory was made) leaves no empty directory."""
    from stagectl.outputs import remove_created_if_empty

    remove_created_if_empty()


def _after_interrupt(args: argparse.Namespace, started: float) -> str:
    """What an interrupted command leaves: the output directories it created and left empty are removed; the
    outputs it wrote to (files changed since it started) are named as incomplete; otherwise nothing."""
    from stagectl.outputs import remove_created_if_empty

    remove_created_if_empty()
    kept: list[str] = []
    for name in ("out", "plot"):
        value = getattr(args, name, None)
        if not isinstance(value, str) or not value:
            continue
        p = Path(value)
        try:
            files = [f for f in p.rglob("*") if f.is_file()] if p.is_dir() else [p] if p.is_file() else []
            if any(f.stat().st_mtime >= started - 1.0 for f in files):
                kept.append(value)
        except OSError:
            continue
    if kept:
        return f"; what was written so far is in {' and '.join(kept)} (incomplete)"
    return "; no output was written" if any(getattr(args, n, None) for n in ("out", "plot")) else ""


#: set by :func:`_on_sigint`: a Ctrl-C arrived in this process
_interrupted = False
#: set by :func:`_on_sigterm`: the interrupt was a SIGTERM (``kill``, ``timeout``, a supervisor), exit 143
_terminated = False


def _on_sigint(signum: int, frame: object) -> None:
    """Python's own SIGINT behaviour (raise KeyboardInterrupt), remembering that it happened: a
    KeyboardInterrupt raised half way through a module import or class creation can come out as another
    exception (the next use of the half-made module fails with ImportError/AttributeError), which
    :func:`main` must still report as the interrupt, not as a bug."""
    global _interrupted
    _interrupted = True
    raise KeyboardInterrupt


def _on_sigterm(signum: int, frame: object) -> None:
    """SIGTERM ends a foreground command the way Ctrl-C does (run stops its loop: zero force, drive disabled,
    and writes what it recorded; simulate keeps what it simulated; identify, discover and bench leave no
    output), instead of the default action, which killed the process at once: the recording lost and a
    drive left enabled until its own heartbeat consumer time-out. A SIGTERM while an interrupt (this one or a
    Ctrl-C) is being handled is ignored, so it cannot cut that clean stop short (a Ctrl-C stays the way to cut
    it). The daemon and sim-plant install their own."""
    from stagectl.errors import set_interrupt_name

    global _interrupted, _terminated
    if _terminated or _interrupted:
        return
    _interrupted = _terminated = True
    set_interrupt_name("SIGTERM")
    raise KeyboardInterrupt


def _catch_sigint(term: bool = True) -> Callable[[], None]:
    """Install :func:`_on_sigint` where Python's default handler is in place (not over SIG_IGN: a job
    started in the background or under nohup keeps ignoring Ctrl-C), and with ``term`` :func:`_on_sigterm`
    where SIGTERM has its default action; returns what puts the old ones back (main() called in-process, e.g. by a test,
    leaves the process as it found it)."""
    import signal

    from stagectl.errors import set_interrupt_name

    global _interrupted, _terminated
    _interrupted = _terminated = False
    set_interrupt_name("Ctrl-C")
    undo: list[Callable[[], None]] = []
    try:
        if term and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
            signal.signal(signal.SIGTERM, _on_sigterm)

            def default_term() -> None:
                signal.signal(signal.SIGTERM, signal.SIG_DFL)

            undo.append(default_term)
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            signal.signal(signal.SIGINT, _on_sigint)
            old_hook = sys.unraisablehook
            sys.unraisablehook = _unraisable

            def restore() -> None:
                signal.signal(signal.SIGINT, signal.default_int_handler)
                sys.unraisablehook = old_hook

            undo.append(restore)
    except ValueError:  # not the main thread (main() called from a test's thread): keep Python's handlers
        pass

    def restore_all() -> None:
        for f in undo:
            f()

    return restore_all


def _unraisable(u: Any) -> None:
    """A Ctrl-C that lands in a C callback (llvmlite's, while numba compiles) is swallowed there and printed as
    "Exception ignored ... Traceback"; deliver it to the main thread instead, silently. Anything else goes to
    Python's default hook."""
    if isinstance(u.exc_value, KeyboardInterrupt):
        import signal
        import threading

        # a real SIGINT again (it also wakes a blocking call), but not from here: the main thread would take it
        # inside this hook, which swallows it; 5 ms later it is back in the command (or in another callback,
        # which comes here again)
        main_id = threading.main_thread().ident
        t = threading.Timer(0.005, signal.pthread_kill, (main_id, signal.SIGINT))
        t.daemon = True
        t.start()
        return
    sys.__unraisablehook__(u)


def _was_interrupted(exc: BaseException) -> bool:
    """A Ctrl-C arrived in this process, or ``exc`` was raised while handling a KeyboardInterrupt."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return _interrupted


#: commands that install their own SIGTERM handler and exit 0 on it (the service, sim-plant): until they do,
#: SIGTERM keeps its default action rather than turning into an interrupt (exit 143)
OWN_SIGTERM = frozenset({"daemon", "sim-plant", "sim_plant"})


def main(argv: Sequence[str] | None = None) -> int:
    first = (sys.argv[1:] if argv is None else list(argv))[:1]
    restore = _catch_sigint(term=not (first and first[0] in OWN_SIGTERM))
    try:
        return _main(argv)
    finally:
        restore()


def _main(argv: Sequence[str] | None) -> int:
    from stagectl.errors import StageError

    argv = list(sys.argv[1:] if argv is None else argv)
    one_blas_thread()
    # fast path: `stagectl sim-plant ...` imports only its own module (it installs its SIGTERM handler
    # first thing; a full parser build took ~0.4 s during which SIGTERM killed it with status 143)
    first = argv[0].replace("-", "_") if argv and not argv[0].startswith("-") else None
    first = COMMAND_ALIASES.get(argv[0], first) if first is not None else None
    try:
        parser = build_parser(first if first in COMMAND_MODULES else None)
        args = parser.parse_args(argv)
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM while the parser is built: one line, not a traceback
        return _interrupt_exit(argparse.Namespace(), time.time())
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    started = time.time()
    try:
        return int(args.func(args) or 0)
    except StageError as exc:
        if _was_interrupted(exc):  # e.g. a device's reply lost to the Ctrl-C: the interrupt, not the device
            return _interrupt_exit(args, started)
        _end_progress_line()
        _remove_created_if_empty()
        msg = str(exc)
        lines = [line for line in msg.splitlines() if line.strip()] or [type(exc).__name__]
        for line in lines:  # one line per problem, each greppable as an error
            print(f"stagectl: error: {line}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return _interrupt_exit(args, started)
    except BrokenPipeError:
        return 0
    except OSError as exc:  # the environment, not a bug: disk full, permission, a path that vanished
        if _was_interrupted(exc):
            return _interrupt_exit(args, started)
        _end_progress_line()
        _remove_created_if_empty()
        name = exc.filename if exc.filename is not None else "output"
        print(f"stagectl: error: {name}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # a bug: one line for the user, the traceback on request
        if _was_interrupted(exc):  # a Ctrl-C that came out as another exception: still the interrupt
            return _interrupt_exit(args, started)
        if os.environ.get("STAGECTL_TRACEBACK"):
            raise
        _end_progress_line()
        print(f"stagectl: internal error: {type(exc).__name__}: {str(exc)[:200]} "
              "(a bug in stagectl: please report it; STAGECTL_TRACEBACK=1 shows the traceback)", file=sys.stderr)
        return 70


def _interrupt_exit(args: argparse.Namespace, started: float) -> int:
    """Ctrl-C: one line saying so (and what output it left), exit 130; SIGTERM: the same line, exit 143."""
    _end_progress_line()
    what = "SIGTERM" if _terminated else "Ctrl-C"
    print(f"stagectl: interrupted ({what}){_after_interrupt(args, started)}", file=sys.stderr)
    return 143 if _terminated else 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
