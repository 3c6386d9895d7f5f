"""The one test of "plain effects" (the effects the plant's plain loops handle) against the effects' names."""

from __future__ import annotations

import pytest

from stagectl.friction import Effects, parse_effects

#: one active setting of every effect; the plain loops handle a constant force (offset) and no other effect
#: (the delay is checked by the callers beside the effects)
_ONE = {
    "asymmetry": {"ratio": 0.1},
    "viscous_asymmetry": {"difference_n_s_m": 1.0},
    "position_ripple": {"amplitude": 0.1, "wavelength_m": 1e-3},
    "cogging": {"amplitude_n": 0.1, "wavelength_m": 1e-3},
    "offset": {"force_n": 0.2},
    "spring": {"stiffness_n_m": 100.0},
    "delay": {"delay_s": 3e-4},
}


def _effects(spec: dict) -> Effects:
    problems: list[str] = []
    eff = parse_effects(spec, "effects", problems)
    assert not problems and eff is not None
    return eff


@pytest.mark.parametrize("names", [(), *((n,) for n in _ONE), ("offset", "delay"), ("offset", "spring")])
def test_plain_effects_is_offset_and_delay_only(names):
    from stagectl.sim.plant import _plain_effects, plain_effects

    eff = _effects({n: _ONE[n] for n in names})
    assert set(eff.active()) == set(names)
    want = set(names) <= {"offset", "delay"}
    ep = eff.packed()
    assert plain_effects(ep) is want
    assert bool(_plain_effects(ep)) is want  # the compiled twin the loops paste in


def test_plant_with_plain_effects_runs_the_plain_loop(repo_root):
    from stagectl.friction import load_model_file
    from stagectl.sim.plant import PlantConfig, StagePlant, loops_for

    fr = load_model_file(repo_root / "config" / "models" / "kamenar2016_gms.yaml").friction
    plain, general = (StagePlant(PlantConfig(mass_kg=1.0, friction=fr, effects=_effects(e)))
                      for e in ({"offset": _ONE["offset"]}, {"spring": _ONE["spring"]}))
    kstep = fr.kernel().step
    assert plain._integrate is loops_for(kstep, plain_only=True)[0]
    assert general._integrate is loops_for(kstep)[0] is not plain._integrate
