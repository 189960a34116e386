"""A sweep's output directory ``OUT``: made, locked, and never a silent replacement of an
earlier sweep.

``SweepDirectory`` (a context manager around the sweep) makes ``OUT`` (an ``--out`` that
cannot be made is a bad option: exit 2), takes its lock (``run.run_directory.
DirectoryLock``: one writer at a time) and then claims it:

- an ``OUT`` holding anything besides the sweep's inputs (``sweep_files.INPUT_NAMES``:
  ``paper.json``, the lock) is refused, naming what it holds, unless ``overwrite``;
- ``overwrite`` deletes the files a sweep writes, by their names alone
  (``sweep_files.is_sweep_file`` at the top, ``images/<stage>/<frame>/*.png`` below),
  then the image directories this leaves empty. A link is removed itself, never
  followed; a directory is never entered through a link; every other file stays.

A sweep cannot be resumed (its configurations' memories are not checkpointed): an
interrupted sweep keeps its finished rows and report, and the next sweep into that
``OUT`` needs ``--overwrite``.
"""

from __future__ import annotations

from contextlib import suppress
from pathlib import Path

from phrt_usd.errors import BadOption
from phrt_usd.evaluate.sweep_files import IMAGES_DIR, INPUT_NAMES, is_report_image, is_sweep_file
from phrt_usd.run.run_directory import DirectoryLock

#: How many of the names found in a refused ``OUT`` the message shows.
SHOWN_NAMES = 3


class SweepDirectory:
    """``OUT`` held for one sweep (see the module docstring); released on exit."""

    def __init__(self, out: Path, overwrite: bool = False) -> None:
        self.out = Path(out)
        self.overwrite = overwrite
        self._lock: DirectoryLock | None = None

    def __enter__(self) -> SweepDirectory:
        make_out(self.out)
        self._lock = DirectoryLock(self.out).acquire()
        try:
            claim(self.out, self.overwrite)
        except BaseException:
            self._lock.release()
            self._lock = None
            raise
        return self

    def __exit__(self, *exc) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None


def claim_sweep_out(out: Path, overwrite: bool = False) -> None:
    """Make, refuse or clear ``out`` under its lock, then release it: for a writer that
    takes the lock itself (a sweep on a cluster)."""
    with SweepDirectory(out, overwrite):
        pass


def make_out(out: Path) -> None:
    """Create ``out`` (and its parents); BadOption naming ``--out`` when it is a file or
    cannot be made."""
    if out.exists() and not out.is_dir():
        raise BadOption(f"--out {out}: exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise BadOption(f"--out {out}: cannot create ({error.strerror or error})") from None


def check_out(out: Path, overwrite: bool = False) -> None:
    """BadOption when ``out`` is a file, or holds anything but the sweep's inputs and
    ``overwrite`` is not given. Reads only: no directory is made, nothing is deleted."""
    if out.exists() and not out.is_dir():
        raise BadOption(f"--out {out}: exists and is not a directory")
    if overwrite or not out.is_dir():
        return
    try:
        present = sorted(p.name for p in out.iterdir() if p.name not in INPUT_NAMES)
    except OSError as error:
        raise BadOption(f"--out {out}: cannot read ({error.strerror or error})") from None
    if present:
        shown = ", ".join(present[:SHOWN_NAMES]) + (", ..." if len(present) > SHOWN_NAMES else "")
        raise BadOption(
            f"--out {out}: not empty ({shown}); choose an empty directory or use --overwrite "
            "to replace the sweep files in it"
        )


def claim(out: Path, overwrite: bool) -> None:
    """Refuse a non-empty ``out`` (``check_out``) or, with ``overwrite``, delete the
    sweep's files in it (``clear``). Call with ``out``'s lock held."""
    check_out(out, overwrite)
    if overwrite:
        clear(out)


def clear(out: Path) -> None:
    """Delete the files an earlier sweep wrote in ``out`` (see the module docstring)."""
    for entry in out.iterdir():
        if is_sweep_file(entry.name) and (entry.is_symlink() or not entry.is_dir()):
            entry.unlink()
    images = out / IMAGES_DIR
    if images.is_symlink():
        images.unlink()
        return
    if not images.is_dir():
        return
    for stage in list(images.iterdir()):
        if stage.is_symlink() or not stage.is_dir():
            continue  # not a directory a sweep made: left alone
        for frame in list(stage.iterdir()):
            if frame.is_symlink() or not frame.is_dir():
                continue
            for entry in frame.iterdir():
                relative = entry.relative_to(images)
                if is_report_image(relative) and (entry.is_symlink() or not entry.is_dir()):
                    entry.unlink()
            _remove_if_empty(frame)
        _remove_if_empty(stage)
    _remove_if_empty(images)


def _remove_if_empty(directory: Path) -> None:
    with suppress(OSError):
        directory.rmdir()  # only succeeds when nothing else is left in it
