"""Issue 12: the HIL configs' controllers settle 10 µm steps without a limit cycle.

The shipped config/hil-canopen.yaml and config/hil-serial.yaml, their ``sim:`` section run in-process instead of in a
``stagectl sim-plant`` process (``io.kind: embedded_canopen``: the same real CiA 402 driver, the same virtual drive
with the config's force units, the interferometer sampled on SYNC), in lock-step and simulated time:
:func:`stagectl.bench.control.steps_check` with ``keep_io``. The controller section is the shipped one, untouched.
The 10 mN force units shipped before (rated force 10 N) make the same controller hunt at rest: checked as the
contrast, so the test could fail.
"""

from __future__ import annotations

import pytest

from support import embedded_hil_mapping


def _embedded(name: str, force_per_unit_n: float | None = None):
    from pathlib import Path

    from stagectl.config import parse_app_config

    data = embedded_hil_mapping(name)
    if force_per_unit_n is not None:
        data["io"]["drive"]["force_per_unit_n"] = data["sim"]["drive"]["force_per_unit_n"] = force_per_unit_n
    return parse_app_config(data, Path(__file__).resolve().parents[2] / "config" / name)


@pytest.mark.parametrize("name,window_s", [("hil-canopen.yaml", 0.03), ("hil-serial.yaml", 0.08)])
def test_shipped_hil_controller_settles_steps_without_limit_cycle(name, window_s):
    from stagectl.bench.control import steps_check

    cfg = _embedded(name)
    assert cfg.controller.rest_stiffness_fraction > 0 and cfg.controller.settle is not None
    r = steps_check(cfg, cfg.controller, hold_s=0.6, keep_io=True, window_s=window_s)
    assert r["fault"] is None
    assert len(r["settle_s"]) == 4 and r["settled_within_window"], r["settle_s"]
    assert not r["limit_cycle"], r["steps"]
    assert r["max_late_excursion_m"] < 10e-9


def test_coarse_force_units_make_the_rest_structure_hunt():
    """With 10 mN units (15.6 nm of pre-sliding per unit on the stuck stage) the same controller hunts."""
    from stagectl.bench.control import steps_check

    cfg = _embedded("hil-canopen.yaml", force_per_unit_n=0.01)
    r = steps_check(cfg, cfg.controller, hold_s=0.6, keep_io=True)
    assert r["limit_cycle"] or not r["settled_within_window"]
