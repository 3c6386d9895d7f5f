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
#: look the same thinned evenly, and Agg draws markers one by one
MAX_SCATTER_POINTS = 4000
#: PNG encoder options: zlib level 1 instead of PIL's 6 (a third of the encoding time for files ~20 % larger;
#: the pixels are the same). Titles are placed at y = 1 explicitly (``set_title(..., y=1.0)``): the automatic
#: placement measures every tick label's extent to avoid top-side labels these axes do not have, the same
#: place for a quarter of the drawing time.
_PNG = {"compress_level": 1}


def _plots(res: dsc.DiscoveryResult, out: Path) -> list[str]:
    # heavy optional library, imported only when plots are written; Figure without pyplot (no GUI backend
    # machinery to import, nothing global to close)
    from matplotlib.figure import Figure

    def subplots(*grid: int, **kw: Any) -> tuple[Any, Any]:
        fig = Figure(figsize=kw.pop("figsize"))
        ax = fig.subplots(*grid, **kw)
        return fig, ax

    ds = res.dataset
    if ds is None:
        raise ValueError("plots need the result's dataset")
    sig, rows = ds.val, ds.val_rows
    r0 = rg.residual(sig, res.start.hyp)
    r1 = rg.residual(sig, res.final.hyp)
    files: list[str] = []
    t = sig.t

    fig, ax = subplots(2, 1, figsize=(10, 6), sharex=True)
    r0p = np.where(rows, r0, np.nan)
    r1p = np.where(rows, r1, np.nan)
    ax[0].plot(t, r0p, lw=0.6, label=f"start model (RMS {res.gap_before:.4g} N)")
    ax[0].plot(t, r1p, lw=0.6, label=f"final model (RMS {res.gap_after:.4g} N)")
    ax[0].set_ylabel("force residual [N]")
    ax[0].legend(loc="upper right", fontsize=8)
    ax[0].set_title("validation residual over time", y=1.0)
    ax[1].plot(t, sig.xf, lw=0.8, color="k")
    ax[1].set_ylabel("position [m]")
    ax[1].set_xlabel("time [s]")
    fig.subplots_adjust(left=0.08, right=0.98, top=0.95, bottom=0.09, hspace=0.12)  # fixed: tight_layout draws twice
    fig.savefig(out / "residual_time.png", dpi=90, pil_kwargs=_PNG)
    files.append("residual_time.png")

    regs = regimes(sig, rows)
    names = [k for k, m in regs.items() if m.any()]
    b = [float(np.sqrt(np.mean(r0[regs[k]] ** 2))) for k in names]
    a = [float(np.sqrt(np.mean(r1[regs[k]] ** 2))) for k in names]
    fig, ax = subplots(figsize=(10, 4))
    y = np.arange(len(names))
    ax.barh(y - 0.2, b, 0.4, label="start model")
    ax.barh(y + 0.2, a, 0.4, label="final model")
    ax.set_yticks(y, [n.split(" (")[0] for n in names], fontsize=8)
    ax.set_xlabel("RMS force residual [N]")
    ax.set_title("validation residual by regime", y=1.0)
    ax.legend(fontsize=8)
    fig.subplots_adjust(left=0.2, right=0.98, top=0.9, bottom=0.13)
    fig.savefig(out / "residual_regimes.png", dpi=90, pil_kwargs=_PNG)
    files.append("residual_regimes.png")

    fig, ax = subplots(1, 2, figsize=(11, 4))
    idx = np.flatnonzero(rows)
    idx = idx[:: max(1, -(-idx.size // MAX_SCATTER_POINTS))]
    for rr, lab in ((r0, "start"), (r1, "final")):
        ax[0].plot(sig.xf[idx], rr[idx], ".", ms=1, label=lab)
        ax[1].plot(sig.v[idx], rr[idx], ".", ms=1, label=lab)
    ax[0].set_xlabel("position [m]")
    ax[1].set_xlabel("velocity [m/s]")
    for a_ in ax:
        a_.set_ylabel("force residual [N]")
        a_.legend(fontsize=8, markerscale=8)
    ax[0].set_title("residual by position", y=1.0)
    ax[1].set_title("residual by velocity", y=1.0)
    fig.subplots_adjust(left=0.07, right=0.99, top=0.92, bottom=0.13, wspace=0.25)
    fig.savefig(out / "residual_position_velocity.png", dpi=90, pil_kwargs=_PNG)
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
