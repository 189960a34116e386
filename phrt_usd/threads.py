"""How many threads phrt's own pools use: one setting, declared once.

Every per-pixel and per-ray pool (the tracer's ray chunks, the G-buffer derivation and
shadow-map lookups, local shading) splits work that releases the GIL (Embree, numpy
loops), so each uses the machine's cores. ``RenderOptions.threads`` defaults to it.
"""

import os

#: Threads of each of phrt's pools: the cores this process may run on (at least 1).
DEFAULT_THREADS = max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                      else (os.cpu_count() or 1))  # fmt: skip
