"""``stagectl warm [--config FILE ...] [--all]``: compile the kernels a configuration uses into the cache.

Run it at install time (and as the daemon unit's ``ExecStartPre``) so that the first start loads compiled
kernels instead of compiling them (docs/performance.md). With ``--config`` it compiles, for every friction model
and every simulated plant found in the configuration, exactly the kernels ``stagectl run`` / the daemon use:
the model's step and force (feed-forward), the plant's per-cycle step and its fused ``simulate`` loop. A config
with ``io.kind: canopen`` (a real stage: no plant in that process) has a plain-Python feed-forward and nothing to
warm but its ``sim:`` section's plant, if any (for ``stagectl sim-plant``); its path is listed under
``plain_feedforward``, and without a ``sim:`` section numba is not even imported. ``--all``
does it for every registered friction model (a GMS, LuGre, … parameter set each) instead. Prints one JSON line: the cache
directory, the kernels compiled and loaded, the time taken.
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("warm", help="compile the numba kernels a config uses into the cache (install / first start)")
    p.add_argument("--config", action="append", default=[], help="stagectl YAML (repeatable)")
    p.add_argument("--all", action="store_true", help="every registered friction model (default without --config)")
    p.set_defaults(func=run)


def _collect(obj: Any, models: list[Any], plants: list[Any], seen: set[int]) -> None:
    """Every FrictionModel and PlantConfig reachable through dataclass fields, sequences and mappings."""
    import dataclasses

    from stagectl.friction import FrictionModel
    from stagectl.sim.plant import PlantConfig

    if id(obj) in seen:
        return
    seen.add(id(obj))
    if isinstance(obj, FrictionModel):
        models.append(obj)
        return
    if isinstance(obj, PlantConfig):
        plants.append(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        for f in dataclasses.fields(obj):
            _collect(getattr(obj, f.name), models, plants, seen)
    elif isinstance(obj, (list, tuple)):
        for e in obj:
            _collect(e, models, plants, seen)
    elif isinstance(obj, dict):
        for e in obj.values():
            _collect(e, models, plants, seen)


def warm_models(models: list[Any], plants: list[Any]) -> dict[str, Any]:
    """Compile (or load) the kernels of ``models`` (step, force) and of ``plants`` (per-cycle step, fused loop,
    batch not)."""
    import numpy as np

    from stagectl.jit import cache_dir, compiled_signatures, loaded_from_cache
    from stagectl.sim.plant import StagePlant

    t0 = time.perf_counter()
    disps: list[Any] = []
    for m in models:
        st = m.initial_state()
        m.force(st, 0.0)
        m.step(st, 1e-9, 1e-5, 1e-4)
        k = m.kernel()
        disps += [k.step, k.force]
    for pc in plants:
        plant = StagePlant(pc)
        plant.step(0.0, 1e-3)
        plant.simulate(np.zeros(2), 1e-3, outputs=("x",))
        disps.append(plant._integrate)
        if plant._cycle is not None:  # the per-cycle step of a plain plant (what run/the daemon step)
            disps.append(plant._cycle)
    uniq = {id(d): d for d in disps}.values()
    return {
        "cache_dir": str(cache_dir()),
        "kernels": len(uniq),
        "signatures": sum(compiled_signatures(d) for d in uniq),
        "loaded_from_cache": sum(loaded_from_cache(d) for d in uniq),
        "seconds": time.perf_counter() - t0,
        "models": sorted({m.tag for m in models}),
        "plants": len(plants),
    }


def run(args: argparse.Namespace) -> int:
    from stagectl.friction import build, registry

    models: list[Any] = []
    plants: list[Any] = []
    plain_ff: list[str] = []
    if args.config:
        from stagectl.config import load_app_config

        from stagectl.config import IoKind

        seen: set[int] = set()
        for path in args.config:
            cfg = load_app_config(path)
            if cfg.io.kind is IoKind.CANOPEN:
                # no plant in run's/the daemon's process: the feed-forward steps its model as plain Python (no
                # numba, nothing to warm); a sim: section's plant is for a sim-plant process, which compiles
                plain_ff.append(str(path))
                _collect(cfg.sim, models, plants, seen)
            else:
                _collect(cfg, models, plants, seen)
    if args.all or not args.config:
        from stagectl.bench.models import SPECS, _spec_for
        from stagectl.sim.plant import PlantConfig

        for tag in sorted(registry()):
            spec = _spec_for(tag) or SPECS.get(tag)
            if spec is None:
                continue
            m = build(spec)
            models.append(m)
            try:
                plants.append(PlantConfig(mass_kg=1.0, friction=m, substep_s=1e-6))
            except ValueError:  # a sub-step limit of this parameter set: the model kernels are warmed anyway
                pass
    print(json.dumps({**warm_models(models, plants), "plain_feedforward": plain_ff}))
    return 0
