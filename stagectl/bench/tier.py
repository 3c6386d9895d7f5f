"""``stagectl bench startup --switch``: could the loop's first cycles run without numba? (issue 14)

A *tiered* start would run the first control cycles on plain-Python kernels (same state layout as the
compiled ones) while numba is imported and the compiled kernels are compiled or loaded, then switch to them
with the state carried over. This module measures what that would cost the loop, each case in a fresh
interpreter (a real subprocess that has not imported numba) running a 1 kHz loop on the system-wide
``CLOCK_MONOTONIC`` with absolute-deadline sleeps (``stagectl.clock.MonotonicClock``, as the real loop):

* **path** ``ff``: per cycle one GMS feed-forward step along a reference and a PD law (what the loop computes
  on real hardware: the drive is the plant); ``plant``: the same plus the embedded simulated plant's cycle
  (``sim.plant``'s per-cycle step: ``period / substep_s`` sub-steps of rigid body + GMS);
* **tier** ``plain``: the plain kernels below throughout; ``compiled``: numba's kernels, loaded (warm cache)
  before the loop's first cycle, i.e. today's start; ``switch``: plain kernels from the first cycle while a
  background thread imports ``stagectl.friction``/``stagectl.sim.plant`` (numba) and compiles (``cold``: empty
  cache) or loads (``warm``) the GMS step and the plant's cycle kernel; at the next cycle the loop carries the
  states over (lists → arrays, same layout) and runs the compiled kernels.

Reported per case: wake-up lateness of every cycle (worst, p99, cycles later than one period), the cycle's own
cost (p50, p99), and for ``switch`` when the compiled tier took over (cycles and seconds after the loop's start)
and the worst lateness from the loop's start to 100 cycles after the switch, against the worst lateness of the
``plain`` and ``compiled`` runs over the same number of cycles in the same bench.

The plain kernels are the plain twins (``stagectl.jit.plain``: the kernel's own source run as Python) of
``friction.gms._kstep`` and ``sim.plant._make_cycle``'s ``cycle``, on Python lists: ``tests/loop/test_bench_tier.py``
checks them against the compiled kernels (equal within 1e-12 relative; in practice bit-identical). Importing this
module imports no numba.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from stagectl.errors import StageError

from stagectl.friction import gms
from stagectl.jit import plain
from stagectl.sim import plant as _plant

#: sim.plant's plant-state layout (``ps``): t, x, v, friction, F_other, applied u, stuck, work in/friction/other
PS_T, PS_X, PS_V, PS_FF, PS_FO, PS_UA, PS_STUCK, PS_WIN, PS_WF, PS_WO = (
    _plant._T, _plant._X, _plant._V, _plant._FF, _plant._FO, _plant._UA, _plant._STUCK, _plant._WIN, _plant._WF,
    _plant._WO)

#: ``friction.gms._kstep`` as plain Python (its plain twin, :func:`stagectl.jit.plain`): advance ``state``
#: (``[F_1..F_N, mode_1..mode_N]``, a list) in place over ``dx`` [m] at ``v`` [m/s] during ``dt`` [s]; returns the
#: friction force [N]. The same twin a real stage's feed-forward runs (``FrictionModel.plain_stepper``).
gms_step_plain = plain(gms._kstep)

#: ``sim.plant``'s per-cycle step of a plain plant with GMS friction as plain Python
#: (:func:`stagectl.sim.plant.plain_cycle`): ``(kp, fs, ps, inv_m, fo_c, u, dt, nsub)``, ``u`` [N] held for ``dt``
#: [s] in ``nsub`` sub-steps, plant state ``ps`` (layout ``PS_*``) and friction state ``fs`` advanced in place.
plant_cycle_plain = _plant.plain_cycle(gms._kstep)


# The child: a 1 kHz loop in the main thread; argv[1] is a JSON job (see _case).
_CHILD = r"""
import json, math, sys, threading, time
T0 = time.monotonic()
job = json.loads(sys.argv[1])
from stagectl.bench.tier import gms_step_plain, plant_cycle_plain
from stagectl.clock import MonotonicClock
if job["switch_interval_s"]:
    sys.setswitchinterval(job["switch_interval_s"])
period = job["period_s"]; nsub = job["nsub"]; p = job["p"]; inv_m = job["inv_m"]; fo_c = job["fo_c"]
plant = job["path"] == "plant"; tier = job["tier"]
ff_state = [0.0] * job["n_states"]; pl_state = [0.0] * job["n_states"]; ps = [0.0] * 10
ready = {}
done = {}

def load():
    t = time.monotonic()
    c0 = time.thread_time()  # this thread's CPU time: the parts' cost without the loop thread's
    import numpy as np
    import numba
    c1 = time.thread_time()
    from stagectl.friction import build
    from stagectl.sim.plant import cycle_for
    c2 = time.thread_time()
    model = build(job["spec"])
    model.step(model.initial_state(), 1e-9, 1e-6, period)      # compiles or loads the GMS step (as the FF does)
    c3 = time.thread_time()
    kstep = type(model)._kstep
    cyc = cycle_for(kstep)
    cyc(np.asarray(p), np.zeros(job["n_states"]), np.zeros(10), inv_m, fo_c, 0.0, period, nsub)   # and the cycle
    c4 = time.thread_time()
    done["load_s"] = time.monotonic() - t
    done["cpu_s"] = {"import_numba": c1 - c0, "import_friction_and_plant": c2 - c1,
                     "gms_step_first_call": c3 - c2, "plant_cycle_first_call": c4 - c3}
    ready.update(np=np, kstep=kstep, cycle=cyc)

if tier == "compiled":
    load()
elif tier == "switch":
    threading.Thread(target=load, daemon=True).start()
ff_fn = gms_step_plain; cyc_fn = plant_cycle_plain; kp = p; fs = pl_state; fsff = ff_state; on = "plain"
if tier == "compiled":
    np = ready["np"]
    kp = np.asarray(p); fsff = np.asarray(ff_state); fs = np.asarray(pl_state); ps = np.asarray(ps)
    ff_fn = ready["kstep"]; cyc_fn = ready["cycle"]; on = "compiled"
clock = MonotonicClock()
n = job["cycles"]; late = []; cost = []; xs = []; sw = None; sw_t = None
amp = 5e-5; w = 2 * math.pi * 1.0
xr = 0.0; u = 0.0
t_start = clock.now() + period; nxt = t_start; k = 0
while k < n or (tier == "switch" and (sw is None or k < sw + 100) and clock.now() < t_start + 120.0):
    clock.sleep_until(nxt)
    wake = clock.now()
    late.append(wake - nxt)
    if on == "plain" and ready:
        np = ready["np"]
        kp = np.asarray(p); fsff = np.asarray(fsff, dtype=np.float64); fs = np.asarray(fs, dtype=np.float64)
        ps = np.asarray(ps, dtype=np.float64); ff_fn = ready["kstep"]; cyc_fn = ready["cycle"]; on = "compiled"
        sw = k
        sw_t = wake - t_start
    t = k * period
    xr1 = amp * (1.0 - math.cos(w * (t + period)))
    dxr = xr1 - xr
    xr = xr1
    f = ff_fn(kp, fsff, dxr, dxr / period, period)
    if plant:
        x = ps[1]; v = ps[2]
        u = f + 4.0e4 * (xr - x) - 400.0 * v
        u = 10.0 if u > 10.0 else (-10.0 if u < -10.0 else u)
        cyc_fn(kp, fs, ps, inv_m, fo_c, u, period, nsub)
    cost.append(clock.now() - wake)
    xs.append(float(ps[1]) if plant else f)
    k += 1
    nxt += period
    now = clock.now()
    if now > nxt + period:  # more than a period behind: skip the missed slots, as the loop does
        nxt += math.floor((now - nxt) / period) * period
res = {"late_s": late, "cost_s": cost, "switch_cycle": sw, "switch_t_s": sw_t, "load_s": done.get("load_s"),
       "load_cpu_s": done.get("cpu_s"),
       "out": xs, "cpu_s": time.process_time(), "loop_start_s": t_start - T0}
json.dump(res, open(sys.argv[2], "w"))
"""


def _pct(xs: Sequence[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, int(q * len(s)))] if s else math.nan


def _case(python: str, job: dict[str, Any], cache: Path) -> dict[str, Any]:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    with tempfile.TemporaryDirectory(prefix="stagectl-tier-") as tmp:
        outp = Path(tmp) / "out.json"
        try:
            r = subprocess.run([python, "-c", _CHILD, json.dumps(job), str(outp)], check=False, env=env,
                               capture_output=True, text=True, timeout=600)
        except subprocess.TimeoutExpired:
            raise StageError(f"bench startup --switch: the {job['path']}/{job['tier']} run took over 600 s "
                             "(the machine is too loaded for this benchmark)") from None
        if r.returncode != 0 or not outp.exists():
            last = (r.stderr.strip().splitlines() or ["no output"])[-1][:300]
            raise StageError(f"bench startup --switch: the {job['path']}/{job['tier']} run failed: {last}")
        d = json.loads(outp.read_text())
    late = d["late_s"]
    cost = d["cost_s"]
    period = job["period_s"]
    out: dict[str, Any] = {
        "cycles": len(late),
        "late_max_us": max(late) * 1e6, "late_p99_us": _pct(late, 0.99) * 1e6,
        "late_over_period": sum(1 for x in late if x > period),
        "cost_p50_us": _pct(cost, 0.5) * 1e6, "cost_p99_us": _pct(cost, 0.99) * 1e6,
        "process_cpu_s": d["cpu_s"],
        "first_cycle_after_s": d["loop_start_s"],  # from the child's first line (plain: no numba imported)
    }
    sw = d["switch_cycle"]
    if d["load_cpu_s"]:
        out["load_thread_cpu_s"] = d["load_cpu_s"]  # the loading thread's CPU time per part
    if job["tier"] == "switch":
        out["switch_cycle"] = sw
        out["load_s"] = d["load_s"]
        if sw is not None:
            span = late[: sw + 100]
            out["switch_after_s"] = d["switch_t_s"]  # from the loop's first cycle (slots skipped when late)
            out["window_cycles"] = len(span)
            out["window_late_max_us"] = max(span) * 1e6
            out["window_late_over_period"] = sum(1 for x in span if x > period)
            out["plain_cost_p50_us"] = _pct(cost[:sw], 0.5) * 1e6 if sw else math.nan
            out["compiled_cost_p50_us"] = _pct(cost[sw:], 0.5) * 1e6
    out["_late"] = late
    out["_out"] = d["out"]  # per cycle: x [m] (path plant) or the feed-forward force [N] (path ff)
    return out


def job_for(config: Any, cycles: int, switch_interval_s: float | None = None) -> dict[str, Any] | None:
    """The child's job for ``config`` (an ``AppConfig``): its simulated plant's GMS friction, mass, sub-steps and
    the loop period; ``None`` when it has no simulated plant with GMS friction (the plain tier transcribes GMS
    only)."""
    plant_cfg = getattr(getattr(config, "sim", None), "plant", None)
    if plant_cfg is None or getattr(plant_cfg.friction, "tag", "") != "gms":
        return None
    fr = plant_cfg.friction
    ep = plant_cfg.effects.packed()
    period = float(config.loop.period_s)
    return {"spec": fr.spec(), "p": [float(x) for x in fr.kernel().p], "n_states": int(fr.n_states),
            "inv_m": 1.0 / float(plant_cfg.mass_kg), "fo_c": float(ep[7]), "period_s": period,
            "nsub": max(1, math.ceil(period / float(plant_cfg.substep_s) - 1e-9)), "cycles": int(cycles),
            "switch_interval_s": switch_interval_s}


def run_switch(config: Any, cycles: int, switch_interval_s: float | None, tell: Any) -> dict[str, Any]:
    """The tiered-start experiment for ``config`` (an ``AppConfig`` with a GMS ``sim.plant``): for both paths,
    runs ``switch`` (cold), ``switch`` (warm), ``plain``, ``compiled``; ``cycles`` cycles each (a switch run goes on
    to 100 cycles past its switch; the plain and compiled runs then as long as the longer switch window). Returns
    the figures, or ``{"skipped": reason}``."""
    job0 = job_for(config, cycles, switch_interval_s)
    if job0 is None:
        return {"skipped": "needs a config with a simulated plant with GMS friction (the plain tier transcribes GMS)"}
    period = float(job0["period_s"])
    res: dict[str, Any] = {"period_s": period, "nsub": job0["nsub"], "cycles": int(cycles),
                           "switch_interval_s": switch_interval_s if switch_interval_s else sys.getswitchinterval(),
                           "loadavg_before": list(os.getloadavg())}
    # the switch runs first (cold fills the path's private cache, warm reads it), then the plain and the compiled
    # run (warm) for at least as many cycles as a switch run's window, so that both compare over the same count
    order = [("switch", False), ("switch", True), ("plain", False), ("compiled", True)]
    total = 2 * len(order)
    i = 0
    for path in ("ff", "plant"):
        with tempfile.TemporaryDirectory(prefix="stagectl-numba-") as cache:
            cases: dict[str, Any] = {}
            for tier, warm in order:
                name = tier if tier != "switch" else f"switch_{'warm' if warm else 'cold'}"
                tell(i, total, f"{path}: {name}")
                n = max([int(cycles)] + [int(c.get("window_cycles") or 0) for c in cases.values()])
                cases[name] = _case(sys.executable, dict(job0, path=path, tier=tier, cycles=n), Path(cache))
                i += 1
        for name in ("switch_cold", "switch_warm"):
            c = cases[name]
            w = c.get("window_cycles")
            if w:
                for ref in ("plain", "compiled"):
                    c[f"{ref}_late_max_us_same_cycles"] = max(cases[ref]["_late"][:w]) * 1e6
        for c in cases.values():
            del c["_late"], c["_out"]
        res[path] = cases
    res["loadavg_after"] = list(os.getloadavg())
    return res


__all__ = ["gms_step_plain", "job_for", "plant_cycle_plain", "run_switch"]
