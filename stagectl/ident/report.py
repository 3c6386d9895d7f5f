"""Discovery outputs: ``report.json``, ``report.md`` with PNG plots, and the augmented model file."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from stagectl.friction import save_model_file
from stagectl.ident import discover as dsc
from stagectl.ident import effects as fx
from stagectl.ident import regress as rg
from stagectl.ident.hypothesis import Hyp
from stagectl.ident.localise import regimes
from stagectl.ident.modelio import hyp_to_model, hyp_to_spec
from stagectl.ident.results import BOOT_QUANTILE, BOOT_SAMPLES, MIN_REL_GAIN
from stagectl.outputs import plain, prepare_out_dir


def base_model_text(h: Hyp) -> str:
    """What the model file's friction section really is (its tag can hold less than it says)."""
    names = [e for e in h.effects]
    if h.given_spec is not None:
        return f"base model: the given {h.given_spec.get('model')} friction model, rescaled"
    parts = ["mass", "Coulomb", "viscous friction"]
    if "stribeck" in names:
        rising = h.theta.get("ds", 0.0) < 0.0  # Fs < Fc
        parts.append(("a low-speed friction curve rising with speed (Fs < Fc)" if rising else "a Stribeck curve")
                     + (" with frictional lag" if "frictional_lag" in names else ""))
    if "presliding" in names:
        parts.append("pre-sliding (Maxwell-slip elements)")
    tag = "gms" if "presliding" in names else "stribeck"
    extra = [e for e in names if e not in ("stribeck", "frictional_lag", "presliding")]
    txt = f"base model: {', '.join(parts)}, written with the `{tag}` tag"
    if tag == "stribeck" and "stribeck" not in names:
        txt += " (fs_n = fc_n: no Stribeck effect was found, the tag only holds Coulomb + viscous)"
    if extra:
        txt += f"; effects: {', '.join(extra)}"
    return txt


def build_report(res: dsc.DiscoveryResult, sources: dict[str, str]) -> dict[str, Any]:
    """The ``report.json`` mapping (plain JSON data: non-finite numbers are ``None``)."""
    ds = res.dataset
    if ds is None:
        raise ValueError("build_report needs the result's dataset")
    rep: dict[str, Any] = plain({
        "gap_metric": dsc.GAP_METRIC,
        "gap_before": res.gap_before,
        "gap_after": res.gap_after,
        "gap_unit": "N",
        "effects": [e.as_json() for e in res.effects],
        "rejected": [r.as_json() for r in res.rejected],
        "disagreement": res.disagreement_before,
        "disagreement_after": res.disagreement_after,
        "validation": res.split,
        "acceptance_rule": {
            "min_relative_gap_reduction": MIN_REL_GAIN,
            "min_explained_force_fraction_of_rms_u_minus_ma": dsc.MIN_EXPLAINED_FRACTION,
            "min_explained_force_times_noise_floor": dsc.MIN_EXPLAINED_NOISE,
            "min_explained_force_n": res.min_explained_n,
            "noise_floor_n": res.noise_floor_n,
            "bootstrap": f"circular block bootstrap of the mean per-sample squared-residual reduction, "
                         f"{BOOT_SAMPLES} resamples, lower {100 * BOOT_QUANTILE:.1f} % quantile > 0",
            "nested": {k: list(v) for k, v in fx.REGISTRY.nested().items()},
        },
        "rounds": [r.as_json() for r in res.rounds],
        "start_model": hyp_to_spec(res.start.hyp),
        "final_model": hyp_to_spec(res.final.hyp),
        "samples": {"estimation": int(ds.est_rows.sum()), "validation": int(ds.val_rows.sum())},
        "data_notes": [*ds.est.notes, *([] if ds.val is ds.est else ds.val.notes)],
        "base_model": base_model_text(res.final.hyp),
        "filter_cutoff_hz": ds.est.cutoff_hz,
        "stick_threshold_m_s": ds.est.v_stick,
        "sources": sources,
        "elapsed_s": res.elapsed_s,
    }, json=True)
    return rep


def write_outputs(res: dsc.DiscoveryResult, out_dir: str | Path, sources: dict[str, str],
                  plots: bool = True) -> dict[str, Any]:
    """Write report.json, report.md, plots and ``model.yaml`` into ``out_dir``; return the report."""
    out = prepare_out_dir(out_dir)
    rep = build_report(res, sources)
    meta = {
        "source": "stagectl discover",
        "data": sources,
        "effects_found": [e.name for e in res.effects],
        "gap_metric": "force_residual_rms_n (validation)",
        "gap_before_n": rep["gap_before"],
        "gap_after_n": rep["gap_after"],
    }
    model = hyp_to_model(res.final.hyp, meta)
    save_model_file(model, out / "model.yaml",
                    header=f"model written by `stagectl discover` (see report.md); {base_model_text(res.final.hyp)}")
    rep["model_file"] = str(out / "model.yaml")
    pngs = _plots(res, out) if plots else []
    rep["plots"] = pngs
    (out / "report.json").write_text(json.dumps(rep, indent=2), encoding="utf-8")
    (out / "report.md").write_text(_markdown(rep, pngs), encoding="utf-8")
    return rep


#: at most this many points per scatter series: the residual-by-position/velocity clouds of a long recording
#: look the same thinned evenly
MAX_SCATTER_POINTS = 4000


def _plots(res: dsc.DiscoveryResult, out: Path) -> list[str]:
    # drawn with Pillow (stagectl.ident.figures): matplotlib's import and its tick/text objects cost ~0.6 s of CPU
    from stagectl.ident.figures import COLORS, Figure

    ds = res.dataset
    if ds is None:
        raise ValueError("plots need the result's dataset")
    sig, rows = ds.val, ds.val_rows
    r0 = rg.residual(sig, res.start.hyp)
    r1 = rg.residual(sig, res.final.hyp)
    files: list[str] = []
    t = sig.t

    fig = Figure(900, 540)
    top = fig.panel(0.08, 0.05, 0.98, 0.50)
    bot = fig.panel(0.08, 0.56, 0.98, 0.91)
    r0p = np.where(rows, r0, np.nan)
    r1p = np.where(rows, r1, np.nan)
    top.limits([t], [r0p, r1p])
    top.grid()
    top.line(t, r0p, COLORS[0], 0.6, f"start model (RMS {res.gap_before:.4g} N)")
    top.line(t, r1p, COLORS[1], 0.6, f"final model (RMS {res.gap_after:.4g} N)")
    top.axes(ylabel="force residual [N]", title="validation residual over time", xticks=False)
    top.legend()
    bot.limits([t], [sig.xf])
    bot.xlim = top.xlim
    bot.grid()
    bot.line(t, sig.xf, "black", 0.8)
    bot.axes(xlabel="time [s]", ylabel="position [m]")
    fig.save(out / "residual_time.png")
    files.append("residual_time.png")

    regs = regimes(sig, rows)
    names = [k for k, m in regs.items() if m.any()]
    b = [float(np.sqrt(np.mean(r0[regs[k]] ** 2))) for k in names]
    a = [float(np.sqrt(np.mean(r1[regs[k]] ** 2))) for k in names]
    fig = Figure(900, 360)
    ax = fig.panel(0.2, 0.1, 0.98, 0.87)
    y = np.arange(len(names), dtype=float)
    ax.xlim = (0.0, 1.05 * max([*b, *a, 1e-12]))
    ax.ylim = (len(names) - 0.4, -0.6)  # first regime at the top
    ax.grid(yticks=[])
    ax.hbars(y - 0.2, b, 0.4, COLORS[0], "start model")
    ax.hbars(y + 0.2, a, 0.4, COLORS[1], "final model")
    ax.axes(xlabel="RMS force residual [N]", title="validation residual by regime", font=10,
            yticklabels=[(float(i), n.split(" (")[0]) for i, n in enumerate(names)])
    ax.legend(lower=True)
    fig.save(out / "residual_regimes.png")
    files.append("residual_regimes.png")

    fig = Figure(990, 360)
    panels = (fig.panel(0.07, 0.08, 0.50, 0.87), fig.panel(0.57, 0.08, 0.99, 0.87))
    idx = np.flatnonzero(rows)
    idx = idx[:: max(1, -(-idx.size // MAX_SCATTER_POINTS))]
    for p, xv, xlabel, title in ((panels[0], sig.xf, "position [m]", "residual by position"),
                                 (panels[1], sig.v, "velocity [m/s]", "residual by velocity")):
        p.limits([xv[idx]], [r0[idx], r1[idx]])
        p.grid()
        for k, (rr, lab) in enumerate(((r0, "start"), (r1, "final"))):
            p.dots(xv[idx], rr[idx], COLORS[k], lab)
        p.axes(xlabel=xlabel, ylabel="force residual [N]", title=title)
        p.legend()
    fig.save(out / "residual_position_velocity.png")
    files.append("residual_position_velocity.png")
    return files


def _markdown(rep: dict[str, Any], pngs: list[str]) -> str:
    lines = ["# stagectl discover report", ""]
    lines.append(f"- estimation data: `{rep['sources'].get('estimation')}`")
    lines.append(f"- validation: {rep['validation']}")
    lines.append(f"- gap metric: {rep['gap_metric']}")
    lines.append(f"- **validation gap: {rep['gap_before']:.5g} N (start) → {rep['gap_after']:.5g} N (final)**")
    lines.append(f"- run time: {rep['elapsed_s']:.1f} s")
    lines.append(f"- {rep['base_model']}")
    for note in rep.get("data_notes", []):
        lines.append(f"- note: {note}")
    lines.append("")
    lines.append("## Effects found (in order)")
    if not rep["effects"]:
        lines.append("No effect was accepted: no catalogue effect reduced the validation gap by the required "
                     f"margin ({100 * rep['acceptance_rule']['min_relative_gap_reduction']:.0f} % and a "
                     "positive block-bootstrap bound), globally or in the regime where it acts.")
    for i, e in enumerate(rep["effects"], 1):
        params = ", ".join(f"{k} = {v:.6g}" if isinstance(v, float) else f"{k} = {v}"
                           for k, v in e["parameters"].items())
        lines.append(f"{i}. **{e['name']}** ({params}): gap {e['gap_before']:.5g} → {e['gap_after']:.5g} N.  ")
        lines.append(f"   Evidence: {e['evidence']}")
    lines.append("")
    lines.append("## Not accepted")
    if not rep["rejected"]:
        lines.append("Every candidate is listed per round below.")
    for e in rep["rejected"]:
        lines.append(f"- {e['name']}: {e['reason']}")
    lines.append("")
    lines.append("## Where the start model disagrees (validation data)")
    lines.append("| kind | where | share of samples | RMS [N] | mean [N] | share of squared residual |")
    lines.append("|---|---|---|---|---|---|")
    for d in rep["disagreement"]:
        where = d["regime"].replace("|", "\\|")
        lines.append(f"| {d['kind']} | {where} | {d['share_of_samples']:.3f} | {d['rms_n']:.4g} | "
                     f"{d['mean_n']:+.4g} | {d['share_of_squared_residual']:.3f} |")
    lines.append("")
    lines.append("## Candidates per round")
    lines.append("Every candidate tried: gain on estimation data (fit) and on validation data (decides), in its "
                 "regime where it acts in one, its key parameter, and the verdict.")
    lines.append("")
    for i, r in enumerate(rep["rounds"], 1):
        lines.append(f"Round {i}: chosen **{r['chosen'] or 'none'}**")
        lines.append("")
        lines.append("| effect | key parameter | estimation gain | validation gap [N] | validation gain | "
                     "regime gain | verdict |")
        lines.append("|---|---|---|---|---|---|---|")
        for c in r["candidates"]:
            if "error" in c:
                lines.append(f"| {c['name']} | – | – | – | – | – | error: {c['error']} |")
                continue
            reg = (f"{100 * c['regime_rel_gain']:.1f} % ({c['regime'].split('_')[0]}…)"
                   if c.get("regime_rel_gain") is not None else "–")
            verdict = str(c.get("verdict") or "").replace("|", "\\|")
            key = str(c.get("key_parameter") or "–").replace("|", "\\|")
            lines.append(f"| {c['name']} | {key} | {100 * c['estimation_rel_gain']:.1f} % | {c['gap_before']:.5g} → "
                         f"{c['gap_after']:.5g} | {100 * c['rel_gain']:.1f} % | {reg} | {verdict} |")
        lines.append("")
    lines.append("## Plots")
    for p in pngs:
        lines.append(f"![{p}]({p})")
    lines.append("")
    lines.append(f"Augmented model: `{rep.get('model_file')}` (loadable by `stagectl.friction.load_model_file`).")
    return "\n".join(lines) + "\n"
