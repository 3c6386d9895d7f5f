"""The models step when ``discover`` cannot read the nested reversals (commission.fit.fit_models).

Fresh plant k112 of tests/commission/plant_kinds.py (0.91 kg, 1.45 N Coulomb, 1.88 N static, 1 nm encoder)
rings and stick-slips in its reversals: ``ident.signals.prepare`` reads that motion above its low-pass as
position noise (0.17 µm at the loop rate, 0.32 µm decimated to 500 Hz), and only 20 decimated samples counted as
moving. ``discover`` raised, and the whole commissioning aborted after its last experiment although the
constant-velocity passes had measured Coulomb and viscous friction within 4 %. Now ``discover`` is retried at
the loop rate, and when that fails too the model is the passes' sliding curve with the effects their own
experiments decide, with one line saying what was not searched.

Oracle: a recording no identification can use (a stage dithering ±0.4 µm about a position, sub-micrometre
moves under it) and a plain constant-velocity pass recording; the sliding curve handed in must come out as the
model's friction, unchanged."""

from __future__ import annotations

import numpy as np

from stagectl.commission.fit import fit_models
from stagectl.recorder import Recorder

T = 1e-3
COLS = ("t", "x", "u", "x_ref", "v_ref", "a_ref", "v")


def _rec(x: np.ndarray, u: np.ndarray, v_ref: np.ndarray) -> Recorder:
    return Recorder.of(COLS, np.column_stack([T * np.arange(x.size), x, u, x, v_ref, np.zeros(x.size), v_ref]))


def test_a_reversal_recording_discover_cannot_read_leaves_the_sliding_curve_not_an_abort() -> None:
    rng = np.random.default_rng(3)
    n = 3000
    k = np.arange(n)
    # reversals: 1 µm triangle at 10 µm/s under a 170 Hz ±0.4 µm ring (what k112's loop did on its pre-sliding spring)
    tri = 1e-6 * (np.abs(((k * T * 10e-6 / 1e-6) % 2.0) - 1.0))
    x_rev = np.round((tri + 0.4e-6 * np.sin(2 * np.pi * 170 * k * T) * rng.uniform(0.5, 1.0, n)) / 1e-9) * 1e-9
    u_rev = 1.2 * np.sign(np.sin(2 * np.pi * 170 * k * T))
    # passes: ±5 mm/s for 1.5 s each way
    v = np.where(k < n // 2, 5e-3, -5e-3)
    x_cv = np.round(np.cumsum(v) * T / 1e-9) * 1e-9
    u_cv = np.sign(v) * 1.45 + 2.2 * v + rng.normal(0, 1e-3, n)
    sliding = {"fc_n": 1.45, "fs_n": 1.88, "vs_m_s": 4e-4, "delta": 2.0, "viscous_n_s_m": 2.2}
    disc, spec = fit_models({"reversals": _rec(x_rev, u_rev, np.zeros(n)), "friction_cv": _rec(x_cv, u_cv, v)},
                            0.9, T, sliding)
    assert "usable in motion" in disc["discover_skipped"] and "not searched" in disc["discover_skipped"]
    assert disc["estimation"] == "none" and disc["effects"] == []
    fr = spec["friction"]
    assert fr["model"] == "stribeck"
    assert {key: fr[key] for key in sliding} == sliding
    assert spec["mass_kg"] == 0.9
