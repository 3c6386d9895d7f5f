"""Signals.cache (stagectl.ident.signals.ArrayCache): arrays beyond the byte budget are dropped least recently
used, other values are kept, and a fit is the same with a tiny budget as with an unbounded one."""

from __future__ import annotations

import numpy as np

from stagectl.ident import regress as rg
from stagectl.ident.hypothesis import Hyp
from stagectl.ident.signals import ArrayCache, prepare
from stagectl.ident import synth


def test_least_recently_used_arrays_go_first() -> None:
    c = ArrayCache(budget=3 * 800)
    for k in "abc":
        c[k] = np.zeros(100)  # 800 bytes each
    c["memo"] = {"x": 1.0}
    assert c.get("a") is not None  # a is now the most recently used
    c["d"] = np.zeros(100)
    assert set(c) == {"a", "c", "d", "memo"} and c.nbytes == 2400
    c["c"] = np.zeros(200)  # replacing an entry counts its new size once
    assert "c" in c and c.nbytes <= 2400 and "memo" in c
    assert c.nbytes == sum(v.nbytes for v in c.values() if isinstance(v, np.ndarray))


def test_fit_does_not_depend_on_the_budget() -> None:
    rng = np.random.default_rng(3)
    rec = synth.closed_loop(synth.hide(synth.draw_stage(rng), "stribeck", rng), synth.Motion(duration_s=3.0), seed=3)
    big, small = prepare(rec), prepare(rec)
    small.cache = ArrayCache(budget=1)  # keeps one array at a time
    h = Hyp(effects=("stribeck",))
    a, b = rg.fit_linear(big, h, big.evaluate), rg.fit_linear(small, h, small.evaluate)
    assert a.rss == b.rss and a.hyp.theta == b.hyp.theta
    assert small.cache.nbytes <= max(v.nbytes for v in big.cache.values() if isinstance(v, np.ndarray))
