"""``stagectl bench control --quick``: result structure, margins of the chosen tunings, the trend targets."""

from __future__ import annotations

import argparse
import json

from stagectl.bench import control as bench


def test_bench_control_quick_reports_errors_margins_and_targets():
    p = argparse.ArgumentParser()
    bench.add_arguments(p)
    args = p.parse_args(["--quick", "--hold", "0.3"])
    told: list[tuple[float, float, str, float]] = []
    args.progress = lambda *a: told.append(a)  # `stagectl bench`'s progress line: one tell per simulated run
    res = bench.run(args)
    dones = [d for d, _, _, _ in told]
    assert dones == list(range(len(told))) and told[0][2] == "pid: candidate 1 of 1, cosine"
    # 5 sweeps x (2 tracking scenarios + the steps run), then 1 or 2 move-and-settle checks and the one with
    # the exact model; the plan knew it (a skipped tuned design lowers the total when it is skipped)
    assert len(told) in (17, 18) and told[-1][1] == len(told) and all(tot in (17, 18) for _, tot, _, _ in told)
    assert told[-1][2] == "move and settle, the config's design with the exact model"
    json.dumps(res)  # JSON-serialisable as printed by --json
    assert set(res["table"]) == {"pid", "pid_coulomb", "pid_dob", "pid_dob_gms", "pid_dob_gms_20"}
    for v, row in res["table"].items():
        assert set(row) == {"cosine", "triangle", "steps"}
        assert all(row[s]["rms_error_nm"] > 0 for s in row)
        m = res["margins"][v]
        assert m["closed_loop_stable"] and m["loop"] == ("pid+dob" if "dob" in v else "pid")
    for s in ("cosine", "triangle"):  # simulated, deterministic: the trend targets
        t = res["targets"][s]
        assert t["improvement_vs_pid"] >= 10.0 and t["met_3x_vs_pid_coulomb"], t
        assert t["met_100x_vs_pid"] == (t["improvement_vs_pid"] >= 100.0)
    st = res["targets"]["steps"]  # move and settle: reported per step with the margins of the design used
    d = st["designs"]["config"]
    assert len(d["settle_ms"]) == 4 and d["max_hold_excursion_nm"] >= 0.0 and d["fault"] is None
    assert d["margins"]["phase_margin_deg"] >= 40.0 and d["margins"]["gain_margin_db"] >= 8.0
    assert st["met"] == all(x["met_settle_30ms"] and x["met_no_limit_cycle"] for x in st["designs"].values())


def test_other_wrong_model_draws_are_seeded_and_run_through_the_steps_check():
    """``--draws N``: the config design's steps on N other wrong models. Each draw is reproducible from its seed,
    scales Σk, F_s, F_c, V_s and σ2 by 10-20 % either way (F_c at most F_s), and differs from the other seeds'."""
    from stagectl.config import load_app_config

    exact = load_app_config(bench.REPO_CONFIG).sim.plant.friction
    spec = exact.spec()
    a, fa = bench.mismatched_draw(exact, 1)
    b, fb = bench.mismatched_draw(exact, 1)
    c, fc = bench.mismatched_draw(exact, 2)
    assert a.spec() == b.spec() and fa == fb and fa != fc
    assert all(0.1 <= abs(v - 1.0) <= 0.2 for v in fa.values())
    sa = a.spec()
    assert sa["k_n_m"][0] == spec["k_n_m"][0] * fa["k"] and sa["fc_n"] <= sa["fs_n"]
    assert sa["vs_m_s"] == spec["vs_m_s"] * fa["vs"]
    p = argparse.ArgumentParser()
    bench.add_arguments(p)
    args = p.parse_args(["--quick", "--hold", "0.3", "--draws", "1"])
    told: list[tuple[float, float, str, float]] = []
    args.progress = lambda *a: told.append(a)
    res = bench.run(args)
    assert told[-1][2] == "move and settle, the config's design, wrong model draw 1" and told[-1][1] == len(told)
    (d,) = res["targets"]["steps"]["config_other_draws"]
    assert d["seed"] == 1 and d["scale"] == {k: round(v, 3) for k, v in fa.items()}
    assert len(d["settle_ms"]) == 4 and d["fault"] is None and d["limit_cycle"] is False
