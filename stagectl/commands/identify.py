"""``stagectl identify DATA.csv --model NAME --out MODEL.yaml [--plot DIR] [--columns ...] [--elements N] [--json]``.

Identifies a friction model (gms, maxwell_slip, stribeck, lugre, dahl, hsieh) from a recording, judges the
fit (verdict good / fair / poor from the force error and the parameters' standard deviations; exit status 3
for poor, with what to record instead) and writes a model file (``mass_kg`` when the data excite it, ``friction``, ``meta`` with the fit quality) that
``stagectl.friction.load_model_file`` and the plant load. See :mod:`stagectl.ident.identify`.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING, Any

from stagectl.commands.args import number
from stagectl.errors import ConfigError
from stagectl.outputs import plain, prepare_out_dir, prepare_out_file
from stagectl.schema import load

if TYPE_CHECKING:
    from stagectl.ident.identify import Identified

MODELS = ("gms", "maxwell_slip", "stribeck", "lugre", "dahl", "hsieh")


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("identify", help="fit a friction model to a recording and write a model file",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", help="recording CSV (columns t [s], x [m], u [N]; see --columns)")
    p.add_argument("--model", required=True, choices=MODELS, help="friction model to identify")
    p.add_argument("--out", required=True, help="model file to write (YAML)")
    p.add_argument("--plot", metavar="DIR", help="write measured-vs-model plots (PNG) into DIR")
    p.add_argument("--columns", help="column mapping, e.g. t=t_s,x=position_m,u=force_N")
    p.add_argument("--elements", type=int, default=None,
                   help="number of Maxwell-slip/GMS elements (default: chosen by BIC, 1..8)")
    p.add_argument("--mass-kg", type=number("kg", lo=0, lo_open=True), default=None, help="known moving mass [kg] (default: estimated)")
    p.add_argument("--cutoff-hz", type=number("Hz", lo=0, lo_open=True), default=None, help="inverse-dynamics low-pass cut-off [Hz]")
    p.add_argument("--json", action="store_true", help="print the fit quality as JSON")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr (for scripts)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # identification pulls in scipy and numba (~0.5 s): imported when the command runs, not for `--help`
    from stagectl.friction import StageModel, save_model_file
    from stagectl.ident.identify import identify
    from stagectl.ident.recording import load_recording

    if args.elements is not None and not 1 <= args.elements <= 32:
        raise ConfigError(f"--elements: must be between 1 and 32 (got {args.elements})")
    prepare_out_file(args.out)
    if args.plot:
        prepare_out_dir(args.plot, "--plot")
    from stagectl.commands.progress import Progress

    progress = Progress("identify", 3, quiet=args.quiet)
    progress.step(1, f"loading {args.data}")
    rec = load_recording(args.data, args.columns, min_rows=50)
    progress.step(2, f"fitting {args.model} to {len(rec)} rows, then its verdict")
    # the fit tells its own line: the stage, and the time left as an upper bound (its work in model runs
    # along the recording, bounded by the optimiser's budget; see stagectl.ident.identify._Runs)
    fit = Progress("identify", 1, quiet=args.quiet, stream=progress.stream)
    res = identify(rec, args.model, n_elements=args.elements, mass_kg=args.mass_kg, cutoff_hz=args.cutoff_hz,
                   progress=lambda done, total, what: fit.bounded(done, f"{args.model}: {what}", total))
    quality: dict[str, Any] = plain(res.quality, json=True)
    spec: dict[str, Any] = {"friction": res.spec, "meta": {"source": f"stagectl identify --model {args.model}",
                                                           "data": args.data, "fit": quality.get("fit", {})}}
    if res.effects:
        spec["effects"] = res.effects
    if res.mass_kg is not None:
        spec = {"mass_kg": res.mass_kg, **spec}
    progress.step(3, "writing the model file" + (" and plots" if args.plot else ""))
    try:
        model = load(StageModel, plain(spec, json=True), "")
    except ConfigError as exc:  # e.g. a negative mass: the fit ran on data in other units than SI
        raise ConfigError(
            f"{args.data}: the {args.model} fit is not physical ({exc}); check the recording's units: t in s, x in "
            f"m, u in N (here x spans {float(rec.x.max() - rec.x.min()):.4g} m, |u| up to "
            f"{float(abs(rec.u).max()):.4g} N)") from None
    try:
        save_model_file(model, args.out,
                        header=f"identified by `stagectl identify --model {args.model}` from {args.data}")
    except OSError as exc:  # a full disk (/dev/full), a vanished directory: name the file, not "output"
        raise ConfigError(f"--out: cannot write {args.out!r} ({exc.strerror or exc})") from None
    out: dict[str, Any] = {"model_file": args.out, "model": plain(res.spec, json=True),
                           "effects": plain(res.effects, json=True), "mass_kg": res.mass_kg, "quality": quality}
    if args.plot:
        out["plots"] = _plots(res, args.plot)
    progress.close()
    if args.json:
        json.dump(out, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        fit = quality.get("fit", {})
        print(f"wrote {args.out}: {args.model}, force RMS error {fit.get('force_rms_error_n', float('nan')):.4g} N "
              f"({100 * fit.get('relative_error', float('nan')):.2f} % of the RMS friction force)")
        for note in quality.get("notes", []):
            print(f"note: {note}")
    return _report_verdict(quality.get("verdict", {}), args.model)


def _report_verdict(v: dict[str, Any], model: str) -> int:
    """The verdict on stderr; exit status 3 when the recording cannot identify what was asked."""
    if not v:
        return 0
    mass = v.get("mass_std_relative")
    mass_txt = f", mass ±{100 * mass:.0f} %" if mass is not None else ""
    print(f"verdict: {v['verdict']} (force error {100 * v['force_error_relative']:.1f} %, model force determined "
          f"to ±{100 * (v.get('prediction_std_relative') or 0.0):.1f} %{mass_txt}; local estimates, see --json)",
          file=sys.stderr)
    for reason in v.get("reasons", []):
        print(f"stagectl: warning: {reason}", file=sys.stderr)
    if v.get("not_determined"):
        print(f"note: not determined by this recording: {', '.join(v['not_determined'])}", file=sys.stderr)
    for advice in v.get("record_instead", []):
        print(f"stagectl: warning: to identify {model}, record {advice}", file=sys.stderr)
    return 3 if v["verdict"] == "poor" else 0


def _plots(res: Identified, out_dir: str) -> list[str]:
    # matplotlib, scipy and the friction models (numba) are heavy: imported only when plots are written
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from scipy import signal

    from stagectl.friction import build
    from stagectl.outputs import prefix_for
    from stagectl.plots import plot_virgin_fit

    out = prepare_out_dir(out_dir, "--plot")
    sig = res.meas.sig
    fm = signal.sosfiltfilt(sig.sos, build(res.spec).force_along(sig.xf, sig.t))
    files: list[str] = []
    fig, ax = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    ax[0].plot(sig.t, res.meas.force, lw=0.7, label="measured (inverse dynamics)")
    ax[0].plot(sig.t, fm, lw=0.7, label=f"model ({res.spec['model']})")
    ax[0].set_ylabel("friction force [N]")
    ax[0].legend(fontsize=8)
    ax[1].plot(sig.t, res.meas.force - fm, lw=0.7, color="C3")
    ax[1].set_ylabel("error [N]")
    ax[1].set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(out / "force_time.png", dpi=90)
    plt.close(fig)
    files.append(str(out / "force_time.png"))
    k, unit = prefix_for(float(np.max(np.abs(sig.xf))), "m")
    fig, ax = plt.subplots(figsize=(6, 5))
    ax.plot(sig.xf * k, res.meas.force, lw=0.7, label="measured")
    ax.plot(sig.xf * k, fm, lw=0.7, label="model")
    ax.set_xlabel(f"position [{unit}]")
    ax.set_ylabel("friction force [N]")
    ax.legend(fontsize=8, framealpha=0.8)
    ax.set_title("hysteresis: force vs position")
    fig.tight_layout()
    fig.savefig(out / "force_position.png", dpi=90)
    plt.close(fig)
    files.append(str(out / "force_position.png"))
    if res.virgin is not None:
        d, f = res.virgin
        model = build(res.spec)
        # log-spaced, so that a few-µm pre-sliding region within a 1 mm curve still has hundreds of points;
        # a quasi-static ramp at 1 µm/s
        dd = np.concatenate(([0.0], np.geomspace(float(d.max()) * 1e-5, float(d.max()), 2000)))
        tt = dd / 1e-6
        files.append(str(plot_virgin_fit(d, f, dd, model.force_along(dd, tt), out / "virgin_curve.png",
                                         label=str(res.spec["model"]))))
    return files
