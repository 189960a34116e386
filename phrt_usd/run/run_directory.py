"""The output directory of one run: its lock, what it may already hold, its disk reserve.

See ``RunDirectory``. File names come from ``run_files`` and ``products``.

The lock and the reserve are phrt's own files, created exclusively (``O_CREAT | O_EXCL |
O_NOFOLLOW``) and only ever written through the descriptor that created them: whatever
is planted under their names (a symlink, a hard link to another file, a folder) is never
opened for writing. A lock file left by a run that died is removed and made anew, never
reused.
"""

from __future__ import annotations

import errno
import fcntl
import os
from collections.abc import Callable
from contextlib import suppress
from pathlib import Path

from phrt_usd.atomic import published_name
from phrt_usd.errors import BadOption, PhrtError
from phrt_usd.run.products import DEFAULT_PREVIEW, DEFAULT_TEMPLATE, template_pattern
from phrt_usd.run.run_files import (
    CHECKPOINT_FILE,
    FRAMES_DIR,
    LOCK_FILE,
    RESERVE_FILE,
    SELECTION_LAYER_FILE,
    STATS_FILE,
)
from phrt_usd.run.selection_layer import check_layer_path
from phrt_usd.usd.stage import StageScene

#: Disk held in reserve for a run's records (see ``RunDirectory.keep_reserve``): at least
#: RESERVE_MIN_BYTES, and RESERVE_FACTOR times what the records took when last written
#: (an atomic rewrite needs the old and the new file at once, and records grow).
RESERVE_MIN_BYTES = 64 * 1024
RESERVE_FACTOR = 3
#: Tries at taking the lock: each loses only to another process that replaced the file
#: at that moment (a dead run's lock file, or its own new one), so a few always suffice.
LOCK_ATTEMPTS = 5
#: The run files ``--overwrite`` deletes in ``OUT`` besides the images (the lock and
#: the reserve are the running render's own).
RUN_FILES = (STATS_FILE, SELECTION_LAYER_FILE, CHECKPOINT_FILE)
#: Flags of a new lock or reserve file: created here or not at all, never through a link.
_EXCLUSIVE = os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW


class DirectoryLock:
    """``OUT/.phrt.lock``, held with ``flock`` by the one process writing ``OUT`` (a render
    or a sweep). The kernel releases it when the process dies, so a killed run never
    blocks the next; a second writer is refused at once, naming the holder's pid.

    The file is created exclusively and the pid written through that descriptor only.
    An existing file is flocked read-only to learn whether a live run holds it: if so the
    run is refused; if not (its run died) it is unlinked while flocked, still the file at
    the name, and a new one created: it is never truncated or written (a hard link
    planted there keeps its target's bytes). A symlink there is refused."""

    def __init__(self, out: Path) -> None:
        self.out = Path(out)
        self._fd: int | None = None

    def __enter__(self) -> DirectoryLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()

    def acquire(self) -> DirectoryLock:
        path = self.out / LOCK_FILE
        for _ in range(LOCK_ATTEMPTS):
            try:
                fd = os.open(path, _EXCLUSIVE, 0o644)
            except FileExistsError:
                self._clear_stale(path)
                continue
            except OSError as error:
                raise BadOption(f"--out {self.out}: cannot write ({error.strerror})") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:  # another run took it for stale before we flocked
                os.close(fd)
                continue
            if _same_file(fd, path):
                os.write(fd, f"{os.getpid()}\n".encode())
                self._fd = fd
                return self
            os.close(fd)  # locked a file another run just removed as stale: try again
        raise PhrtError(f"{path}: could not take the lock (other runs keep replacing it)")

    def _clear_stale(self, path: Path) -> None:
        """The lock file at ``path`` exists: PhrtError naming the holder if a live run
        holds it; else remove it (see the class), so the next attempt creates a new one."""
        try:
            fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
        except FileNotFoundError:
            return  # its holder released it meanwhile
        except OSError as error:
            if error.errno == errno.ELOOP:
                raise PhrtError(f"{path}: is a symlink; remove it") from None
            raise BadOption(
                f"--out {self.out}: cannot read {LOCK_FILE} ({error.strerror})"
            ) from None
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                text = os.read(fd, 64).decode("ascii", "replace").strip()
                holder = text if text.isdigit() else "?"
                raise PhrtError(
                    f"{self.out}: another phrt run is writing here (pid {holder}); "
                    "wait for it or choose another --out"
                ) from None
            if _same_file(fd, path):  # flocked, so no live run holds it: a dead run's
                try:
                    os.unlink(path)
                except FileNotFoundError:
                    pass
                except OSError:
                    raise PhrtError(f"{path}: not a lock file phrt made; remove it") from None
        finally:
            os.close(fd)

    def release(self) -> None:
        if self._fd is not None:
            if _same_file(self._fd, self.out / LOCK_FILE):
                with suppress(OSError):
                    os.unlink(self.out / LOCK_FILE)
            os.close(self._fd)  # closing releases the flock
            self._fd = None


class RunDirectory:
    """Context manager owning ``out`` for one run (see the module docstring).

    On entry: the selection layer's extension is checked (BadOption) and it may not be a
    layer of the stage; ``out`` is created if missing (BadOption if it is a file or
    cannot be made); ``OUT/.phrt.lock`` is taken (``DirectoryLock``) or the run is
    refused naming the holder's pid; an ``out`` holding anything is refused unless
    ``resume`` (the checkpoint must then be this run's: checked by ``_load_checkpoint``)
    or ``overwrite``. On exit the reserve and the lock are released and their files
    removed.

    ``overwrite`` deletes phrt's own files only, known by construction, never by what a
    file in ``out`` says (a handed-over or edited run directory does not choose what is
    deleted): the files in ``out`` that ``images`` (this run's file name templates,
    ``run.products``, relative to ``out``) and the default layout (``frames/NNNN.exr`` and
    ``.png``) name at any frame number, ``stats.json``, ``selection.usda``,
    ``checkpoint.json``, and the temp files a killed writer left for any of those names.
    A symlink is removed itself, never followed, and a folder reached through one is never
    entered; no folder is deleted; files of other names, of another run's templates, and
    a ``--selection-layer`` outside ``out`` stay (the run's records replace the layer).
    """

    def __init__(self, out: Path, layer_path: Path, scene: StageScene | None, *,
                 resume: bool = False, overwrite: bool = False,
                 images: list[str] | tuple[str, ...] = ()):  # fmt: skip
        if resume and overwrite:
            raise BadOption("--resume and --overwrite exclude each other")
        self.out = Path(out)
        self.images = tuple(images)
        self.layer_path = Path(layer_path)
        self.scene = scene
        self.resume = resume
        self.overwrite = overwrite
        self._lock_held: DirectoryLock | None = None
        self._reserve_fd: int | None = None
        self.fresh = True  # False when resuming a run that left files in out

    def __enter__(self) -> RunDirectory:
        out = self.out
        check_layer_path(self.layer_path, "--selection-layer")
        if self.scene is not None:
            _check_not_a_stage_layer(self.layer_path, self.scene)
        if out.exists() and not out.is_dir():
            raise BadOption(f"--out {out}: exists and is not a directory")
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise BadOption(f"--out {out}: cannot create ({error.strerror})") from None
        self._lock()
        try:
            self._claim()
            self.keep_reserve(RESERVE_MIN_BYTES)
            frames = out / FRAMES_DIR
            if frames.is_symlink() or (frames.exists() and not frames.is_dir()):
                raise PhrtError(f"{frames}: not a directory of this run (a link or a file)")
        except BaseException:
            self.release_reserve()
            self._unlock()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.release_reserve()
        self._unlock()

    def keep_reserve(self, nbytes: int) -> None:
        """Hold at least ``max(nbytes, RESERVE_MIN_BYTES)`` of disk in ``OUT/.phrt.reserve``
        (allocated, never written to) so that when the disk fills, releasing it leaves
        room to write the finished frames' records. Without room for it, nothing is held.

        The file is this run's own: created exclusively, allocated only through the
        descriptor that created it, and made anew (never written through) when the name
        no longer leads to it alone (replaced, or hard-linked elsewhere)."""
        nbytes = max(int(nbytes), RESERVE_MIN_BYTES)
        path = self.out / RESERVE_FILE
        fd = self._reserve_fd
        if fd is None or not _sole_name(fd, path):
            self.release_reserve()
            try:
                fd = os.open(path, _EXCLUSIVE, 0o600)
            except OSError:
                return  # something phrt cannot remove is there, or no room for a file
            self._reserve_fd = fd
        try:
            if os.fstat(fd).st_size < nbytes:
                os.posix_fallocate(fd, 0, nbytes)
        except OSError:
            pass  # no room for the reserve (the disk is full already) or no fallocate here

    def release_reserve(self) -> None:
        """Give the reserve's disk back: close it and remove the name (a link planted
        there is removed itself; a folder stays)."""
        if self._reserve_fd is not None:
            os.close(self._reserve_fd)
            self._reserve_fd = None
        with suppress(OSError):
            os.unlink(self.out / RESERVE_FILE)

    def _lock(self) -> None:
        self._lock_held = DirectoryLock(self.out).acquire()

    def _unlock(self) -> None:
        if self._lock_held is not None:
            self._lock_held.release()
            self._lock_held = None

    def _claim(self) -> None:
        """Refuse a non-empty ``out`` unless resuming or overwriting (see the class)."""
        present = sorted(
            p.name for p in self.out.iterdir() if p.name not in (LOCK_FILE, RESERVE_FILE)
        )
        layer_exists = self.layer_path.exists() or self.layer_path.is_symlink()
        outside = layer_exists and self.layer_path.parent.resolve() != self.out.resolve()
        if self.resume:
            # A fresh out_dir starts the run; otherwise _load_checkpoint refuses anything
            # but this run's checkpoint. Its selection layer is rewritten whole.
            self.fresh = not present
            return
        if self.overwrite:
            self._clear()
            return
        if present:
            shown = ", ".join(present[:3]) + (", ..." if len(present) > 3 else "")
            raise PhrtError(
                f"--out {self.out}: not empty ({shown}); use --resume to continue the run "
                "in it or --overwrite to replace phrt's files"
            )
        if outside:
            raise PhrtError(
                f"--selection-layer {self.layer_path}: exists; use --overwrite to replace it"
            )

    def _clear(self) -> None:
        """Delete phrt's own files in ``out`` (see the class)."""
        for template in dict.fromkeys((*self.images, DEFAULT_TEMPLATE, DEFAULT_PREVIEW)):
            _clear_template(self.out, template)
        _clear_names(self.out, RUN_FILES.__contains__)
        frames = self.out / FRAMES_DIR
        if frames.is_symlink():
            frames.unlink()  # the link itself; the default layout writes a real folder


def _clear_template(out: Path, template: str) -> None:
    """Delete the files in ``out`` that ``template`` names at any frame number (see
    ``_clear_names``), when every folder on its way is a real folder inside ``out``."""
    parts = Path(template).parts
    if not parts or Path(template).is_absolute() or ".." in parts:
        return  # never one of ours: products are relative names inside out
    folder = out
    for part in parts[:-1]:
        folder = folder / part
        if folder.is_symlink() or not folder.is_dir():
            return
    _clear_names(folder, template_pattern(parts[-1]).match)


def _clear_names(folder: Path, ours: Callable[[str], object]) -> None:
    """Delete the entries of ``folder`` whose name is ``ours``, or is the temp file of a
    name that is (``atomic.published_name``): files and links (a link is removed itself,
    never followed), never a folder."""
    for entry in folder.iterdir():
        name = published_name(entry.name) or entry.name
        if ours(name) and (entry.is_symlink() or not entry.is_dir()):
            with suppress(FileNotFoundError):
                entry.unlink()


def _sole_name(fd: int, path: Path) -> bool:
    """True if the file open as ``fd`` is the one at ``path`` and has no other name."""
    return os.fstat(fd).st_nlink == 1 and _same_file(fd, path)


def _same_file(fd: int, path: Path) -> bool:
    try:
        here = os.lstat(path)
    except FileNotFoundError:
        return False
    there = os.fstat(fd)
    return (here.st_dev, here.st_ino) == (there.st_dev, there.st_ino)


def _check_not_a_stage_layer(layer_path: Path, scene: StageScene) -> None:
    """BadOption if the selection layer would overwrite a layer the stage uses."""
    target = os.path.realpath(layer_path)
    for layer in scene.stage.GetUsedLayers():
        if layer.realPath and os.path.realpath(layer.realPath) == target:
            raise BadOption(
                f"--selection-layer {layer_path}: is a layer of the stage ({layer.identifier}); "
                "choose another path"
            )
