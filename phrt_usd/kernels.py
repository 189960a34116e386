"""The compiled (numba) kernels of the per-pixel and per-ray code: where they are compiled
to and how a render gets them.

Kernels are written once, as numba ``@njit(**KERNEL_OPTIONS)`` functions in the modules of
``KERNEL_MODULES`` (each with a ``warm_up()`` that compiles every kernel for the argument
types the renderer passes). numba compiles them to machine code on first use and keeps
that code in a disk cache, so only the very first render of an installation compiles
(about 20 s on 2 cores); every later one loads the code (~0.3 s with numba's
import). Nothing needs a C compiler, and an installed wheel behaves as a checkout.

The cache (``cache_dir()``) is phrt's own, not numba's default beside the sources:

* it is named by a hash of every source the kernels depend on (``SOURCE_MODULES``: the
  kernels and the constants they read from other modules) and numba's version. numba's
  own cache checks only the kernel's file and bytecode, so an edited constant in
  ``model/surface.py`` would load stale code; here it names another directory.
* it lives in the user's cache directory (``$PHRT_CACHE_DIR``, else
  ``$XDG_CACHE_HOME/phrt-usd``, else ``~/.cache/phrt-usd``), so a read-only install
  (a system site-packages, a container image) still caches; when that directory cannot
  be written either, the system's temporary directory serves.

When a render is about to compile (no cache of these sources yet), one line on stderr
says so and names ``phrt kernels``, which compiles ahead of time (the set-up runs it).
``phrt kernels --check`` says whether every kernel loads from the cache.

Every kernel releases the GIL (callers split work over their own thread pools; numba's
``parallel`` is never used) and divides by numpy's rules (``error_model``).

A base module below every phase: it names kernel modules by string and imports them only
when asked. Importing it installs the cache locator (numba's import: ~0.25 s), which
every render needs anyway.
"""

from __future__ import annotations

import hashlib
import importlib
import os
import sys
import tempfile
import time
from pathlib import Path

import numba
from numba.core import caching

#: Modules holding numba kernels, each with a ``warm_up()``.
KERNEL_MODULES = (
    "phrt_usd.model.surface_kernels",
    "phrt_usd.engine.trace.trace_kernels",
    "phrt_usd.engine.trace.fill_kernels",
    "phrt_usd.engine.trace.screen_space_kernels",
    "phrt_usd.engine.shade_kernels",
    "phrt_usd.engine.history_kernels",
    "phrt_usd.engine.trace.glossy_kernels",
    "phrt_usd.engine.trace.area_light_kernels",
)
#: Sources the compiled kernels depend on (the kernels and the constants they read):
#: their hash names the cache directory.
SOURCE_MODULES = (
    *KERNEL_MODULES,
    "phrt_usd.model.surface",
    "phrt_usd.model.scene",
    "phrt_usd.engine.trace.bounce_layout",
    "phrt_usd.kernels",
)
#: The numba options of every kernel (``@njit(**KERNEL_OPTIONS)``); ``cache`` puts the
#: compiled code in ``cache_dir()`` (``_KernelCacheLocator``).
KERNEL_OPTIONS = {"nogil": True, "cache": True, "error_model": "numpy"}
#: The environment variable that overrides the cache's parent directory.
CACHE_ENV = "PHRT_CACHE_DIR"

_PACKAGE = Path(__file__).resolve().parent
_loaded: dict[str, object] = {}
_announced = False


def _source_path(module_name: str) -> Path:
    """The file of ``phrt_usd`` module ``module_name`` (without importing it)."""
    parts = module_name.split(".")[1:]
    return _PACKAGE.joinpath(*parts).with_suffix(".py")


def source_hash() -> str:
    """12 hex digits of the SHA-256 of numba's version and every source in SOURCE_MODULES."""
    digest = hashlib.sha256(numba.__version__.encode())
    for name in SOURCE_MODULES:
        digest.update(b"\0" + name.encode() + b"\0" + _source_path(name).read_bytes())
    return digest.hexdigest()[:12]


def _writable(path: Path) -> bool:
    try:
        path.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=path).close()
        return True
    except OSError:
        return False


def _parent_dir() -> Path:
    """The directory phrt caches in (module docstring): the first writable of
    ``$PHRT_CACHE_DIR``, the user's cache directory, the system's temporary directory."""
    if os.environ.get(CACHE_ENV):
        candidates = [Path(os.environ[CACHE_ENV])]
    else:
        xdg = os.environ.get("XDG_CACHE_HOME")
        candidates = [Path(xdg) / "phrt-usd" if xdg else Path.home() / ".cache" / "phrt-usd"]
    candidates.append(Path(tempfile.gettempdir()) / f"phrt-usd-{os.getuid()}")
    for candidate in candidates:
        if _writable(candidate):
            return candidate
    return candidates[-1]  # numba then warns that it cannot cache, and compiles each run


_cache_dir: Path | None = None


def cache_dir() -> Path:
    """The directory of this installation's compiled kernels:
    ``<parent>/kernels/<source_hash()>``."""
    global _cache_dir
    if _cache_dir is None:
        _cache_dir = _parent_dir() / "kernels" / source_hash()
    return _cache_dir


class _KernelCacheLocator(caching._CacheLocator):
    """numba's cache locator for phrt's kernels: ``cache_dir()``, stamped by the sources'
    hash (every other function keeps numba's own locators)."""

    def __init__(self, py_file: str) -> None:
        self._name = Path(py_file).stem

    @classmethod
    def from_function(cls, py_func, py_file):
        module = getattr(py_func, "__module__", "") or ""
        return cls(py_file) if module in KERNEL_MODULES else None

    def get_cache_path(self) -> str:
        return str(cache_dir())

    def get_source_stamp(self) -> str:
        return cache_dir().name

    def get_disambiguator(self) -> str:
        return self._name


#: numba's cache implementation (``CacheImpl`` from numba 0.62, ``_CacheImpl`` before),
#: whose first locator to accept a function caches it.
_CACHE_IMPL = getattr(caching, "CacheImpl", None) or caching._CacheImpl
if not any(c.__name__ == _KernelCacheLocator.__name__ for c in _CACHE_IMPL._locator_classes):
    _CACHE_IMPL._locator_classes.insert(0, _KernelCacheLocator)


def _dispatchers(module) -> dict[str, object]:
    """The numba dispatchers defined in ``module`` (not imported into it) that compile
    code of their own, by name (helpers with ``inline="always"`` are compiled into the
    kernels calling them)."""
    from numba.core.registry import CPUDispatcher

    return {
        name: value
        for name, value in vars(module).items()
        if isinstance(value, CPUDispatcher)
        and value.py_func.__module__ == module.__name__
        and value.targetoptions.get("inline") != "always"
    }


def is_cached(module_name: str) -> bool:
    """Whether every kernel of ``module_name`` has compiled code in ``cache_dir()``."""
    module = importlib.import_module(module_name)
    for dispatcher in _dispatchers(module).values():
        index = Path(dispatcher._cache._cache_file._index_path)
        if not index.is_file():
            return False
    return True


def load(module_name: str):
    """The kernels of ``module_name`` (one of KERNEL_MODULES): the module, whose numba
    dispatchers load their code from ``cache_dir()`` or compile it there on first call.
    The first module found uncompiled says so on stderr, once a process."""
    global _announced
    if module_name not in KERNEL_MODULES:
        raise ValueError(f"{module_name} is not a kernel module")
    if module_name not in _loaded:
        module = importlib.import_module(module_name)
        if not _announced and not is_cached(module_name):
            _announced = True
            print(
                f"phrt: compiling the renderer's kernels into {cache_dir()} (once, about "
                "20 s; `phrt kernels` does it ahead of time)",
                file=sys.stderr,
            )
        _loaded[module_name] = module
    return _loaded[module_name]


def form() -> str:
    """How this process's kernels run: "cached" when every kernel module has compiled
    code in ``cache_dir()``, else "compiled" (this process compiles what is missing)."""
    return "cached" if all(is_cached(m) for m in KERNEL_MODULES) else "compiled"


def warm_up() -> dict[str, float]:
    """Compile every kernel for its warm-up's argument types, or load it from the cache;
    seconds per module."""
    seconds = {}
    for name in KERNEL_MODULES:
        start = time.perf_counter()
        importlib.import_module(name).warm_up()
        seconds[name] = time.perf_counter() - start
    return seconds


def signatures() -> dict[str, set]:
    """The argument types each kernel (``module.kernel``) has compiled code for in this
    process."""
    return {
        f"{name}.{kernel}": set(dispatcher.signatures)
        for name in KERNEL_MODULES
        for kernel, dispatcher in _dispatchers(importlib.import_module(name)).items()
    }


def cache_misses() -> list[str]:
    """The kernels (``module.kernel``) that ``warm_up`` compiled in this process rather
    than loaded from the cache: empty when every kernel was there."""
    missed = []
    for name in KERNEL_MODULES:
        for kernel, dispatcher in _dispatchers(importlib.import_module(name)).items():
            if sum(dispatcher.stats.cache_misses.values()):
                missed.append(f"{name}.{kernel}")
    return missed


def main(argv: list[str] | None = None) -> int:
    """``python -m phrt_usd.kernels [--check]``: compile every kernel into the cache
    (``--check``: exit 1, naming them, when any was not there already)."""
    argv = sys.argv[1:] if argv is None else argv
    for module, took in warm_up().items():
        print(f"{module}: {took:.2f} s")
    missed = cache_misses()
    print(f"kernels: {cache_dir()}")
    if "--check" in argv and missed:
        print(f"not in the cache before this run: {', '.join(missed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    from phrt_usd import kernels  # the package's module, whose locator numba uses

    sys.exit(kernels.main())
