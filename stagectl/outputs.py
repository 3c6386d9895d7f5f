"""One of each for what commands write: the output directory check and the plain-data converter.

* :func:`prepare_out_dir` -- create an ``--out`` directory *before* a long run and prove it writable, so a
  bad path is one clear :class:`~stagectl.errors.ConfigError` line up front, not a traceback afterwards.
* :func:`prefix_for`, :func:`si` -- a value or an axis in the SI prefix that suits it (nm, µm, mm; mN, N).
* :func:`plain` -- dataclasses, enums, tuples, numpy scalars/arrays and paths as plain Python (dict, list,
  float, int, str, bool, None) for YAML and JSON; ``json=True`` also maps NaN/inf to ``None`` (JSON has no
  non-finite numbers).

Foundation layer: imports nothing of stagectl but :mod:`stagectl.errors`.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from stagectl.errors import ConfigError

__all__ = ["plain", "prefix_for", "prepare_out_dir", "prepare_out_file", "remove_created_if_empty", "si"]

#: the directories :func:`prepare_out_dir` made in this process (the topmost one that did not exist), so that
#: an interrupted command can take back the ones it left empty (:func:`remove_created_if_empty`)
_created: list[Path] = []


def prepare_out_dir(path: str | Path, option: str = "--out") -> Path:
    """Create the output directory now and check that a file can be written in it.

    Parameters
    ----------
    path : str or Path
        The directory (created with its parents).
    option : str
        The command-line option or config key named in the error.

    Raises
    ------
    ConfigError
        ``"{option}: cannot write to directory '...' (reason)"``: exists as a file, permission denied,
        read-only file system, ...
    """
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ConfigError(f"{option}: {str(p)!r} exists and is not a directory")
    new = next((a for a in reversed([p, *p.parents]) if not a.exists()), None)
    try:
        p.mkdir(parents=True, exist_ok=True)
        if new is not None and new not in _created:
            _created.append(new)
        probe = p / ".stagectl-write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise ConfigError(f"{option}: cannot write to directory {str(p)!r} ({exc.strerror or exc})") from None
    return p


def remove_created_if_empty() -> list[str]:
    """Remove the directories :func:`prepare_out_dir` created in this process that hold no file (after
    Ctrl-C: an interrupted command leaves no empty output directories behind). Returns the removed paths."""
    import shutil

    removed: list[str] = []
    for d in reversed(_created):
        try:
            if d.is_dir() and not any(f.is_file() or f.is_symlink() for f in d.rglob("*")):
                shutil.rmtree(d)
                removed.append(str(d))
        except OSError:
            continue
    _created.clear()
    return removed


def prepare_out_file(path: str | Path, option: str = "--out") -> Path:
    """Check *before* a long run that ``path`` can be written as a file: not a directory, its directory
    exists and takes a new file. Raises :class:`ConfigError` ``"{option}: ..."`` otherwise."""
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"{option}: {str(p)!r} is a directory (expected a file path)")
    if not p.parent.is_dir():
        raise ConfigError(f"{option}: directory {str(p.parent)!r} does not exist (expected a file path in an "
                          "existing directory)")
    if p.exists() and not p.is_file():  # a device or pipe (/dev/full): written as is, errors caught then
        return p
    try:
        probe = p.parent / f".{p.name}.stagectl-write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise ConfigError(f"{option}: cannot write to {str(p)!r} ({exc.strerror or exc})") from None
    return p


def plain(obj: Any, *, json: bool = False) -> Any:
    """``obj`` as plain Python data (recursively).

    Dataclass instances become dicts of their fields, enums their ``value``, tuples/lists/sets lists,
    mappings dicts with ``str`` keys, numpy scalars Python numbers, numpy arrays lists, paths strings.
    With ``json=True`` a non-finite float (NaN, ±inf) becomes ``None``.
    """
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, enum.Enum):
        return plain(obj.value, json=json)
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        return None if json and not math.isfinite(obj) else float(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: plain(getattr(obj, f.name), json=json) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {str(k): plain(v, json=json) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [plain(v, json=json) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    tolist = getattr(obj, "tolist", None)  # numpy scalar or array
    if callable(tolist):
        return plain(tolist(), json=json)
    return obj


#: SI prefixes for :func:`si`
_PREFIXES = ((1e-9, "n"), (1e-6, "µ"), (1e-3, "m"), (1.0, ""), (1e3, "k"))


def prefix_for(peak: float, unit: str) -> tuple[float, str]:
    """``(factor, label)`` such that ``peak·factor`` reads 1…1000 in ``label`` (``unit`` with an SI prefix;
    forces from 1 mN up stay in N, as a force reads best in N)."""
    peak = abs(peak) if math.isfinite(peak) else 0.0
    if unit == "N" and peak >= 1e-3:
        return 1.0, "N"
    factor, prefix = 1.0, ""
    for f, p in _PREFIXES:
        if peak >= f or f == _PREFIXES[0][0]:
            factor, prefix = f, p
    return 1.0 / factor, prefix + unit


def si(value: float, unit: str, digits: int = 4) -> str:
    """``value`` (in ``unit``) with the prefix that suits it: ``si(1.2345e-6, "m") == "1.2345 µm"``."""
    if not math.isfinite(value):
        return f"{value} {unit}"
    k, label = prefix_for(value, unit)
    return f"{round(value * k, digits) or 0.0:.{digits}f} {label}"  # `or 0.0`: never "-0.0000"
