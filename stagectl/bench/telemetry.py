"""``stagectl bench telemetry``: telemetry at 1 kHz for 10 minutes loses nothing (target: zero dropped samples).

    stagectl bench telemetry [--duration-s 600] [--rate-hz 1000] [--columns 12] [--json]
    stagectl bench telemetry --daemon config/sim.yaml [--duration-s 600] [--json]

A producer thread on absolute deadlines (``clock_nanosleep``, the loop's clock) appends one row per period
into the daemon's :class:`TelemetryRing` (default 60 s of buffer); the daemon's :class:`TelemetryWriter`
writes rotating CSV files into a temporary directory, with a named recording running over the middle half.
Reported: rows produced, dropped (ring full), lost (write errors), rows in the files (re-read and counted),
writer backlog peak, producer ``append`` cost p50/p99/max and producer lateness p99. Not a test: it runs on
the wall clock.

With ``--daemon CONFIG`` the real ``stagectl daemon`` runs on CONFIG (e.g. the embedded simulated plant) in a
temporary runtime directory for the duration; the figures come from its ``status`` reply at the end and from
the telemetry file it leaves after SIGTERM (rows counted against the loop's cycle count).

Exit code 0 when nothing was dropped or lost and every row reached the files, else 1.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from stagectl.bench import tell

import numpy as np
import numpy.typing as npt
import yaml

from stagectl.clock import MonotonicClock
from stagectl.daemon.control import ControlClient
from stagectl.daemon.telemetry import TelemetryRing, TelemetryWriter, WriterSettings
from stagectl.schema import absolute_paths, load_yaml_file

__all__ = ["add_arguments", "exit_code", "run", "run_daemon", "run_ring"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--duration-s", type=float, default=600.0, help="seconds to run (default 600)")
    p.add_argument("--rate-hz", type=float, default=1000.0, help="rows per second (default 1000)")
    p.add_argument("--columns", type=int, default=12, help="columns per row (default 12)")
    p.add_argument("--daemon", metavar="CONFIG", help="measure the real daemon on CONFIG instead")


def run(args: argparse.Namespace) -> dict[str, Any]:
    tell(args, 0.0, args.duration_s, f"{args.duration_s:g} s of rows at {args.rate_hz:g} Hz"
         + (f" through the daemon on {args.daemon}" if args.daemon else ""), span=args.duration_s)
    if args.daemon:
        return run_daemon(args.daemon, args.duration_s)
    return run_ring(args.duration_s, args.rate_hz, args.columns)


def exit_code(res: dict[str, Any]) -> int:
    """0 when the run lost nothing (see the module docstring), else 1."""
    if "complete" in res:  # --daemon
        return 0 if res["complete"] and res["dropped_at_end"] == 0 and res["lost_at_end"] == 0 else 1
    return 0 if res["dropped"] == 0 and res["lost"] == 0 and res["rows_in_files"] == res["rows_produced"] else 1


def _pct_us(a: npt.NDArray[np.float64]) -> dict[str, float]:
    p50, p99 = np.percentile(a, (50, 99))
    return {"p50": float(p50) * 1e6, "p99": float(p99) * 1e6, "max": float(a.max()) * 1e6}


def run_ring(duration_s: float = 600.0, rate_hz: float = 1000.0, ncols: int = 12, buffer_s: float = 60.0,
             rotate_mb: float = 100.0, directory: Path | None = None) -> dict[str, Any]:
    """The ring and writer alone, fed by a producer thread on absolute deadlines."""
    sys.setswitchinterval(2.5e-4)  # as `stagectl daemon` does: the producer gets the GIL back quickly
    period = 1.0 / rate_hz
    cols = ("t", "x", "u", "x_ref", "v_ref", "a_ref", "e", "v") + tuple(f"u_{i}" for i in range(max(0, ncols - 8)))
    ring = TelemetryRing(cols, int(math.ceil(buffer_s * rate_hz)))
    tmp = tempfile.TemporaryDirectory(prefix="stagectl-bench-tel-") if directory is None else None
    d = Path(tmp.name) if tmp is not None else Path(directory or ".")
    writer = TelemetryWriter(ring, WriterSettings(directory=d, rotate_bytes=int(rotate_mb * 1e6), keep_files=0))
    writer.start()
    n_total = int(round(duration_s * rate_hz))
    append_cost = np.zeros(n_total)
    lateness = np.zeros(n_total)
    backlog_peak = [0]  # written by the producer thread
    clock = MonotonicClock()

    def producer() -> None:
        t0 = clock.now()
        perf = time.perf_counter
        rng = np.random.default_rng(1)
        noise = rng.standard_normal(4096).tolist()
        for k in range(n_total):
            deadline = t0 + k * period
            clock.sleep_until(deadline)
            lateness[k] = clock.now() - deadline
            t = k * period
            x = 1e-3 * math.sin(t) + 1e-9 * noise[k & 4095]
            row = (t, x, 0.1 * x, 1e-3 * math.sin(t), 1e-3 * math.cos(t), -1e-3 * math.sin(t), 1e-9, 0.0) + (
                0.5,) * (len(cols) - 8)
            c0 = perf()
            ring.append(row)
            append_cost[k] = perf() - c0
            if (k & 1023) == 0:
                backlog_peak[0] = max(backlog_peak[0], ring.backlog)

    th = threading.Thread(target=producer, name="bench-producer")
    wall0 = time.monotonic()
    th.start()
    th.join(duration_s / 4)
    rec_path = writer.record_start("bench-recording") if th.is_alive() else None
    th.join(duration_s / 2)
    rec = writer.record_stop() if rec_path else None
    th.join()
    writer.stop(timeout=60)
    wall = time.monotonic() - wall0
    st = writer.status()
    rows_in_files = 0
    files = sorted(d.glob("telemetry-*.csv"))
    last_t = -1.0
    monotonic_ok = True
    for f in files:
        with open(f) as fh:
            next(fh)
            for line in fh:
                rows_in_files += 1
                t = float(line.split(",", 1)[0])
                if t <= last_t:
                    monotonic_ok = False
                last_t = t
    out = {
        "command": f"stagectl bench telemetry --duration-s {duration_s:g} --rate-hz {rate_hz:g} "
                   f"--columns {len(cols)}",
        "duration_s": duration_s,
        "wall_s": wall,
        "rate_hz": rate_hz,
        "columns": len(cols),
        "rows_produced": n_total,
        "dropped": st["dropped"],
        "lost": st["lost"],
        "bad_rows": st["bad_rows"],
        "rows_written": st["rows_written"],
        "rows_in_files": rows_in_files,
        "files": len(files),
        "time_strictly_increasing": monotonic_ok,
        "recording_rows": (rec or {}).get("rows"),
        "ring_capacity_rows": ring.capacity,
        "backlog_peak_rows": backlog_peak[0],
        "append_us": _pct_us(append_cost),
        "producer_lateness_us": _pct_us(lateness),
        "write_error": st["error"],
    }
    if tmp:
        tmp.cleanup()
    return out


def run_daemon(config: str, duration_s: float = 600.0) -> dict[str, Any]:
    """Run ``stagectl daemon`` on ``config`` for ``duration_s`` and count what reached the files."""
    tmp = tempfile.TemporaryDirectory(prefix="stagectl-bench-daemon-")
    d = Path(tmp.name)
    src = Path(config).resolve()
    data = load_yaml_file(src)  # the bounded loader, as the daemon reads it

    data = absolute_paths(data, src.parent)
    data.setdefault("daemon", {})
    data["daemon"] = {**(data["daemon"] or {}), "telemetry": {"directory": str(d / "telemetry")}}
    cfg = d / "stagectl.yaml"
    cfg.write_text(yaml.safe_dump(data))
    ns = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    ns.bind(str(d / "notify.sock"))
    ns.settimeout(0.5)
    exe = Path(sys.executable).parent / "stagectl"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "stagectl.cli"]
    errlog = open(d / "daemon.stderr", "w+")  # a file, not a pipe: nobody reads it for 10 minutes
    proc = subprocess.Popen([*cmd, "daemon", "--config", str(cfg), "--runtime-dir", str(d / "run")],
                            env={**os.environ, "NOTIFY_SOCKET": str(d / "notify.sock")},
                            stdout=subprocess.DEVNULL, stderr=errlog, text=True)
    while True:
        try:
            if b"READY=1" in ns.recv(65536):
                break
        except TimeoutError:
            if proc.poll() is not None:
                errlog.seek(0)
                raise RuntimeError(f"daemon exited ({proc.returncode}) before READY:\n{errlog.read()[-3000:]}")
    t_ready = time.monotonic()
    time.sleep(duration_s)
    with ControlClient(d / "run" / "control.sock") as c:
        st = c.request({"request": "status"})["status"]
    proc.send_signal(signal.SIGTERM)
    proc.wait(60)
    errlog.seek(0)
    err = errlog.read()
    errlog.close()
    wall = time.monotonic() - t_ready
    files = sorted((d / "telemetry").glob("telemetry-*.csv"))
    rows = 0
    for f in files:
        with open(f) as fh:
            rows += sum(1 for _ in fh) - 1
    final = [line for line in err.splitlines() if "stopped: drive" in line]
    cycles = int(final[-1].split(" cycles")[0].rsplit(" ", 1)[1]) if final else -1
    tel = st["telemetry"]
    loop = st["loop"]
    out = {
        "command": f"stagectl bench telemetry --daemon {config} --duration-s {duration_s:g}",
        "duration_s": duration_s,
        "wall_s": wall,
        "exit_code": proc.returncode,
        "loop_cycles": cycles,
        "rows_in_files": rows,
        "files": len(files),
        "dropped_at_end": tel["dropped"],
        "lost_at_end": tel["lost"],
        "write_error": tel["error"],
        "loop_overruns": loop["overruns"],
        "loop_lateness_us": loop["lateness_us"],
        "complete": rows == cycles,
    }
    ns.close()
    tmp.cleanup()
    return out
