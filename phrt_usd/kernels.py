"""The compiled (numba) kernels of the per-pixel and per-ray code: how a frame gets them.

Kernels are written once, as numba ``@njit`` functions in the modules of
``KERNEL_MODULES`` (each with a ``warm_up()`` that calls every kernel on tiny inputs of
the renderer's argument types). A render takes them through ``load(module_name)``, in
one of two compiled forms of that same source:

* **ahead of time** (the set-up's ``python -m phrt_usd.kernels`` builds it): one
  extension module in ``phrt_usd/_aot/`` with its argument check beside it (from
  ``kernel_guard.c``), named by a hash of the sources (``SOURCE_MODULES``,
  ``GUARD_SOURCE``), so an edited kernel can never load an old build. Importing it
  costs ~0.07 s and no numba import at all; a JIT start (numba's import, type
  registries, its disk cache) costs ~0.6 s of every render's start and of its first
  frame (measured 2026-12-03: first image of a small stage 1.14 s without kernels,
  1.89 s with JIT-loaded ones).
* **just in time** (numba, cached on disk beside the module): when no build matches the
  sources (a fresh checkout before the set-up, an install without a C toolchain).

Both are compiled by numba from the same functions with the same options: the GIL is
released while a kernel runs (callers split work over their own thread pools; numba's
``parallel`` is never used), and division follows numpy's rules (``error_model``). The
build exports each kernel for the signatures its ``warm_up`` compiled, and a call whose
arguments match none of them runs the JIT kernel instead (``_Guarded``; the test suite
fails on any such call): callers pass the dtypes and layouts their docstrings give
(``tests/test_kernels.py`` checks both forms agree).

A base module: it names kernel modules by string and imports them only when asked, so
it sits below every phase.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.machinery
import importlib.util
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType, SimpleNamespace

import numpy as np

from phrt_usd.atomic import write_bytes_atomic, write_text_atomic

#: Modules holding numba kernels, each with a ``warm_up()``.
KERNEL_MODULES = (
    "phrt_usd.model.surface_kernels",
    "phrt_usd.render.trace.trace_kernels",
    "phrt_usd.render.shade_kernels",
)
#: Sources the compiled kernels depend on (the kernels and the constants they read):
#: their hash names the ahead-of-time build.
SOURCE_MODULES = (
    *KERNEL_MODULES,
    "phrt_usd.model.surface",
    "phrt_usd.render.trace.bounce_layout",
    "phrt_usd.kernels",
)
#: The C source of the argument check in front of the ahead-of-time kernels (``_Guarded``),
#: built with them and named by the same hash.
GUARD_SOURCE = Path(__file__).resolve().parent / "kernel_guard.c"
#: Where the ahead-of-time builds go (not in version control).
AOT_DIR = Path(__file__).resolve().parent / "_aot"
#: The numba options of every kernel (``@njit(**KERNEL_OPTIONS)``); the ahead-of-time
#: build applies the same two to its compile flags.
KERNEL_OPTIONS = {"nogil": True, "cache": True, "error_model": "numpy"}

_loaded: dict[str, object] = {}


def _source_path(module_name: str) -> Path:
    """The file of ``phrt_usd`` module ``module_name`` (without importing it)."""
    parts = module_name.split(".")[1:]
    return Path(__file__).resolve().parent.joinpath(*parts).with_suffix(".py")


def source_hash() -> str:
    """12 hex digits of the SHA-256 of every source in SOURCE_MODULES and GUARD_SOURCE."""
    digest = hashlib.sha256()
    for name in SOURCE_MODULES:
        digest.update(name.encode() + b"\0" + _source_path(name).read_bytes())
    digest.update(b"guard\0" + GUARD_SOURCE.read_bytes())
    return digest.hexdigest()[:12]


def _aot_name() -> str:
    return f"phrt_kernels_{source_hash()}"


def _aot_file() -> Path:
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    return AOT_DIR / f"{_aot_name()}{suffix}"


#: The guard's module name (its ``PyInit_`` function); its file carries the build's hash.
_GUARD_MODULE = "phrt_kernel_guard"


def _guard_file() -> Path:
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    return AOT_DIR / f"{_GUARD_MODULE}_{source_hash()}{suffix}"


def _extension(name: str, path: Path) -> ModuleType:
    """Extension module ``name`` loaded from ``path`` (ImportError when it cannot be)."""
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _export_name(module_name: str, kernel: str) -> str:
    """The ahead-of-time module's name of kernel ``kernel`` of ``module_name``."""
    return f"{module_name.rsplit('.', 1)[-1]}__{kernel}"


def _aot_module() -> tuple[ModuleType, dict, object] | None:
    """The ahead-of-time build of the current sources, its array signatures
    (``build_aot``'s sidecar) and its guard's ``fits``, or None."""
    if "aot" in _loaded:
        return _loaded["aot"]
    path, guard, found = _aot_file(), _guard_file(), None
    arrays = path.with_name(_aot_name() + ".json")
    if path.is_file() and arrays.is_file() and guard.is_file():
        try:
            module = _extension(_aot_name(), path)
            fits = _extension(_GUARD_MODULE, guard).fits
            found = module, json.loads(arrays.read_text()), fits
        except (ImportError, ValueError):
            found = None  # e.g. built for another machine: the JIT form serves
    _loaded["aot"] = found
    return found


class _Guarded:
    """An ahead-of-time kernel behind a check of its arguments.

    The compiled wrapper trusts an array's memory to be of the dtype, rank and layout it
    was built for (numba checks only the item size: an int32 array where int64 is
    expected reads past the buffer), so every call's arguments are checked against the
    build's signatures first, by ``kernel_guard.c``'s ``fits`` (one C call: ~0.1 us; a
    kernel the warm-up compiled for several argument types has one build of each, tried
    in order); when none fits, the call goes to the JIT kernel, which compiles for those
    types, and the mismatch is noted in ``FALLBACKS`` (the test suite fails on any).
    Scalars are converted by the wrapper itself."""

    def __init__(self, variants: list, module_name: str, name: str, fits) -> None:
        self._module_name, self.__name__ = module_name, name
        self._fits = fits
        #: (function, its arguments as ``fits`` takes them) per build
        self._variants = [(function, guard_spec(arrays)) for function, arrays in variants]

    def __call__(self, *args):
        for function, spec in self._variants:
            if self._fits(args, spec):
                return function(*args)
        FALLBACKS.add(f"{self._module_name}.{self.__name__}({_describe(args)})")
        jit = getattr(importlib.import_module(self._module_name), self.__name__)
        return jit(*args)


def guard_spec(arguments: list) -> bytes:
    """A build's arguments (the sidecar's per argument "scalar", "none" or [dtype,
    ndim, layout]) as ``kernel_guard.fits`` takes them: 4 bytes an argument, kind
    (0 scalar, 1 None, 2 array), then for an array its numpy type number, its rank and
    1 when it must be C-contiguous."""
    spec = bytearray()
    for a in arguments:
        if a == "scalar":
            spec += bytes((0, 0, 0, 0))
        elif a == "none":
            spec += bytes((1, 0, 0, 0))
        else:
            spec += bytes((2, np.dtype(a[0]).num, a[1], int(a[2] == "C")))
    return bytes(spec)


def _describe(args) -> str:
    """The argument types of a call, as FALLBACKS names them (``float64[2d C]``)."""
    return ", ".join(
        f"{a.dtype}[{a.ndim}d {'C' if a.flags.c_contiguous else 'A'}]"
        if type(a) is np.ndarray
        else type(a).__name__
        for a in args
    )


#: Kernels called with argument types their ahead-of-time build was not made for
#: ("module.kernel(argument types)"): each such call ran the JIT kernel instead
#: (``_Guarded``).
FALLBACKS: set[str] = set()


def load(module_name: str):
    """The kernels of ``module_name`` (one of KERNEL_MODULES): the ahead-of-time build's
    functions when one matches the sources, else the module itself (numba JIT). Either
    way an object with the kernels as attributes."""
    if module_name not in KERNEL_MODULES:
        raise ValueError(f"{module_name} is not a kernel module")
    if module_name in _loaded:
        return _loaded[module_name]
    aot = _aot_module()
    found = None
    if aot is not None:
        module, signatures, fits = aot
        prefix = _export_name(module_name, "")
        names = {k[len(prefix):]: v for k, v in signatures.items() if k.startswith(prefix)}
        if names:
            found = SimpleNamespace(**{
                n: _Guarded(
                    [(getattr(module, f"{prefix}{n}__{k}"), arrays)
                     for k, arrays in enumerate(variants)],
                    module_name,
                    n,
                    fits,
                )
                for n, variants in names.items()
            })  # fmt: skip
            found.compiled = "aot"
    if found is None:
        found = importlib.import_module(module_name)
    _loaded[module_name] = found
    return found


def form(module_name: str) -> str:
    """"aot" or "jit": which compiled form ``load`` gives for ``module_name``."""
    return getattr(load(module_name), "compiled", "jit")


def warm_up() -> dict[str, float]:
    """Compile (or load from numba's disk cache) every JIT kernel; seconds per module."""
    seconds = {}
    for name in KERNEL_MODULES:
        start = time.perf_counter()
        importlib.import_module(name).warm_up()
        seconds[name] = time.perf_counter() - start
    return seconds


def _kernels(module: ModuleType) -> dict[str, object]:
    """The numba dispatchers defined in ``module`` (not imported into it from another
    kernel module, which exports its own) that its warm-up compiled, by name."""
    from numba.core.registry import CPUDispatcher

    return {
        name: value
        for name, value in vars(module).items()
        if isinstance(value, CPUDispatcher)
        and value.signatures
        and not name.startswith("_")
        and value.py_func.__module__ == module.__name__
    }


def exported_signatures(dispatcher) -> list[tuple]:
    """The argument types ``dispatcher`` is exported for: every signature it compiled but
    those with a literal argument. numba compiles such a variant when another kernel calls
    this one with a constant (``True``), folding the constant in; the C guard tells
    arguments apart by dtype, rank and layout only, so it would hand any value of that
    argument to the folded code."""
    from numba.core import types

    return [
        args
        for args in dispatcher.signatures
        if not any(isinstance(a, types.Literal) for a in args)
    ]


def build_aot() -> Path:
    """Build the ahead-of-time module of the current sources and its guard
    (``kernel_guard.c``) into AOT_DIR (removing older builds) and return the module's
    path; nothing to do when they exist. Needs numba's ``pycc`` (setuptools and a C
    compiler). Each kernel is exported once for each signature its module's
    ``warm_up`` compiled (``name__0``, ``name__1``, ...)."""
    target, guard = _aot_file(), _guard_file()
    sidecar = target.with_name(_aot_name() + ".json")
    if target.is_file() and sidecar.is_file() and guard.is_file():
        return target
    warm_up()
    import numba.pycc.compiler as pycc_compiler
    from numba.core import types
    from numba.pycc import CC

    AOT_DIR.mkdir(exist_ok=True)
    # Built in a folder of its own, then published with the atomic writer: a render
    # starting meanwhile, or a second build, never loads a half-written module.
    building = Path(tempfile.mkdtemp(prefix=".build-", dir=AOT_DIR))
    cc = CC(_aot_name())
    cc.output_dir = str(building)
    cc.verbose = False
    signatures = {}  # export name → per variant, per argument "scalar", "none" or an array
    for module_name in KERNEL_MODULES:
        module = importlib.import_module(module_name)
        for name, dispatcher in _kernels(module).items():
            options = {k: dispatcher.targetoptions.get(k) for k in ("nogil", "error_model")}
            if options != {k: KERNEL_OPTIONS[k] for k in options}:
                raise RuntimeError(
                    f"{module_name}.{name} is compiled with {options}: the build applies "
                    f"KERNEL_OPTIONS to every kernel, so its JIT form must use them too"
                )
            export = _export_name(module_name, name)
            signatures[export] = []
            for k, args in enumerate(exported_signatures(dispatcher)):
                result = dispatcher.overloads[args].signature.return_type
                cc.export(f"{export}__{k}", result(*args))(dispatcher.py_func)
                signatures[export].append([
                    [str(np.dtype(str(a.dtype))), a.ndim, a.layout]
                    if isinstance(a, types.Array)
                    else "none" if isinstance(a, types.NoneType) else "scalar"
                    for a in args
                ])  # fmt: skip
    # pycc compiles with numba's default flags; the kernels' own options (GIL released,
    # numpy's division rules) are set on them for this build.
    original = pycc_compiler.Flags

    class KernelFlags(original):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.release_gil = KERNEL_OPTIONS["nogil"]
            self.error_model = KERNEL_OPTIONS["error_model"]

    pycc_compiler.Flags = KernelFlags
    try:
        cc.compile()
        _build_guard(building / guard.name)
        # The guard first: a module and sidecar are only ever found beside their guard.
        write_bytes_atomic(guard, (building / guard.name).read_bytes())
        write_text_atomic(sidecar, json.dumps(signatures, indent=1))
        write_bytes_atomic(target, (building / target.name).read_bytes())
    finally:
        pycc_compiler.Flags = original
        shutil.rmtree(building, ignore_errors=True)
    for old in [*AOT_DIR.glob("phrt_kernels_*"), *AOT_DIR.glob(f"{_GUARD_MODULE}_*")]:
        if old not in (target, sidecar, guard):
            old.unlink()
    return target


def _build_guard(output: Path) -> None:
    """Compile ``kernel_guard.c`` into extension ``output`` with the toolchain pycc
    uses (the Python and numpy headers)."""
    from numba.pycc.platform import Toolchain

    toolchain = Toolchain()
    objects = toolchain.compile_objects(
        [str(GUARD_SOURCE)], str(output.parent / "guard"),
        include_dirs=toolchain.get_python_include_dirs(), extra_cflags=["-O2"],
    )  # fmt: skip
    toolchain.link_shared(
        str(output), objects, toolchain.get_python_libraries(),
        toolchain.get_python_library_dirs(),
    )  # fmt: skip


def main() -> int:
    """``python -m phrt_usd.kernels``: warm the JIT cache, build the ahead-of-time module."""
    for module, took in warm_up().items():
        print(f"{module}: JIT {took:.2f} s")
    try:
        start = time.perf_counter()
        path = build_aot()
        print(f"ahead of time: {path.name} ({time.perf_counter() - start:.1f} s)")
    except Exception as error:  # no toolchain: renders use the JIT form
        print(f"ahead of time: not built ({type(error).__name__}: {error}); JIT kernels serve")
    return 0


if __name__ == "__main__":
    sys.exit(main())
