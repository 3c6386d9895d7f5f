"""Outputs of ``stagectl commission``: ``model.yaml``, ``stage.yaml``, ``report.json``, ``report.md`` and plots.

``stage.yaml`` is the given configuration file with its ``controller:`` section replaced (measured mass,
designed PID and observer, friction feed-forward from ``model.yaml``) and every relative file path in it
made absolute (the new file lives in another directory); it is loaded back with the same loader as
``check-config`` before anything uses it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import yaml

from stagectl.commission.sequence import FALLBACK_MIN_GAIN_MARGIN_DB as FALLBACK_GM
from stagectl.commission.sequence import FALLBACK_MIN_PHASE_MARGIN_DEG as FALLBACK_PM
from stagectl.commission.sequence import MIN_GAIN_MARGIN_DB as MIN_GM
from stagectl.commission.sequence import MIN_PHASE_MARGIN_DEG as MIN_PM
from stagectl.commission.sequence import Results, controller_mapping
from stagectl.commission.sliding import sliding_line
from stagectl.config import AppConfig, load_app_config
from stagectl.friction import StageModel, save_model_file
from stagectl.outputs import plain
from stagectl.schema import absolute_paths, load, load_yaml_file


def controller_section(res: Results) -> dict[str, Any]:
    """The new ``controller:`` mapping (model file next to stage.yaml)."""
    assert res.gains is not None and res.plant is not None
    return controller_mapping(res.gains["chosen"], float(res.gains["mass_kg"]), int(res.gains["delay_samples"]),
                              res.config.loop.period_s, res.plant.delay_s, res.model_spec,
                              res.config.controller.max_force_n, "model.yaml")


def write_config(res: Results, out: Path) -> AppConfig:
    """Write model.yaml and stage.yaml into ``out``; return stage.yaml loaded (raises ConfigError if invalid)."""
    assert res.model_spec is not None
    model = load(StageModel, res.model_spec, "")
    save_model_file(model, out / "model.yaml", header="identified by `stagectl commission` (see report.md)")
    cfg = res.config
    data = load_yaml_file(cfg.path) if cfg.path is not None else {}
    assert isinstance(data, dict)
    data = absolute_paths(dict(data), cfg.base_dir, resolve=True)
    res.controller_yaml = controller_section(res)
    data["controller"] = res.controller_yaml
    data["description"] = f"{data.get('description', '')} (commissioned by stagectl commission)".strip()
    text = ("# written by `stagectl commission` from " + (str(cfg.path) if cfg.path else "-")
            + ": the given configuration with the commissioned controller (see report.md)\n"
            + yaml.safe_dump(plain(data, json=True), sort_keys=False, default_flow_style=None))
    (out / "stage.yaml").write_text(text, encoding="utf-8")
    return load_app_config(out / "stage.yaml")


#: the runs of the commissioned controller (Commissioning._rest_on_stage, _verify): a fault or Ctrl-C in one of them
#: leaves the given controller recommended
COMMISSIONED_RUNS = ("verify_after", "wipe_after", "verify_rest_", "wipe_rest_")


def report_dict(res: Results) -> dict[str, Any]:
    r: dict[str, Any] = {
        "command": "commission",
        "config": str(res.config.path) if res.config.path else None,
        "status": "aborted" if res.aborted else "complete",
        "envelope": res.envelope.as_dict(),
        "experiments": [e.as_dict() for e in res.experiments],
        "notes": res.notes,
    }
    if res.aborted is not None:
        r["aborted"] = {"experiment": res.aborted.experiment, "reason": res.aborted.reason,
                        "interrupted": res.aborted.interrupted, "drive_state_after": res.drive_state}
    if res.sanity is not None:
        r["sanity"] = res.sanity.as_dict()
    if res.plant is not None:
        r["plant"] = res.plant.as_dict()
    if res.frf is not None:
        r["frf"] = {"f_hz": res.frf.f_hz.tolist(), "re": res.frf.p.real.tolist(), "im": res.frf.p.imag.tolist(),
                    "std": res.frf.p_std.tolist(), "periods": res.frf.periods,
                    "distortion": None if res.frf.distortion is None else res.frf.distortion.tolist(),
                    "margin_lines_left_out_hz": res.frf.f_hz[~res.frf.margin_lines()].tolist()}
    if res.cv is not None:
        r["friction_cv"] = res.cv.as_dict()
    if res.discovery is not None:
        r["discovery"] = res.discovery
    if res.model_spec is not None:
        r["model"] = res.model_spec
    fitted: dict[str, Any] = {}
    if res.plant is not None:
        fitted["mass_kg"] = {"value": res.plant.mass_kg, "std": res.plant.mass_std_kg,
                              "from": res.plant.mass_from}
        used = (res.discovery or {}).get("mass_kg_used")
        if used is not None and used != res.plant.mass_kg:
            fitted["mass_kg_frf"] = fitted["mass_kg"]
            fitted["mass_kg"] = {"value": used, "std": float("nan"),
                                 "from": "inverse dynamics of friction_cv (the FRF disagreed)"}
        elif (res.discovery or {}).get("mass_warning"):
            fitted["mass_kg_inverse_dynamics"] = {"value": (res.discovery or {}).get("mass_kg_inverse_dynamics"),
                                                  "std": float("nan"), "from": "friction_cv (not used)"}
        fitted["delay_s"] = {"value": res.plant.delay_s, "std": res.plant.delay_std_s, "from": "frf"}
    if res.cv is not None:
        fitted["coulomb_n"] = {"value": res.cv.coulomb_n, "std": res.cv.coulomb_std_n, "from": "friction_cv"}
        fitted["viscous_n_s_m"] = {"value": res.cv.viscous_n_s_m, "std": res.cv.viscous_std_n_s_m,
                                   "from": "friction_cv"}
        fitted["offset_n"] = {"value": res.cv.offset_n, "std": res.cv.offset_std_n, "from": "friction_cv"}
    if res.discovery is not None:
        fitted["effects"] = [e["name"] for e in res.discovery["effects"]]
        if res.discovery.get("mass_warning"):
            r["notes"] = [*r["notes"], res.discovery["mass_warning"]]
    r["fitted"] = fitted
    if res.gains is not None:
        r["gains"] = res.gains
    if res.controller_yaml is not None:
        r["controller"] = res.controller_yaml
    r["verification"] = res.verification
    r["verdict"] = verdict(res.verification, margin_standing(res.gains))
    gv = (res.gains or {}).get("given")
    if gv and r["verdict"]["recommend"] == "given" and not gv["measured"]["healthy"] \
            and "margin" not in r["verdict"]:
        mm = gv["measured"]
        ch = (res.gains or {}).get("chosen") or {}
        if ch.get("healthy", True):
            keeps = f"below the {MIN_PM:g} deg / {MIN_GM:g} dB the commissioned one keeps"
        else:  # the fallback tier's design misses the floor too (gains.fallback)
            ds = [d for d in (ch.get("model"), ch.get("measured")) if d]
            low = {k: min(float(d[k]) for d in ds) for k in ("phase_margin_deg", "gain_margin_db")}
            keeps = (f"the commissioned one (fallback tier) {_margin_text(low)} (the lower of the model's and the "
                     f"measured FRF's), also below the {MIN_PM:g} deg / {MIN_GM:g} dB floor")
        r["verdict"]["text"] += (f" (note: the given controller has PM {mm['phase_margin_deg']:.0f} deg / GM "
                                 f"{mm['gain_margin_db']:.1f} dB on the measured FRF, {keeps})")
    # (every run of the commissioned controller: the rest additions' check on the stage, the verification's)
    if res.aborted is not None and res.aborted.experiment.startswith(COMMISSIONED_RUNS):
        r["verdict"] = {"recommend": "given", "worse": [f"{res.aborted.experiment}: {res.aborted.reason}"],
                        "better": [], "text": f"keep the given controller: the commissioned one faulted in "
                        f"{res.aborted.experiment} ({res.aborted.reason})"}
    return plain(r, json=True)  # type: ignore[no-any-return]


#: the verdict's tolerance on a scenario's RMS error: the commissioned controller "tracks at least as well" when
#: its RMS is at most (1 + VERDICT_RMS_TOL) times the given one's. The before and after runs are single runs of
#: a few seconds starting from different states (the given controller's right after the sequence's last
#: move), and on a real stage their RMS carries the sensor's noise and the stage's drift: a 1 % difference
#: (HIL commissioning: cosine 17.4 nm after vs 17.2 before, while triangle settled 1/1 after vs 0/1 and
#: steps 4/4 vs 3/4) is not a measured difference. 5 % stays well under the gains a retuning is for (the
#: quick start: 6.78 -> 2.06 nm on the cosine, 14 % on the steps).
VERDICT_RMS_TOL = 0.05


def margin_standing(gains: dict[str, Any] | None) -> dict[str, Any] | None:
    """The margins the verdict weighs (:func:`verdict`): None unless the given controller misses the floor the
    commissioned one meets. The floor is PM ≥ ``MIN_PM``, GM ≥ ``MIN_GM`` where the commissioned design is
    healthy, the fallback tier's ``FALLBACK_PM``/``FALLBACK_GM`` where it is a fallback design; the given
    controller's margins are on the measured FRF, the commissioned one's the lower of the model's and the
    measured FRF's."""
    gv = (gains or {}).get("given")
    ch = (gains or {}).get("chosen")
    if not gv or not ch or not gv.get("measured"):
        return None
    ds = [d for d in (ch.get("model"), ch.get("measured")) if d]
    if not ds:
        return None
    low = {k: min(float(d[k]) for d in ds) for k in ("phase_margin_deg", "gain_margin_db")}
    floor = (MIN_PM, MIN_GM) if ch.get("healthy", True) else (FALLBACK_PM, FALLBACK_GM)
    given = {k: float(gv["measured"][k]) for k in ("phase_margin_deg", "gain_margin_db")}

    def meets(mm: dict[str, float]) -> bool:
        return mm["phase_margin_deg"] >= floor[0] and mm["gain_margin_db"] >= floor[1]

    if meets(given) or not meets(low):
        return None
    return {"given": given, "commissioned": low, "floor_pm_deg": floor[0], "floor_gm_db": floor[1],
            "tier": "healthy" if ch.get("healthy", True) else "fallback"}


#: a commissioned controller that meets the margin floor the given one misses is recommended unless it is worse
#: by a wide margin on every figure: each scenario's RMS error above VERDICT_WIDE_RATIO times the given one's and
#: no scenario with more moves settled. A near-unstable controller's tracking edge is not worth its margins (an
#: outside stage: the given PM 13 deg / GM 1.9 dB won on triangle RMS by 15 % and steps settled 4/4 vs 3/4, while
#: its cosine was 43x and its steps' RMS 11x the commissioned one's)
VERDICT_WIDE_RATIO = 2.0


def verdict(ver: dict[str, dict[str, Any]], margins: dict[str, Any] | None = None) -> dict[str, Any]:
    """The advice, checked before it is given. A scenario got worse when the commissioned controller's RMS
    error exceeds ``(1 + VERDICT_RMS_TOL)·`` the given controller's, or fewer of its moves settle.
    ``stage.yaml`` is recommended if no scenario got worse; the text states the rule, each scenario's
    RMS change and the settled moves before and after over all scenarios. Otherwise the report says which
    scenarios got worse and recommends keeping the given controller, except where ``margins``
    (:func:`margin_standing`: the given controller misses the margin floor the commissioned one meets) weigh
    against it: then ``stage.yaml`` is recommended unless it is worse by a wide margin on every figure
    (``VERDICT_WIDE_RATIO``), and the text says why."""
    worse: list[str] = []
    better: list[str] = []
    tol = 100 * VERDICT_RMS_TOL
    n_b = n_a = n_moves = n_runs = 0
    wide_all = True   # every scenario's RMS beyond VERDICT_WIDE_RATIO x the given one's, none settling more
    for name, d in ver.items():
        b, a = d.get("before"), d.get("after")
        if not b or not a:
            continue
        rb, ra = b.get("rms_error_m"), a.get("rms_error_m")
        if rb is None or ra is None or not (math.isfinite(rb) and math.isfinite(ra)):
            continue
        sb, sa = int(b.get("moves_settled", 0)), int(a.get("moves_settled", 0))
        n_b, n_a, n_moves = n_b + sb, n_a + sa, n_moves + int(a.get("moves", 0))
        rms_worse = ra > (1.0 + VERDICT_RMS_TOL) * rb
        n_runs += 1
        wide_all = wide_all and ra > VERDICT_WIDE_RATIO * rb and sa <= sb
        fewer = sa < sb
        change = f"RMS {ra * 1e9:.3g} nm after vs {rb * 1e9:.3g} nm before ({100 * (ra / rb - 1) if rb > 0 else 0.0:+.1f} %)"
        settled = f"settled {sa}/{a.get('moves')} after vs {sb}/{b.get('moves')} before"
        if rms_worse or fewer:
            what = []  # name exactly what got worse, and what did not
            if rms_worse:
                what.append(change)
            if fewer:
                what.append(settled)
            if not rms_worse:
                what.append(f"though its RMS is within the {tol:.0f} % tolerance: {ra * 1e9:.3g} vs {rb * 1e9:.3g} nm")
            worse.append(f"{name}: " + ", ".join(what))
        else:
            better.append(f"{name}: {change}" + (f", {settled}" if sa != sb else ""))
    rule = (f"rule: on every scenario the RMS error at most {tol:.0f} % above the given controller's (run-to-run "
            "noise) and no fewer moves settled")
    if not worse and not better:
        return {"recommend": "unverified", "worse": [], "better": [], "rms_tolerance": VERDICT_RMS_TOL,
                "text": "not verified (no before/after runs): check stage.yaml with `stagectl simulate`/`run` first"}
    tally = f"moves settled {n_a}/{n_moves} after vs {n_b}/{n_moves} before"
    if worse and margins is not None:
        mt = (f"the given controller has {_margin_text(margins['given'])} on the measured FRF, below the "
              f"PM {margins['floor_pm_deg']:g} deg / GM {margins['floor_gm_db']:g} dB floor"
              + (" (the fallback tier's)" if margins["tier"] == "fallback" else "")
              + f" the commissioned one meets ({_margin_text(margins['commissioned'])})")
        wide = f"each scenario's RMS more than {VERDICT_WIDE_RATIO:g}x the given one's and none with more moves settled"
        if not (wide_all and n_runs > 0):
            return {"recommend": "new", "worse": worse, "better": better, "rms_tolerance": VERDICT_RMS_TOL,
                    "margin": margins,
                    "text": (f"use stage.yaml: {mt}; the commissioned one is not worse by a wide margin on every "
                             f"figure ({wide}), so the margins decide ({tally}): worse on " + "; ".join(worse)
                             + ("; better on " + "; ".join(better) if better else ""))}
        return {"recommend": "given", "worse": worse, "better": better, "rms_tolerance": VERDICT_RMS_TOL,
                "margin": margins,
                "text": (f"keep the given controller, though {mt}: the commissioned one is worse by a wide margin "
                         f"on every figure ({wide}; {tally}): " + "; ".join(worse))}
    if worse:
        return {"recommend": "given", "worse": worse, "better": better, "rms_tolerance": VERDICT_RMS_TOL,
                "text": (f"keep the given controller ({rule}; {tally}): the commissioned one is worse on "
                         + "; ".join(worse))}
    return {"recommend": "new", "worse": [], "better": better, "rms_tolerance": VERDICT_RMS_TOL,
            "text": (f"use stage.yaml: it tracks at least as well on every scenario ({rule}; {tally}): "
                     + "; ".join(better))}


def _fmt(v: Any, scale: float = 1.0, unit: str = "", digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v * scale:.{digits}g}{unit}"


def _margin_text(mm: dict[str, Any]) -> str:
    """``"PM 26 deg / GM 3.4 dB"`` (no crossing in the measured band: "PM -")."""
    pm, gm = float(mm["phase_margin_deg"]), float(mm["gain_margin_db"])
    return (f"PM {pm:.0f} deg" if math.isfinite(pm) else "PM -") + " / " + \
        (f"GM {gm:.1f} dB" if math.isfinite(gm) else "GM -")


def _num(v: Any, fmt: str) -> str:
    """A figure for the report's tables; "—" where there is none (e.g. no phase crossover: infinite GM)."""
    return "—" if v is None else format(v, fmt)


def report_markdown(rep: dict[str, Any], pngs: list[str]) -> str:
    L: list[str] = ["# Commissioning report", "", f"Configuration: `{rep.get('config')}`; status: **{rep['status']}**"]
    if "aborted" in rep:
        a = rep["aborted"]
        L += ["", (f"Aborted in `{a['experiment']}`: {a['reason']}. The drive was disabled; the recordings made so "
                  "far are in `recordings/`.")]
    env = rep["envelope"]
    L += ["", "## Envelope", "",
          (f"Travel {env['x_lo_m'] * 1e3:.4g} .. {env['x_hi_m'] * 1e3:.4g} mm, force <= {env['f_max_n']:.3g} N, "
          f"velocity <= {env['v_max_m_s'] * 1e3:.3g} mm/s."), "", "## Experiments", "",
          "| experiment | purpose | duration [s] | samples | ended by | recording |", "|---|---|---|---|---|---|"]
    for e in rep["experiments"]:
        fault = f" (fault {e['fault']['name']})" if e.get("fault") else ""
        L.append(f"| {e['name']} | {e['purpose']} | {e['duration_s']:.2f} | {e['rows']} | {e['ended_by']}{fault} | "
                 f"`{e['csv']}` |")
    for note in rep.get("notes", []):
        L += ["", f"**Note:** {note}"]
    f = rep.get("fitted", {})
    if f:
        L += ["", "## Fitted values (± one standard deviation)", "", "| quantity | value | from |", "|---|---|---|"]
        for k, v in f.items():
            if isinstance(v, dict):
                sd = f" ± {_fmt(v['std'], digits=2)}" if v.get("std") is not None else ""
                L.append(f"| {k} | {_fmt(v['value'], digits=5)}{sd} | {v['from']} |")
        if "effects" in f:
            L.append(f"| effects found | {', '.join(f['effects']) or 'none'} | discover on reversals / friction_cv; "
                     "cogging, offset and pre-sliding by their experiments (below) |")
        for name, ev in ((rep.get("discovery") or {}).get("evidence") or {}).items():
            src = {"cogging": "slow_passes (period scan)",
                   "offset": "friction_cv (even part, t-test over the speeds), slow_passes",
                   "asymmetry": "friction_cv (even part against the friction level)"}.get(
                name, "reversals, presliding (Maxwell-slip vs rigid)")
            L.append(f"| {name} | {'present' if ev['present'] else 'absent'}, evidence ratio {_fmt(ev['ratio'], digits=3)},"
                     f" confidence {ev['confidence']} (discover {'accepted' if ev['discover'] else 'rejected'} it)"
                     f"{': ' + ev['reason'] if ev.get('reason') else ''} | {src} |")
        pr = (rep.get("discovery") or {}).get("presliding_regression") or {}
        if pr.get("k_n_m"):
            ba = ", ".join(f"{1e6 * d:.3g}" for d in pr["break_away_m"])
            L.append(f"| pre-sliding elements | {len(pr['k_n_m'])}, total stiffness {_fmt(sum(pr['k_n_m']), digits=4)} "
                     f"N/m, break-aways {ba} µm, σ1/k {_fmt(pr['damping_s'], digits=3)} s, delay "
                     f"{_fmt(pr['delay_s'], digits=3)} s (residual {_fmt(pr['residual_rms_n'], digits=2)} N) "
                     "| reversals / presliding / friction_cv |")
    if "plant" in rep:
        p = rep["plant"]
        L += ["", (f"Mass and delay from the lines above {p['fit_band_hz'][0]:.3g} Hz; the stiffness term of that "
                  f"fit, {p['presliding_stiffness_n_m']:.3g} N/m ({p['presliding_resonance_hz']:.3g} Hz with the "
                  "mass), is the small-amplitude pre-sliding stiffness; below the band the stage is friction-"
                  "dominated (see frf.png). Unmodelled resonances: "
                  f"{', '.join(f'{x:.3g} Hz' for x in p['unmodelled_resonances_hz']) or 'none'}.")]
    if "gains" in rep:
        ch = rep["gains"]["chosen"]
        pid = ch["pid"]
        L += ["", "## Gains", "",
              (f"Crossover target {ch['crossover_target_hz']:.3g} Hz, Kp {pid['kp_n_m']:.4g} N/m, Ki {pid['ki_n_m_s']:.4g} "
              f"N/(m s), Kd {pid['kd_n_s_m']:.4g} N s/m, "
               + (f"Q-filter DOB {ch['dob_bandwidth_hz']:.3g} Hz." if ch["dob_kind"] == "qfilter" else "no DOB.")
               + ("" if ch.get("healthy", True) else f" Below the PM {MIN_PM:g} deg / GM {MIN_GM:g} dB floor: the "
                  "fallback tier's design (confidence low; see below).")),
              "",
              "| loop | phase margin [deg] | gain margin [dB] | crossover [Hz] |", "|---|---|---|---|",
              (f"| model | {_num(ch['model']['phase_margin_deg'], '.1f')} | {_num(ch['model']['gain_margin_db'], '.1f')} | "
              f"{_num(ch['model']['crossover_hz'], '.3g')} |")]
        if "measured" in ch:
            mm = ch["measured"]
            L.append(f"| measured FRF | {_num(mm['phase_margin_deg'], '.1f')} | {_num(mm['gain_margin_db'], '.1f')} | "
                     f"{_num(mm['crossover_hz'], '.3g')} |")
        gv = rep["gains"].get("given")
        if gv:
            mm = gv["measured"]
            L.append(f"| given controller, measured FRF | {_num(mm['phase_margin_deg'], '.1f')} | "
                     f"{_num(mm['gain_margin_db'], '.1f')} | {_num(mm['crossover_hz'], '.3g')} |")
        out_hz = (rep.get("frf") or {}).get("margin_lines_left_out_hz") or []
        if out_hz:
            L += ["", (f"The margins on the measured FRF leave out its lines at {', '.join(f'{x:.3g}' for x in out_hz)}"
                       " Hz: the friction's distortion dominates them (report.json frf.distortion) and their phase "
                       "leads, which a passive stage's cannot.")]
        sl = sliding_line(rep["gains"].get("unstable_sliding"))
        if sl:
            L += ["", sl]
        L += _rest_lines(ch.get("rest"))
        ros = rep["gains"].get("rest_on_stage")
        if ros:
            k = int(ros.get("pairs") or 1)
            sm = ros.get("scatter_measured")
            L += ["", (f"Rest additions ({', '.join(ros.get('additions') or [])}) checked on the stage, "
                       + ("one pair of runs" if k == 1 else f"{k} pairs of runs (arms' order swapped each pair)")
                       + f" with and without, {_num(ros.get('stage_s'), '.3g')} s of stage time (confidence "
                       f"{ros.get('confidence')}; one run's cosine scatter "
                       + (f"measured {sm * 100:.2g} %, " if sm is not None else "")
                       + f"used {_num(100 * float(ros.get('scatter_used') or ros.get('scatter') or 0.0), '.2g')} %"
                       + (f"; still undecided: {ros['undecided']}" if ros.get("undecided") else "")
                       + f"): {ros.get('decision')}.")]
        sr = rep["gains"].get("stiction_rule")
        if sr:
            lam = ch.get("excess_stiction_length_m")
            L += ["", (f"Stiction rule (confidence {sr.get('confidence')}): {sr.get('decision')}; the chosen design's "
                       f"excess stiction length (F_s - F_c)/K_p is {_num(None if lam is None else lam * 1e6, '.3g')} "
                       f"um against the {_num(sr['limit_m'] * 1e6, '.3g')} um following-error limit; sticky "
                       f"finalists: {', '.join(sr.get('sticky') or []) or 'none'}.")]
        fb = rep["gains"].get("fallback")
        if fb:
            L += ["", (f"Fallback tier (confidence {fb.get('confidence')}): {fb.get('why')}. Candidates with K_p >= "
                       f"{_num(fb['kp_min_n_m'] / 1e3, '.3g')} kN/m keeping PM >= "
                       f"{_num(fb['reduced_floor']['phase_margin_deg'], 'g')} deg and GM >= "
                       f"{_num(fb['reduced_floor']['gain_margin_db'], 'g')} dB on the model"
                       + (" and the measured FRF: " if "frf" in rep else " (no measured FRF): ")
                       + f"{', '.join(c['design'] for c in fb.get('candidates') or []) or 'none'}"
                       + f". Decision: {fb.get('decision')}.")]
    ver = rep.get("verification", {})
    if "verdict" in rep:
        L += ["", "## Verdict", "", f"**{rep['verdict']['text']}**"]
    if ver:
        L += ["", "## Verification: before (given config) and after (stage.yaml)", "",
              ("| scenario | RMS before [nm] | RMS after [nm] | max before [nm] | max after [nm] | settled before | "
              "settled after | settling before [ms] | settling after [ms] |"), "|---|---|---|---|---|---|---|---|---|"]
        band = None
        for name, d in ver.items():
            b, a = d.get("before", {}), d.get("after", {})
            band = band or b.get("settling_tolerance_m") or a.get("settling_tolerance_m")
            L.append(f"| {name} | {_fmt(b.get('rms_error_m'), 1e9)} | {_fmt(a.get('rms_error_m'), 1e9)} | "
                     f"{_fmt(b.get('max_error_m'), 1e9)} | {_fmt(a.get('max_error_m'), 1e9)} | "
                     f"{b.get('moves_settled', '-')}/{b.get('moves', '-')} | {a.get('moves_settled', '-')}/"
                     f"{a.get('moves', '-')} | {_fmt(b.get('settling_time_max_s'), 1e3)} | "
                     f"{_fmt(a.get('settling_time_max_s'), 1e3)} |")
        L += ["", ("Both controllers run each scenario under the same conditions: a run of the controller that wipes "
                   "the stage's friction memory at the centre (moves of alternating sign and decaying amplitude, "
                   "`wipe_*`), then a run of a freshly built controller (nothing learned carries over): gently to "
                   "the centre less the approach and back, 0.3 s at rest, the scenario; the figures are from the "
                   "scenario's start on. Settling: the longest time after a move's end until the error stays within "
                   f"±{_fmt(band, 1e9)} nm.")]
    if pngs:
        L += ["", "## Plots", ""] + [f"![{Path(p).stem}]({Path(p).name})" for p in pngs]
    return "\n".join(L) + "\n"



def _rest_lines(rest: dict[str, Any] | None) -> list[str]:
    """report.md lines on the rest spring stage.yaml carries (or why it does not), from report.json's
    ``gains.chosen.rest``."""
    if not rest:
        return []
    if not rest.get("enabled"):
        why = rest.get("reason")
        return ["", "Rest spring: not used" + (f" ({why})." if why else ".")] + _trial_lines(rest)
    out = ["", (f"Rest spring: on in stage.yaml (`rest_stiffness_fraction` {_num(rest.get('rest_stiffness_fraction'), '.3g')}, "
                f"{_num(rest.get('rest_spring_n_m'), '.3g')} N/m on the identified pre-sliding stiffness "
                f"{_num(rest.get('stiffness_n_m'), '.3g')} N/m), confidence {rest.get('confidence', '-')}"
                + (f": {rest['reason']}" if rest.get("reason") else "") + ".")]
    loops = rest.get("loops") or {}
    stuck = loops.get("rest/stuck")
    if stuck:
        out.append(f"Its rest loop on the stuck stage: phase margin {_num(stuck.get('phase_margin_deg'), '.1f')} deg, "
                   f"gain margin {_num(stuck.get('gain_margin_db'), '.1f')} dB"
                   + ("" if stuck.get("healthy") else f" (below the {MIN_PM:g} deg / {MIN_GM:g} dB floor)") + ".")
    rg = rest.get("rest_gains") or {}
    if rg:
        g = (f"`rest_kd_fraction` {_num(rest.get('rest_kd_fraction'), '.3g')}, `rest_dob_bandwidth_fraction` "
             f"{_num(rest.get('rest_dob_bandwidth_fraction'), '.3g')}, `rest_spring_section_count` "
             f"{_num(rest.get('rest_spring_section_count'), '.0f')}")
        best = rg.get("best_stuck") or {}
        if rg.get("chosen") == "grid":
            out.append(f"Its rest gains ({g}): of {rg.get('grid_points', '-')} grid points, "
                       f"{rg.get('meeting_floor', '-')} meet the floor on the stuck stage; of those tried on the twins "
                       f"(the largest K_d fraction, then the most margin, first) the one that passed with the lowest "
                       f"matched-twin RMS.")
        elif not rg.get("meeting_floor"):
            out.append(f"None of the {rg.get('grid_points', '-')} rest-gain grid points meets the floor on the stuck "
                       f"stage (best: phase margin {_num(best.get('phase_margin_deg'), '.1f')} deg, gain margin "
                       f"{_num(best.get('gain_margin_db'), '.1f')} dB); the spring is tried with the controller's own "
                       f"rest gains ({g}).")
        else:
            out.append(f"Of {rg.get('grid_points', '-')} rest-gain grid points {rg.get('meeting_floor', '-')} meet the "
                       f"floor on the stuck stage, but those tried failed on the twin; the spring is tried with the "
                       f"controller's own rest gains ({g}).")
    out += _trial_lines(rest)
    if rest.get("relies_on"):
        out.append(f"It relies on {rest['relies_on']}.")
    return out


def _trial_lines(rest: dict[str, Any]) -> list[str]:
    """report.md lines on the rest-gain grid points tried on the twin and why they failed."""
    out: list[str] = []
    for t in (rest.get("rest_gains") or {}).get("twin_trials") or []:
        out.append(f"Tried on the twins: `rest_kd_fraction` {_num(t.get('rest_kd_fraction'), '.3g')}, "
                   f"`rest_dob_bandwidth_fraction` {_num(t.get('rest_dob_bandwidth_fraction'), '.3g')}, "
                   f"`rest_spring_section_count` {_num(t.get('rest_spring_section_count'), '.0f')} (phase margin "
                   f"{_num(t.get('phase_margin_deg'), '.1f')} deg, gain margin {_num(t.get('gain_margin_db'), '.1f')}"
                   f" dB): {t.get('twin', '-')}" + ("; passed." if t.get("passed") else "."))
    return out


def write_report(res: Results, out: Path, plots: bool) -> dict[str, Any]:
    rep = report_dict(res)
    pngs: list[str] = []
    if plots:
        from stagectl.commission.plots import write_plots

        pngs = write_plots(res, out)
    rep["plots"] = [Path(p).name for p in pngs]
    (out / "report.json").write_text(json.dumps(rep, indent=1, allow_nan=True), encoding="utf-8")
    (out / "report.md").write_text(report_markdown(rep, pngs), encoding="utf-8")
    return rep
