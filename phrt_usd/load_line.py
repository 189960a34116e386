"""The load's progress line on stderr: what ``phrt render`` is doing before its first frame.

A ``LoadLine`` listens to ``phrt_usd.progress`` steps (opening the stage, reading and
triangulating its meshes, building the BVH, uploading the geometry, the first frame's
set-up) while it is entered. A load shorter than ``SHOW_AFTER_SECONDS`` shows nothing.
Past it, on a terminal, one line is rewritten in place (``\\r``) at most every
``REDRAW_SECONDS``, or handed to a live progress display (``hand_over``: the render's
rich bar, whose description then carries it); elsewhere (logs) a plain line is printed
when the step changes, at most every ``LOG_LINE_SECONDS`` for the same step. ``finish``
(at the first frame, or on leaving the block) ends it with
``load NAME: ready in 8.2 s`` where anything was shown. A disabled line (``-q``,
``--json``) prints nothing at all.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import TextIO

from phrt_usd import progress

#: A load shorter than this shows no line (the issue's "anything longer than a second").
SHOW_AFTER_SECONDS = 1.0
#: A terminal's line is redrawn at most this often (10 Hz, a progress bar's rate).
REDRAW_SECONDS = 0.1
#: Off a terminal, the same step is printed again at most this often.
LOG_LINE_SECONDS = 5.0


class LoadLine:
    """One load's progress line (module doc). ``name``: what is loaded (the stage's
    file name); ``stream``: where it is written (stderr); ``tty``: rewrite in place
    (default: whether ``stream`` is a terminal); ``clock``: seconds (tests)."""

    def __init__(
        self,
        name: str,
        enabled: bool = True,
        stream: TextIO | None = None,
        tty: bool | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.name, self.enabled = name, enabled
        self.stream = sys.stderr if stream is None else stream
        self.tty = self.stream.isatty() if tty is None else tty
        self.clock = clock
        self.start = clock()
        self.shown = False  # something was written (or handed over)
        self.finished = False
        self._drawn_at = -1e300
        self._label = ""
        self._describe: Callable[[str], None] | None = None
        self._context = None

    def __enter__(self) -> LoadLine:
        self._context = progress.listening(self)
        self._context.__enter__()
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:
            self.finish()
        else:  # the load failed: no "ready", the error follows on its own line
            self.erase()
            self.finished = True
        self._context.__exit__(exc_type, *exc)

    def __call__(self, label: str, done: int = 0, total: int | None = None) -> None:
        """A ``progress`` step."""
        if self.finished or not self.enabled:
            return
        now = self.clock()
        elapsed = now - self.start
        if elapsed < SHOW_AFTER_SECONDS:
            self._label = label
            return
        changed = label != self._label
        every = REDRAW_SECONDS if self.tty else LOG_LINE_SECONDS
        if not changed and now - self._drawn_at < every:
            return
        self._label, self._drawn_at = label, now
        count = f" {done:,}/{total:,}" if total else (f" {done:,}" if done else "")
        self._show(f"load {self.name}: {label}{count} ({elapsed:.0f} s)")

    def hand_over(self, describe: Callable[[str], None]) -> None:
        """From now on show the line through ``describe`` (a live display's text, on a
        terminal): the line drawn so far is erased."""
        if self.tty and self.enabled and not self.finished:
            self.erase()
            self._describe = describe

    def erase(self) -> None:
        """On a terminal, clear the line drawn so far (before other lines are printed);
        the next step draws it again."""
        if self.tty and self.shown and self._describe is None and not self.finished:
            self.stream.write("\r\x1b[K")
            self.stream.flush()
            self._drawn_at = -1e300

    def finish(self) -> None:
        """The load is over: ``ready in N s`` where anything was shown; no more lines."""
        if self.finished:
            return
        self.finished = True
        if self.enabled and self.shown:
            self._show(f"load {self.name}: ready in {self.clock() - self.start:.1f} s", end=True)

    def _show(self, text: str, end: bool = False) -> None:
        self.shown = True
        if self._describe is not None:
            self._describe(text)
        elif self.tty:
            self.stream.write(f"\r{text}\x1b[K" + ("\n" if end else ""))
            self.stream.flush()
        else:
            self.stream.write(text + "\n")
            self.stream.flush()
