"""Meta-test over every configuration dataclass (docs/architecture.md §2, §5): each field has a description, and
every numeric key with a physical dimension carries a unit suffix matching its declared unit.

Classes checked: everything :func:`stagectl.schema.describe` reaches from ``stagectl.config.AppConfig``, the
``Params`` of every registered friction model, ``StageModel``/``Effects``, ``stagectl.sim.plant.PlantConfig``,
and every other dataclass in ``stagectl``, ``stagectl.sim`` and ``stagectl.drivers`` declared with
``stagectl.schema.param`` (so a new config class is covered without editing this file).

Unit-suffix rule: a field with unit ``u`` must end in ``_<suffix(u)>``, where ``suffix`` lower-cases the unit
turns ``/ * · (`` into ``_`` and drops ``^ )`` (``N·s/m`` → ``_n_s_m``, ``m/s^2`` → ``_m_s2``, ``N/(m*s)`` → ``_n_m_s``),
with the aliases below. A numeric field with no unit must be a dimensionless or count-like name:
:data:`DIMENSIONLESS` (paper symbols and ratios) or a name ending in one of :data:`COUNT_SUFFIXES`.
"""

from __future__ import annotations

import dataclasses
import importlib
import pkgutil
import re
import types
import typing

import pytest

from stagectl.schema import describe, type_hints

#: dimensionless parameters (paper symbols, ratios, identifiers) that need no unit suffix
DIMENSIONLESS = frozenset({
    "alpha", "delta", "a", "ratio", "amplitude", "exponent", "seed", "node_id", "controller_node_id", "code",
    "port", "cycles", "count", "signal", "min_signal", "fifo_priority", "cpus", "at_frame", "at_cycle",
    "quick_stop_option_code",
    "max_missed", "max_sequence_gap", "max_clients", "max_crc_errors", "keep_files", "stats_window",
})
#: count-like integer names: a number of cycles, steps, samples, ...
COUNT_SUFFIXES = ("_cycles", "_steps", "_samples", "_count", "_id", "_fraction", "_window")
#: unit → accepted suffix where the mechanical rule does not give the conventional one
UNIT_ALIASES = {"B": "bytes", "MB": "mb"}
#: keys with a unit whose conventional name has no suffix (key: reason)
SUFFIX_EXCEPTIONS = {
    "baudrate": "serial line rate in bit/s, the universal name",
    "psi": "Hsieh & Pan plastic compliance in N^a/m (a is itself a parameter): paper symbol",
}


def _modules() -> list[str]:
    import stagectl
    import stagectl.drivers
    import stagectl.sim

    names = []
    for pkg in (stagectl, stagectl.sim, stagectl.drivers):
        names += [m.name for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + ".")]
    return names


def _config_classes() -> dict[str, type]:
    from stagectl.friction import Effects, StageModel, registry
    from stagectl.sim.plant import PlantConfig

    found: dict[str, type] = {}
    for c in [StageModel, Effects, PlantConfig, *(m.Params for m in registry().values())]:
        found[f"{c.__module__}.{c.__qualname__}"] = c
    try:
        from stagectl.config import AppConfig

        found["stagectl.config.AppConfig"] = AppConfig
    except ImportError:  # pragma: no cover - the app layer is optional for this test
        pass
    for name in _modules():
        try:
            mod = importlib.import_module(name)
        except ImportError:  # pragma: no cover - optional dependency of one module
            continue
        for obj in vars(mod).values():
            if (isinstance(obj, type) and dataclasses.is_dataclass(obj) and obj.__module__ == name
                    and any("desc" in f.metadata for f in dataclasses.fields(obj))):
                found[f"{name}.{obj.__qualname__}"] = obj
    return found


CLASSES = _config_classes()


def _numeric(tp: typing.Any) -> bool:
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    if typing.get_origin(tp) in (typing.Union, types.UnionType) and len(args) == 1:
        tp = args[0]
    if typing.get_origin(tp) is tuple:
        tp = (typing.get_args(tp) or (None,))[0]
    return tp in (int, float)


def _suffix(unit: str) -> str:
    if unit in UNIT_ALIASES:
        return UNIT_ALIASES[unit]
    s = unit.lower().replace("µ", "u")
    s = re.sub(r"[/*·( ]", "_", s).replace(")", "").replace("^", "")
    return re.sub(r"_+", "_", s).strip("_")


def test_the_walk_finds_the_configuration_classes():
    names = set(CLASSES)
    for must in ("stagectl.friction.gms.GmsParams", "stagectl.friction.hsieh.HsiehParams",
                 "stagectl.friction.effects.Effects", "stagectl.world_schema.PlantConfig",
                 "stagectl.world_schema.SimWorldConfig", "stagectl.config.AppConfig"):
        assert must in names
    assert len(names) >= 20


@pytest.mark.parametrize("name", sorted(CLASSES))
def test_every_config_field_has_a_description(name):
    missing = [key for key, _unit, _default, desc in describe(CLASSES[name]) if not desc.strip()]
    assert not missing, f"{name}: fields without a description: {missing}"


@pytest.mark.parametrize("name", sorted(CLASSES))
def test_numeric_keys_carry_their_unit_suffix(name):
    cls = CLASSES[name]
    hints = type_hints(cls)  # typing.get_type_hints, with the lazily imported types (AppConfig.sim) imported
    bad = []
    for f in dataclasses.fields(cls):
        if not _numeric(hints[f.name]) or f.name in SUFFIX_EXCEPTIONS:
            continue
        unit = f.metadata.get("unit", "")
        if unit:
            suf = _suffix(unit)
            if not (f.name == suf or f.name.endswith("_" + suf)):
                bad.append(f"{f.name} [{unit}]: should end in _{suf}")
        elif f.name not in DIMENSIONLESS and not f.name.endswith(COUNT_SUFFIXES):
            bad.append(f"{f.name}: numeric key without a unit (declare unit= and a suffix, or list it as "
                       f"dimensionless in tests/test_meta.py)")
    assert not bad, f"{name}: {bad}"


def test_suffix_rule_examples():
    assert _suffix("N·s/m") == "n_s_m" and _suffix("N*s/m") == "n_s_m"
    assert _suffix("m/s^2") == "m_s2" and _suffix("N/(m*s)") == "n_m_s" and _suffix("1/m") == "1_m"
    assert _suffix("N/sqrt(s)") == "n_sqrt_s" and _suffix("Hz") == "hz" and _suffix("B") == "bytes"
