"""The bounded least-squares solver of the regression (``regress.nonneg_lstsq``, Lawson-Hanson with free
variables) against ``scipy.optimize.lsq_linear`` (bvls), the oracle, on random problems with active bounds,
nearly collinear columns and free columns."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from stagectl.ident import regress as rg
from stagectl.ident.regress import nonneg_lstsq


def test_matches_bvls_on_random_bounded_problems() -> None:
    rng = np.random.default_rng(42)
    active = 0
    for trial in range(300):
        p = int(rng.integers(1, 14))
        a = rng.standard_normal((60, p))
        if p > 2 and trial % 3 == 0:
            a[:, 1] = a[:, 0] + 1e-4 * rng.standard_normal(60)  # nearly collinear pair
        y = rng.standard_normal(60) * 2.0 + a @ rng.standard_normal(p)
        r = np.linalg.qr(a, mode="r")
        c = np.linalg.solve(r.T, a.T @ y)
        nonneg = rng.random(p) < 0.6
        lo = np.where(nonneg, 0.0, -np.inf)
        ref = lsq_linear(r, c, bounds=(lo, np.full(p, np.inf)), method="bvls", tol=1e-14).x
        got = nonneg_lstsq(r, c, nonneg)
        assert np.all(got[nonneg] >= 0.0)
        f_ref = float(np.sum((c - r @ ref) ** 2))
        f_got = float(np.sum((c - r @ got) ** 2))
        assert f_got <= f_ref * (1 + 1e-9) + 1e-12, (trial, f_got, f_ref)
        active += int(np.sum(got[nonneg] == 0.0))
    assert active > 100  # the bounds were active often: the active set was exercised


def test_a_warm_start_ends_at_the_cold_start_solution_bit_for_bit() -> None:
    """Shape searches start each bounded fit from the previous fit's passive set; from any guess (right,
    wrong, infeasible) the solver must return exactly what it returns from a cold start."""
    rng = np.random.default_rng(7)
    warm_used = 0
    for trial in range(300):
        p = int(rng.integers(2, 16))
        a = rng.standard_normal((80, p))
        y = rng.standard_normal(80) * 2.0 + a @ rng.standard_normal(p)
        r = np.linalg.qr(a, mode="r")
        c = np.linalg.solve(r.T, a.T @ y)
        nonneg = rng.random(p) < 0.7
        cold = nonneg_lstsq(r, c, nonneg)
        right = ~nonneg | (cold > 0.0)
        for guess in (right, rng.random(p) < 0.5, np.ones(p, dtype=bool), right ^ (rng.random(p) < 0.2)):
            assert np.array_equal(nonneg_lstsq(r, c, nonneg, guess), cold), trial
        warm_used += int((right & nonneg).any())
    assert warm_used > 100


def test_direct_lapack_calls_equal_numpy_linalg_and_raise_the_same() -> None:
    """The fits call numpy's LAPACK gufuncs without numpy.linalg's argument checks: the same values bit for bit,
    and singular or indefinite matrices still raise LinAlgError."""

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


def test_a_numpy_without_the_private_gufuncs_falls_back_to_numpy_linalg(monkeypatch: pytest.MonkeyPatch) -> None:
    """The fast small solves use numpy's private gufuncs only when they exist and agree with numpy.linalg on a
    probe; a numpy that renamed or changed them gets numpy.linalg (same results, slower), never an error."""
    assert rg._pick_solvers() == (rg._fast_lsolve, rg._fast_cholesky)  # this numpy: the fast path is taken
    monkeypatch.setattr(rg, "_UL", object())  # renamed gufuncs: AttributeError inside the probe
    lsolve, chol = rg._pick_solvers()
    assert (lsolve, chol) == (rg._public_lsolve, rg._public_cholesky)
    a = np.array([[2.0, 0.5], [0.5, 1.0]])
    assert np.array_equal(lsolve(a, np.array([1.0, 2.0])), np.linalg.solve(a, np.array([1.0, 2.0])))
