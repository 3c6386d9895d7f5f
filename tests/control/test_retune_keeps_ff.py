"""A reload that changes only live feed-forward keys (adapt_*, rest_sync_*, inertia*) keeps the friction
feed-forward running: its model state, θ and β survive; a key that defines the model rebuilds it."""

from __future__ import annotations

import dataclasses
import pickle
from pathlib import Path

import numpy as np
import pytest

from stagectl.control.api import Reference


def _reload(repo_root: Path, tmp_path: Path, old: str, new: str):
    """config/sim.yaml loaded as shipped and a second time with ``old`` replaced by ``new`` (the daemon's reload:
    the real loader, the model file read again)."""
    from stagectl.config import load_app_config

    src = repo_root / "config" / "sim.yaml"
    text = src.read_text()
    assert text.count(old) == 1, old
    text = text.replace(old, new).replace("model_file: models/", f"model_file: {src.parent / 'models'}/")
    p = tmp_path / "edited.yaml"
    p.write_text(text)
    return load_app_config(src), load_app_config(p)


def _running(cfg):
    """A controller on ``cfg`` after 60 moving steps with the stage 50 nm behind (θ has moved off 1, the model
    has slid)."""
    from stagectl.control.controller import StageController

    ctl = StageController(cfg.controller, cfg.timing)
    dt, v = cfg.loop.period_s, 1e-3
    for k in range(60):
        x_r = v * k * dt
        ctl.step(dt, x_r - 50e-9 * (k > 0), Reference(x_r, v, 0.0))
    assert ctl.ff_scale != 1.0
    return ctl


@pytest.mark.parametrize("old,new", [
    ("adapt_bandwidth_hz: 1.0", "adapt_bandwidth_hz: 2.0"),
    ("rest_sync_hz: 30.0", "rest_sync_hz: 10.0"),
    ("rest_sync_max_step_m: 5.0e-9", "rest_sync_max_step_m: 3.0e-9"),
    ("inertia: true", "inertia: false"),
    ("learn_moves_fraction: 1.0", "learn_moves_fraction: 0.0"),
    ("adapt_bandwidth_hz: 1.0", "adapt_bandwidth_hz: 1.0"),  # nothing changed, the model file read again
])
def test_live_keys_keep_the_feedforward_and_apply(repo_root, tmp_path, old, new):
    from stagectl.control.controller import FF_LIVE_KEYS

    a, b = _reload(repo_root, tmp_path, old, new)
    ctl = _running(a)
    ff, th, beta = ctl.ff, ctl.ff_scale, ctl.ff.input_scale
    mstate = ff.model_state.copy()
    sent = pickle.loads(pickle.dumps(b.controller))  # as the daemon hands it to its loop process
    ctl.request_retune(sent)
    dt = a.loop.period_s
    x_r = 1e-3 * 60 * dt
    ctl.step(dt, x_r - 50e-9, Reference(x_r, 0.0, 0.0))  # the swap happens at this step's start
    assert ctl.ff is ff and ctl.cfg is sent  # the new live values are in force
    assert {k: getattr(ctl.cfg.feedforward, k) for k in FF_LIVE_KEYS} == \
        {k: getattr(b.controller.feedforward, k) for k in FF_LIVE_KEYS}
    assert ctl.ff_scale == th and ff.input_scale == beta
    assert not np.array_equal(ff.model_state, np.zeros_like(mstate)) and ctl.state.u_ff_n != 0.0


@pytest.mark.parametrize("old,new", [
    ("lookahead_s: 0.0015", "lookahead_s: 0.001"),
    ("kind: model", "kind: coulomb"),
])
def test_model_keys_rebuild_the_feedforward(repo_root, tmp_path, old, new):
    a, b = _reload(repo_root, tmp_path, old, new)
    ctl = _running(a)
    ff = ctl.ff
    ctl.retune(b.controller)
    assert ctl.ff is not ff and ctl.ff_scale == 1.0


def test_model_file_change_rebuilds(repo_root):
    """The same key, another model (a friction parameter changed): compared by value, so it rebuilds."""
    from stagectl.config import load_app_config
    from stagectl.control.controller import FF_LIVE_KEYS, FeedforwardConfig, same_friction_ff

    a = load_app_config(repo_root / "config" / "sim.yaml").controller.feedforward
    m = a.model
    assert m is not None
    key = next(k for k, v in m.friction.spec().items() if isinstance(v, float) and v > 0.0)
    other = dataclasses.replace(m, friction=m.friction.replace(**{key: m.friction.spec()[key] * 1.1}))
    assert not same_friction_ff(a, dataclasses.replace(a, model=other))
    assert same_friction_ff(a, dataclasses.replace(a, model=dataclasses.replace(m)))
    assert FF_LIVE_KEYS <= {f.name for f in dataclasses.fields(FeedforwardConfig)}
