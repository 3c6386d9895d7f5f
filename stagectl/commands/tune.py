"""``stagectl tune --config FILE [--out DIR] [--json] [--mass-kg M --bandwidth-hz F --period-s T ...]``.

Designs PID and observer gains from the moving mass and a target crossover frequency with python-control
(discrete ZOH plant at the loop period, plus the I/O delay in whole samples), prints gain/phase margins
and crossover frequency of the *configured* controller and of the *designed* one, and writes a Bode plot
(``tune_bode.png``) into ``--out``. See :mod:`stagectl.control.design` for the rule and the loop model.

Inputs: the application config (``stagectl.config.load_app_config``: ``loop.period_s``,
``controller.*``, ``controller.mass_kg`` or the simulated plant's mass, ``controller.design_delay_samples`` or
``io.delay_cycles``); flags override. Without ``--config`` the flags ``--mass-kg`` and ``--period-s`` are required.
With a Q-filter observer and a known pre-sliding stiffness the configured *rest* loop (the PID's integrator
held if ``hold_integrator_at_rest``, the observer's own nominal mass, the rest spring of
``rest_stiffness_fraction``, and the rest gains ``rest_kd_fraction``, ``rest_dob_bandwidth_fraction``,
``rest_spring_section_count``, the rest integral of ``rest_integral_hz``) is analysed too, on the stage stuck in
pre-sliding and on the free mass (``configured.rest`` in the JSON; the free mass with the spring a stage not seen
held gets, min(k_v, ``rest_spring_unconfirmed_kp_fraction``·K_p), :func:`_free_spring`), and what it relies on is
stated when it is below the floor. The spring follows the feed-forward's adapted scale θ (capped at 1), so the rest loop is reported worst case over the θ range
the configuration allows (1 − ``adapt_max_change_fraction`` .. 1 when the adaptation or the learning from moves
is on).
Each loop is marked ``healthy`` when stable with phase margin >= 40 deg and gain margin >= 8 dB (delay
included), else shown as thin.

Advice is checked before it is given. Without ``--bandwidth-hz`` the crossover is searched downward from
0.02/period until the PID + observer loop is healthy. The design is then run, in simulated time, on the
config's simulated plant (``sim:``) through 10 µm steps with 0.5 s holds
(:func:`stagectl.bench.control.steps_check`), with the configured friction model and with a 20 %-wrong one.
The suggestion's rest loop (:func:`_suggested_rest`): the configured rest gains when both rest loops, stuck and free,
meet the floor with the designed PID and observer; otherwise the rest gains of
:func:`stagectl.control.design.design_rest_gains` (the floor on both, for this delay, mass and stiffness), written into
the suggested YAML and used in the steps check below.
It is **refused** (no suggested YAML, exit 1, the reasons printed) when it is unstable, its margins are thin,
or it hunts in a limit cycle, is still more than 1 µm off in the second half of a hold, or faults on the steps. Otherwise it is offered with a confidence: ``high`` (every
step settles to ±10 nm, both models), ``medium`` (no limit cycle, but not every step settles within the hold),
``low`` (margins only: no ``sim:`` plant to check on). ``high`` becomes ``medium`` when the configured rest spring,
which the suggestion keeps, does worse than none in the simulated checks on stages that are not held (a free mass,
the plant at ×0.2 of its pre-sliding stiffness: an excursion above :data:`SPRING_WORSE_RATIO` × the spring-less one),
and the reason names those figures (``rest_spring_worse``); so it does when the configured rest loop on a free
mass (``rest/free``) of the suggestion misses the floor (no rest gains meet it on both stages): the gains rely on
friction holding the stage (``rest_free_thin``). Exit code 1 also when the configured loop is unstable
(moving, or at standstill on the stuck stage anywhere in the θ range), 2 on bad input.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from stagectl.commands.args import number
from stagectl.errors import ConfigError
from stagectl.outputs import prepare_out_dir

if TYPE_CHECKING:
    from stagectl.control.dob import DobConfig
    from stagectl.control.pid import PidConfig

# config and control.design (numpy, numba, python-control) are imported where a command runs, not at module
# level: `stagectl --help` imports every command module and must stay light.

#: margins below these are reported as thin (typical robustness targets for a motion loop)
HEALTHY_PHASE_MARGIN_DEG = 40.0
HEALTHY_GAIN_MARGIN_DB = 8.0
#: hold after each 10 µm step of the design check [s]
CHECK_HOLD_S = 0.5
#: an error above this in the second half of a hold is a drift, not a settle: the design is refused [m]
#: (10 % of the step)
MAX_HOLD_EXCURSION_M = 1e-6
#: values of the feed-forward scale θ at which the rest loop is analysed over its configured range
THETA_POINTS = 5
#: the rest spring on a stage that is not held: lock-step 10 µm steps (CHECK_HOLD_S holds) on the config's plant with
#: its pre-sliding stiffness (and micro-damping) at these fractions of its own (below the shipped designs' stiffness
#: margins, 0.47 and 0.85), the spring on and off
NOT_HELD_STIFFNESS_FRACTIONS = (0.2,)
#: ... and on a free mass (no friction), started this far off the reference at standstill [m]
FREE_MASS_KICKS_M = (1e-9, 2e-8, 1e-7)
#: in those checks the spring does worse than none when an excursion with it exceeds the one without by this factor
SPRING_WORSE_RATIO = 1.2


#: heaviest moving mass [kg] the loop design resolves numerically (python-control transfer functions)
MAX_DESIGN_MASS_KG = 1e5

def _healthy(s: dict[str, Any]) -> bool:
    return bool(s["closed_loop_stable"] and s["phase_margin_deg"] >= HEALTHY_PHASE_MARGIN_DEG
                and s["gain_margin_db"] >= HEALTHY_GAIN_MARGIN_DB)


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("tune", help="design PID/observer gains from mass and bandwidth; margins and Bode plot")
    p.add_argument("--config", help="stagectl YAML (period, mass, current controller)")
    p.add_argument("--out", help="directory for tune_bode.png (default: no plot)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--mass-kg", type=number("kg"), help="moving mass [kg] (default: controller.mass_kg / plant mass)")
    p.add_argument("--bandwidth-hz", type=number("Hz"),
                   help="target PID crossover [Hz] (default: 0.02/period, e.g. 20 Hz at 1 kHz)")
    p.add_argument("--dob-bandwidth-hz", type=number("Hz"),
                   help="Q-filter DOB bandwidth [Hz] for the design (default: min(5 x crossover, 0.1/period))")
    p.add_argument("--period-s", type=number("s"), help="control period [s] (default: loop.period_s)")
    p.add_argument("--delay-samples", type=int,
                   help="I/O delay in whole periods (default: controller.design_delay_samples, else "
                   "io.delay_cycles for plant_io, else 1)")
    p.set_defaults(func=run)


def _bounds(cls: type, name: str) -> tuple[float, float]:
    """The [ge, le] bounds of the configuration key ``name`` of the schema dataclass ``cls``."""
    meta = next(f.metadata for f in dataclasses.fields(cls) if f.name == name)
    return float(meta["ge"]), float(meta["le"])


def _load_inputs(args: argparse.Namespace) -> dict[str, Any]:
    from stagectl.config import IoKind, load_app_config
    from stagectl.control.controller import ControllerConfig, controller_mass
    from stagectl.runtime.config import LoopConfig

    out: dict[str, Any] = {"controller": None, "mass_kg": None, "period_s": None, "delay_samples": None,
                           "app": None}
    if args.config:
        cfg = load_app_config(args.config)
        out["app"] = cfg
        ctl = cfg.controller
        out["controller"] = ctl
        out["period_s"] = cfg.loop.period_s
        if ctl.design_delay_samples is not None:
            out["delay_samples"] = int(ctl.design_delay_samples)
        elif cfg.io.kind is IoKind.PLANT_IO:
            out["delay_samples"] = int(cfg.io.delay_cycles)
        mass = controller_mass(ctl, ctl.feedforward.model)
        if mass is None and cfg.sim is not None:
            mass = cfg.sim.plant.mass_kg
        out["mass_kg"] = mass
    for key, flag in (("mass_kg", args.mass_kg), ("period_s", args.period_s), ("delay_samples", args.delay_samples)):
        if flag is not None:
            out[key] = flag
    problems = []
    # the bounds a configuration takes (loop.period_s, controller.design_delay_samples): outside them the
    # analysis divides by zero (a period of 1 ns) or allocates a state space of the delay's size (10^5 cycles)
    t_lo, t_hi = _bounds(LoopConfig, "period_s")
    d_lo, d_hi = _bounds(ControllerConfig, "design_delay_samples")
    if out["mass_kg"] is None:
        problems.append("--mass-kg: required (no controller.mass_kg or plant mass in the config)")
    elif not (out["mass_kg"] > 0 and math.isfinite(out["mass_kg"])):
        problems.append(f"--mass-kg: must be > 0 kg (got {out['mass_kg']})")
    elif out["mass_kg"] > MAX_DESIGN_MASS_KG:
        # the loop's transfer functions lose the plant's 1/(m s²) in their coefficients: 1e7 kg bent Kp by 0.1 %,
        # 1e8 kg failed the design's own check and 1e12 kg divided by zero (exit 70)
        src = "--mass-kg" if args.mass_kg is not None else "controller.mass_kg (or the plant's mass)"
        problems.append(f"{src}: {out['mass_kg']:g} kg is above the {MAX_DESIGN_MASS_KG:g} kg the design resolves "
                        "(a value in g written as kg?)")
    if out["period_s"] is None:
        problems.append("--period-s: required (no loop.period_s in the config)")
    elif not t_lo <= out["period_s"] <= t_hi:
        problems.append(f"--period-s: must be within [{t_lo:g}, {t_hi:g}] s, as loop.period_s (got {out['period_s']:g})")
    # the Nyquist checks below divide by the period: only a period inside its bounds (0 divided by zero)
    nyquist_hz = 0.5 / out["period_s"] if out["period_s"] is not None and t_lo <= out["period_s"] <= t_hi else None
    if out["delay_samples"] is None:
        out["delay_samples"] = 1
    if not d_lo <= out["delay_samples"] <= d_hi:
        problems.append(f"--delay-samples: must be within [{d_lo:g}, {d_hi:g}] periods, as "
                        f"controller.design_delay_samples (got {out['delay_samples']})")
    bw = args.bandwidth_hz
    if bw is not None and not (bw > 0 and math.isfinite(bw)):
        problems.append(f"--bandwidth-hz: must be > 0 Hz (got {bw})")
    elif nyquist_hz is not None and bw is not None and bw >= nyquist_hz:
        problems.append(f"--bandwidth-hz: {bw:g} Hz must be below the Nyquist frequency {nyquist_hz:g} Hz")
    dbw = args.dob_bandwidth_hz
    if dbw is not None and not (dbw > 0 and math.isfinite(dbw)):
        problems.append(f"--dob-bandwidth-hz: must be > 0 Hz (got {dbw})")
    elif nyquist_hz is not None and dbw is not None and dbw >= nyquist_hz:
        problems.append(f"--dob-bandwidth-hz: {dbw:g} Hz must be below the Nyquist frequency {nyquist_hz:g} Hz")
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
                                      dob.command_delay_samples, dob_mass_kg=m_dob, dob_kind=dob.kind, kalman_k=K,
                                      velocity_cutoff_hz=ctl.velocity_cutoff_hz)
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
        rest = _rest_loops(inp["app"], ctl, m, m_dob, T, nd)
        if rest is not None:
            conf["rest"] = rest
            if rest["stuck_unstable_at_theta"]:  # the configured controller oscillates at standstill there
                exit_code = 1
        result["configured"] = conf
    bw, dbw, pid, loops, searched = _design(args, m, T, nd)
    for a in loops:
        a.name = f"designed {a.name}"
    analyses += loops
    summaries = {a.name.removeprefix("designed "): {**a.summary(), "healthy": _healthy(a.summary())} for a in loops}
    healthy = all(v["healthy"] for v in summaries.values())
    rest = result.get("configured", {}).get("rest")
    rest_d = _suggested_rest(inp["app"], ctl, rest, pid, dbw, nd, m, T) if rest is not None and healthy else None
    rest_gains = rest_d["gains"] if rest_d is not None and rest_d["source"] == "designed" else None
    check = _check(inp["app"], pid, dbw, nd, rest_gains) if inp["app"] is not None and healthy else None
    verdict = _verdict(summaries, check)
    result["designed"] = d_out = {
        "target_crossover_hz": bw,
        "searched_crossover_hz": searched,
        "pid": _pid_dict(pid),
        "dob": {"kind": "qfilter", "bandwidth_hz": dbw, "command_delay_samples": nd},
        "loops": summaries,
        "rest": rest_d,
        "check": check,
        **verdict,
        "yaml": None if verdict["refused"] else _yaml_snippet(m, pid, dbw, nd, rest_gains),
    }
    worse = _spring_worse(rest)
    thin = _free_rest_thin(rest_d)
    # the suggestion keeps the configured rest spring (and the configured rest gains unless it designs its own): what
    # they do on stages that are not held (worse than no spring; thin margins on a free stage) caps its confidence
    for key, value, why in (
            ("rest_spring_worse", worse, (f"the rest spring these gains keep does worse than none on stages that "
                                          f"are not held (simulated with the configured gains: {'; '.join(worse)})")),
            ("rest_free_thin", thin, (f"the suggestion's rest loop misses the floor on a free stage ({thin}) and no "
                                      f"rest gains meet it on both stages: it relies on friction holding the stage "
                                      f"at standstill"))):
        if value and not verdict["refused"]:
            verdict[key] = value
            if verdict["confidence"] == "high":
                verdict["confidence"] = "medium"
            verdict["confidence_reason"] += "; " + why
            d_out.update(verdict)
    if verdict["refused"]:
        exit_code = 1
    if args.out:
        png = Path(args.out) / "tune_bode.png"
        design.bode_png(analyses, str(png), f"open loop at the plant input: m = {m:g} kg, T = {T * 1e3:g} ms, "
                        f"{nd} sample(s) I/O delay")
        result["bode_png"] = str(png)
    result["exit_code"] = exit_code
    return result, exit_code


def _suggested_rest_lines(rd: dict[str, Any] | None) -> list[str]:
    """The suggestion's rest loop (:func:`_suggested_rest`) as printed lines."""
    if rd is None:
        return []
    g = rd["gains"]
    gains = (f"rest_kd_fraction {g['kd_fraction']:g}, rest_dob_bandwidth_fraction {g['dob_bandwidth_fraction']:g}, "
             f"rest_spring_section_count {int(g['spring_sections'])}")
    floor = f"PM {HEALTHY_PHASE_MARGIN_DEG:g} deg / GM {HEALTHY_GAIN_MARGIN_DB:g} dB"
    if rd["source"] == "designed":
        was = "; ".join(f"{k} PM {v['phase_margin_deg']:.1f} deg, GM {v['gain_margin_db']:.1f} dB"
                        for k, v in rd["configured_loops"].items())
        head = (f"at standstill: the configured rest gains miss the {floor} floor with these gains ({was}); "
                f"designed for this delay, mass and stiffness on the stuck stage and the free mass: {gains}")
    elif rd["healthy"]:
        head = f"at standstill: the configured rest gains ({gains}) meet the {floor} floor on both stages"
    else:
        head = f"at standstill: no rest gains meet the {floor} floor on both stages; keeps the configured ({gains})"
    return [head] + [_fmt_loop(name, s).strip() for name, s in rd["loops"].items()]


def _free_rest_thin(rest: dict[str, Any] | None) -> str:
    """A rest loop's figure on a free mass (``rest/free`` of :func:`_rest_loops` / :func:`_suggested_rest`, worst over θ) when it misses
    the PM/GM floor, as "PM x deg, GM y dB" ("unstable" when it is); "" when it meets it or was not analysed."""
    loops = (rest or {}).get("loops") or {}
    s = next((v for k, v in loops.items() if k.endswith("free")), None)
    if s is None or s.get("healthy", True):
        return ""
    if not s.get("closed_loop_stable", True):
        return "unstable"
    return f"PM {s['phase_margin_deg']:.1f} deg, GM {s['gain_margin_db']:.1f} dB"


def _spring_worse(rest: dict[str, Any] | None) -> list[str]:
    """Where the rest checks of :func:`_rest_loops` (free mass, plant stiffness × :data:`NOT_HELD_STIFFNESS_FRACTIONS`)
    found the spring worse than none: a largest excursion (per start offset, per step's hold) above
    :data:`SPRING_WORSE_RATIO` × the one without it. One phrase per check, with the figures; [] when none (or no
    check ran)."""
    if not rest:
        return []
    out: list[str] = []
    fm = rest.get("free_mass_check") or []
    bad = [r for r in fm if r["max_excursion_m"] > SPRING_WORSE_RATIO * r["no_spring"]["max_excursion_m"]]
    if bad:
        out.append("a free mass started " + "/".join(f"{r['kick_m'] * 1e9:g}" for r in bad) + " nm off: largest "
                   "excursion " + "/".join(f"{r['max_excursion_m'] * 1e9:.0f}" for r in bad) + " nm against "
                   + "/".join(f"{r['no_spring']['max_excursion_m'] * 1e9:.0f}" for r in bad) + " nm without")
    chk = rest.get("not_held_check") or {}
    for row in chk.get("fractions", []):
        on, off = row["spring"]["hold_excursion_m"], row["no_spring"]["hold_excursion_m"]
        steps = [i for i, (a, b) in enumerate(zip(on, off, strict=False)) if a > SPRING_WORSE_RATIO * b]
        if steps:
            out.append(f"pre-sliding stiffness x{row['stiffness_fraction']:g}: hold excursion after step "
                       + "/".join(str(i + 1) for i in steps) + " "
                       + "/".join(f"{on[i] * 1e9:.0f}" for i in steps) + " nm against "
                       + "/".join(f"{off[i] * 1e9:.0f}" for i in steps) + " nm without")
    return out


def _free_spring(ctl: Any, kv: float) -> float:
    """The rest spring [N/m] the controller applies to a stage not (yet) seen held, which is all a free mass gets
    (:mod:`stagectl.control.controller`, "Held before the full spring"): min(k_v, κ_u·K_p) with the stiffness test on
    (``rest_spring_held_fraction`` > 0), else the full ``kv``."""
    if ctl.rest_spring_held_fraction <= 0.0:
        return kv
    return min(kv, float(ctl.rest_spring_unconfirmed_kp_fraction) * float(ctl.pid.kp_n_m))


def _rest_gains(ctl: Any) -> dict[str, Any]:
    """The controller's rest-loop gains as :func:`stagectl.control.design.analyse_rest` takes them."""
    return {"kd_fraction": ctl.rest_kd_fraction, "dob_bandwidth_fraction": ctl.rest_dob_bandwidth_fraction,
            "spring_sections": ctl.rest_spring_section_count}


def _rest_setup(app: Any, ctl: Any) -> dict[str, Any] | None:
    """What the rest loop of :func:`_rest_loops` is analysed on: the stuck plant's pre-sliding stiffness ``k_plant``
    [N/m] and damping ``c_plant`` [N s/m] (the config's simulated plant's, else the controller model's), the rest
    spring ``kv`` = φ·Σk of the model [N/m] (0: off; ``spring``), the rest integral's gain ``kr`` [N/(m s)], whether
    the PID's integrator is ``held`` at rest, and the feed-forward scales ``thetas`` to sweep. None without a
    Q-filter observer or a known pre-sliding stiffness."""
    if ctl.dob.kind != "qfilter":
        return None
    model = ctl.feedforward.model
    model_fr = model.friction if model is not None else None
    plant_fr = app.sim.plant.friction if app is not None and app.sim is not None else model_fr
    k_plant = getattr(plant_fr, "stiffness_n_m", None)
    c_plant = getattr(plant_fr, "damping_n_s_m", None)
    if not isinstance(k_plant, float) or not isinstance(c_plant, float) or k_plant <= 0.0:
        return None
    k_model = getattr(model_fr, "stiffness_n_m", None)
    spring = ctl.feedforward.kind == "model" and isinstance(k_model, float) and ctl.rest_stiffness_fraction > 0.0
    kv = ctl.rest_stiffness_fraction * k_model if spring and isinstance(k_model, float) else 0.0
    # the rest integral (controller.rest_integral_hz): its gain on the stiff side, 2π·f_r·min(θ, 1)·Σk
    kr = (2.0 * math.pi * ctl.rest_integral_hz * k_model
          if ctl.feedforward.kind == "model" and isinstance(k_model, float) else 0.0)
    ffc = ctl.feedforward
    learns = ffc.adapt_bandwidth_hz > 0.0 or ffc.learn_moves_fraction > 0.0
    lo = 1.0 - ffc.adapt_max_change_fraction if learns else 1.0
    hi = 1.0  # the spring's θ is capped at 1 (above it θ still scales the feed-forward, not the spring)
    thetas = [1.0] if not (spring or kr) or lo == hi else [lo + (hi - lo) * i / (THETA_POINTS - 1)
                                                           for i in range(THETA_POINTS)]
    return {"k_plant": k_plant, "c_plant": c_plant, "kv": kv, "kr": kr, "spring": spring,
            "held": bool(ctl.hold_integrator_at_rest), "thetas": thetas}


def _design_rest(app: Any, ctl: Any, m: float, m_dob: float, T: float, nd: int) -> dict[str, Any] | None:
    """Rest-loop gains for ``ctl``'s PID and observer by :func:`stagectl.control.design.design_rest_gains`: both rest
    loops of :func:`_rest_loops` (the stuck stage and the free mass, with the spring a stage not seen held gets) at
    the floor over the θ range, for this delay, mass and stiffness; None when the rest loop is not analysed."""
    from stagectl.control import design

    setup = _rest_setup(app, ctl)
    if setup is None:
        return None
    cap = (float(ctl.rest_spring_unconfirmed_kp_fraction) * float(ctl.pid.kp_n_m)
           if ctl.rest_spring_held_fraction > 0.0 else None)
    return design.design_rest_gains(m, T, ctl.pid, nd, ctl.dob.bandwidth_hz, ctl.dob.command_delay_samples,
                                    setup["k_plant"], setup["c_plant"], setup["kv"], ctl.velocity_cutoff_hz,
                                    dob_mass_kg=m_dob, integrator_held=setup["held"], thetas=setup["thetas"],
                                    free_spring_cap_n_m=cap, rest_integral_n_m_s=setup["kr"],
                                    min_phase_margin_deg=HEALTHY_PHASE_MARGIN_DEG,
                                    min_gain_margin_db=HEALTHY_GAIN_MARGIN_DB)


def _rest_loops(app: Any, ctl: Any, m: float, m_dob: float, T: float, nd: int, *,
                simulate: bool = True) -> dict[str, Any] | None:
    """Margins of the configured *rest* loop (:func:`stagectl.control.design.analyse_rest`: the PID with its
    integrator held when ``hold_integrator_at_rest`` (else the full PID) + Q-filter observer of nominal mass
    ``m_dob`` + the rest spring k_v = φ·min(θ, 1)·Σk of the controller's model) on a stage of mass ``m`` [kg] stuck
    in pre-sliding (the config's simulated plant's friction stiffness and damping, else the controller model's)
    and on the free mass. None when it does not apply (no Q-filter observer, or no pre-sliding stiffness
    known).

    θ (the feed-forward's force scale) moves within 1 ± ``adapt_max_change_fraction`` when the adaptation or the
    learning from moves is on, else it stays 1; the spring follows it up to 1 (the controller caps it there: a
    larger spring thins the rest loop's margins, see :mod:`stagectl.control.controller`, "Rest spring"). The loop
    is analysed at ``THETA_POINTS`` values of θ over that range and each loop's figures are the worst case (the
    lowest phase margin, with its θ; the lowest gain margin; unstable if unstable anywhere); ``theta_sweep``
    lists the stuck plant's margins per θ. ``stuck_unstable_at_theta`` names the θ values where the stuck plant's
    rest loop is unstable (the configured controller would oscillate at standstill there).

    With a spring: ``stiffness_margin`` (:func:`_stiffness_margin`) and, with ``simulate``, what the spring does on
    stages that are not held, in simulated time (``free_mass_check``: :func:`_free_mass_check`; ``not_held_check``:
    :func:`_not_held_check`; about 1 s of CPU)."""
    from stagectl.control import design

    setup = _rest_setup(app, ctl)
    if setup is None:
        return None
    k_plant, c_plant, kv, kr = setup["k_plant"], setup["c_plant"], setup["kv"], setup["kr"]
    spring, held, thetas = setup["spring"], setup["held"], setup["thetas"]
    hi = thetas[-1]
    per: list[tuple[float, list[Any]]] = []
    for th in thetas:
        per.append((th, design.analyse_rest(m, T, ctl.pid, nd, ctl.dob.bandwidth_hz, ctl.dob.command_delay_samples,
                                            k_plant, c_plant, th * kv, ctl.velocity_cutoff_hz, dob_mass_kg=m_dob,
                                            integrator_held=held, rest_integral_n_m_s=th * kr,
                                            free_spring_n_m=_free_spring(ctl, th * kv), **_rest_gains(ctl))))
    summ: dict[str, dict[str, Any]] = {}
    for j, a0 in enumerate(per[0][1]):
        i, w = design.worst_over([loops[j].summary() for _, loops in per])
        w["theta"] = per[i][0]
        summ[a0.name] = {**w, "healthy": _healthy(w)}
    sweep = [{"theta": th, "phase_margin_deg": loops[0].phase_margin_deg, "gain_margin_db": loops[0].gain_margin_db,
              "closed_loop_stable": loops[0].stable} for th, loops in per]
    unstable_at = [r["theta"] for r in sweep if not r["closed_loop_stable"]]
    healthy = all(v["healthy"] for v in summ.values())
    relies = None
    if not healthy:
        relies = (f"the stage being stuck in pre-sliding at standstill (stiffness {k_plant:.3g} N/m); "
                  + (f"the rest spring is released (bumplessly) when |x - x_ref| exceeds "
                     f"{ctl.rest_spring_release_m * 1e9:.0f} nm or it swings across +-{ctl.rest_spring_rearm_m * 1e9:.0f}"
                     f" nm twice"
                     + (f" or the stiffness it measures after a reversal is below {ctl.rest_spring_held_fraction:g} "
                        f"of the model's" if ctl.rest_spring_held_fraction > 0.0 else "")
                     + f", and its force is bounded by {kv * ctl.rest_spring_range_m * 1e3:.0f} mN"
                     + (f"; the full spring acts only once the stage is seen held (it takes a force, or a branch is "
                        f"judged held), before that {_free_spring(ctl, kv):.3g} N/m"
                        if ctl.rest_spring_held_fraction > 0.0 else "")
                     if spring else ("with the integrator held the rest loop is PD + observer only" if held
                                     else "the rest loop is the full PID + observer"))
                  + (f"; the rest integral stops for the standstill when |x - x_ref| exceeds "
                     f"{ctl.rest_spring_release_m * 1e9:.0f} nm or it swings across "
                     f"+-{ctl.rest_spring_rearm_m * 1e9:.0f} nm twice, and adds at most the model's Coulomb level"
                     if kr else ""))
    margin = (_stiffness_margin(m, T, ctl, nd, m_dob, held, k_plant, c_plant, hi * kv, hi * kr)
              if spring else None)
    check = _not_held_check(app, ctl) if spring and simulate else None
    free_check = _free_mass_check(ctl, m, T, nd) if spring and simulate else None
    return {"rest_spring_n_m": kv, "rest_stiffness_fraction": ctl.rest_stiffness_fraction if spring else 0.0,
            "stiffness_margin": margin, "held_fraction": ctl.rest_spring_held_fraction if spring else None,
            "not_held_check": check, "free_mass_check": free_check,
            "rest_integral_n_m_s": kr,
            "mass_kg": m, "observer_mass_kg": m_dob, "integrator_held": held,
            "plant_stiffness_n_m": k_plant, "plant_damping_n_s_m": c_plant, "loops": summ, "healthy": healthy,
            "theta_range": [thetas[0], thetas[-1]], "theta_sweep": sweep, "stuck_unstable_at_theta": unstable_at,
            "relies_on": relies}


def _rest_spring_lines(rest: dict[str, Any]) -> list[str]:
    """The stiffness margin and the not-held check of :func:`_rest_loops`, as printed lines."""
    out: list[str] = []
    mg, rho = rest.get("stiffness_margin"), rest.get("held_fraction")
    if rest.get("rest_stiffness_fraction"):
        if mg is None:
            out.append("stiffness margin: none (the rest loop is below the floor on the stuck stage itself)")
        else:
            guard = ("no stiffness test (controller.rest_spring_held_fraction 0)" if not rho else
                     f"the spring is released when the stiffness measured after a reversal at standstill is below "
                     f"{rho:g} of the model's"
                     + ("" if rho >= mg else f" -- below the margin: on a stage held by {rho:g} to {mg:g} of the "
                        f"model's stiffness the spring stays on while its linear rest loop misses the floor"))
            out.append(f"stiffness margin: the rest loop meets the floor down to {mg:g} x the stuck stage's "
                       f"pre-sliding stiffness (theta 1); {guard}")
    fm = rest.get("free_mass_check")
    if fm:
        kicks = "/".join(f"{r['kick_m'] * 1e9:g}" for r in fm)
        cyc = "/".join("never" if r["release_cycle"] is None else f"{r['release_cycle']}" for r in fm)
        why = "/".join(r["release_reason"] or "-" for r in fm)
        exc = "/".join(f"{r['max_excursion_m'] * 1e9:.0f}" for r in fm)
        exc0 = "/".join(f"{r['no_spring']['max_excursion_m'] * 1e9:.0f}" for r in fm)
        late = max(r["late_excursion_m"] for r in fm)
        late0 = max(r["no_spring"]["late_excursion_m"] for r in fm)
        out.append(f"rest/free check (simulated: a free mass, no friction, started {kicks} nm off the reference at "
                   f"standstill, 0.5 s): the spring was released after {cyc} cycles ({why}); largest excursion "
                   f"{exc} nm (without the spring {exc0} nm); within {late * 1e9:.0f} nm over the last 0.1 s "
                   f"(without {late0 * 1e9:.0f} nm)")
    chk = rest.get("not_held_check")
    if chk is None:
        return out
    if "error" in chk:
        out.append(f"not-held check: {chk['error']}")
        return out
    def per_step(r: dict[str, Any]) -> str:
        exc = "/".join(f"{x * 1e9:.0f}" for x in r["hold_excursion_m"])
        st = "/".join("-" if x is None else f"{x * 1e3:.0f}" for x in r["settle_s"])
        return f"hold excursion {exc} nm, settled after {st} ms"

    for row in chk["fractions"]:
        sp, ns = row["spring"], row["no_spring"]
        when = (f"the spring was released {row['releases']}x ({', '.join(row['reasons'])}), at the latest "
                f"{row['latest_release_cycles']} cycles after a move's end" if row["releases"]
                else "the spring was never released")
        lc = "LIMIT CYCLE" if sp["limit_cycle"] or ns["limit_cycle"] else "no limit cycle"
        out.append(f"rest/free check (simulated: the plant's pre-sliding stiffness x{row['stiffness_fraction']:g}, "
                   f"not held; 10 um steps, {chk['hold_s']:g} s holds): {when}; {per_step(sp)} (without the spring "
                   f"{per_step(ns)}); {lc}" + (f", fault {sp['fault']}" if sp["fault"] else ""))
    return out


def _stiffness_margin(m: float, T: float, ctl: Any, nd: int, m_dob: float, held: bool, k_plant: float,
                      c_plant: float, kv: float, kr: float) -> float | None:
    """The lowest fraction r of the plant's pre-sliding stiffness (stiffness and damping × r) for which the rest
    loop with the spring ``kv`` [N/m] (θ = 1, the largest spring: the worst case for a soft stage) is still healthy
    (PM >= 40°, GM >= 8 dB), to 0.01 by bisection (margins are monotonic in r below 1 on the shipped designs); None
    if it is not healthy at r = 1, 0.0 if it is healthy on the free mass too."""
    from stagectl.control import design

    def ok(r: float) -> bool:
        a = design.analyse_rest(m, T, ctl.pid, nd, ctl.dob.bandwidth_hz, ctl.dob.command_delay_samples,
                                max(r * k_plant, 1e-9), r * c_plant, kv, ctl.velocity_cutoff_hz, dob_mass_kg=m_dob,
                                integrator_held=held, rest_integral_n_m_s=kr, **_rest_gains(ctl))[0]
        return _healthy(a.summary())

    if not ok(1.0):
        return None
    if ok(0.0):
        return 0.0
    lo, hi = 0.0, 1.0  # not healthy at lo, healthy at hi
    while hi - lo > 0.01:
        mid = 0.5 * (lo + hi)
        if ok(mid):
            hi = mid
        else:
            lo = mid
    return round(hi, 2)


def _free_mass_check(ctl: Any, m: float, T: float, nd: int) -> list[dict[str, Any]]:
    """The configured controller at standstill on a free mass ``m`` [kg] (the ``rest/free`` plant), period ``T`` [s],
    ``nd`` periods of I/O delay, started each of :data:`FREE_MASS_KICKS_M` off the reference, with and without its rest
    spring (:func:`stagectl.bench.control.free_mass_rest_check`, 0.5 s of simulated time each)."""
    import dataclasses

    from stagectl.bench.control import free_mass_rest_check

    out = []
    for kick in FREE_MASS_KICKS_M:
        on = free_mass_rest_check(ctl, T, m, kick, delay_samples=nd)
        off = free_mass_rest_check(dataclasses.replace(ctl, rest_stiffness_fraction=0.0), T, m, kick,
                                   delay_samples=nd)
        out.append({**on, "no_spring": {k: off[k] for k in ("max_excursion_m", "late_excursion_m", "final_m")}})
    return out


def _not_held_check(app: Any, ctl: Any) -> dict[str, Any] | None:
    """What the rest spring does on a stage that is not held, checked in simulated time rather than assumed: the
    configured controller, with and without its spring, through 10 µm steps (:data:`CHECK_HOLD_S` holds,
    :func:`stagectl.bench.control.steps_check`) on the config's simulated plant with its pre-sliding stiffness and
    micro-damping at each of :data:`NOT_HELD_STIFFNESS_FRACTIONS` of its own (the friction levels kept). Per
    fraction: the spring's releases (the latest after a move's end, in loop cycles, and why), the holds' largest
    excursion and late excursion with and without the spring, limit cycle, settled moves. None without a ``sim:``
    plant with a GMS/Maxwell friction (``k_n_m``)."""
    import dataclasses

    from stagectl.bench.control import steps_check
    from stagectl.friction import build

    if app is None or app.sim is None:
        return None
    plant = app.sim.plant
    spec = dict(plant.friction.spec())
    if not isinstance(spec.get("k_n_m"), list):
        return None
    out: dict[str, Any] = {"hold_s": CHECK_HOLD_S, "fractions": []}
    for r in NOT_HELD_STIFFNESS_FRACTIONS:
        sp = dict(spec)
        sp["k_n_m"] = [r * k for k in spec["k_n_m"]]
        if isinstance(spec.get("sigma1_n_s_m"), list):
            sp["sigma1_n_s_m"] = [r * c for c in spec["sigma1_n_s_m"]]
        soft = dataclasses.replace(app, sim=dataclasses.replace(
            app.sim, plant=dataclasses.replace(plant, friction=build(sp))))
        row: dict[str, Any] = {"stiffness_fraction": r}
        for name, c in (("spring", ctl), ("no_spring", dataclasses.replace(ctl, rest_stiffness_fraction=0.0))):
            try:
                res = steps_check(soft, c, hold_s=CHECK_HOLD_S)
            except (ConfigError, ValueError) as exc:
                return {"error": str(exc)}
            row[name] = {k: res[k] for k in ("max_hold_excursion_m", "max_late_excursion_m", "settled",
                                             "limit_cycle", "fault", "settle_s")}
            row[name]["hold_excursion_m"] = [st["hold_excursion_m"] for st in res["steps"]]
            row[name]["moves"] = len(res["steps"])
            if name == "spring":
                rel = res["rest_spring_releases"]
                after = [x["after_move_s"] for x in rel if x["after_move_s"] is not None]
                row["releases"] = len(rel)
                row["reasons"] = sorted({x["reason"] for x in rel})
                row["latest_release_cycles"] = (round(max(after) / app.loop.period_s) if after else None)
        out["fractions"].append(row)
    return out


def _design(args: argparse.Namespace, m: float, T: float, nd: int) -> tuple[float, float, PidConfig, list[Any],
                                                                          list[float]]:
    """The design rule of :mod:`stagectl.control.design`; without ``--bandwidth-hz`` the crossover is lowered
    from 0.02/T in steps of 10 % (down to 0.002/T) until the PID + observer loop is healthy."""
    from stagectl.control import design

    fixed = args.bandwidth_hz is not None
    bw = args.bandwidth_hz if fixed else 0.02 / T
    searched: list[float] = []
    while True:
        dbw = args.dob_bandwidth_hz if args.dob_bandwidth_hz is not None else min(5.0 * bw, 0.1 / T)
        pid = design.design_pid(m, bw, T, nd)
        loops = design.analyse_design(m, T, pid, nd, dbw, nd)
        searched.append(bw)
        if fixed or all(_healthy(a.summary()) for a in loops) or bw * 0.9 < 0.002 / T:
            return bw, dbw, pid, loops, searched
        bw *= 0.9


def _designed_controller(base: Any, pid: PidConfig, dbw: float, nd: int,
                         rest_gains: dict[str, Any] | None = None) -> Any:
    """``base`` (the configured controller) with the designed PID and Q-filter observer (and ``rest_gains``, the
    keyword arguments of :func:`stagectl.control.design.analyse_rest`, when given)."""
    import dataclasses

    ctl = dataclasses.replace(base, pid=pid, dob=dataclasses.replace(
        base.dob, kind="qfilter", bandwidth_hz=dbw, command_delay_samples=nd))
    if rest_gains:
        ctl = dataclasses.replace(ctl, rest_kd_fraction=float(rest_gains["kd_fraction"]),
                                  rest_dob_bandwidth_fraction=float(rest_gains["dob_bandwidth_fraction"]),
                                  rest_spring_section_count=int(rest_gains["spring_sections"]))
    return ctl


def _suggested_rest(app: Any, ctl: Any, rest: dict[str, Any], pid: PidConfig, dbw: float, nd: int, m: float,
                    T: float) -> dict[str, Any] | None:
    """The rest loop of the suggestion (the designed PID and observer with the configured rest spring): the
    configured rest gains when both rest loops (stuck, free) meet the floor with them (``source: configured``),
    else the gains :func:`_design_rest` chooses (``source: designed``; with ``configured_loops``, what the configured
    gains would give), else the configured ones below the floor (``source: configured``, ``designed: None``).
    ``loops`` are :func:`_rest_loops`' figures (worst over θ)."""
    d_ctl = _designed_controller(ctl, pid, dbw, nd)
    m_dob = d_ctl.dob.nominal_mass_kg if d_ctl.dob.nominal_mass_kg is not None else m
    same = d_ctl.pid == ctl.pid and d_ctl.dob == ctl.dob
    kept = rest if same else _rest_loops(app, d_ctl, m, m_dob, T, nd, simulate=False)
    if kept is None:
        return None
    out = {"source": "configured", "gains": _rest_gains(ctl), "loops": kept["loops"], "healthy": kept["healthy"]}
    if kept["healthy"]:
        return out
    des = _design_rest(app, d_ctl, m, m_dob, T, nd)
    if des is None or des["gains"] is None:
        return {**out, "designed": None}
    return {"source": "designed", "gains": des["gains"], "loops": des["loops"], "healthy": True,
            "configured_loops": kept["loops"], "points": des["points"]}


def _check(app: Any, pid: PidConfig, dbw: float, nd: int, rest_gains: dict[str, Any] | None = None
           ) -> dict[str, Any] | None:
    """Run the design on the config's simulated plant (10 µm steps, :data:`CHECK_HOLD_S` holds), with the
    configured friction model and a 20 %-wrong one; None without a ``sim:`` plant. ``rest_gains``: the rest-loop
    gains the suggestion carries (None: the configured ones)."""
    from stagectl.bench.control import mismatched, steps_check
    from stagectl.friction import StageModel

    if app.sim is None:
        return None
    ctl = _designed_controller(app.controller, pid, dbw, nd, rest_gains)
    plant = app.sim.plant
    models: dict[str, Any] = {"configured model": None}
    out: dict[str, Any] = {}
    try:
        models["20 %-wrong model"] = StageModel(friction=mismatched(plant.friction), effects=plant.effects,
                                                mass_kg=plant.mass_kg)
    except (KeyError, TypeError, ValueError, ConfigError) as exc:  # the mismatch recipe is for GMS plants
        out["20 %-wrong model"] = {"skipped": f"no 20 %-wrong model of this plant's friction ({exc})"}
    for name, model in models.items():
        try:
            r = steps_check(app, ctl, model=model, hold_s=CHECK_HOLD_S, delay_samples=nd)
        except (ConfigError, ValueError) as exc:
            out[name] = {"error": str(exc)}
            continue
        out[name] = {k: r[k] for k in ("settle_s", "max_hold_excursion_m", "max_late_excursion_m", "settled",
                                       "limit_cycle", "fault")}
        out[name]["moves"] = len(r["steps"])
    return out


def _verdict(loops: dict[str, dict[str, Any]], check: dict[str, Any] | None) -> dict[str, Any]:
    """Refusal reasons and the confidence of an offered design (see the module docstring)."""
    reasons: list[str] = []
    for name, s in loops.items():
        if not s["closed_loop_stable"]:
            reasons.append(f"{name} loop unstable")
        elif not s["healthy"]:
            reasons.append(f"{name} margins thin (PM {s['phase_margin_deg']:.1f} deg, GM {s['gain_margin_db']:.1f} dB; "
                           f"need {HEALTHY_PHASE_MARGIN_DEG:g} deg / {HEALTHY_GAIN_MARGIN_DB:g} dB)")
    if check is None:
        return {"refused": bool(reasons), "reasons": reasons,
                "confidence": None if reasons else "low",
                "confidence_reason": "margins only: no sim: plant in the config to check the design on"}
    all_settled = True
    skipped = [r["skipped"] for r in check.values() if "skipped" in r]
    check = {k: r for k, r in check.items() if "skipped" not in r}
    for name, r in check.items():
        if "error" in r:
            reasons.append(f"steps check with the {name} failed: {r['error']}")
            continue
        if r["fault"]:
            reasons.append(f"{name}: fault {r['fault']} on the 10 um steps")
        if r["limit_cycle"]:
            reasons.append(f"{name}: limit cycle in the hold after a 10 um step "
                           f"(max excursion {r['max_hold_excursion_m'] * 1e9:.0f} nm)")
        elif r["max_late_excursion_m"] > MAX_HOLD_EXCURSION_M:
            reasons.append(f"{name}: still {r['max_late_excursion_m'] * 1e9:.0f} nm off in the second half of the "
                           f"hold after a 10 um step (more than {MAX_HOLD_EXCURSION_M * 1e9:.0f} nm)")
        if r["settled"] < r["moves"]:
            all_settled = False
    if reasons:
        return {"refused": True, "reasons": reasons, "confidence": None, "confidence_reason": None}
    if all_settled and not skipped:
        why = "every 10 um step settled to +-10 nm without a limit cycle, exact and 20 %-wrong model"
        return {"refused": False, "reasons": [], "confidence": "high", "confidence_reason": why}
    if all_settled:
        why = f"every 10 um step settled with the configured model; not checked: {'; '.join(skipped)}"
        return {"refused": False, "reasons": [], "confidence": "medium", "confidence_reason": why}
    worst = max(r["max_late_excursion_m"] for r in check.values())
    why = (f"no limit cycle, but not every 10 um step settled to +-10 nm within {CHECK_HOLD_S:g} s "
           f"(max error in the second half of a hold {worst * 1e9:.0f} nm)")
    return {"refused": False, "reasons": [], "confidence": "medium", "confidence_reason": why}


def _kalman_q(m: float, T: float, dob: DobConfig) -> float:
    if dob.disturbance_noise_n_sqrt_s is not None:
        return float(dob.disturbance_noise_n_sqrt_s)
    from stagectl.control import design

    return design.kalman_noise_for_bandwidth(m, T, dob.bandwidth_hz, dob.measurement_noise_m, use_control=True)


def _pid_dict(p: PidConfig) -> dict[str, float]:
    return {"kp_n_m": p.kp_n_m, "ki_n_m_s": p.ki_n_m_s, "kd_n_s_m": p.kd_n_s_m,
            "derivative_cutoff_hz": p.derivative_cutoff_hz}


def _yaml_snippet(m: float, pid: PidConfig, dbw: float, nd: int, rest_gains: dict[str, Any] | None = None) -> str:
    out = (
        "controller:\n"
        f"  mass_kg: {m:.6g}\n"
        f"  pid: {{kp_n_m: {pid.kp_n_m:.4g}, ki_n_m_s: {pid.ki_n_m_s:.4g}, kd_n_s_m: {pid.kd_n_s_m:.4g}, "
        f"derivative_cutoff_hz: {pid.derivative_cutoff_hz:.4g}}}\n"
        f"  dob: {{kind: qfilter, bandwidth_hz: {dbw:.4g}, command_delay_samples: {nd}}}\n"
    )
    if rest_gains:
        out += (f"  rest_kd_fraction: {rest_gains['kd_fraction']:g}\n"
                f"  rest_dob_bandwidth_fraction: {rest_gains['dob_bandwidth_fraction']:g}\n"
                f"  rest_spring_section_count: {int(rest_gains['spring_sections'])}\n")
    return out


def _fmt_loop(name: str, s: dict[str, Any]) -> str:
    gm = s["gain_margin_db"]
    gm_s = "inf" if math.isinf(gm) else f"{gm:.1f} dB"
    if not s["closed_loop_stable"]:
        st = "   ** UNSTABLE **"
    elif not _healthy(s):
        st = f"   (thin: below PM {HEALTHY_PHASE_MARGIN_DEG:g} deg / GM {HEALTHY_GAIN_MARGIN_DB:g} dB)"
    else:
        st = ""
    return (f"  {name:<11s} crossover {s['crossover_hz']:7.2f} Hz   phase margin {s['phase_margin_deg']:6.1f} deg   "
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
        rest = c.get("rest")
        if rest is not None:
            held = "integrator held" if rest["integrator_held"] else "integrator running"
            obs = (f", observer mass {rest['observer_mass_kg']:g} kg"
                   if rest["observer_mass_kg"] != rest["mass_kg"] else "")
            lo, hi = rest["theta_range"]
            over = (f"; worst case over the feed-forward scale theta {lo:g}..{hi:g} the adaptation allows (the "
                    f"spring follows theta up to 1)" if lo != hi else "")
            print(f"  at standstill ({held}{obs}, rest spring {rest['rest_spring_n_m']:.3g} N/m = "
                  f"{rest['rest_stiffness_fraction']:g} x the model's pre-sliding stiffness; plant stuck at "
                  f"{rest['plant_stiffness_n_m']:.3g} N/m, or free{over}):")
            for name, s in rest["loops"].items():
                print(_fmt_loop(name, s) + (f" (lowest PM at theta {s['theta']:g})" if lo != hi else ""))
            if rest["stuck_unstable_at_theta"]:
                at = ", ".join(f"{t:g}" for t in rest["stuck_unstable_at_theta"])
                print(f"  the rest loop is UNSTABLE on the stuck stage at theta {at}: the design fails there (the stage "
                      f"hunts at standstill until the guard releases the spring); lower "
                      f"controller.rest_stiffness_fraction or the PID/observer gains")
            if not rest["healthy"]:
                floor = f"PM {HEALTHY_PHASE_MARGIN_DEG:g} deg / GM {HEALTHY_GAIN_MARGIN_DB:g} dB floor"
                if all(v["healthy"] for k, v in rest["loops"].items() if k.endswith("stuck")):
                    print(f"  the rest loop meets the {floor} on the stuck stage; on a free stage (no friction holding "
                          f"it) it does not: it relies on {rest['relies_on']}")
                else:
                    print(f"  the rest loop is below the {floor}: it relies on {rest['relies_on']}")
            for line in _rest_spring_lines(rest):
                print("  " + line)
    d = result["designed"]
    p = d["pid"]
    print(f"designed for a {d['target_crossover_hz']:g} Hz crossover: Kp {p['kp_n_m']:.4g} N/m, "
          f"Ki {p['ki_n_m_s']:.4g} N/(m s), Kd {p['kd_n_s_m']:.4g} N s/m, D cut-off {p['derivative_cutoff_hz']:g} Hz; "
          f"DOB qfilter {d['dob']['bandwidth_hz']:g} Hz")
    for name, s in d["loops"].items():
        print(_fmt_loop(name, s))
    for line in _suggested_rest_lines(d.get("rest")):
        print("  " + line)
    if d["check"] is not None:
        for name, r in d["check"].items():
            if "skipped" in r:
                print(f"  steps check ({name}): skipped: {r['skipped']}")
                continue
            if "error" in r:
                print(f"  steps check ({name}): {r['error']}")
                continue
            st = ", ".join("-" if v is None else f"{v * 1e3:.0f}" for v in r["settle_s"])
            print(f"  steps check ({name}): settled {r['settled']}/{r['moves']} to +-10 nm within the "
                  f"{CHECK_HOLD_S:g} s hold, after [{st}] ms, "
                  f"max hold excursion {r['max_hold_excursion_m'] * 1e9:.0f} nm, "
                  f"limit cycle {'YES' if r['limit_cycle'] else 'no'}, fault {r['fault'] or 'none'}")
    if d["refused"]:
        print("no suggestion: this design is refused:")
        for reason in d["reasons"]:
            print(f"  - {reason}")
    else:
        print(f"confidence: {d['confidence']} ({d['confidence_reason']})")
        print("suggested YAML:")
        print("".join(f"  {line}\n" for line in d["yaml"].splitlines()), end="")
    if "bode_png" in result:
        print(f"Bode plot: {result['bode_png']}")
    if "configured" in result and not result["configured"]["stable"]:
        print("stagectl: warning: the configured closed loop is UNSTABLE", file=sys.stderr)
    if d["refused"]:
        print("stagectl: warning: no gains suggested (the design failed its own check)", file=sys.stderr)
    return code
