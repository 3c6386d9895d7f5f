"""``stagectl scope [--socket PATH] [--window S] [--every K]``: a live terminal scope of the running daemon.

Works in any terminal, over SSH on a headless stage PC. It pulls the daemon's decimated telemetry stream
(the ``subscribe`` request on the control socket) ten times a second and draws,
over the last ``--window`` seconds:

* position and its reference, the tracking error, the force with its terms (PID, observer, friction and
  inertia feed-forward) and the velocity, each axis in the unit that suits its range (nm, µm, mm; mN, N);
* the loop state, cycle count, overruns and lateness, whether the drive is enabled, and the history of
  faults seen while the scope runs.

Keys: ``q`` quits, ``space`` pauses the display (the stream keeps being read). ``--once`` prints one text
frame and exits (for scripts and for a README sample). Built on Textual (terminal UI) and plotext (plots).
"""

from __future__ import annotations

import argparse
import math
import re
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any, ClassVar

from stagectl.commands.args import number
from stagectl.outputs import prefix_for

if TYPE_CHECKING:  # textual is imported when the command runs (the CLI parser stays fast)
    from textual.app import App

_ANSI = re.compile(r"\x1b\[[0-9;]*m")

#: plots: title, [(column, label)], SI unit of the columns
PLOTS: tuple[tuple[str, tuple[tuple[str, str], ...], str], ...] = (
    ("position", (("x_ref", "reference"), ("x", "position")), "m"),
    ("tracking error", (("e", "error"),), "m"),
    ("force", (("u", "total"), ("u_pid", "PID"), ("u_dob", "observer"), ("u_ff", "friction FF"),
               ("u_inertia", "inertia FF")), "N"),
    ("velocity", (("v", "velocity"), ("v_ref", "reference")), "m/s"),
)


def scale_for(values: Iterable[float], unit: str) -> tuple[float, str]:
    """The factor and unit label for values in ``unit`` so the largest magnitude reads 1…1000."""
    return prefix_for(max((abs(v) for v in values if v is not None and math.isfinite(v)), default=0.0), unit)


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("scope", help="live terminal scope of the running daemon (position, error, force terms)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--socket", metavar="PATH",
                   help="the daemon's control socket (default: $STAGECTL_SOCKET, else the daemon's)")
    p.add_argument("--window", type=number("s", lo=0.1, hi=600), default=5.0, metavar="S",
                   help="time span shown [s] (default 5)")
    p.add_argument("--every", type=number("rows", lo=1, hi=100000, integer=True), default=None, metavar="K",
                   help="keep every K-th telemetry row (default: about 200 points per second)")
    p.add_argument("--timeout", type=number("s", lo=0, lo_open=True, hi=60), default=2.0, metavar="S",
                   help="reply timeout [s] (default 2)")
    p.add_argument("--once", action="store_true", help="print one text frame and exit")
    p.set_defaults(func=run)


class ScopeData:
    """The rolling window of rows, the last status and the fault history (no terminal, no socket)."""

    def __init__(self, window_s: float) -> None:
        self.window_s = window_s
        self.columns: list[str] = []
        self.rows: deque[list[float | None]] = deque()
        self.status: dict[str, Any] = {}
        self.faults: list[str] = []
        self.lost = 0
        self.next: int | None = None

    def add(self, reply: dict[str, Any]) -> None:
        """One ``subscribe`` reply."""
        if reply["columns"] != self.columns:
            self.columns, self.rows = list(reply["columns"]), deque()
        self.rows.extend(reply["rows"])
        self.lost += int(reply.get("lost", 0))
        self.next = int(reply["next"])
        if self.rows and "t" in self.columns:
            it = self.columns.index("t")
            t_end = self.rows[-1][it] or 0.0
            while self.rows and (self.rows[0][it] or 0.0) < t_end - self.window_s:
                self.rows.popleft()

    def set_status(self, status: dict[str, Any]) -> None:
        loop = status.get("loop") or {}
        fault = loop.get("fault")
        if fault:
            line = f"t={fault.get('t_s', float('nan')):.3f} s  {fault.get('name')}: {fault.get('cause')}"
            if not self.faults or self.faults[-1] != line:
                self.faults.append(line)
        self.status = status

    def series(self, column: str) -> list[float]:
        if column not in self.columns:
            return []
        i = self.columns.index(column)
        out: list[float] = []
        for r in self.rows:
            v = r[i]
            out.append(math.nan if v is None else float(v))
        return out

    def header(self) -> str:
        st, loop = self.status, self.status.get("loop") or {}
        late = loop.get("lateness_us") or {}
        drive = st.get("drive") or ("enabled" if st.get("drive_enabled") else "disabled")
        fault = loop.get("fault")
        p99 = late.get("p99")
        late_txt = f"{p99:.0f} µs" if isinstance(p99, (int, float)) else "-"
        return (f"daemon {st.get('state', '?')}  loop {loop.get('state', '?')}  drive {drive}  "
                f"cycle {loop.get('cycle', '-')}  overruns {loop.get('overruns', '-')}  lateness p99 {late_txt}  "
                f"stream lost {self.lost}" + (f"  FAULT {fault.get('name')}" if fault else ""))

    def values(self) -> str:
        """The newest value of every plotted signal in its unit."""
        lines = []
        for _, sigs, unit in PLOTS:
            for col, label in sigs:
                s = self.series(col)
                if s:
                    k, u = scale_for(s, unit)
                    lines.append(f"{label:>12} {s[-1] * k:11.4f} {u}")
        return "\n".join(lines)

    def draw(self, plt: Any, title: str, sigs: Sequence[tuple[str, str]], unit: str) -> None:
        """One panel into a plotext figure: the signals over time (0 = now), in the unit that suits them."""
        t = self.series("t")
        k, u = scale_for([v for col, _ in sigs for v in self.series(col)], unit)
        for col, label in sigs:
            s = self.series(col)
            if s and t:
                plt.plot([ti - t[-1] for ti in t], [v * k for v in s], label=label)
        plt.title(f"{title} [{u}]")

    def text_frame(self, width: int = 100, height: int = 40) -> str:
        """The whole view as plain text (``--once``): header, plots drawn by plotext, values, faults."""
        import plotext as plt  # type: ignore[import-untyped]  # no type information shipped

        out = [self.header(), ""]
        for title, sigs, unit in PLOTS:
            plt.clear_figure()
            plt.plotsize(width, max(8, height // 4))
            plt.theme("clear")
            self.draw(plt, title, sigs, unit)
            plt.xlabel("time [s] (0 = now)")
            out.append(_ANSI.sub("", plt.build()))  # plain text: no terminal colour codes
        out += ["", self.values(), "", "faults: " + ("; ".join(self.faults) if self.faults else "none")]
        return "\n".join(out)


Poll = Callable[[], None]


def make_app(data: ScopeData, poll: Poll, rate_hz: float = 10.0) -> App[None]:
    """The Textual application over ``data``; ``poll()`` refreshes it (called ``rate_hz`` times a second)."""
    from textual.app import App, ComposeResult
    from textual.binding import Binding
    from textual.containers import Horizontal, Vertical
    from textual.widgets import Footer, Static
    from textual_plotext import PlotextPlot

    class ScopeApp(App[None]):
        CSS = """
        #header { height: 1; background: $primary-background; }
        #plots { width: 3fr; }
        #side { width: 1fr; min-width: 34; }
        PlotextPlot { height: 1fr; }
        #faults { height: 1fr; border-top: solid $secondary; }
        """
        BINDINGS: ClassVar = [Binding("q", "quit", "quit"), Binding("space", "pause", "pause/resume")]

        def __init__(self) -> None:
            super().__init__()
            self.paused = False
            self.error = ""

        def compose(self) -> ComposeResult:
            yield Static(id="header")
            with Horizontal():
                with Vertical(id="plots"):
                    for i, _ in enumerate(PLOTS):
                        yield PlotextPlot(id=f"plot{i}")
                with Vertical(id="side"):
                    yield Static(id="values")
                    yield Static(id="faults")
            yield Footer()

        def on_mount(self) -> None:
            self.title = "stagectl scope"
            self.redraw()
            # the socket is read in a worker thread: a slow or vanished daemon (a request may wait for its
            # timeout) never freezes the view or its keys; the data is touched only between a poll and the
            # redraw that poll asks for, which runs on the UI thread while the worker waits for it
            self.run_worker(self.poll_forever, thread=True, exclusive=True, name="scope-poll")

        def poll_forever(self) -> None:
            from textual.worker import get_current_worker

            worker = get_current_worker()
            period = 1.0 / rate_hz
            while not worker.is_cancelled:
                t0 = time.monotonic()
                try:
                    poll()
                    error = ""
                except Exception as exc:  # noqa: BLE001 - a daemon gone away is shown, the scope keeps trying
                    error = str(exc)[:200]
                if worker.is_cancelled:
                    return
                try:
                    self.call_from_thread(self.after_poll, error)
                except RuntimeError:  # the app has stopped
                    return
                time.sleep(max(0.0, period - (time.monotonic() - t0)))

        def action_pause(self) -> None:
            self.paused = not self.paused

        def after_poll(self, error: str) -> None:
            self.error = error
            if not self.paused:
                self.redraw()

        def redraw(self) -> None:
            head = self.query_one("#header", Static)
            head.update(("PAUSED  " if self.paused else "") + (f"NO DATA: {self.error}" if self.error
                                                              else data.header()))
            for i, (title, sigs, unit) in enumerate(PLOTS):
                widget = self.query_one(f"#plot{i}", PlotextPlot)
                widget.plt.clear_data()
                data.draw(widget.plt, title, sigs, unit)
                widget.refresh()
            self.query_one("#values", Static).update(data.values())
            self.query_one("#faults", Static).update(
                "faults while watching:\n" + ("\n".join(data.faults[-12:]) if data.faults else "none"))

    return ScopeApp()


def socket_poller(client: Any, data: ScopeData, every: int | None, signals: Sequence[str] | None = None) -> Poll:
    """A ``poll()`` pulling the stream (and, twice a second, the status) through ``client.request``."""
    every_k: list[int | None] = [every]
    status_due = [0.0]

    def poll() -> None:
        now = time.monotonic()
        if now >= status_due[0] or every_k[0] is None:
            st = client.request({"request": "status"})
            data.set_status(st.get("status", {}))
            status_due[0] = now + 0.5
            if every_k[0] is None:  # about 200 points per second of loop time
                period = (st.get("status", {}).get("loop") or {}).get("period_s") or 1e-3
                every_k[0] = max(1, round(1.0 / (200.0 * period)))
        req: dict[str, Any] = {"request": "subscribe", "since": data.next, "every": every_k[0]}
        if signals:
            req["signals"] = list(signals)
        reply = client.request(req)
        if "error" in reply:
            raise RuntimeError(str(reply["error"]))
        data.add(reply)

    return poll


def run(args: argparse.Namespace) -> int:
    from stagectl.commands.clients import open_client

    data = ScopeData(args.window)
    with open_client(args.socket, args.timeout) as client:
        poll = socket_poller(client, data, args.every)
        if args.once:
            poll()  # the first request attaches the stream: the frame shows what arrives in the next second
            time.sleep(min(args.window, 1.0))
            poll()
            print(data.text_frame())
            return 0
        make_app(data, poll).run()
    return 0
