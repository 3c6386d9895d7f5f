"""``stagectl model plot MODEL.yaml --out DIR`` and ``stagectl model compare A.yaml B.yaml --out DIR``.

``plot`` writes the virgin curve, nested hysteresis loops and the Stribeck curve of a model file as PNG
(``virgin.png``, ``hysteresis.png``, ``stribeck.png``); ``compare`` overlays two model files
(``virgin_compare.png``, ...) and reports the RMS / max difference of their virgin curves. Both print the
written paths, or a JSON summary with ``--json``. Model files: see ``stagectl.friction.StageModel``
(a bare ``friction`` mapping with ``model:`` is accepted too).
"""

from __future__ import annotations

import argparse

from stagectl.commands.args import number


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("model", help="plot or compare friction model files (virgin curve, loops, Stribeck)")
    acts = p.add_subparsers(dest="model_action", metavar="ACTION")

    def common(q: argparse.ArgumentParser) -> None:
        q.add_argument("--out", required=True, help="output directory for the PNG files (created)")
        q.add_argument("--x-max-um", type=number("µm", lo=0, lo_open=True), default=30.0,
                       help="virgin-curve range [µm] (default 30); loops use 2/3 of it")
        q.add_argument("--json", action="store_true", help="print a JSON summary instead of the paths")

    pp = acts.add_parser("plot", help="virgin curve, nested hysteresis loops and Stribeck curve of MODEL.yaml")
    pp.add_argument("model", metavar="MODEL.yaml")
    common(pp)
    pp.set_defaults(func=run_plot)
    pc = acts.add_parser("compare", help="overlay the curves of two model files (e.g. GMS vs Hsieh, Fig. 4)")
    pc.add_argument("model_a", metavar="A.yaml")
    pc.add_argument("model_b", metavar="B.yaml")
    common(pc)
    pc.set_defaults(func=run_compare)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def _load(path: str):  # type: ignore[no-untyped-def]
    from pathlib import Path

    from stagectl.friction import load_model_file

    p = Path(path)
    return load_model_file(p).friction, p.stem


def _x_max(args: argparse.Namespace) -> float:
    from stagectl.errors import ConfigError

    if not (args.x_max_um > 0.0):
        raise ConfigError(f"--x-max-um: must be > 0 µm (got {args.x_max_um:g})")
    return float(args.x_max_um) * 1e-6


def run_plot(args: argparse.Namespace) -> int:
    import json

    from stagectl import plots

    x_max = _x_max(args)
    model, label = _load(args.model)
    curves = plots.compute_curves(model, f"{label} ({model.tag})", x_max)
    files = plots.plot_curves([curves], args.out)
    if args.json:
        print(json.dumps({"model": str(args.model), "tag": model.tag, "files": [str(f) for f in files],
                          "summary": plots.summary(curves, model)}, indent=2))
    else:
        for f in files:
            print(f)
    return 0


def run_compare(args: argparse.Namespace) -> int:
    import json

    from stagectl import plots

    x_max = _x_max(args)
    ma, la = _load(args.model_a)
    mb, lb = _load(args.model_b)
    ca = plots.compute_curves(ma, f"{la} ({ma.tag})", x_max)
    cb = plots.compute_curves(mb, f"{lb} ({mb.tag})", x_max)
    files = plots.plot_curves([ca, cb], args.out, suffix="_compare")
    diff = plots.compare_virgin(ca, cb)
    if args.json:
        print(json.dumps({"models": [str(args.model_a), str(args.model_b)], "files": [str(f) for f in files],
                          "summary": [plots.summary(ca, ma), plots.summary(cb, mb)], "difference": diff}, indent=2))
    else:
        for f in files:
            print(f)
        print(f"virgin curves over 0-{diff['range_m'] * 1e6:g} µm: RMS difference {diff['virgin_rms_diff_n']:.4f} N, "
              f"max {diff['virgin_max_abs_diff_n']:.4f} N")
    return 0
