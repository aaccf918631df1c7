"""How cfsr's numba kernels are compiled: once per machine, by whoever needs one first.

Every kernel of the package is declared with :func:`njit` from here instead of numba's. It is
numba's ``njit`` with ``cache=True`` and a cache of its own (:class:`_KernelCache`) that adds
two things numba's on-disk cache lacks:

* **One compile per kernel.** A process that finds a kernel missing from the cache takes an
  exclusive lock (``flock`` on a file beside the kernel's cache index) before it compiles, and
  looks in the cache again once it holds it: a second process that needs the same kernel
  (another pool process, the background warm-up, a second server, a test) waits for the
  first compile and loads its result instead of compiling the kernel a second time at once.
  The lock is held from the second look until the result is saved (or the compile fails), and
  the kernel's callees take their own locks inside that; since the call graph has no cycles,
  neither do the waits.
* **A stamp that follows the code a kernel is built from.** numba keys a kernel's cache entry
  by its own source file only; a kernel that calls (and so embeds) a helper from another
  module, or freezes one of its constants, would load stale machine code after an edit there.
  The stamp here hashes the kernel's module and the cfsr modules it imports (and, through
  modules that hold kernels, theirs): an edit recompiles the kernels that depend on it and no
  others, so no caller needs to throw the whole cache away.

It also keeps a record of what the compiler is doing in this process (:func:`activity`): the
kernel being compiled or waited for, how many were compiled and loaded, and their names.
Progress bars read it, and the pool's heartbeat sends it to the
pool's owner so that a process busy compiling is never taken for a hung one. With
``CFSR_COMPILE_LOG`` set to a file, every process appends a line per compile to it, so the
compile cost of a whole run (a server and its pool, a test suite) can be added up.

Kernels are plain typed loops (the pool gives the parallelism, one frame per single-threaded
process). The few declared ``hot`` get their helpers inlined at numba's IR (:func:`njit`) and
borrow their arrays (:mod:`cfsr._borrow`), which is what numba's parallel loops had given
them on one thread too, at a fraction of the compile. The simulator's kernels, which no pool
runs, keep their parfors.
"""

from __future__ import annotations

import ast
import fcntl
import functools
import hashlib
import json
import os
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numba
from numba.core import event
from numba.core.caching import (
    CompileResultCacheImpl,
    FunctionCache,
    UserProvidedCacheLocator,
    UserWideCacheLocator,
    _CacheLocator,
)

__all__ = ["njit", "activity", "CompileActivity", "on_compile", "kernel_name", "waiting_for"]

_ROOT = Path(__file__).resolve().parent


# ----------------------------------------------------------------------------------------------
# the stamp: a kernel's module and the cfsr modules it is built from
# ----------------------------------------------------------------------------------------------
def _module_file(name: str) -> Path | None:
    """The file of cfsr module ``name`` (dotted, absolute), or None when it is not one."""
    if name != "cfsr" and not name.startswith("cfsr."):
        return None
    rel = Path(*name.split(".")[1:])
    for cand in (_ROOT / rel.with_suffix(".py"), _ROOT / rel / "__init__.py"):
        if cand.is_file():
            return cand
    return None


@functools.cache
def _imports(path: Path) -> tuple[tuple[Path, ...], bool]:
    """The cfsr modules ``path`` imports (top level and in functions), and whether it holds
    kernels of its own."""
    src = path.read_text(encoding="utf-8")
    tree = ast.parse(src, str(path))
    rel = path.relative_to(_ROOT).with_suffix("")
    parts = ["cfsr", *rel.parts]
    package = parts[:-1] if parts[-1] != "__init__" else parts[:-1]
    found: list[Path] = []
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package[: len(package) - (node.level - 1)]
                base = ".".join([*up, *([base] if base else [])])
            names = [base] + [f"{base}.{a.name}" for a in node.names]
        for n in names:
            f = _module_file(n)
            if f is not None and f != path:
                found.append(f)
    return tuple(sorted(set(found))), "njit(" in src or "@njit" in src


@functools.cache
def _stamp(path: Path) -> bytes:
    """Hash of ``path`` and of what its kernels may embed: the cfsr modules it imports, and
    through those that hold kernels, theirs (a non-kernel module contributes only the
    constants it defines, which it does not take from further down)."""
    seen: set[Path] = set()
    todo = [path]
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        deps, has_kernels = _imports(p)
        if p == path or has_kernels:
            todo.extend(deps)
    h = hashlib.sha256()
    for p in sorted(seen):
        h.update(str(p.relative_to(_ROOT)).encode() + b"\0" + p.read_bytes() + b"\0")
    return h.digest()


class _StampedLocator(_CacheLocator):
    """numba's own locator with :func:`_stamp` as the source stamp, and, in a cache folder
    shared by every copy of the package (``NUMBA_CACHE_DIR``, or numba's per-user folder),
    the kernel's entry kept under its module's name and stamp instead of its file's path.

    numba files a kernel under a hash of its source folder, so the same code installed at
    another path (a wheel's venv beside the checkout it was built from) compiled every kernel
    again into a folder of its own. Keyed by content, identical code shares one compiled
    kernel (and its compile lock), and different code sits beside it, each still checked
    against its stamp by numba's index. A ``__pycache__`` beside the module stays numba's.
    """

    def __init__(self, inner: _CacheLocator, py_file: str, module: str) -> None:
        self._inner, self._py_file = inner, Path(py_file).resolve()
        self._path = inner.get_cache_path()
        if isinstance(inner, (UserProvidedCacheLocator, UserWideCacheLocator)):
            try:
                key = _stamp(self._py_file).hex()[:24]
            except (OSError, ValueError, SyntaxError):  # not a file of the package
                pass
            else:
                self._path = os.path.join(os.path.dirname(self._path), f"{module}-{key}")

    def get_cache_path(self) -> str:
        return self._path

    def get_source_stamp(self) -> Any:
        try:
            return _stamp(self._py_file)
        except (OSError, ValueError, SyntaxError):  # not a file of the package: numba's own
            return self._inner.get_source_stamp()

    def get_disambiguator(self) -> str:
        return self._inner.get_disambiguator()

    @classmethod
    def from_function(cls, py_func: Any, py_file: str) -> None:  # pragma: no cover - unused
        return None


class _StampedImpl(CompileResultCacheImpl):
    def __init__(self, py_func: Any) -> None:
        super().__init__(py_func)
        import inspect

        self._locator = _StampedLocator(self._locator, inspect.getfile(py_func),
                                        py_func.__module__)


# ----------------------------------------------------------------------------------------------
# one compile per kernel: a lock file beside the cache index
# ----------------------------------------------------------------------------------------------
class _KernelCache(FunctionCache):
    """numba's function cache, with a compile taken under an exclusive per-kernel lock."""

    _impl_class = _StampedImpl

    def __init__(self, py_func: Any) -> None:
        super().__init__(py_func)
        self._lock_fd: int | None = None
        self._kernel = kernel_name(py_func)

    def _lock_path(self) -> str:
        return os.path.join(self._cache_path, f"{self._impl.filename_base}.lock")

    def load_overload(self, sig: Any, target_context: Any) -> Any:
        got = super().load_overload(sig, target_context)
        if got is not None or not self._enabled or self._lock_fd is not None:
            if got is not None:
                _record_load()
            return got
        try:
            self._impl.locator.ensure_cache_path()
            fd = os.open(self._lock_path(), os.O_RDWR | os.O_CREAT, 0o666)
        except OSError:  # a cache we cannot write to: compile without the lock
            return None
        with waiting_for(self._kernel):
            fcntl.flock(fd, fcntl.LOCK_EX)
        got = super().load_overload(sig, target_context)  # compiled while we waited?
        if got is not None:
            os.close(fd)  # closing the descriptor drops the lock
            _record_load()
            return got
        self._lock_fd = fd  # held until save_overload, or the compile's failure
        _held[id(self)] = self
        return None

    def save_overload(self, sig: Any, data: Any) -> None:
        try:
            super().save_overload(sig, data)
        finally:
            self.release()

    def release(self) -> None:
        fd, self._lock_fd = self._lock_fd, None
        _held.pop(id(self), None)
        if fd is not None:
            os.close(fd)


#: caches holding their kernel's lock (a compile in progress in this process)
_held: dict[int, _KernelCache] = {}


def kernel_name(py_func: Any) -> str:
    """``module.qualname`` of a kernel, as progress and the measured table name it."""
    return f"{py_func.__module__}.{py_func.__qualname__}"


#: ``module.qualname`` of the kernels declared ``hot``: numba IR-inlines helpers into them
_HOT: set[str] = set()


def _inline_into_hot(expr: Any, caller_ir: Any, callee_ir: Any) -> bool:
    """numba's inline cost model for helpers: inline (at the IR, before typing) into a hot
    kernel, and into nothing else. A helper called from a cold kernel is compiled once on its
    own and called; LLVM still inlines it where it is small."""
    fid = caller_ir.func_id
    return f"{fid.modname}.{fid.func_qualname}" in _HOT


def njit(*args: Any, hot: bool = False, helper: bool = False, **options: Any) -> Any:
    """numba's ``njit`` with cfsr's cache: ``@njit``, ``@njit(hot=True)``,
    ``@njit(helper=True)`` or ``@njit(**numba_options)``.

    ``hot``: a kernel whose frame cost needs its helpers inlined at the IR (their array
    arguments then cost nothing per call; LLVM's own inlining leaves 5-10 % of the frame).
    It compiles a few times slower, so only the few where it pays are hot (measured:
    ``cfsr bench --compile``, docs/speed.md). Its loops are plain; it borrows its arrays
    (:func:`cfsr._borrow.borrow`) so that they cost no reference counting. ``helper``: a
    small function inlined into the hot kernels that call it and called from the others.
    ``cache`` is always on (:class:`_KernelCache`); other options are numba's.
    """
    options.pop("cache", None)
    if helper:
        options["inline"] = _inline_into_hot

    def wrap(fn: Callable[..., Any]) -> Any:
        if hot:
            _HOT.add(f"{fn.__module__}.{fn.__qualname__}")
        disp = numba.njit(**options)(fn)
        disp._cache = _KernelCache(disp.py_func)
        return disp

    if args and callable(args[0]) and len(args) == 1 and not options:
        return wrap(args[0])
    if args:
        raise TypeError("cfsr._jit.njit takes the function, or options by keyword")
    return wrap


# ----------------------------------------------------------------------------------------------
# what the compiler is doing in this process
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CompileActivity:
    """What numba has done for cfsr's kernels in this process.

    ``kernel``: the kernel being compiled, or waited for while another process compiles it
    (``waiting``), None when neither; ``compiled``/``loaded``: kernels compiled here /
    loaded from the cache so far; ``done``: names of the kernels compiled here, in order.
    """

    kernel: str | None = None
    waiting: bool = False
    compiled: int = 0
    loaded: int = 0
    done: tuple[str, ...] = field(default_factory=tuple)

    @property
    def busy(self) -> bool:
        """Compiling, or waiting for another process's compile."""
        return self.kernel is not None


_state_lock = threading.Lock()
_state = CompileActivity()
#: (kernel, declared here, thread CPU seconds at its start) per nesting level of compiles
_stack: list[tuple[str, bool, float]] = []
_listeners: list[Callable[[str, CompileActivity], None]] = []


def activity() -> CompileActivity:
    """This process's :class:`CompileActivity` now."""
    with _state_lock:
        return _state


def on_compile(fn: Callable[[str, CompileActivity], None]) -> Callable[[], None]:
    """Call ``fn(event, activity)`` on each compile event of a cfsr kernel in this process
    (``event``: "start", "end", "wait" or "load"); returns a function that stops it."""
    _listeners.append(fn)
    return lambda: _listeners.remove(fn) if fn in _listeners else None


def _emit(kind: str) -> None:
    st = activity()
    for fn in list(_listeners):
        fn(kind, st)


def _set(**changes: Any) -> None:
    global _state
    with _state_lock:
        _state = replace(_state, **changes)


def _record_load() -> None:
    _set(loaded=_state.loaded + 1)
    _emit("load")


@contextmanager
def waiting_for(kernel: str) -> Iterator[None]:
    """Mark this process as waiting for another process's compile of ``kernel`` while the
    body runs (the lock's wait; the pool's test hook for a slow first frame)."""
    outer = (_state.kernel, _state.waiting)
    _set(kernel=kernel, waiting=True)
    _emit("wait")
    try:
        yield
    finally:
        _set(kernel=outer[0], waiting=outer[1])


class _Listener(event.Listener):
    """Follows numba's compile events for the kernels declared with :func:`njit`; releases
    a lock a compile that failed still holds."""

    def on_start(self, ev: event.Event) -> None:
        disp = ev.data["dispatcher"]
        ours = isinstance(getattr(disp, "_cache", None), _KernelCache)
        name = kernel_name(disp.py_func)
        _stack.append((name, ours, time.thread_time()))
        if ours:
            _set(kernel=name, waiting=False)
            _emit("start")

    def on_end(self, ev: event.Event) -> None:
        disp = ev.data["dispatcher"]
        name, ours, cpu0 = _stack.pop()
        if not _stack:
            _log_compile(name, time.thread_time() - cpu0)
        if getattr(ev, "_exc_details", None) is not None:  # numba has no public accessor
            cache = getattr(disp, "_cache", None)
            if isinstance(cache, _KernelCache):
                cache.release()
        if not ours:
            return
        outer = next((s for s in reversed(_stack) if s[1]), None)
        global _state
        with _state_lock:
            _state = replace(
                _state,
                kernel=outer[0] if outer else None,
                waiting=False,
                compiled=_state.compiled + 1,
                done=(*_state.done, name),
            )
        _emit("end")


def _log_compile(name: str, cpu_s: float) -> None:
    """Append an outermost compile (its kernel and thread CPU seconds, callees included) to
    the file named by ``CFSR_COMPILE_LOG``, when set: one JSON line per compile, from every
    process that inherits the variable, so a whole run (a test suite, a server and its pool)
    can be added up. Short lines appended with ``O_APPEND`` in one write do not interleave."""
    path = os.environ.get("CFSR_COMPILE_LOG")
    if not path:
        return
    line = json.dumps({"kernel": name, "cpu_s": round(cpu_s, 3), "pid": os.getpid()})
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    except OSError:
        return  # a diagnostic: never fail a compile for it
    try:
        os.write(fd, (line + "\n").encode())
    finally:
        os.close(fd)


event.register("numba:compile", _Listener())
