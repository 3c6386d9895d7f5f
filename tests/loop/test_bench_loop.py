"""``stagectl bench loop``'s per-cycle breakdown: every part of the cycle is timed, the simulated devices are
counted apart, and the real-time pass reports the sleep floor beside the cycle. Structure only: timing figures
are measured by the bench, never asserted here."""

from __future__ import annotations

import dataclasses

import pytest
from stagectl.bench import loop as bench_loop
from stagectl.config import IoKind, load_app_config


@pytest.mark.parametrize("io", [IoKind.EMBEDDED_CANOPEN, IoKind.PLANT_IO])
def test_breakdown_times_every_part_and_keeps_the_simulated_devices_apart(io):
    cfg = load_app_config(bench_loop.REPO_CONFIG)
    rt_off = dataclasses.replace(cfg.loop.realtime, gc_freeze=False)  # (the test process keeps its gc)
    cfg = dataclasses.replace(cfg, io=dataclasses.replace(cfg.io, kind=io),
                              loop=dataclasses.replace(cfg.loop, realtime=rt_off))
    stages: list[tuple[str, float]] = []
    out = bench_loop.breakdown(cfg, 300, on_stage=lambda what, s: stages.append((what, s)))
    assert [s for _, s in stages] == pytest.approx(list(bench_loop.breakdown_plan(cfg.loop.period_s, 300)))
    assert all(s > 0.0 for _, s in stages)  # each stage is planned: the line shows no "0 s left" there
    hot, rt = out["hot"], out["realtime"]
    labels = {label for label, _, _ in bench_loop.PARTS}
    assert set(hot["parts"]) == labels | {"loop_other"}
    calls = {k: v["calls_per_cycle"] for k, v in hot["parts"].items() if k != "loop_other"}
    assert calls["safety_checks"] == pytest.approx(3.0) and calls["controller"] == pytest.approx(1.0)
    assert all(0.99 <= c <= 1.1 for k, c in calls.items() if k != "safety_checks")  # sync/read: + start-up
    assert all(v["p50_us"] >= 0.0 for k, v in hot["parts"].items() if k != "loop_other")
    assert len(hot["own_us_per_cycle_runs"]) == hot["runs"] and hot["own_us_per_cycle"] > 0.0
    assert hot["target_met"] == (hot["own_us_per_cycle"] <= bench_loop.HOT_TARGET_US)
    if io is IoKind.EMBEDDED_CANOPEN:  # the virtual drive and plant, served through the driver's pump
        assert hot["simulated_devices_us_per_cycle"] > 0.0 and rt["simulated_devices_cpu_per_cycle_us"] > 0.0
    else:  # PlantIO has no pump: nothing is taken out
        assert hot["simulated_devices_us_per_cycle"] == 0.0 and rt["simulated_devices_cpu_per_cycle_us"] == 0.0
    assert rt["cycles"] == 300 and rt["sleep_floor_cpu_per_cycle_us"] > 0.0
    assert rt["own_minus_sleep_floor_us"] == pytest.approx(rt["own_cpu_per_cycle_us"]
                                                           - rt["sleep_floor_cpu_per_cycle_us"])
    spun = rt["spinning"]  # the same cycles busy-waiting through the period: the CPU is never given up
    assert spun["cycles"] == 300 and spun["exec_p50_us"] > 0.0
    cold = rt["cold_after_sleep_us"]["cycle_exec_p50"]
    assert cold == pytest.approx(rt["exec_p50_us"] - spun["exec_p50_us"])
    assert set(rt["during_cycles"]) == {"page_faults", "voluntary_switches_per_cycle", "involuntary_switches",
                                        "gc_collections"}
    assert rt["during_cycles"]["voluntary_switches_per_cycle"] > 0.5  # it sleeps every cycle ...
    assert spun["during_cycles"]["voluntary_switches_per_cycle"] < 0.5  # ... and spinning, it does not


def test_progress_plan_includes_the_breakdown(monkeypatch):
    """The progress line's plan covers the loop run and both breakdown stages: while the breakdown runs, part
    of the plan is still ahead (the review leftover: that stage showed "0 s left")."""
    import argparse

    from stagectl import config

    load = config.load_app_config

    def load_keeping_gc(path):  # (the test process keeps its gc: no gc.freeze)
        cfg = load(path)
        return dataclasses.replace(cfg, loop=dataclasses.replace(
            cfg.loop, realtime=dataclasses.replace(cfg.loop.realtime, gc_freeze=False)))

    monkeypatch.setattr(config, "load_app_config", load_keeping_gc)
    parser = argparse.ArgumentParser()
    bench_loop.add_arguments(parser)
    args = parser.parse_args(["--duration", "0.1", "--breakdown-cycles", "300"])
    told: list[tuple[float, float, str, float]] = []
    args.progress = lambda done, total, what, span: told.append((done, total, what, span))
    out = bench_loop.run(args)
    assert out["cycle_breakdown"] is not None
    hot_s, rt_s = bench_loop.breakdown_plan(0.001, 300)
    assert [t for _, t, _, _ in told] == pytest.approx([0.1 + hot_s + rt_s] * len(told))
    stages = [(d, t, sp) for d, t, w, sp in told if "breakdown" in w]
    assert len(stages) == 2
    assert all(t - d >= sp > 0.0 for d, t, sp in stages)
    assert stages[1][0] == pytest.approx(0.1 + hot_s) and told[-1][:2] == (told[-1][1], told[-1][1])
    # the feed-forward cost: the plain-Python twin and the compiled kernel computed the same forces
    ff = out["feedforward"]
    assert ff["plain"]["plain_python"] and not ff["compiled"]["plain_python"] and ff["model"] == "gms"
    assert ff["max_force_difference_n"] == 0.0 and ff["force_range_n"] > 1.0  # it slid both ways (Fc 1 N)
