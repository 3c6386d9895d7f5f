"""The recordings behind the commissioned pre-sliding model (docs/commissioning.md, *Which recordings the
pre-sliding regression reads*): the regression reads the experiments designed for it, not the
constant-velocity passes' stops. Synthetic data; no plant runs."""

from __future__ import annotations

import itertools

import numpy as np

from stagectl.commission.fit import fit_presliding, presliding_recordings
from stagectl.friction import build
from stagectl.recorder import Recorder

#: generated plant 29's friction (tests/commission/plant_gen.py): 0.60 kg on Σk = 2.1e6 N/m, a pre-sliding
#: resonance at 296 Hz (3.4 samples a period at 1 kHz)
_GMS = {"model": "gms", "k_n_m": [1047871.3, 550368.4, 174557.6, 131294.6, 122186.1, 56540.4],
        "alpha": [0.1643, 0.1618, 0.0962, 0.1357, 0.2367, 0.2054], "fs_n": 0.859, "fc_n": 0.7432,
        "vs_m_s": 0.002883, "delta": 2.0, "c_n_s": 8589.9, "viscous_n_s_m": 0.0, "sigma1_n_s_m": 0.0}
_T, _M, _UP = 1e-3, 0.6, 16


def _record(xt_fine: np.ndarray, seed: int) -> Recorder:
    """The force acts on the true path (``_UP`` points a sampling period); the recording has it at the
    samples, applied 1 ms + half a sample late, and the path measured (0.5 nm noise, 1 nm quantum)."""
    n = (xt_fine.shape[0] - 1) // _UP + 1
    f = build(_GMS).force_along(xt_fine, np.arange(xt_fine.shape[0]) * _T / _UP)[::_UP][:n]
    xt = xt_fine[::_UP][:n]
    a = np.zeros(n)
    a[1:-1] = (xt[2:] - 2 * xt[1:-1] + xt[:-2]) / _T ** 2
    i = np.arange(n, dtype=float)
    u = np.interp(i + 1.5, i, _M * a + f)
    rng = np.random.default_rng(seed)
    x = np.round((xt + 0.5e-9 * rng.standard_normal(n)) / 1e-9) * 1e-9
    return Recorder.of(("x", "u"), np.column_stack([x, u]))


def _move(a: float, b: float, dur: float) -> np.ndarray:
    s = np.linspace(0.0, 1.0, max(int(dur * _UP / _T), 2))
    out: np.ndarray = a + (b - a) * (1 - np.cos(np.pi * s[1:])) / 2
    return out


def _loops() -> np.ndarray:
    """The pre-sliding loops: a long move, then back and forth by log-spaced travels, slowly."""
    pts = [0.0, 300e-6]
    for A in (25e-6 / 2 ** i for i in range(6)):
        pts += [300e-6 - A, 300e-6]
    x = [np.zeros(1)]
    for a, b in itertools.pairwise(pts):
        x += [_move(a, b, 0.75 if abs(b - a) < 100e-6 else 1.0), np.full(50 * _UP, b)]
    return np.concatenate(x)


def _passes() -> np.ndarray:
    """Moves at 10 mm/s that stop ringing at the 296 Hz resonance (150 nm, ζ = 0.1), then stand 0.4 s."""
    x, pos, w = [np.zeros(1)], 0.0, 2 * np.pi * 296.0
    for b in (400e-6, -400e-6, 300e-6, -300e-6, 0.0):
        t = np.arange(1, int(0.4 * _UP / _T) + 1) * _T / _UP
        x += [_move(pos, b, abs(b - pos) / 0.01 * 1.6),
              b + 150e-9 * np.sign(b - pos) * np.exp(-0.1 * w * t) * np.sin(w * t)]
        pos = b
    return np.concatenate(x)


def test_presliding_regression_reads_the_loops_not_the_passes_stops() -> None:
    """After a fast stop the stage rings between the samples and the play's element states stay off the
    plant's while it stands: with those rows the reversal curve Σ k_i·min(s, 2Δ_i) came out 10 % off (0.3 %
    on the loops alone). presliding_recordings leaves the passes out while the loops have slow rows."""
    sliding = {"fc_n": 0.7432, "fs_n": 0.859, "vs_m_s": 0.002883, "delta": 2.0, "viscous_n_s_m": 0.0}
    loops, passes = _record(_loops(), 1), _record(_passes(), 2)
    k = np.array(_GMS["k_n_m"])
    d = np.array(_GMS["alpha"]) * 0.859 / k

    def curve_error(recs: list[Recorder]) -> float:
        p = fit_presliding(recs, _M, _T, 1e-3, sliding, None)  # type: ignore[arg-type]
        kf, df = np.array(p["k_n_m"]), np.array(p["break_away_m"])
        return max(abs(float((kf * np.minimum(s, 2 * df)).sum()) / float((k * np.minimum(s, 2 * d)).sum()) - 1)
                   for s in np.geomspace(0.2e-6, 20e-6, 15))

    chosen = presliding_recordings({"reversals": loops, "friction_cv": passes}, _M, _T, sliding)  # type: ignore[dict-item]
    assert chosen == [loops]
    assert curve_error(chosen) < 5e-3
    assert curve_error([loops, passes]) > 3e-2  # what reading the passes too costs
    # designed recordings without slow rows (too short here): the passes are read after all
    short = Recorder.of(("x", "u"), np.column_stack([loops.col("x")[:20], loops.col("u")[:20]]))
    assert presliding_recordings({"reversals": short, "friction_cv": passes}, _M, _T, sliding) == [short, passes]  # type: ignore[dict-item]
