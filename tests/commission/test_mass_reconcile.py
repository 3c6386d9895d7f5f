"""Which mass the commissioned model uses when the FRF's and the inverse-dynamics regression's disagree.

Hand-built figures: a 0.79 kg stage whose FRF measured 0.79 kg; the inverse-dynamics masses a cogging fitted
with a 90-180 degree phase error gave (1.6-4.9 kg) must not replace it, one within a factor 2 (an FRF on a stage
held by its friction) still does, and agreement within 20 % says nothing."""

from __future__ import annotations

import math

from stagectl.commission import fit


def test_an_inverse_dynamics_mass_beyond_a_factor_two_keeps_the_frf_mass() -> None:
    for m_id in (1.6, 2.5, 4.9, 0.3):
        m, note = fit.reconcile_mass(0.79, m_id)
        assert m == 0.79, m_id
        assert note is not None and "keep the FRF mass" in note and f"factor {fit.MASS_ID_MAX_RATIO:g}" in note


def test_an_inverse_dynamics_mass_within_the_bound_replaces_the_frf_mass() -> None:
    m, note = fit.reconcile_mass(0.79, 1.2)
    assert m == 1.2
    assert note is not None and "use the inverse-dynamics mass" in note
    m, note = fit.reconcile_mass(0.79, 0.45)
    assert m == 0.45 and note is not None


def test_agreeing_or_missing_masses_keep_the_frf_mass_silently() -> None:
    assert fit.reconcile_mass(0.79, 0.85) == (0.79, None)
    assert fit.reconcile_mass(0.79, None) == (0.79, None)
    assert fit.reconcile_mass(0.79, math.nan) == (0.79, None)
