"""``stagectl bench models``: result structure and targets (smoke run; speed is judged by the benchmark)."""

from __future__ import annotations

import argparse
import json

from stagectl.bench import models as bench


def test_bench_models_quick_run_reports_every_figure_and_target(capsys):
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    args = parser.parse_args(["--quick", "--steps", "3000", "--sets", "4", "--repeat", "1",
                              "--models", "gms,hsieh,stribeck", "--first-steps", "3000"])
    told: list[tuple[float, float, str, float]] = []
    args.progress = lambda *a: told.append(a)  # what `stagectl bench` puts there: its progress line's tell
    out = bench.run(args)
    assert [(d, tot) for d, tot, _, _ in told] == [(0, 4), (1, 4), (2, 4), (3, 4)]  # 3 models, then the baselines
    assert told[1][2] == "model 2 of 3, hsieh"
    json.dumps(out)  # --json must be able to print it
    assert out["baseline_python_gms_steps_per_s"] > 0
    assert set(out["models"]) == {"gms", "hsieh", "stribeck"}
    for tag, entry in out["models"].items():
        assert "skipped" not in entry, (tag, entry)
        for key in ("single_steps_per_s", "batch_steps_per_s", "per_sample_step_us", "plant_step_100us_us",
                    "single_vs_baseline", "warmup_s"):
            assert entry[key] > 0, (tag, key)
        assert entry["batch_sets"] == 4
    t = out["targets"]
    base = {"gms_single_steps_per_s", "gms_single_vs_baseline", "gms_per_sample_step_us"}
    c = out["c_reference"]
    if "skipped" in c:  # no C compiler on this machine: said so, no C targets
        assert "compiler" in c["skipped"] and set(t) == base
    else:
        assert set(t) == base | {"gms_single_vs_c", "gms_first_call_vs_c", "gms_batch_vs_c"}
        # the C reference integrates the same recurrence: the trajectories agree (to rounding)
        assert c["c_max_abs_dx_m"] <= 1e-12 and c["c_batch_max_abs_dx_m"] <= 1e-12
        assert t["gms_single_vs_c"]["target"] == 0.9 and t["gms_batch_vs_c"]["target"] == 1.0
    assert t["gms_single_steps_per_s"]["target"] == 2_000_000.0 and t["gms_single_vs_baseline"]["target"] == 20.0
    assert t["gms_per_sample_step_us"]["met"] == (t["gms_per_sample_step_us"]["value"] <= 10.0)
