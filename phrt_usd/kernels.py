"""The compiled (numba) kernels of the per-pixel and per-ray code, and their warm-up.

Each module listed in ``KERNEL_MODULES`` holds kernels compiled on first use and cached
on disk by numba (beside the module, in ``__pycache__``), and a ``warm_up()`` that runs
every kernel once on tiny inputs of the renderer's argument types. The set-up (``./run``)
calls ``python -m phrt_usd.kernels`` after installing, so a render's first frame loads
compiled code instead of waiting seconds for the compiler; a stale or missing cache only
costs that compile, never a wrong result (numba keys its cache by the source file).
"""

from __future__ import annotations

import importlib
import time

#: Modules holding numba kernels, each with a ``warm_up()``.
KERNEL_MODULES = ("phrt_usd.model.surface_kernels", "phrt_usd.render.trace.trace_kernels")


def warm_up() -> dict[str, float]:
    """Compile (or load from numba's disk cache) every kernel; seconds per module."""
    seconds = {}
    for name in KERNEL_MODULES:
        start = time.perf_counter()
        importlib.import_module(name).warm_up()
        seconds[name] = time.perf_counter() - start
    return seconds


if __name__ == "__main__":
    for module, took in warm_up().items():
        print(f"{module}: {took:.2f} s")
