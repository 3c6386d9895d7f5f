"""``stagectl bench flood``: what flooding and half-open clients cost the loop, the watchdog and ``stop``.

    stagectl bench flood --config config/sim.yaml [--phase-s 10] [--clients 16] [--half-open 32] [--fifo 80]
                         [--isolation both|thread|process] [--json]

For each isolation (``thread``: the loop is a thread of the daemon, the baseline; ``process``: the loop in its
own process) the real ``stagectl daemon`` runs on CONFIG in a temporary runtime directory, with a notify
socket of our own and ``WATCHDOG_USEC`` = 2 s so it pings the watchdog. Two phases of ``--phase-s`` each:

1. **quiet**: nothing but the daemon (the machine's own load: the reference figure);
2. **flood**: ``--clients`` connections sending pipelined ``status`` requests as fast as they are answered,
   one client sending ``gains`` requests that never reads a reply (it is dropped and reconnects),
   ``--half-open`` connections that never finish a line, and one client that sends ``move`` + ``stop``
   repeatedly and times each ``stop`` reply.

Reported per isolation and phase: missed cycles (skipped slots / all slots, from the loop's own counters at
the phase's start and end), the largest gap between two ``WATCHDOG=1`` pings, status requests served, and
``stop`` reply latency p50/max. Not a test: wall clock on a shared machine; say the load when quoting it.
"""

from __future__ import annotations

import argparse
import itertools
import json
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

import yaml

from stagectl.daemon.control import ControlClient
from stagectl.schema import absolute_paths, load_yaml_file

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, metavar="FILE", help="stagectl YAML to run the daemon on")
    p.add_argument("--phase-s", type=float, default=10.0, help="seconds per phase (default 10)")
    p.add_argument("--clients", type=int, default=16, help="flooding clients (default 16)")
    p.add_argument("--half-open", type=int, default=32, help="half-open connections (default 32)")
    p.add_argument("--fifo", type=int, default=None, metavar="PRIO",
                   help="run the loop at SCHED_FIFO PRIO (loop.realtime.fifo_priority; needs privileges)")
    p.add_argument("--isolation", choices=("both", "thread", "process"), default="both",
                   help="which isolation(s) to measure (default both: thread is the baseline)")


class _Notify:
    """Our stand-in for systemd's notify socket: records WATCHDOG=1 arrival times."""

    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.pings: list[float] = []
        self.ready = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        while True:
            try:
                data = self.sock.recv(65536)
            except OSError:
                return
            now = time.monotonic()
            if b"WATCHDOG=1" in data:
                self.pings.append(now)
            if b"READY=1" in data:
                self.ready.set()

    def max_gap(self, t0: float, t1: float) -> float:
        ts = [t0] + [t for t in self.pings if t0 <= t <= t1] + [t1]
        return max(b - a for a, b in itertools.pairwise(ts))


def _loop_counters(sock: Path) -> tuple[int, int]:
    with ControlClient(sock, timeout_s=30) as c:
        st = c.request({"request": "status"})["status"]["loop"]
    return int(st["cycle"]), int(st["overruns"])


def _measure(config: Path, isolation: str, phase_s: float, clients: int, half_open: int,
             fifo: int | None = None) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="stagectl-flood-") as tmp:
        d = Path(tmp)
        base = config.resolve().parent

        raw = absolute_paths(load_yaml_file(config) or {}, base)  # relative paths keep pointing where they did
        if fifo is not None:
            loop = raw.setdefault("loop", {}) or {}
            loop["realtime"] = {**(loop.get("realtime") or {}), "fifo_priority": fifo}
            raw["loop"] = loop
        dm = raw.setdefault("daemon", {}) or {}
        raw["daemon"] = {**dm, "isolation": isolation, "ready_timeout_s": 120, "status_interval_s": 1.0,
                         "telemetry": {**(dm.get("telemetry") or {}), "directory": str(d / "tel")}}
        cfg = d / "flood.yaml"
        cfg.write_text(yaml.safe_dump(raw))
        notify = _Notify(d / "notify.sock")
        env = {**os.environ, "NOTIFY_SOCKET": str(d / "notify.sock"), "WATCHDOG_USEC": "2000000"}
        env.pop("WATCHDOG_PID", None)
        exe = Path(sys.executable).parent / "stagectl"
        cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "stagectl.cli"]
        errlog = open(d / "daemon.stderr", "w+")  # a file, not a pipe nobody reads
        proc = subprocess.Popen([*cmd, "daemon", "--config", str(cfg), "--runtime-dir", str(d / "run")], env=env,
                                stdout=subprocess.DEVNULL, stderr=errlog)
        sock = d / "run" / "control.sock"
        out: dict[str, Any] = {"isolation": isolation}
        try:
            while not notify.ready.wait(0.5):
                if proc.poll() is not None:
                    errlog.seek(0)
                    raise RuntimeError(f"daemon exited {proc.returncode}: {errlog.read()[-2000:]}")
            # ---------------------------------------------------------------- quiet
            c0, o0 = _loop_counters(sock)
            t0 = time.monotonic()
            time.sleep(phase_s)
            c1, o1 = _loop_counters(sock)
            t1 = time.monotonic()
            out["quiet"] = {"missed_cycles_pct": 100.0 * (o1 - o0) / max(1, (c1 - c0) + (o1 - o0)),
                            "watchdog_max_gap_s": notify.max_gap(t0, t1)}
            # ---------------------------------------------------------------- flood
            done = threading.Event()
            served = [0]
            holders: list[socket.socket] = []

            def flood() -> None:
                line = b'{"request": "status"}\n' * 32
                while not done.is_set():
                    try:
                        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                            s.settimeout(5)
                            s.connect(str(sock))
                            buf = b""
                            while not done.is_set():
                                s.sendall(line)
                                got = 0
                                while got < 32 and not done.is_set():
                                    chunk = s.recv(1 << 20)
                                    if not chunk:
                                        raise OSError("closed")
                                    buf += chunk
                                    n = buf.count(b"\n")
                                    got += n
                                    buf = buf[buf.rfind(b"\n") + 1:]
                                served[0] += got
                    except OSError:
                        continue

            kicked = [0]

            def never_reads() -> None:  # sends requests and never reads a reply (dropped, comes back)
                line = b'{"request": "gains"}\n' * 256
                while not done.is_set():
                    try:
                        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
                            s.settimeout(1)
                            s.connect(str(sock))
                            while not done.is_set():
                                s.sendall(line)
                    except OSError:
                        kicked[0] += 1

            threads = [threading.Thread(target=flood, daemon=True) for _ in range(clients)]
            threads.append(threading.Thread(target=never_reads, daemon=True))
            for th in threads:
                th.start()
            for i in range(half_open):
                try:
                    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                    s.connect(str(sock))
                    if i % 2:
                        s.sendall(b'{"request": "sta')
                    holders.append(s)
                except OSError:
                    pass
            c0, o0 = _loop_counters(sock)
            t0 = time.monotonic()
            stop_lat: list[float] = []
            stop_fail = 0
            while time.monotonic() - t0 < phase_s:
                try:
                    with ControlClient(sock, timeout_s=10) as c:
                        c.request({"request": "move", "relative_m": 1e-6 if len(stop_lat) % 2 else -1e-6})
                        ts = time.monotonic()
                        r = c.request({"request": "stop"})
                        if r.get("ok"):
                            stop_lat.append(time.monotonic() - ts)
                        else:
                            stop_fail += 1
                except OSError:
                    stop_fail += 1
                time.sleep(0.2)
            c1, o1 = _loop_counters(sock)
            t1 = time.monotonic()
            done.set()
            for s in holders:
                s.close()
            stop_lat.sort()
            out["flood"] = {
                "missed_cycles_pct": 100.0 * (o1 - o0) / max(1, (c1 - c0) + (o1 - o0)),
                "watchdog_max_gap_s": notify.max_gap(t0, t1),
                "status_requests_served": served[0],
                "non_reader_disconnects": kicked[0],
                "stop_replies": len(stop_lat), "stop_failures": stop_fail,
                "stop_latency_p50_ms": 1e3 * stop_lat[len(stop_lat) // 2] if stop_lat else None,
                "stop_latency_max_ms": 1e3 * stop_lat[-1] if stop_lat else None,
            }
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(30)
            errlog.close()
            notify.sock.close()
        return out


def run(args: argparse.Namespace) -> dict[str, Any]:
    kinds = ("thread", "process") if args.isolation == "both" else (args.isolation,)
    res: dict[str, Any] = {"config": str(args.config), "phase_s": args.phase_s, "clients": args.clients,
                           "fifo": args.fifo,
                           "half_open": args.half_open, "cpus": os.cpu_count(),
                           "loadavg_1min_at_start": os.getloadavg()[0]}
    for i, kind in enumerate(kinds):
        tell(args, 2 * args.phase_s * i, 2 * args.phase_s * len(kinds),
             f"case {i + 1} of {len(kinds)}, {kind} isolation (2 phases of {args.phase_s:g} s)", span=2 * args.phase_s)
        res[kind] = _measure(Path(args.config), kind, args.phase_s, args.clients, args.half_open, args.fifo)
    res["loadavg_1min_at_end"] = os.getloadavg()[0]
    json.dumps(res)  # plain data only
    return res
