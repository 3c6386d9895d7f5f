"""Serial streaming benchmark: virtual interferometer (separate process) → :class:`SerialInterferometer`.

For each transport (pty, TCP ``socket://``) a child process runs a :class:`SimInterferometer` streaming in real
time at ``rate_hz``; this process reads with the real driver (``select`` + non-blocking ``read(4096)`` + the
pure parser). One-way latency = receive time − the frame's send timestamp; both are ``time.monotonic_ns()``
on the same host (CLOCK_MONOTONIC is system-wide), so no clock offset enters.

Used by ``stagectl bench io`` (``run_serial_bench``); standalone::

    python -c "from stagectl.bench.io_serial import run_serial_bench; print(run_serial_bench(1000, 10))"

The child is ``python -m stagectl.bench.io_serial --serve ...`` (ready line on stdout: JSON with ``url``;
it starts streaming on ``go`` from stdin, prints its counters as JSON when done and exits on ``quit``/EOF).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

__all__ = ["run_serial_bench", "bench_transport", "add_arguments", "run"]


class _StaticPlant:
    """A plant standing still at 1.234567 mm (the benchmark measures the link, not the physics)."""

    t_s = 0.0

    def measure(self) -> float:
        return 1.234567e-3


def _serve(transport: str, rate_hz: float, duration_s: float, baudrate: int | None, link_path: str | None) -> int:
    from stagectl.sim.interferometer import SimInterferometer, SimInterferometerConfig

    cfg = SimInterferometerConfig(transport=transport, rate_hz=rate_hz, baudrate=baudrate, link_path=link_path)
    with SimInterferometer(_StaticPlant(), cfg) as sim:
        print(json.dumps({"url": sim.url}), flush=True)
        if sys.stdin.readline().strip() != "go":
            return 1
        gc.collect()
        gc.freeze()
        sim.start()
        time.sleep(duration_s)  # benchmark: real time is the point
        sim.stop()
        print(json.dumps({"frames_sent": sim.frames_sent, "bytes_sent": sim.bytes_sent,
                          "frames_overrun": sim.frames_overrun, "seq": sim.seq}), flush=True)
        sys.stdin.readline()  # keep the link open until the reader has drained it
    return 0


def _pct(sorted_us: list[float], q: float) -> float:
    if not sorted_us:
        return float("nan")
    i = min(len(sorted_us) - 1, max(0, round(q / 100.0 * (len(sorted_us) - 1))))
    return sorted_us[i]


def bench_transport(transport: str, rate_hz: float, duration_s: float, baudrate: int | None = None) -> dict[str, Any]:
    """Stream for ``duration_s`` [s] at ``rate_hz`` [Hz] over one transport; return latency and loss figures."""
    from stagectl.drivers.interferometer import InterferometerConfig, SerialInterferometer

    tmpdir = tempfile.mkdtemp(prefix="stagectl-bench-ifm-")
    link = str(Path(tmpdir) / "ifm") if transport == "pty" else None
    cmd = [sys.executable, "-m", "stagectl.bench.io_serial", "--serve", "--transport", transport,
           "--rate-hz", repr(rate_hz), "--duration-s", repr(duration_s)]
    if baudrate:
        cmd += ["--baudrate", str(baudrate)]
    if link:
        cmd += ["--link-path", link]
    child = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        if child.stdout is None or child.stdin is None:
            raise RuntimeError("serial bench: no pipes to the simulator process")
        ready = json.loads(child.stdout.readline() or "{}")
        if "url" not in ready:
            raise RuntimeError(f"serial bench: simulator did not start (exit code {child.poll()})")
        lat_us: list[float] = []
        received = 0
        dut = SerialInterferometer(InterferometerConfig(url=ready["url"], baudrate=baudrate or 921600))
        with dut:
            dut.configure()
            gc.collect()
            gc.freeze()
            child.stdin.write("go\n")
            child.stdin.flush()
            end = time.monotonic() + duration_s + 0.5
            while time.monotonic() < end:
                frames = dut.read_frames(0.05)
                rx = dut.last_rx_ns
                for f in frames:
                    lat_us.append((rx - f.timestamp_ns) / 1e3)
                received += len(frames)
            sent = json.loads(child.stdout.readline() or "{}")
            # drain what is still in flight
            while True:
                frames = dut.read_frames(0.1)
                if not frames:
                    break
                rx = dut.last_rx_ns
                lat_us.extend((rx - f.timestamp_ns) / 1e3 for f in frames)
                received += len(frames)
            st = dut.stats
        gc.unfreeze()
        child.stdin.write("quit\n")
        child.stdin.flush()
        child.wait(timeout=10)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
        try:
            os.rmdir(tmpdir)
        except OSError:
            pass
    lat_us.sort()
    frames_sent = int(sent.get("frames_sent", 0))
    return {
        "transport": transport,
        "rate_hz": rate_hz,
        "duration_s": duration_s,
        "baudrate": baudrate,
        "frames_sent": frames_sent,
        "frames_received": received,
        "frames_lost": frames_sent - received,
        "frames_overrun_at_sender": int(sent.get("frames_overrun", 0)),
        "loss_pct": 100.0 * (frames_sent - received) / frames_sent if frames_sent else float("nan"),
        "sequence_gaps": st.sequence_gaps,
        "crc_errors": st.crc_errors,
        "bytes_discarded": st.bytes_discarded,
        "latency_us": {"p50": _pct(lat_us, 50), "p99": _pct(lat_us, 99), "max": lat_us[-1] if lat_us else float("nan")},
    }


def run_serial_bench(rate_hz: float, duration_s: float, transports: tuple[str, ...] = ("pty", "tcp"),
                     baudrate: int | None = None) -> dict[str, Any]:
    """Serial streaming benchmark at ``rate_hz`` [Hz] for ``duration_s`` [s] per transport.

    Returns ``{"rate_hz", "duration_s", "pty": {...}, "tcp": {...}}``; each transport entry holds
    ``frames_sent``, ``frames_received``, ``frames_lost``, ``loss_pct``, ``sequence_gaps``, ``crc_errors``,
    ``bytes_discarded`` and ``latency_us`` {p50, p99, max} (one-way, send timestamp → driver receive).
    ``baudrate`` [bit/s] paces the simulator as an 8N1 line (None: unpaced).
    """
    out: dict[str, Any] = {"rate_hz": rate_hz, "duration_s": duration_s}
    for t in transports:
        out[t] = bench_transport(t, rate_hz, duration_s, baudrate)
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rate-hz", type=float, action="append", help="stream rate(s) [Hz] (default 1000 and 5000)")
    parser.add_argument("--duration-s", type=float, default=10.0, help="seconds per case (default 10)")
    parser.add_argument("--baudrate", type=int, default=None, help="pace the simulator as an 8N1 line [bit/s]")


def run(args: argparse.Namespace) -> dict[str, Any]:
    rates = args.rate_hz or [1000.0, 5000.0]
    return {f"serial_{r:g}hz": run_serial_bench(r, args.duration_s, baudrate=args.baudrate) for r in rates}


def _main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m stagectl.bench.io_serial")
    p.add_argument("--serve", action="store_true", help="run the simulator side (child process)")
    p.add_argument("--transport", choices=("pty", "tcp"), default="pty")
    p.add_argument("--rate-hz", type=float, default=1000.0)
    p.add_argument("--duration-s", type=float, default=10.0)
    p.add_argument("--baudrate", type=int, default=None)
    p.add_argument("--link-path", default=None)
    a = p.parse_args(argv)
    if a.serve:
        return _serve(a.transport, a.rate_hz, a.duration_s, a.baudrate, a.link_path)
    print(json.dumps(run_serial_bench(a.rate_hz, a.duration_s, baudrate=a.baudrate), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
