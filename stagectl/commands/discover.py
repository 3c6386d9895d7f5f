"""``stagectl discover DATA.csv [--model MODEL.yaml] [--validate OTHER.csv] [--columns ...] --out DIR [--json]``.

Finds where a model and a closed-loop recording disagree, names the missing effect from the catalogue
(stribeck, presliding, frictional_lag, asymmetry, position_ripple, cogging, offset, spring, delay,
viscous_asymmetry, backlash), adds it,
and accepts it only if the validation gap shrinks significantly (globally, or in the regime where the effect
acts while the global gap does not get worse); iterates. Irregularly sampled recordings are resampled onto a
uniform grid (with a note). See docs/discovery.md and
:mod:`stagectl.ident.discover` for the gap metric and the decision rule.
"""

from __future__ import annotations

import argparse
import json
import sys

from stagectl.commands.args import number
from stagectl.outputs import prepare_out_dir


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "discover",
        help="name the friction/plant effects a model is missing (validated on held-out data)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("data", help="recording CSV (columns t [s], x [m], u [N]; see --columns)")
    p.add_argument("--model", help="starting model file (default: mass + Coulomb + viscous fitted to the data)")
    p.add_argument("--validate", help="validation recording (default: held-out contiguous blocks of DATA)")
    p.add_argument("--columns", help="column mapping, e.g. t=t_s,x=position_m,u=force_N,x_ref=reference_m")
    p.add_argument("--out", required=True, help="output directory (report.json, report.md, PNGs, model.yaml)")
    p.add_argument("--cutoff-hz", type=number("Hz", lo=0, lo_open=True), default=None,
                   help="zero-phase low-pass cut-off for the inverse dynamics [Hz] (default min(fs/10, 100 Hz))")
    p.add_argument("--max-rounds", type=number("effects", lo=0, hi=20, integer=True), default=6, help="maximum number of effects to add")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--json", action="store_true", help="print report.json to stdout")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr (for scripts)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # one BLAS thread: set by stagectl.cli.main before numpy is imported
    # identification pulls in scipy and numba (~0.5 s): imported when the command runs, not for `--help`
    from stagectl.commands.progress import Progress
    from stagectl.ident.discover import discover
    from stagectl.ident.modelio import load_start
    from stagectl.ident.recording import load_recording
    from stagectl.ident.report import write_outputs

    prepare_out_dir(args.out)
    progress = Progress("discover", 3, quiet=args.quiet)
    progress.step(1, "loading the recordings")
    rec = load_recording(args.data, args.columns, min_rows=200)
    val = load_recording(args.validate, args.columns, min_rows=200) if args.validate else None
    start = load_start(args.model) if args.model else None
    progress.step(2, f"searching for missing effects (up to {args.max_rounds} rounds)")
    search = Progress("discover", args.max_rounds, quiet=args.quiet, stream=progress.stream)
    res = discover(rec, validate=val, start=start, max_rounds=args.max_rounds, cutoff_hz=args.cutoff_hz,
                   progress=search.bounded)
    search.close()
    sources = {"estimation": args.data, "validation": args.validate or "held-out blocks of estimation file"}
    if args.model:
        sources["start_model"] = args.model
    progress.step(3, "writing the report" + ("" if args.no_plots else " and plots"))
    rep = write_outputs(res, args.out, sources, plots=not args.no_plots)
    progress.close()
    if args.json:
        json.dump(rep, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(f"gap metric: force-residual RMS on validation data ({res.split})")
        for note in rep["data_notes"]:
            print(f"note: {note}")
        print(f"validation gap: {rep['gap_before']:.5g} N -> {rep['gap_after']:.5g} N")
        if not rep["effects"]:
            print("no effect accepted")
        for e in rep["effects"]:
            print(f"found {e['name']}: {e['gap_before']:.5g} -> {e['gap_after']:.5g} N; {e['evidence']}")
        for e in rep["rejected"]:
            print(f"rejected {e['name']}: {e['reason']}")
        print(f"wrote {args.out}/report.json, report.md, model.yaml ({rep['elapsed_s']:.1f} s)")
    return 0
