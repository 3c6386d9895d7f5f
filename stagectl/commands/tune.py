"""``stagectl tune --config FILE [--out DIR] [--json] [--mass-kg M --bandwidth-hz F --period-s T ...]``.

Designs PID and observer gains from the moving mass and a target crossover frequency with python-control
(discrete ZOH plant at the loop period, plus the I/O delay in whole samples), prints gain/phase margins
and crossover frequency of the *configured* controller and of the *designed* one, and writes a Bode plot
(``tune_bode.png``) into ``--out``. See :mod:`stagectl.control.design` for the rule and the loop model.

Inputs: the application config (``stagectl.config.load_app_config``: ``loop.period_s``,
``controller.*``, ``controller.mass_kg`` or the simulated plant's mass, ``io.delay_cycles``); flags
override. Without ``--config`` the flags ``--mass-kg`` and ``--period-s`` are required.
Each loop is marked ``healthy`` when stable with phase margin >= 40 deg and gain margin >= 6 dB, else shown as
thin. Exit code 1 when the configured loop is unstable, 2 on bad input.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from stagectl.errors import ConfigError
from stagectl.outputs import prepare_out_dir

if TYPE_CHECKING:
    from stagectl.control.dob import DobConfig
    from stagectl.control.pid import PidConfig

# config and control.design (numpy, numba, python-control) are imported where a command runs, not at module
# level: `stagectl --help` imports every command module and must stay light.

#: margins below these are reported as thin (typical robustness targets for a motion loop)
HEALTHY_PHASE_MARGIN_DEG = 40.0
HEALTHY_GAIN_MARGIN_DB = 6.0


def _healthy(s: dict[str, Any]) -> bool:
    return bool(s["closed_loop_stable"] and s["phase_margin_deg"] >= HEALTHY_PHASE_MARGIN_DEG
                and s["gain_margin_db"] >= HEALTHY_GAIN_MARGIN_DB)


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("tune", help="design PID/observer gains from mass and bandwidth; margins and Bode plot")
    p.add_argument("--config", help="stagectl YAML (period, mass, current controller)")
    p.add_argument("--out", help="directory for tune_bode.png (default: no plot)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--mass-kg", type=float, help="moving mass [kg] (default: controller.mass_kg / plant mass)")
    p.add_argument("--bandwidth-hz", type=float,
                   help="target PID crossover [Hz] (default: 0.02/period, e.g. 20 Hz at 1 kHz)")
    p.add_argument("--dob-bandwidth-hz", type=float,
                   help="Q-filter DOB bandwidth [Hz] for the design (default: min(5 x crossover, 0.1/period))")
    p.add_argument("--period-s", type=float, help="control period [s] (default: loop.period_s)")
    p.add_argument("--delay-samples", type=int,
                   help="I/O delay in whole periods (default: io.delay_cycles for plant_io, else 1)")
    p.set_defaults(func=run)


def _load_inputs(args: argparse.Namespace) -> dict[str, Any]:
    from stagectl.config import IoKind, load_app_config
    from stagectl.control.controller import controller_mass

    out: dict[str, Any] = {"controller": None, "mass_kg": None, "period_s": None, "delay_samples": None}
    if args.config:
        cfg = load_app_config(args.config)
        ctl = cfg.controller
        out["controller"] = ctl
        out["period_s"] = cfg.loop.period_s
        if cfg.io.kind is IoKind.PLANT_IO:
            out["delay_samples"] = int(cfg.io.delay_cycles)
        mass = controller_mass(ctl, ctl.feedforward.model)
        if mass is None and cfg.sim is not None:
            mass = cfg.sim.plant.mass_kg
        out["mass_kg"] = mass
    for key, flag in (("mass_kg", args.mass_kg), ("period_s", args.period_s), ("delay_samples", args.delay_samples)):
        if flag is not None:
            out[key] = flag
    problems = []
    if out["mass_kg"] is None:
        problems.append("--mass-kg: required (no controller.mass_kg or plant mass in the config)")
    elif not (out["mass_kg"] > 0 and math.isfinite(out["mass_kg"])):
        problems.append(f"--mass-kg: must be > 0 kg (got {out['mass_kg']})")
    if out["period_s"] is None:
        problems.append("--period-s: required (no loop.period_s in the config)")
    elif not (out["period_s"] > 0 and math.isfinite(out["period_s"])):
        problems.append(f"--period-s: must be > 0 s (got {out['period_s']})")
    if out["delay_samples"] is None:
        out["delay_samples"] = 1
    if out["delay_samples"] < 0:
        problems.append(f"--delay-samples: must be >= 0 (got {out['delay_samples']})")
    bw = args.bandwidth_hz
    if bw is not None and not (bw > 0 and math.isfinite(bw)):
        problems.append(f"--bandwidth-hz: must be > 0 Hz (got {bw})")
    if out["period_s"] is not None and bw is not None and bw >= 0.5 / out["period_s"]:
        problems.append(f"--bandwidth-hz: {bw:g} Hz must be below the Nyquist frequency {0.5 / out['period_s']:g} Hz")
    dbw = args.dob_bandwidth_hz
    if dbw is not None and not (dbw > 0 and math.isfinite(dbw)):
        problems.append(f"--dob-bandwidth-hz: must be > 0 Hz (got {dbw})")
    if problems:
        raise ConfigError(problems)
    return out


def tune(args: argparse.Namespace) -> tuple[dict[str, Any], int]:
    """Compute the result dict (and exit code) without printing."""
    from stagectl.control import design

    inp = _load_inputs(args)
    if args.out:
        prepare_out_dir(args.out)
    m, T, nd = float(inp["mass_kg"]), float(inp["period_s"]), int(inp["delay_samples"])
    result: dict[str, Any] = {"mass_kg": m, "period_s": T, "delay_samples": nd}
    analyses = []
    exit_code = 0
    ctl = inp["controller"]
    if ctl is not None:
        dob = ctl.dob
        m_dob = dob.nominal_mass_kg if dob.nominal_mass_kg is not None else m
        K = None
        if dob.kind == "kalman":
            K, _ = design.kalman_gain_for_noise(m_dob, T, dob.measurement_noise_m, _kalman_q(m_dob, T, dob),
                                                use_control=True)
        loops = design.analyse_design(m, T, ctl.pid, nd, None if dob.kind == "none" else dob.bandwidth_hz,
                                      dob.command_delay_samples, dob_mass_kg=m_dob, dob_kind=dob.kind, kalman_k=K)
        conf: dict[str, Any] = {
            "pid": _pid_dict(ctl.pid),
            "dob": {"kind": dob.kind, "bandwidth_hz": dob.bandwidth_hz,
                    "command_delay_samples": dob.command_delay_samples, "nominal_mass_kg": m_dob},
            "loops": {a.name: {**a.summary(), "healthy": _healthy(a.summary())} for a in loops},
        }
        if K is not None:
            conf["dob"]["kalman_gain"] = [float(k) for k in K]
            conf["dob"]["observer_bandwidth_hz"] = design.observer_bandwidth_hz(K, m_dob, T)
        for a in loops:
            a.name = f"configured {a.name}"
        analyses += loops
        unstable = [a.name for a in loops if not a.stable]
        conf["stable"] = not unstable
        if unstable:
            exit_code = 1
        result["configured"] = conf
    bw = args.bandwidth_hz if args.bandwidth_hz is not None else 0.02 / T
    dbw = args.dob_bandwidth_hz if args.dob_bandwidth_hz is not None else min(5.0 * bw, 0.1 / T)
    pid = design.design_pid(m, bw, T, nd)
    loops = design.analyse_design(m, T, pid, nd, dbw, nd)
    for a in loops:
        a.name = f"designed {a.name}"
    analyses += loops
    result["designed"] = {
        "target_crossover_hz": bw,
        "pid": _pid_dict(pid),
        "dob": {"kind": "qfilter", "bandwidth_hz": dbw, "command_delay_samples": nd},
        "loops": {a.name.removeprefix("designed "): {**a.summary(), "healthy": _healthy(a.summary())} for a in loops},
        "yaml": _yaml_snippet(m, pid, dbw, nd),
    }
    if args.out:
        png = Path(args.out) / "tune_bode.png"
        design.bode_png(analyses, str(png), f"open loop at the plant input: m = {m:g} kg, T = {T * 1e3:g} ms, "
                        f"{nd} sample(s) I/O delay")
        result["bode_png"] = str(png)
    result["exit_code"] = exit_code
    return result, exit_code


def _kalman_q(m: float, T: float, dob: DobConfig) -> float:
    if dob.disturbance_noise_n_sqrt_s is not None:
        return float(dob.disturbance_noise_n_sqrt_s)
    from stagectl.control import design

    return design.kalman_noise_for_bandwidth(m, T, dob.bandwidth_hz, dob.measurement_noise_m, use_control=True)


def _pid_dict(p: PidConfig) -> dict[str, float]:
    return {"kp_n_m": p.kp_n_m, "ki_n_m_s": p.ki_n_m_s, "kd_n_s_m": p.kd_n_s_m,
            "derivative_cutoff_hz": p.derivative_cutoff_hz}


def _yaml_snippet(m: float, pid: PidConfig, dbw: float, nd: int) -> str:
    return (
        "controller:\n"
        f"  mass_kg: {m:.6g}\n"
        f"  pid: {{kp_n_m: {pid.kp_n_m:.4g}, ki_n_m_s: {pid.ki_n_m_s:.4g}, kd_n_s_m: {pid.kd_n_s_m:.4g}, "
        f"derivative_cutoff_hz: {pid.derivative_cutoff_hz:.4g}}}\n"
        f"  dob: {{kind: qfilter, bandwidth_hz: {dbw:.4g}, command_delay_samples: {nd}}}\n"
    )


def _fmt_loop(name: str, s: dict[str, Any]) -> str:
    gm = s["gain_margin_db"]
    gm_s = "inf" if math.isinf(gm) else f"{gm:.1f} dB"
    if not s["closed_loop_stable"]:
        st = "   ** UNSTABLE **"
    elif not _healthy(s):
        st = f"   (thin: below PM {HEALTHY_PHASE_MARGIN_DEG:g} deg / GM {HEALTHY_GAIN_MARGIN_DB:g} dB)"
    else:
        st = ""
    return (f"  {name:<10s} crossover {s['crossover_hz']:7.2f} Hz   phase margin {s['phase_margin_deg']:6.1f} deg   "
            f"gain margin {gm_s:>8s} (at {s['phase_crossover_hz']:.1f} Hz){st}")


def run(args: argparse.Namespace) -> int:
    result, code = tune(args)
    if args.json:
        json.dump(result, sys.stdout, indent=2, default=float)
        sys.stdout.write("\n")
        return code
    print(f"plant: m = {result['mass_kg']:g} kg, period {result['period_s'] * 1e3:g} ms, "
          f"I/O delay {result['delay_samples']} sample(s)")
    if "configured" in result:
        c = result["configured"]
        p = c["pid"]
        print(f"configured: Kp {p['kp_n_m']:.4g} N/m, Ki {p['ki_n_m_s']:.4g} N/(m s), Kd {p['kd_n_s_m']:.4g} N s/m, "
              f"D cut-off {p['derivative_cutoff_hz']:g} Hz; DOB {c['dob']['kind']} {c['dob']['bandwidth_hz']:g} Hz "
              f"(command delay {c['dob']['command_delay_samples']})")
        for name, s in c["loops"].items():
            print(_fmt_loop(name, s))
        if "kalman_gain" in c["dob"]:
            kg = ", ".join(f"{k:.4g}" for k in c["dob"]["kalman_gain"])
            print(f"  kalman filter gain [{kg}] (x, v, d), observer bandwidth "
                  f"{c['dob']['observer_bandwidth_hz']:.1f} Hz")
    d = result["designed"]
    p = d["pid"]
    print(f"designed for a {d['target_crossover_hz']:g} Hz crossover: Kp {p['kp_n_m']:.4g} N/m, "
          f"Ki {p['ki_n_m_s']:.4g} N/(m s), Kd {p['kd_n_s_m']:.4g} N s/m, D cut-off {p['derivative_cutoff_hz']:g} Hz; "
          f"DOB qfilter {d['dob']['bandwidth_hz']:g} Hz")
    for name, s in d["loops"].items():
        print(_fmt_loop(name, s))
    print("suggested YAML:")
    print("".join(f"  {line}\n" for line in d["yaml"].splitlines()), end="")
    if "bode_png" in result:
        print(f"Bode plot: {result['bode_png']}")
    if code:
        print("stagectl: warning: the configured closed loop is UNSTABLE", file=sys.stderr)
    return code
