"""``stagectl plot RECORDING.csv [--out FILE.png] [--columns t=…,x=…,u=…] [--title TEXT]``.

Draws any recording (daemon telemetry, ``simulate``/``run`` output, commissioning recordings, a user's CSV
with t [s], x [m], u [N] and optional columns) the same way ``simulate`` draws its runs: one panel per
quantity, each axis in the unit that suits it (nm, µm, mm; mN, N), legends beside the axes. Writes
``RECORDING.png`` next to the file unless ``--out`` says otherwise.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("plot", help="draw a recording CSV (telemetry, simulate, commissioning) as a PNG",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", help="recording CSV (columns t [s], x [m], u [N], any others)")
    p.add_argument("--out", help="PNG to write (default: the recording's name with .png)")
    p.add_argument("--columns", help="column mapping, e.g. t=t_s,x=position_m,u=force_N")
    p.add_argument("--title", default=None, help="figure title (default: the file name)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from stagectl.errors import ConfigError
    from stagectl.ident.recording import load_recording
    from stagectl.outputs import prepare_out_file
    from stagectl.plots import plot_recording

    out = Path(args.out) if args.out else Path(args.data).with_suffix(".png")
    if out.suffix.lower() not in (".png", ".svg", ".pdf"):
        raise ConfigError(f"--out {out}: the image type is taken from the suffix: .png, .svg or .pdf")
    prepare_out_file(out)
    rec = load_recording(args.data, args.columns, min_rows=2)
    optional = {"x_ref": rec.x_ref, "v": rec.v, **rec.extra}
    named = {"t": rec.t, "x": rec.x, "u": rec.u, **{k: v for k, v in optional.items() if v is not None}}
    cols = list(named)
    data = np.column_stack([named[k] for k in cols])
    path = plot_recording(cols, data, out, args.title if args.title is not None else Path(args.data).name)
    print(f"wrote {path}")
    return 0
