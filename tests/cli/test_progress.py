"""Progress lines with a time left on identify and bench, from the one progress machinery
(stagectl.commands.progress), and ``--quiet`` silencing them. The clock is the test's own (no wall-clock
sleeps); real processes on a real pty where the line's terminal behaviour is the point."""

from __future__ import annotations

import argparse
import io
import re
from pathlib import Path

import numpy as np
import pytest

from stagectl.commands.progress import Progress, Ticker
from support import run_on_pty

LEFT = re.compile(r"\((\d+) s elapsed, (at most ~|about )(\d+) s left\)")


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def lefts(text: str) -> list[int]:
    return [int(m.group(3)) for m in LEFT.finditer(text)]


def test_bounded_time_left_follows_the_rate_and_the_shrinking_bound() -> None:
    """10 units per second; the bound (total) shrinks when an optimiser ends early: the figure is
    (total - done) / rate, falls with the work and reads 0 at the end."""
    clock, out = FakeClock(), io.StringIO()
    p = Progress("identify", 1, stream=out, every_s=0.0, clock=clock)
    p.bounded(0, "measuring")
    assert "left" not in out.getvalue()  # no rate yet: no figure
    for k in range(1, 31):
        clock.t += 0.1
        p.bounded(k, "fit", total=100 if k < 20 else 40)  # the refinement ends at 20 runs of its budget
    got = lefts(out.getvalue())
    # from 1 s of work on: (100 - 10) / 10 per s, ... (100 - 19) / 10 per s; then (40 - 20) / 10 ... (40 - 30) / 10
    assert got[0] == 9 and got[got.index(2) - 1] == 8 and got[-1] == 1
    assert all(b <= a for a, b in zip(got, got[1:]))
    clock.t += 1.0
    p.bounded(40, "verdict", total=40)
    assert out.getvalue().splitlines()[-1].endswith("at most ~0 s left)")


def test_the_rate_is_the_recent_one() -> None:
    """A slow first stage (compilation) does not skew the figure once the window has moved past it."""
    clock, out = FakeClock(), io.StringIO()
    p = Progress("identify", 1, stream=out, every_s=0.0, clock=clock)
    p.bounded(0, "x", total=1000)
    clock.t += 30.0
    p.bounded(1, "x")  # 1 unit in 30 s
    for k in range(2, 402):  # then 10 units per second for 40 s
        clock.t += 0.1
        p.bounded(k, "x")
    assert lefts(out.getvalue())[-1] == 60  # (1000 - 401) / 10 per s, not / (401 / 70 s)


def test_ticker_counts_a_timed_case_and_estimates_the_rest() -> None:
    """bench's line: a case that runs for a set time moves on by itself (span); the estimate falls to 0."""
    clock, out = FakeClock(), io.StringIO()
    t = Ticker("bench io", stream=out, clock=clock, every_s=0.0)
    t.tell(0.0, 30.0, "case 1 of 2, baseline (10 s)", span=10.0)
    for _ in range(10):
        clock.t += 1.0
        t.tick()
    t.tell(10.0, 30.0, "case 2 of 2, canopen_virtual (20 s)", span=20.0)
    for _ in range(20):
        clock.t += 1.0
        t.tick()
    t.tell(30.0, 30.0, "done")
    text = out.getvalue()
    assert "case 1 of 2, baseline (10 s) (1 s elapsed, about 29 s left)" in text
    assert "case 2 of 2, canopen_virtual (20 s) (15 s elapsed, about 15 s left)" in text
    got = lefts(text)
    assert got == sorted(got, reverse=True) and got[-1] == 0
    assert text.splitlines()[-1].startswith("bench io: done (")


def test_quiet_prints_nothing() -> None:
    clock, out = FakeClock(), io.StringIO()
    p = Progress("identify", 1, stream=out, every_s=0.0, clock=clock, quiet=True)
    t = Ticker("bench io", stream=out, clock=clock, quiet=True)
    for k in range(5):
        clock.t += 1.0
        p.bounded(k, "fit", total=10)
        t.tell(k, 10, "case", span=1.0)
    p.close("done")
    with t:
        pass
    assert out.getvalue() == ""


def _triangle(tmp: Path) -> Path:
    """A triangle scan with Coulomb + viscous friction and a few-µm pre-sliding spring (quasi-static)."""
    t = np.arange(0.0, 3.0, 1e-3)
    x = 2e-4 * (2 * np.abs(((t / 1.0) % 1.0) - 0.5) - 0.5)
    v = np.gradient(x, t)
    u = 0.8 * np.tanh(v / 2e-5) + 50.0 * v
    p = tmp / "tri.csv"
    np.savetxt(p, np.column_stack([t, x, u]), delimiter=",", header="t,x,u", comments="", fmt="%.10g")
    return p


@pytest.mark.parametrize("model", ["hsieh", "gms"])
def test_identify_tells_a_bounded_work_count_that_ends_at_its_total(tmp_path: Path, model: str) -> None:
    """identify's work in model runs: what is left (total - done) never grows once runs are counted, ends
    at 0, and the hsieh refinement's total starts at its evaluation budget and shrinks to what it used."""
    from stagectl.ident.identify import _refine_budget, identify
    from stagectl.ident.recording import load_recording

    rec = load_recording(_triangle(tmp_path), None, min_rows=50)
    seen: list[tuple[float, float, str]] = []
    identify(rec, model, progress=lambda d, tot, w: seen.append((d, tot, w)))
    counted = [(d, tot) for d, tot, _ in seen if d > 0]
    left = [tot - d for d, tot in counted]
    assert len(counted) >= 5 and all(b <= a for a, b in zip(left, left[1:]))
    assert seen[-1][0] == seen[-1][1] and seen[-1][2].startswith("verdict: sensitivity to ")
    assert [d for d, _, _ in seen] == sorted(d for d, _, _ in seen)
    if model == "hsieh":
        assert max(tot for _, tot in counted) >= _refine_budget("hsieh") > seen[-1][1]
        assert any("joint least squares by simulation" in w for _, _, w in seen)


def test_identify_quiet_prints_nothing_on_a_terminal(tmp_path: Path) -> None:
    """--quiet: not even the step lines a terminal gets at once (the line itself, and Ctrl-C during the fit, is
    tests/cli/test_interrupt.py's)."""
    rc, err = run_on_pty(["identify", str(_triangle(tmp_path)), "--model", "dahl", "--out", str(tmp_path / "m.yaml"),
                          "--quiet"])
    assert rc in (0, 3) and "identify:" not in err and "\x1b[K" not in err, err
    assert (tmp_path / "m.yaml").is_file()


def test_bench_tell_reaches_the_line_only_when_there_is_one() -> None:
    from stagectl.bench import tell

    seen: list[tuple[float, ...]] = []
    tell(argparse.Namespace(progress=lambda *a: seen.append(a)), 1.0, 4.0, "case 2 of 4", 3.0)
    tell(argparse.Namespace(), 1.0, 4.0, "no line: nothing happens")
    assert seen == [(1.0, 4.0, "case 2 of 4", 3.0)]
