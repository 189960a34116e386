"""Progress of long steps, for whoever listens: ``step`` announces, ``listening`` listens.

Library code that may take long on a large input (reading a stage's meshes, building
the BVH, a renderer's first-frame set-up) says what it is doing with ``step(label, done,
total)``; when nobody listens that costs one context-variable read, so a step may be
announced often. A front end listens for the length of a ``with listening(listener)``
block (the CLI's load line: ``phrt_usd.load_line``); library calls made outside such a
block report nothing.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from contextvars import ContextVar

#: A listener: (what is being done, how much of it is done, of how much or None).
Listener = Callable[[str, int, int | None], None]

_LISTENER: ContextVar[Listener | None] = ContextVar("phrt_progress_listener", default=None)


def step(label: str, done: int = 0, total: int | None = None) -> None:
    """Announce that ``label`` is being done (``done`` of ``total`` units so far)."""
    listener = _LISTENER.get()
    if listener is not None:
        listener(label, done, total)


@contextlib.contextmanager
def listening(listener: Listener) -> Iterator[Listener]:
    """Send every ``step`` of this context (thread or task) to ``listener`` inside the
    block; the previous listener, if any, afterwards."""
    token = _LISTENER.set(listener)
    try:
        yield listener
    finally:
        _LISTENER.reset(token)
