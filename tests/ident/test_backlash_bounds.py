"""A backlash fit is acceptable only if the model file can hold it (issue 13): every fit within the physical
bounds maps onto a valid motor + load plant. Before, a fit with a slightly negative lost mass passed the bounds,
was accepted, and the model writer then refused it, failing the whole discovery run with exit 2."""

from __future__ import annotations

import numpy as np
import pytest

from stagectl.errors import ConfigError
from stagectl.ident import effects as fx
from stagectl.ident.effects import BACKLASH, BacklashShape
from stagectl.ident.hypothesis import Hyp
from stagectl.ident.modelio import _backlash_spec

M, FC = 0.89, 1.3


def _hyp(mass_lost_kg: float, coulomb_lost_n: float, m: float = M) -> Hyp:
    return Hyp(effects=(BACKLASH.name,), shapes={BACKLASH.name: BacklashShape(20e-6)},
               theta={"m": m, "fc": FC, "fv": 2.0, "bc": -coulomb_lost_n, "bv": 0.0, "bm": -mass_lost_kg, "bi": 0.1})


def test_the_fit_seen_on_a_long_stroke_recording_is_out_of_bounds() -> None:
    """The case found by the outside evaluation: 0.041 kg of mass *gained* in the play, friction on the motor."""
    p = BACKLASH.params(_hyp(-0.041, 0.1))
    assert BACKLASH.bounds is not None and any("no motor/load split" in b for b in BACKLASH.bounds(p))


@pytest.mark.parametrize("coulomb_lost", [-0.1 * FC, 0.2 * FC, 0.49 * FC, 0.51 * FC, FC, 1.1 * FC])
def test_every_fit_within_the_bounds_can_be_written(coulomb_lost: float) -> None:
    assert BACKLASH.bounds is not None
    for mass_lost in np.linspace(-0.1 * M, M, 45):
        h = _hyp(float(mass_lost), coulomb_lost)
        if BACKLASH.bounds(BACKLASH.params(h)):
            with pytest.raises(ConfigError):
                _backlash_spec(h)
        else:
            spec = _backlash_spec(h)
            assert 0.0 < spec["other_mass_kg"] < M
            assert spec["friction_side"] == ("load" if fx.backlash_split(BACKLASH.params(h))[0] else "motor")


@pytest.mark.parametrize("mass", [0.0, -0.2])
def test_a_fit_without_mass_is_out_of_bounds(mass: float) -> None:
    """A recording whose force follows the speed (a massless damper: x = A sin ωt, u = B cos ωt) fitted a total
    mass of 0 kg; the bound skipped the split check for m <= 0, discovery accepted the play and the model writer
    then failed the whole run (exit 2, 'fitted mass lost in the play (25 kg of 0 kg)'); audit16."""
    assert BACKLASH.bounds is not None
    for mass_lost in (-0.5, 0.0, 0.3, 25.0):
        h = _hyp(mass_lost, 0.2 * FC, m=mass)
        assert any("no motor/load split" in b for b in BACKLASH.bounds(BACKLASH.params(h)))
        with pytest.raises(ConfigError):
            _backlash_spec(h)


def test_discover_on_a_massless_damper_recording_completes(tmp_path) -> None:
    """x = A sin ωt with u = B cos ωt (force in phase with the speed, no inertia): discovery ran into the
    backlash writer's refusal (exit 2) and its evidence said "nan N at constant speed" (no such stretch)."""
    from stagectl.cli import main

    k = np.arange(3000)
    rows = np.column_stack([k * 1e-3, 1e-6 * np.sin(k * 0.01), 0.5 * np.cos(k * 0.01)])
    rec = tmp_path / "damper.csv"
    np.savetxt(rec, rows, delimiter=",", header="t,x,u", comments="", fmt="%.17g")
    assert main(["discover", str(rec), "--out", str(tmp_path / "d"), "-q"]) == 0
    report = (tmp_path / "d" / "report.md").read_text()
    assert "backlash: rejected" in report and "nan N" not in report
