"""Typed configuration: YAML mapping -> frozen dataclasses, all errors reported at once.

Every configurable object in stagectl is a frozen dataclass whose fields are declared with
:func:`param`, which records the unit, a one-line description and the bounds. :func:`load`
turns a plain mapping (from ``yaml.safe_load``) into such a dataclass:

* unknown keys are rejected with their full path (Klipper's unused-option check);
* missing required keys, wrong types, NaN/inf and out-of-bounds values are reported with the
  path and the unit, e.g. ``controller.pid.kp_n_m: must be > 0 N/m (got -3)``;
* **every** problem found is collected and raised together as one :class:`ConfigError`.

Supported field types: ``float``, ``int``, ``bool``, ``str``, ``Enum`` subclasses (by value),
``X | None``, ``tuple[float, ...]`` / ``tuple[int, ...]`` / ``tuple[str, ...]``, nested frozen
dataclasses, ``dict[str, Any]`` (passed through, e.g. the ``can:`` block handed to ``can.Bus``),
and any type with a custom ``parse=`` hook (used for the polymorphic ``friction:`` block).

Example::

    @dataclass(frozen=True)
    class PidConfig:
        kp_n_m: float = param(unit="N/m", desc="proportional gain", gt=0)
        cutoff_hz: float = param(500.0, unit="Hz", desc="derivative filter cut-off", gt=0)

    cfg = load(PidConfig, {"kp_n_m": 1e5}, path="controller.pid")
"""

from __future__ import annotations

import dataclasses
import difflib
import enum
import functools
import importlib
import math
import operator
import re
import sys
import types
import typing
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar

from stagectl.errors import ConfigError, cut, short

T = TypeVar("T")

_MISSING = dataclasses.MISSING
_INT64 = 2**63

#: signature of a custom parse hook: (value, path, problems) -> parsed value (or None on error,
#: after appending messages to ``problems``)
ParseHook = Callable[[Any, str, list[str]], Any]


def param(
    default: Any = _MISSING,
    *,
    unit: str = "",
    desc: str,
    gt: float | None = None,
    ge: float | None = None,
    lt: float | None = None,
    le: float | None = None,
    choices: tuple[Any, ...] | None = None,
    allow_inf: bool = False,
    parse: ParseHook | None = None,
    default_factory: Callable[[], Any] | None = None,
) -> Any:
    """Declare a configuration field with its unit, description and bounds.

    Parameters
    ----------
    default : optional
        Default value; omit for a required key.
    unit : str
        SI unit shown in messages and docs ("" for dimensionless).
    desc : str
        One-line description (a meta-test checks every field has one).
    gt, ge, lt, le : float, optional
        Bounds (strictly greater, greater-equal, ...). Applied to numbers and to every element of
        numeric tuples.
    choices : tuple, optional
        Allowed values (strings).
    allow_inf : bool
        Accept ``inf`` / ``-inf`` (e.g. "no limit"); NaN is never accepted.
    parse : callable, optional
        Custom hook ``(value, path, problems) -> object`` for polymorphic fields.
    """
    meta = {
        "unit": unit,
        "desc": desc,
        "gt": gt,
        "ge": ge,
        "lt": lt,
        "le": le,
        "choices": choices,
        "allow_inf": allow_inf,
        "parse": parse,
    }
    if default_factory is not None:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    if default is _MISSING:
        return dataclasses.field(metadata=meta)
    if isinstance(default, (list, dict, set)):
        raise TypeError("mutable default; use default_factory")
    return dataclasses.field(default=default, metadata=meta)


def _unit(meta: Mapping[str, Any]) -> str:
    u = meta.get("unit") or ""
    return f" {u}" if u else ""


def _unit_of_list(meta: Mapping[str, Any]) -> str:
    u = meta.get("unit") or ""
    return f" (values in {u})" if u else ""


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    return repr(v)


def yaml_kind(value: Any) -> str:
    """What a parsed YAML value is, in YAML's words (``null``, ``true``, a list …), never a Python class name."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, Mapping):
        return f"a mapping {short(dict(value))}"
    if isinstance(value, (list, tuple)):
        return f"list {short(list(value))}"
    if isinstance(value, str):
        return f"a string {short(value)}"
    if isinstance(value, (int, float)):
        return f"the number {short(value)}"
    return f"a {type(value).__name__} value"


def _check_number(value: Any, path: str, meta: Mapping[str, Any], problems: list[str], *, integer: bool) -> Any:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        # accept numeric strings like "1e-3" that YAML 1.1 leaves as str
        if isinstance(value, str):
            try:
                value = int(value) if integer else float(value)
            except ValueError:
                problems.append(f"{path}: expected a number{_unit(meta)}, got {short(value)}")
                return None
        else:
            problems.append(f"{path}: expected a number{_unit(meta)}, got {yaml_kind(value)}")
            return None
    if integer:
        if isinstance(value, float):
            if not value.is_integer():
                problems.append(f"{path}: expected an integer{_unit(meta)}, got {short(value)}")
                return None
            value = int(value)
        if not -_INT64 <= value < _INT64:
            problems.append(f"{path}: out of range{_unit(meta)} (got {short(value)})")
            return None
    else:
        try:
            value = float(value)
        except OverflowError:  # an integer beyond 1.8e308
            problems.append(f"{path}: must be finite{_unit(meta)}, got {short(value)}")
            return None
        if math.isnan(value):
            problems.append(f"{path}: must be a finite number{_unit(meta)}, got NaN")
            return None
        if math.isinf(value) and not meta.get("allow_inf"):
            problems.append(f"{path}: must be finite{_unit(meta)}, got {value}")
            return None
    u = _unit(meta)
    checks: tuple[tuple[str, Callable[[float, float], bool], str], ...] = (
        ("gt", operator.gt, ">"),
        ("ge", operator.ge, ">="),
        ("lt", operator.lt, "<"),
        ("le", operator.le, "<="),
    )
    for key, ok, word in checks:
        bound = meta.get(key)
        if bound is not None and not ok(value, bound):
            problems.append(f"{path}: must be {word} {_fmt(bound)}{u} (got {_fmt(value)}{u})")
            return None
    return value


def _parse_value(tp: Any, value: Any, path: str, meta: Mapping[str, Any], problems: list[str]) -> Any:
    hook = meta.get("parse")
    if hook is not None:
        return hook(value, path, problems)
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    # Optional / unions with None
    if origin in (typing.Union, types.UnionType):
        non_none = [a for a in args if a is not type(None)]
        if value is None and len(non_none) < len(args):
            return None
        if len(non_none) == 1:
            return _parse_value(non_none[0], value, path, meta, problems)
        problems.append(f"{path}: unsupported union type {tp}")
        return None
    if origin is typing.Literal:
        if value not in args:
            problems.append(f"{path}: must be one of {', '.join(map(str, args))} (got {short(value)})")
            return None
        return value
    if tp is float:
        return _check_number(value, path, meta, problems, integer=False)
    if tp is int:
        return _check_number(value, path, meta, problems, integer=True)
    if tp is bool:
        if not isinstance(value, bool):
            problems.append(f"{path}: expected true or false, got {short(value)}")
            return None
        return value
    if tp is str:
        if not isinstance(value, str):
            problems.append(f"{path}: expected a string, got {short(value)}")
            return None
        choices = meta.get("choices")
        if choices and value not in choices:
            problems.append(f"{path}: must be one of {', '.join(choices)} (got {short(value)})")
            return None
        return value
    if tp is Path:
        if not isinstance(value, str):
            problems.append(f"{path}: expected a path string, got {short(value)}")
            return None
        return Path(value)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        for member in tp:
            if value == member.value or (isinstance(value, str) and value.lower() == member.name.lower()):
                return member
        allowed = ", ".join(str(m.value) for m in tp)
        problems.append(f"{path}: must be one of {allowed} (got {short(value)})")
        return None
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            problems.append(f"{path}: expected a list{_unit_of_list(meta)}, got {short(value)}")
            return None
        elem_t = args[0] if args else Any
        out = []
        n_before = len(problems)
        for i, item in enumerate(value):
            out.append(_parse_value(elem_t, item, f"{path}[{i}]", meta, problems))
        return tuple(out) if len(problems) == n_before else None
    if origin is dict or tp is dict:
        if not isinstance(value, Mapping):
            problems.append(f"{path}: expected a mapping, got {short(value)}")
            return None
        return dict(value)
    if tp is Any:
        return value
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return _load_into(tp, value, path, problems)
    problems.append(f"{path}: unsupported field type {tp}")
    return None


class _LazyTypes(Mapping[str, Any]):
    """The names of a module's ``LAZY_TYPES`` (``{"Name": "package.module"}``: types its annotations name but that
    it imports only under ``TYPE_CHECKING``), each imported when an annotation is evaluated that needs it."""

    def __init__(self, module: Any) -> None:
        self._module = module
        self._lazy: Mapping[str, str] = getattr(module, "LAZY_TYPES", {})

    def __getitem__(self, name: str) -> Any:
        where = self._lazy.get(name)
        if where is None:
            raise KeyError(name)
        value = getattr(importlib.import_module(where), name)
        setattr(self._module, name, value)  # once imported, the module's own global (typing.get_type_hints finds it)
        return value

    def __iter__(self) -> typing.Iterator[str]:
        return iter(self._lazy)

    def __len__(self) -> int:
        return len(self._lazy)


@functools.cache
def field_type(cls: type, name: str) -> Any:
    """The evaluated type annotation of field ``name`` of dataclass ``cls`` (``typing.get_type_hints(cls)[name]``,
    evaluated for this field alone: a field whose type lives in a module imported only when needed, named in its
    module's ``LAZY_TYPES``, imports it only when that field is parsed or described; e.g. ``AppConfig.sim``,
    whose ``stagectl.sim`` a real stage's process never imports)."""
    for base in cls.__mro__:
        ann = base.__dict__.get("__annotations__", {})
        if name in ann:
            module = sys.modules[base.__module__]
            holder = types.SimpleNamespace(__annotations__={name: ann[name]})
            return typing.get_type_hints(holder, globalns=vars(module), localns=_LazyTypes(module))[name]
    raise KeyError(f"{cls.__name__} has no field {name!r}")


def type_hints(cls: type) -> dict[str, Any]:
    """:func:`field_type` of every field of dataclass ``cls`` (what ``typing.get_type_hints`` gives, with the
    lazily imported types of ``LAZY_TYPES`` imported)."""
    return {f.name: field_type(cls, f.name) for f in dataclasses.fields(cls)}


def _load_into(cls: type[T], data: Any, path: str, problems: list[str]) -> T | None:
    where = path or "<top>"
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        problems.append(f"{where}: expected a mapping, got {yaml_kind(data)}")
        return None
    flds = {f.name: f for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    prefix = f"{path}." if path else ""
    for key in data:
        if key not in flds:
            name = key if isinstance(key, str) and len(key) <= 60 else short(key)
            close = difflib.get_close_matches(name, list(flds), n=2, cutoff=0.6)
            hint = f" (did you mean {', '.join(close)}?)" if close else f" (known keys: {', '.join(flds)})"
            problems.append(f"{prefix}{name}: unknown key{hint}")
    kwargs: dict[str, Any] = {}
    ok = True
    for name, f in flds.items():
        sub = f"{prefix}{name}"
        if name in data:
            n_before = len(problems)
            val = _parse_value(field_type(typing.cast(type, cls), name), data[name], sub, f.metadata, problems)
            if len(problems) > n_before:
                ok = False
                continue
            kwargs[name] = val
        elif f.default is _MISSING and f.default_factory is _MISSING:
            problems.append(f"{sub}: required key missing{_unit(f.metadata)} ({f.metadata.get('desc', '')})")
            ok = False
    if not ok:
        return None
    try:
        obj = cls(**kwargs)
    except (ConfigError, ValueError, TypeError) as exc:  # __post_init__ cross-field checks
        msgs = exc.problems if isinstance(exc, ConfigError) else [str(exc)]
        for m in msgs:
            problems.append(_post_init_message(m, prefix, where, flds))
        return None
    return obj


def _post_init_message(msg: str, prefix: str, where: str, names: Mapping[str, Any]) -> str:
    """Give a ``__post_init__`` message its full key path.

    ``"fs_n: must be >= fc_n ..."`` raised by the dataclass at ``friction`` becomes
    ``"friction.fs_n: must be >= fc_n ..."``; a message that names no field of the class is put under the
    class's own path (``"friction: ..."``).
    """
    if prefix and msg.startswith(prefix):
        return msg
    head = re.split(r"[\[.:\s]", msg, maxsplit=1)[0]
    if head in names and msg[len(head):len(head) + 1] in (":", "[", "."):
        return f"{prefix}{msg}"
    return f"{where}: {msg}"


def load(cls: type[T], data: Any, path: str = "") -> T:
    """Build the frozen dataclass ``cls`` from a plain mapping.

    Raises
    ------
    ConfigError
        With every problem found (unknown keys, missing keys, bad types, bounds), each prefixed
        by its key path.
    """
    problems: list[str] = []
    obj = _load_into(cls, data, path, problems)
    if problems or obj is None:
        raise ConfigError(problems or [f"{path or '<top>'}: invalid"])
    return obj


def section_parser(cls: type[T]) -> ParseHook:
    """A ``parse=`` hook for a field holding the dataclass ``cls``, built with :func:`load` under the field's
    path (its problems are collected with the caller's). An instance of ``cls`` passes through unchanged.
    Use it where a section needs a hook, e.g. to pass a ready-made object from Python."""

    def hook(value: Any, path: str, problems: list[str]) -> T | None:
        if isinstance(value, cls):
            return value
        try:
            return load(cls, value, path)
        except ConfigError as exc:
            problems.extend(exc.problems)
            return None

    return hook


#: bounds of a YAML file read by :func:`load_yaml_file` (configurations and model files are a few KB): the
#: file size, the alias count (``*name``), the nesting depth and the node count with aliases expanded. They
#: refuse "billion laughs" alias bombs and deep nesting before any value is built.
MAX_YAML_BYTES = 256 * 1024
MAX_YAML_ALIASES = 100
MAX_YAML_DEPTH = 32
MAX_YAML_NODES = 100_000


#: configuration keys that hold a path besides those ending in ``_file`` (``model_file``, ``eds_file``)
PATH_KEYS = ("directory",)


def absolute_paths(node: Any, base: Path, *, resolve: bool = False) -> Any:
    """A parsed configuration (mappings, lists) with its relative paths, the values of keys ending in ``_file``
    or in :data:`PATH_KEYS`, made absolute against ``base`` (``resolve``: symlinks resolved too), so that the
    same files load when the mapping is written to another directory."""
    if isinstance(node, dict):
        out = {}
        for k, v in node.items():
            if isinstance(v, str) and (k.endswith("_file") or k in PATH_KEYS) and not Path(v).is_absolute():
                out[k] = str((base / v).resolve()) if resolve else str(base / v)
            else:
                out[k] = absolute_paths(v, base, resolve=resolve)
        return out
    if isinstance(node, list):
        return [absolute_paths(v, base, resolve=resolve) for v in node]
    return node


class _YamlRefused(Exception):
    """A bound of the bounded loader was exceeded (message: what and where)."""


def _bounded_loader(text: str) -> Any:
    """A ``yaml.SafeLoader`` for ``text`` that counts aliases and depth while composing, refuses duplicate
    mapping keys, and turns any exception raised while building a value into a ``ConstructorError`` that
    names the value and its line."""
    import yaml

    class BoundedLoader(yaml.SafeLoader):
        def __init__(self, stream: str) -> None:
            super().__init__(stream)
            self.n_aliases = 0
            self.depth = 0

        def compose_node(self, parent: Any, index: Any) -> Any:
            if self.check_event(yaml.AliasEvent):
                self.n_aliases += 1
                if self.n_aliases > MAX_YAML_ALIASES:
                    line = self.peek_event().start_mark.line + 1  # type: ignore[no-untyped-call]
                    raise _YamlRefused(f"more than {MAX_YAML_ALIASES} aliases (*name) at line {line}")
                return super().compose_node(parent, index)
            self.depth += 1
            try:
                if self.depth > MAX_YAML_DEPTH:
                    line = self.peek_event().start_mark.line + 1  # type: ignore[no-untyped-call]
                    raise _YamlRefused(f"nested deeper than {MAX_YAML_DEPTH} levels at line {line}")
                return super().compose_node(parent, index)
            finally:
                self.depth -= 1

        def construct_object(self, node: Any, deep: bool = False) -> Any:
            try:
                return super().construct_object(node, deep=deep)
            except (yaml.YAMLError, _YamlRefused):
                raise
            except Exception as exc:  # noqa: BLE001 - PyYAML's constructors raise AttributeError, ValueError
                what = short(node.value, 40) if isinstance(node, yaml.ScalarNode) else node.id
                raise yaml.constructor.ConstructorError(
                    None, None, f"cannot read {what} as {cut(node.tag.rsplit(':', 1)[-1], 40)} ({type(exc).__name__})",
                    node.start_mark) from None

        def construct_mapping(self, node: Any, deep: bool = False) -> Any:
            if isinstance(node, yaml.MappingNode):
                seen: dict[Any, int] = {}
                for key_node, _value in node.value:
                    if key_node.tag == "tag:yaml.org,2002:merge":
                        continue
                    key = self.construct_object(key_node, deep=True)
                    line = key_node.start_mark.line + 1
                    try:
                        first = seen.get(key)
                    except TypeError:
                        continue  # unhashable: PyYAML's own check names it
                    if first is not None:
                        raise yaml.constructor.ConstructorError(
                            None, None, f"duplicate key {short(key, 40)} (first at line {first})",
                            key_node.start_mark)
                    seen[key] = line
            return super().construct_mapping(node, deep=deep)

    return BoundedLoader(text)


def _expanded_nodes(root: Any) -> int:
    """How many nodes the document would have with every alias expanded (refused above MAX_YAML_NODES or
    when an alias refers to a node that contains it)."""
    import yaml

    sizes: dict[int, int] = {}
    busy: set[int] = set()

    def size(node: Any) -> int:
        key = id(node)
        if key in sizes:
            return sizes[key]
        if key in busy:
            raise _YamlRefused(f"recursive alias at line {node.start_mark.line + 1}")
        busy.add(key)
        n = 1
        if isinstance(node, yaml.SequenceNode):
            for child in node.value:
                n += size(child)
                if n > MAX_YAML_NODES:
                    break
        elif isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                n += size(k) + size(v)
                if n > MAX_YAML_NODES:
                    break
        busy.discard(key)
        if n > MAX_YAML_NODES:
            raise _YamlRefused(f"more than {MAX_YAML_NODES} values once aliases are expanded "
                               f"(line {node.start_mark.line + 1})")
        sizes[key] = n
        return n

    return size(root) if root is not None else 0


def parse_yaml_text(text: str, name: str = "<yaml>") -> Any:
    """Parse one YAML document with the bounded safe loader (see :data:`MAX_YAML_BYTES` and the others).

    Raises
    ------
    ConfigError
        One line naming ``name``, the line and what is wrong: syntax, a bound exceeded, a duplicate key, a
        value PyYAML cannot build (``!!timestamp 2001-13-45x``). Never another exception.
    """
    import yaml

    if len(text) > MAX_YAML_BYTES:
        raise ConfigError(f"{name}: larger than {MAX_YAML_BYTES // 1024} KiB; not a configuration file")
    loader = None
    try:
        loader = _bounded_loader(text)
        node = loader.get_single_node()
        _expanded_nodes(node)
        return loader.construct_document(node) if node is not None else None
    except _YamlRefused as exc:
        raise ConfigError(f"{name}: YAML refused: {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        kind = "YAML error" if isinstance(exc, yaml.constructor.ConstructorError) else "YAML syntax error"
        problem = cut(str(getattr(exc, "problem", None) or exc))
        raise ConfigError(f"{name}: {kind}{where}: {problem}") from None
    except RecursionError:
        raise ConfigError(f"{name}: YAML refused: nested too deeply") from None
    except Exception as exc:  # noqa: BLE001 - whatever else PyYAML raises is still one line, not a traceback
        raise ConfigError(f"{name}: YAML cannot be read ({type(exc).__name__}: {cut(str(exc))})") from None
    finally:
        if loader is not None:
            loader.dispose()


def load_yaml_file(path: str | Path, what: str = "configuration file") -> Any:
    """Read a YAML file with the bounded safe loader (:func:`parse_yaml_text`); file and syntax errors,
    oversize files, alias bombs, deep nesting and duplicate keys become one-line :class:`ConfigError`.
    ``what`` names the file's kind in those lines (``cannot read scenario file``)."""
    p = Path(path)
    try:
        with p.open("rb") as f:
            raw = f.read(MAX_YAML_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read {what} ({exc.strerror or exc})") from exc
    if len(raw) > MAX_YAML_BYTES:
        raise ConfigError(f"{p}: larger than {MAX_YAML_BYTES // 1024} KiB; not a {what}")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not a UTF-8 text file (byte {exc.start}: {exc.reason})") from exc
    return parse_yaml_text(text, str(p))


def describe(cls: type) -> list[tuple[str, str, str, str]]:
    """Flatten a config dataclass into rows ``(key path, unit, default, description)`` for docs/tests."""
    rows: list[tuple[str, str, str, str]] = []

    def walk(c: type, prefix: str) -> None:
        h = type_hints(c)
        for f in dataclasses.fields(c):
            key = f"{prefix}{f.name}"
            tp = h[f.name]
            args = [a for a in typing.get_args(tp) if a is not type(None)]
            inner = args[0] if (typing.get_origin(tp) in (typing.Union, types.UnionType) and len(args) == 1) else tp
            if f.default is not _MISSING:
                d = _fmt(f.default.value if isinstance(f.default, enum.Enum) else f.default)
            elif f.default_factory is not _MISSING:
                d = "(section)"
            else:
                d = "required"
            rows.append((key, f.metadata.get("unit", ""), d, f.metadata.get("desc", "")))
            if dataclasses.is_dataclass(inner) and f.metadata.get("parse") is None:
                walk(inner, key + ".")  # type: ignore[arg-type]

    walk(cls, "")
    return rows
