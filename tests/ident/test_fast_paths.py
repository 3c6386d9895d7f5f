"""The discovery speed-ups that must not change a number: the fits' direct LAPACK calls, the compiled
sine/cosine of position, and the Pillow figures (drawn where the data are)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from stagectl.ident import regress as rg
from stagectl.ident._kernels import sin_cos_of_position
from stagectl.ident.figures import Figure, nice_ticks, tick_label


def test_sin_cos_kernel_equals_numpy_bit_for_bit() -> None:
    x = np.random.default_rng(3).uniform(-0.3, 0.3, 20_000)
    for lam in (2.5e-3, 0.0123456789, 1.7):
        ph = 2.0 * np.pi * x / lam
        got = sin_cos_of_position(x, lam)
        assert np.array_equal(got[0], np.sin(ph)) and np.array_equal(got[1], np.cos(ph))


def test_direct_lapack_calls_equal_numpy_linalg_and_raise_the_same() -> None:
    rng = np.random.default_rng(4)
    for p in (1, 3, 9, 25):
        a = rng.standard_normal((p, p))
        g = a @ a.T + p * np.eye(p)
        b = rng.standard_normal(p)
        assert np.array_equal(rg._lsolve(g, b), np.linalg.solve(g, b))
        assert np.array_equal(rg._lsolve(g.T, b), np.linalg.solve(g.T, b))
        assert np.array_equal(rg._cholesky(g), np.linalg.cholesky(g))
    with pytest.raises(np.linalg.LinAlgError):
        rg._lsolve(np.zeros((3, 3)), np.ones(3))
    with pytest.raises(np.linalg.LinAlgError):
        rg._cholesky(-np.eye(3))


def test_ticks_are_round_and_cover_the_range() -> None:
    assert nice_ticks(0.0, 24.8) == [0.0, 5.0, 10.0, 15.0, 20.0]
    t = nice_ticks(-0.13, 0.13)
    assert t[0] >= -0.13 and t[-1] <= 0.13 and len(t) >= 5 and 0.0 in t
    assert [tick_label(v, 0.05) for v in (-0.1, 0.0, 0.25)] == ["-0.10", "0", "0.25"]
    assert tick_label(2.5, 2.5) == "2.5" and tick_label(1e-5, 1e-5) == "1e-05"


def test_figure_draws_the_line_where_the_data_are(tmp_path: Path) -> None:
    fig = Figure(200, 100)
    p = fig.panel(0.1, 0.1, 0.9, 0.9)
    x = np.linspace(0.0, 1.0, 50)
    y = np.where(x < 0.5, 0.0, np.nan)  # a gap: the right half stays empty
    p.xlim, p.ylim = (0.0, 1.0), (-1.0, 1.0)
    p.line(x, y, "#ff0000", 1.0, "data")
    p.axes(xlabel="x [m]", ylabel="y [N]", title="t")
    p.legend()
    fig.save(tmp_path / "f.png")
    im = np.asarray(Image.open(tmp_path / "f.png").convert("RGB")).astype(int)
    assert im.shape == (100, 200, 3)
    red = (im[:, :, 0] > 150) & (im[:, :, 1] < 120) & (im[:, :, 2] < 120)
    rows, cols = np.nonzero(red[:, 20:180])
    # the line lies on y = 0 (the middle row) from x = 0 to 0.5 only (the legend key sits at the upper right)
    on_line = np.abs(rows - 50) <= 1
    assert on_line.sum() > 50
    assert cols[on_line].max() + 20 < 0.1 * 200 + 0.5 * 160 + 3
