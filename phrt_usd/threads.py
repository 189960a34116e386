"""How many threads phrt uses: one setting (``--threads N``, ``threads=``), declared once.

Every per-pixel and per-ray pool (the tracer's ray chunks and shadow rays, the G-buffer
derivation and shadow-map lookups, local shading) splits work that releases the GIL
(Embree, numpy loops) into that many chunks. ``RenderOptions.threads`` defaults to
``DEFAULT_THREADS``; ``FrameRenderer`` applies its setting with ``apply_threads`` before
it creates a GL context or a pool.

What one process can and cannot change once a library is loaded (``apply_threads``):

* phrt's own pools: each renderer's tracer and raster pools take its setting; the
  shading pool is one per process and follows the latest ``apply_threads``.
* llvmpipe (Mesa's CPU OpenGL, OSMesa and EGL alike) reads ``LP_NUM_THREADS`` once,
  when the process's first GL context is created (measured: later contexts keep the
  first count), so a process's first renderer with a raster phase decides it;
  ``llvmpipe_threads`` counts its render threads as they are.
* OpenBLAS (numpy's, loaded with numpy): set through its ``*set_num_threads*`` entry
  point, found among the libraries the process has loaded.
* numba (if a kernel module loaded it): ``numba.set_num_threads``, at most the pool it
  started with (``NUMBA_NUM_THREADS``, read at its import; set here when not loaded yet).
* OpenMP runtimes read ``OMP_NUM_THREADS`` when they load; it is set for libraries
  loaded later, never changed in one already loaded.
* Embree: embreex 4.4 creates its device without a configuration string (its
  ``EmbreeDevice()`` takes no argument), so Embree's own tasking threads (they build the
  BVHs; every ray query runs on the calling thread) are Embree's default, all cores.
"""

from __future__ import annotations

import ctypes
import os
import sys

from phrt_usd.checks import check_integer, check_range
from phrt_usd.errors import BadOption

#: Threads of each of phrt's pools by default: the cores this process may run on (at
#: least 1).
DEFAULT_THREADS = max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                      else (os.cpu_count() or 1))  # fmt: skip
#: Largest thread setting: far above any machine phrt runs on, and small enough that a
#: typo (``--threads 100000``) is refused instead of starting that many threads.
MAX_THREADS = 1024
#: Environment variables native libraries read once, when they load (set for those not
#: loaded yet).
LOAD_TIME_VARIABLES = ("LP_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                       "NUMBA_NUM_THREADS")  # fmt: skip
#: OpenBLAS entry points that set its thread count, by build (numpy's scipy-openblas
#: wheels use the prefixed 64-bit-integer names).
OPENBLAS_SETTERS = ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads",
                    "openblas_set_num_threads64_", "openblas_set_num_threads")  # fmt: skip

_current = {"threads": DEFAULT_THREADS}


def check_threads(value: object, name: str = "threads") -> int:
    """``value`` as a thread count in 1..MAX_THREADS; BadOption (one line) otherwise."""
    return check_range(check_integer(value, name), 1, MAX_THREADS, name)


def current_threads() -> int:
    """The setting last applied in this process (``DEFAULT_THREADS`` before any)."""
    return _current["threads"]


def apply_threads(threads: int) -> int:
    """Make ``threads`` this process's setting for what reads it process-wide (see the
    module docstring): the shading pool, the load-time variables, OpenBLAS, numba.
    Returns it."""
    threads = check_threads(threads)
    _current["threads"] = threads
    for name in LOAD_TIME_VARIABLES:
        os.environ[name] = str(threads)
    _set_openblas_threads(threads)
    numba = sys.modules.get("numba")
    if numba is not None:
        numba.set_num_threads(min(threads, int(numba.config.NUMBA_NUM_THREADS)))
    return threads


def _set_openblas_threads(threads: int) -> None:
    """Set every loaded OpenBLAS's thread count (Linux: the libraries in
    /proc/self/maps); nothing where none is loaded or the maps are unreadable."""
    try:
        with open("/proc/self/maps") as maps:
            paths = {line.split()[-1] for line in maps if "openblas" in line.lower()}
    except OSError:
        return
    for path in sorted(p for p in paths if p.startswith("/") and ".so" in p):
        try:
            lib = ctypes.CDLL(path, mode=os.RTLD_NOLOAD)  # the loaded copy, never a new one
        except OSError:
            continue
        for setter in OPENBLAS_SETTERS:
            function = getattr(lib, setter, None)
            if function is not None:
                function.argtypes = [ctypes.c_int]
                function(threads)
                break


def llvmpipe_threads() -> int | None:
    """llvmpipe's render threads running in this process (its ``llvmpipe-N`` threads),
    None where none runs (no GL context yet, another OpenGL driver) or /proc is absent."""
    try:
        tasks = os.listdir("/proc/self/task")
    except OSError:
        return None
    count = 0
    for task in tasks:
        try:
            with open(f"/proc/self/task/{task}/comm") as comm:
                count += comm.read().startswith("llvmpipe-")
        except OSError:
            continue  # the thread ended meanwhile
    return count or None


def parse_threads(text: str, option: str = "--threads") -> int:
    """``"4"`` → 4 (a command line's thread count); BadOption (one line) otherwise."""
    try:
        value = int(text.strip())
    except ValueError:
        raise BadOption(
            f"{option} {text!r}: expected a whole number of threads in 1..{MAX_THREADS}"
        ) from None
    return check_threads(value, option)
