"""Compiled kernels: compile on first use, cache in a writable directory, with an honest cache key.

Every numba kernel of the package is declared with :func:`kernel` instead of ``numba.njit``:

* **Lazy.** No signature is given, so nothing is compiled at import; a kernel is compiled (or loaded from
  the on-disk cache) the first time it is called or passed to a compiled loop. Importing
  ``stagectl.friction`` therefore compiles nothing; a command pays only for the models it uses. numba itself is
  imported only then (:class:`LazyKernel`), and :func:`plain` runs a kernel's own source as plain Python: a real
  stage's controller (no simulated plant in the process) never imports numba (docs/performance.md §1).
* **Cache directory** (:func:`cache_dir`), first that applies: ``$NUMBA_CACHE_DIR`` if set;
  ``$CACHE_DIRECTORY/numba`` (systemd's ``CacheDirectory=`` of the daemon's unit); ``$XDG_CACHE_HOME`` (or
  ``~/.cache``) ``/stagectl/numba``. If that directory cannot be created or written, numba's own locators
  are used (``__pycache__`` next to the source, then numba's user-wide cache). The numba process-wide
  configuration is left untouched.
* **Honest key.** numba keys a cached kernel on its own source file and bytecode only; a kernel that
  inlines (or calls) a kernel of *another* module keeps loading the old machine code after that module
  changes. :func:`kernel` adds to the key a SHA-256 over the source text of every module that holds a
  kernel reachable from this one's globals (transitively: ``_integrate`` → ``effects.modify_friction_kernel``
  → …, and kernels held in a closure's cells), so editing any of them recompiles every kernel built on it.
  Global constants the reached kernels read (numba freezes them into the code) are in the key by value.
  No manual cache deletion is needed. A closure kernel specialised on another kernel (``make(kstep)``,
  the plant's per-model loop) is cached under a stable description of its cells (module and name of the
  kernel), where numba's own key (a pickle of the cells) would change from one process to the next.

``stagectl warm`` (``stagectl.commands.warm``) compiles the kernels a configuration uses into the cache
ahead of the first start (docs/performance.md).
"""

from __future__ import annotations

import hashlib
import importlib.abc
import os
import sys
import threading
import types as pytypes
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar, overload

F = TypeVar("F", bound=Callable[..., Any])

_CACHE_CLASS: Any = None


def cache_dir() -> Path:
    """The directory compiled kernels are cached in (see the module docstring for the order)."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    if env:
        return Path(env)
    sd = os.environ.get("CACHE_DIRECTORY")  # systemd CacheDirectory= (colon-separated if several)
    if sd:
        return Path(sd.split(":")[0]) / "numba"
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(xdg) / "stagectl" / "numba"


def _is_dispatcher(obj: Any) -> bool:
    """A kernel: a :class:`LazyKernel` (without making its dispatcher) or a numba dispatcher."""
    return isinstance(obj, LazyKernel) or (hasattr(obj, "py_func") and hasattr(obj, "overloads"))


def _names(code: pytypes.CodeType) -> set[str]:
    out = set(code.co_names)
    for c in code.co_consts:
        if isinstance(c, pytypes.CodeType):
            out |= _names(c)
    return out


_SIMPLE = (bool, int, float, complex, str, bytes)


def _is_simple(v: Any) -> bool:
    if isinstance(v, tuple):
        return all(_is_simple(e) for e in v)
    return isinstance(v, _SIMPLE)


def _walk(py_func: Callable[..., Any]) -> tuple[set[str], set[tuple[str, str]]]:
    """Source files of every kernel reachable from ``py_func`` (transitive, its own included), and the
    global constants (numbers, strings, tuples of them) the reached functions read: numba freezes those into
    the machine code, so a constant imported from another module must be in the key too."""
    files: set[str] = set()
    consts: set[tuple[str, str]] = set()
    seen: set[int] = set()
    stack = [py_func]
    while stack:
        fn = stack.pop()
        if id(fn) in seen:
            continue
        seen.add(id(fn))
        code = getattr(fn, "__code__", None)
        if code is None:
            continue
        if os.path.exists(code.co_filename):
            files.add(os.path.abspath(code.co_filename))
        g = getattr(fn, "__globals__", {})
        names = _names(code)
        cells = [("<cell>", c.cell_contents) for c in (getattr(fn, "__closure__", None) or ())]
        for name, obj in [(name, g.get(name)) for name in names] + cells:
            cands = [(name, obj)]
            if isinstance(obj, pytypes.ModuleType):
                cands = [(f"{name}.{n}", getattr(obj, n, None)) for n in names]
            for cname, c in cands:
                if _is_dispatcher(c):
                    stack.append(getattr(c, "py_func"))
                elif _is_simple(c) and cname != "<cell>":
                    consts.add((f"{getattr(fn, '__module__', '?')}:{cname}", repr(c)))
    return files, consts


def dependency_files(py_func: Callable[..., Any]) -> list[str]:
    """Source files of every kernel reachable from ``py_func``'s globals (transitive), its own excluded.

    Followed: global names that are dispatchers, attributes of imported modules named in the code
    (``effects.modify_friction_kernel``) that are dispatchers, and dispatchers held in closure cells."""
    files, _ = _walk(py_func)
    own = getattr(py_func, "__code__", None)
    if own is not None:
        files.discard(os.path.abspath(own.co_filename))
    return sorted(files)


def dependency_constants(py_func: Callable[..., Any]) -> list[tuple[str, str]]:
    """``(module:name, repr(value))`` of the global constants read by ``py_func`` and the kernels it reaches."""
    return sorted(_walk(py_func)[1])


def _file_digest(path: str) -> str:
    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).hexdigest()


class _NoScipyLinalg(importlib.abc.MetaPathFinder):
    """Makes ``import scipy.linalg…`` fail (installed only around one import, see :func:`_numba_registries`)."""

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> None:
        if name == "scipy.linalg" or name.startswith("scipy.linalg."):
            raise ImportError("hidden by stagectl.jit while numba loads its registries")
        return None


def _numba_registries() -> None:
    """Import ``numba.np.arraymath`` (numba imports it at its first compile or cache load) with ``scipy.linalg``
    hidden, unless either is imported already.

    arraymath only asks whether a BLAS is there (``import scipy.linalg.cython_blas``: 0.1–0.3 s, a tenth of a
    warm start) to pick BLAS or a plain loop for ``np.convolve``/``np.correlate`` inside kernels, which no
    stagectl kernel uses; ``np.dot``/``np.linalg`` in a kernel still import scipy.linalg when typed. Python code
    imports scipy.linalg normally afterwards."""
    if "numba.np.arraymath" in sys.modules or "scipy.linalg" in sys.modules:
        return
    hide = _NoScipyLinalg()
    sys.meta_path.insert(0, hide)
    try:
        import numba.np.arraymath  # noqa: F401
    finally:
        sys.meta_path.remove(hide)


def _cache_class() -> Any:
    """The numba ``FunctionCache`` subclass (built on first use: importing numba's caching is not free)."""
    global _CACHE_CLASS
    if _CACHE_CLASS is not None:
        return _CACHE_CLASS
    from numba.core import caching

    class _Locator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
        def __init__(self, py_func: Any, py_file: str) -> None:
            self._py_file = py_file
            self._lineno = py_func.__code__.co_firstlineno
            self._cache_path = str(cache_dir() / self.get_suitable_cache_subpath(py_file))  # type: ignore[no-untyped-call]

        def get_cache_path(self) -> str:
            return self._cache_path

    class _Impl(caching.CompileResultCacheImpl):
        _locator_classes = [_Locator, *caching.CompileResultCacheImpl._locator_classes]

    class HonestCache(caching.FunctionCache):
        """numba's function cache with the dependencies' source hash in the index key."""

        _impl_class = _Impl

        def __init__(self, py_func: Any) -> None:
            super().__init__(py_func)  # type: ignore[no-untyped-call]
            self._deps_hash: str | None = None

        def load_overload(self, sig: Any, target_context: Any) -> Any:
            _numba_registries()  # before numba's first target refresh, which this call starts
            return super().load_overload(sig, target_context)  # type: ignore[no-untyped-call]

        def deps_hash(self) -> str:
            if self._deps_hash is None:
                h = hashlib.sha256()
                for f in dependency_files(self._py_func):
                    h.update(f.encode())
                    h.update(_file_digest(f).encode())
                h.update(repr(dependency_constants(self._py_func)).encode())
                self._deps_hash = h.hexdigest()
            return self._deps_hash

        def _index_key(self, sig: Any, codegen: Any) -> Any:
            # numba hashes a closure's cell contents pickled, which for a kernel (dispatcher) differs from one
            # process to the next: the entry would never be found again. A dispatcher cell is described by
            # its module and name instead (its source is in deps_hash); other cells as numba does.
            from numba.core.serialize import dumps

            cells = tuple(c.cell_contents for c in (self._py_func.__closure__ or ()))
            desc = [("kernel", c.py_func.__module__, c.py_func.__qualname__, str(c.targetoptions.get("inline")))
                    if _is_dispatcher(c)
                    else dumps(c)  # type: ignore[no-untyped-call]
                    for c in cells]
            code = hashlib.sha256(self._py_func.__code__.co_code).hexdigest()
            cellh = hashlib.sha256(repr(desc).encode()).hexdigest()
            return (sig, codegen.magic_tuple(), (code, cellh), self.deps_hash())

    _CACHE_CLASS = HonestCache
    return HonestCache


#: makes a LazyKernel's dispatcher once (re-entrant: making one may import a module that makes another)
_MAKE_LOCK = threading.RLock()


class LazyKernel:
    """A kernel declared with :func:`kernel`: numba is imported, and the ``njit`` dispatcher made, only when the
    kernel is first called, passed to numba or asked for something only the dispatcher has.

    Until then a process that only needs the plain-Python twins (:func:`plain`: a real stage's feed-forward)
    never imports numba. Calling it from Python calls the compiled dispatcher (compiling or loading it first).
    numba sees it through the duck type it checks: ``py_func`` and ``targetoptions`` (its inlining pass pastes
    ``inline="always"`` kernels in) and ``_numba_type_`` (the dispatcher's type, for a global or closure cell
    that holds it). Where a kernel is handed to compiled code as a value from Python (a first-class function
    argument), hand :func:`dispatcher` of it."""

    __slots__ = ("py_func", "targetoptions", "_disp", "__weakref__")

    def __init__(self, fn: Callable[..., Any], options: dict[str, Any]) -> None:
        self.py_func = fn
        self.targetoptions = {"nopython": True, **options}
        self._disp: Any = None

    @property
    def __name__(self) -> str:
        return str(self.py_func.__name__)

    def dispatcher(self) -> Any:
        """The numba dispatcher (made on first use: this imports numba; compiles nothing by itself). One per
        kernel also when threads use it first together (each extra dispatcher would compile it again)."""
        d = self._disp
        if d is None:
            with _MAKE_LOCK:
                d = self._disp
                if d is None:
                    from numba import njit

                    opts = {k: v for k, v in self.targetoptions.items() if k != "nopython"}
                    d = njit(**opts)(self.py_func)
                    if not os.environ.get("NUMBA_DISABLE_JIT"):
                        d._cache = _cache_class()(self.py_func)
                    self._swap_class_attributes(d)
                    self._disp = d
        return d

    def _swap_class_attributes(self, d: Any) -> None:
        """Class attributes of the kernel's module that hold it (``_kstep = staticmethod(_kstep)`` of a friction
        model) hold the dispatcher from now on: calling through this proxy from Python costs ~1 µs a call
        (``model.step`` on the feed-forward's compiled path), the dispatcher itself ~1.3 µs in all."""
        mod = sys.modules.get(self.py_func.__module__)
        for cls in list(vars(mod).values()) if mod is not None else ():
            if isinstance(cls, type):
                for name, attr in list(vars(cls).items()):
                    if isinstance(attr, staticmethod) and attr.__func__ is self:
                        setattr(cls, name, staticmethod(d))

    @property
    def _numba_type_(self) -> Any:
        from numba.core import types

        return types.Dispatcher(self.dispatcher())

    def __call__(self, *args: Any) -> Any:
        d = self._disp
        if d is None:
            d = self.dispatcher()
        return d(*args)

    def __getattr__(self, name: str) -> Any:
        # overloads, signatures, compile, disable_compile, _cache_hits, ...: the dispatcher's
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self.dispatcher(), name)

    def __repr__(self) -> str:
        state = "made" if self._disp is not None else "not made yet"
        return f"<kernel {self.py_func.__module__}.{self.py_func.__qualname__} ({state})>"


def dispatcher(k: Any) -> Any:
    """The numba dispatcher of kernel ``k`` (a :class:`LazyKernel`, made now; a dispatcher is returned as is)."""
    return k.dispatcher() if isinstance(k, LazyKernel) else k


@overload
def kernel(fn: F) -> F: ...


@overload
def kernel(fn: None = None, **options: Any) -> Callable[[F], F]: ...


def kernel(fn: F | None = None, **options: Any) -> Any:
    """``numba.njit(**options)`` compiled lazily, cached in :func:`cache_dir` with an honest key.

    Use as ``@kernel`` or ``@kernel(inline="always")``. ``cache`` is always on; a signature cannot be given
    (it would compile at import). Returns a :class:`LazyKernel`: numba is not imported until the kernel is
    used compiled; :func:`plain` runs the same source as plain Python."""
    if "cache" in options:
        raise TypeError("kernel(): the cache is always on")

    def deco(f: F) -> Any:
        return LazyKernel(f, dict(options))

    if fn is not None:
        return deco(fn)
    return deco


_INLINED: dict[int, tuple[Any, Any]] = {}


def inlined(dispatcher: Any) -> Any:
    """A second kernel of ``dispatcher``'s function with ``inline="always"`` (made once per dispatcher).

    A compiled loop that calls a kernel through a closure cell or a global calls it as a function: numba links
    the callee's machine code after optimising the caller, so LLVM cannot inline it, and the call (arrays
    passed as seven scalars each, an exception status to test) cost ~15 % of a GMS plant step. Calling this
    variant pastes the callee's body into the caller at numba's IR level. The original keeps being the one
    called from Python. Compile the caller with ``_nrt=False`` if it allocates nothing: numba otherwise counts
    references of the arrays handed to the pasted-in body on every call, which ate half of the gain."""
    got = _INLINED.get(id(dispatcher))
    if got is None:
        opts = {k: v for k, v in dispatcher.targetoptions.items() if k not in ("cache", "nopython", "boundscheck")}
        opts["inline"] = "always"
        got = (kernel(**opts)(dispatcher.py_func), dispatcher)  # the original kept alive: its id stays valid
        _INLINED[id(dispatcher)] = got
    return got[0]


_PLAIN: dict[int, tuple[Callable[..., Any], Any]] = {}


class _PlainModule:
    """A module seen by a plain twin: its kernels' plain twins for the attributes the code names, else the
    module's own attributes."""

    def __init__(self, mod: pytypes.ModuleType, subst: dict[str, Any]) -> None:
        self._mod = mod
        self.__dict__.update(subst)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._mod, name)


def plain(k: Any) -> Callable[..., Any]:
    """The plain-Python twin of kernel ``k``: its own Python source (``py_func``) run by the interpreter, with every
    kernel it calls (globals, attributes of imported modules, closure cells; transitively) replaced by that
    kernel's twin. Imports no numba. The same operations in the same order as the compiled kernel; IEEE double
    arithmetic and the C library's ``exp``/``pow`` in both, so the results agree bit for bit in practice
    (``tests/friction/test_plain_twins.py``; numba's default compiles without fast-math, so no reassociation or
    fused multiply-add). numpy's integer casts run as Python's ``int`` (same value, faster). Fastest on Python
    lists (a numpy array works too, its scalars are slower). Made once per kernel."""
    py = k.py_func
    got = _PLAIN.get(id(py))
    if got is not None:
        return got[0]
    g: dict[str, Any] = dict(py.__globals__)
    cells = py.__closure__
    fn = pytypes.FunctionType(py.__code__, g, py.__name__, py.__defaults__,
                              tuple(pytypes.CellType(c.cell_contents) for c in cells) if cells else None)
    fn.__qualname__ = py.__qualname__
    fn.__doc__ = py.__doc__
    fn.__module__ = py.__module__
    _PLAIN[id(py)] = (fn, py)  # before the recursion: a kernel reached twice gets the same twin; py kept alive
    names = _names(py.__code__)
    for name in names:
        obj = g.get(name)
        if _is_dispatcher(obj):
            g[name] = plain(obj)
        elif getattr(obj, "__name__", None) == "numpy" and isinstance(obj, pytypes.ModuleType):
            # numpy's integer casts (np.int64(p[0]): a cast in a kernel) as Python's int: the same value, and a
            # numpy integer is slow in the interpreter (every index computed from it: 4.3 µs for a GMS N = 6 step
            # against 2.3 µs)
            g[name] = _PlainModule(obj, {"int64": int, "int32": int, "intp": int})
        elif isinstance(obj, pytypes.ModuleType):
            subst = {n: plain(getattr(obj, n)) for n in names if _is_dispatcher(getattr(obj, n, None))}
            if subst:
                g[name] = _PlainModule(obj, subst)
    for cell in fn.__closure__ or ():
        if _is_dispatcher(cell.cell_contents):
            cell.cell_contents = plain(cell.cell_contents)
    return fn


def compiled_signatures(dispatcher: Any) -> int:
    """How many signatures ``dispatcher`` has compiled or loaded in this process (0: never used)."""
    if isinstance(dispatcher, LazyKernel) and dispatcher._disp is None:
        return 0
    return len(getattr(dispatcher, "overloads", {}))


def loaded_from_cache(dispatcher: Any) -> int:
    """Cache hits of ``dispatcher`` in this process (numba's per-signature counters)."""
    if isinstance(dispatcher, LazyKernel) and dispatcher._disp is None:
        return 0
    return int(sum(getattr(dispatcher, "_cache_hits", {}).values()))


__all__ = ["LazyKernel", "cache_dir", "compiled_signatures", "dependency_constants", "dependency_files", "dispatcher",
           "inlined", "kernel", "loaded_from_cache", "plain"]
