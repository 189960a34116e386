"""Loading without transparent huge pages: the one switch, as a context manager.

numpy asks the kernel for transparent huge pages (``madvise(MADV_HUGEPAGE)``) on every
array of 4 MB or more. A load writes each of its large arrays once (the scene's
geometry, the BVH's copies and per-triangle table, the G-buffer's table), so what it
pays is the first touch of every page, and on this machine (a 2-core virtual machine)
a huge page's first touch costs far more than the 512 small pages it replaces: measured
on a 1.43 M-triangle stage, read + BVH took 6.6-8.4 s with huge pages and 3.0-3.6 s
without (system time 2.6 s → 0.55 s in the BVH build alone), the first frame's set-up
3.0-4.8 s → 2.3 s, the same peak memory. ``small_pages()`` turns numpy's request off
for the block and restores it after, so frames keep numpy's default; on a numpy
without the switch it does nothing.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

try:  # numpy >= 2: _core; the private switch exists since numpy 1.20
    from numpy._core.multiarray import _set_madvise_hugepage
except ImportError:  # pragma: no cover - an older or future numpy
    _set_madvise_hugepage = None


@contextlib.contextmanager
def small_pages() -> Iterator[None]:
    """Inside the block, numpy's new large arrays do not ask for huge pages."""
    if _set_madvise_hugepage is None:
        yield
        return
    previous = _set_madvise_hugepage(False)
    try:
        yield
    finally:
        _set_madvise_hugepage(previous)
