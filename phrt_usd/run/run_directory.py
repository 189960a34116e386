"""The output directory of one run: its lock, what it may already hold, its disk reserve.

See ``RunDirectory``. File names come from ``run_files``.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import re
from contextlib import suppress
from pathlib import Path

from phrt_usd.errors import BadOption, PhrtError
from phrt_usd.run.products import template_pattern
from phrt_usd.run.run_files import (
    CHECKPOINT_FILE,
    FRAMES_DIR,
    LOCK_FILE,
    RESERVE_FILE,
    SELECTION_LAYER_FILE,
    STATS_FILE,
)
from phrt_usd.usd.stage import StageScene

#: Disk held in reserve for a run's records (see ``RunDirectory.keep_reserve``): at least
#: RESERVE_MIN_BYTES, and RESERVE_FACTOR times what the records took when last written
#: (an atomic rewrite needs the old and the new file at once, and records grow).
RESERVE_MIN_BYTES = 64 * 1024
RESERVE_FACTOR = 3

#: Frame image names phrt writes in ``OUT/frames`` (see ``run_files.frame_name``).
_FRAME_IMAGE = re.compile(r"^-?\d{3,}(\.\d{3})?\.(exr|png)$")
#: The temp file ``atomic_path`` writes a file through (``.<stem>.<random>.tmp<ext>``).
_TEMP_FILE = re.compile(r"^\.(.+)\.[^.]+\.tmp(\.[^.]+)$")


class DirectoryLock:
    """``OUT/.phrt.lock``, held with ``flock`` by the one process writing ``OUT`` (a render
    or a sweep). The kernel releases it when the process dies, so a killed run never
    blocks the next; a second writer is refused at once, naming the holder's pid."""

    def __init__(self, out: Path) -> None:
        self.out = Path(out)
        self._fd: int | None = None

    def __enter__(self) -> DirectoryLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()

    def acquire(self) -> DirectoryLock:
        path = self.out / LOCK_FILE
        for _ in range(3):  # the holder may remove the file between our open and flock
            try:
                fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
            except OSError as error:
                if error.errno == errno.ELOOP:
                    raise PhrtError(f"{path}: is a symlink; remove it") from None
                raise BadOption(f"--out {self.out}: cannot write ({error.strerror})") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(fd, 64).decode("ascii", "replace").strip() or "?"
                os.close(fd)
                raise PhrtError(
                    f"{self.out}: another phrt run is writing here (pid {holder}); "
                    "wait for it or choose another --out"
                ) from None
            if _same_file(fd, path):
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()}\n".encode())
                self._fd = fd
                return self
            os.close(fd)  # locked a file that was just removed: try the new one
        raise PhrtError(f"{path}: could not take the lock")

    def release(self) -> None:
        if self._fd is not None:
            with suppress(OSError):
                os.unlink(self.out / LOCK_FILE)
            os.close(self._fd)  # closing releases the flock
            self._fd = None


class RunDirectory:
    """Context manager owning ``out`` for one run (see the module docstring).

    On entry: ``out`` is created if missing (PhrtError if it is a file or cannot be
    made); ``OUT/.phrt.lock`` is taken with ``flock`` (released by the kernel if the
    process dies, so a killed run never blocks the next) or the run is refused naming the
    holder's pid; an ``out`` holding anything is refused unless ``resume`` (the checkpoint
    must then be this run's: checked by ``_load_checkpoint``) or ``overwrite`` (phrt's own
    files are deleted first: frame images, stats, selection layer, checkpoint; anything
    else stays); the selection layer may not be a layer of the stage. On exit the lock is
    released and its file removed.

    ``images``: the file name templates of the run's images (``run.products``, relative
    to ``out``). ``overwrite`` deletes the files they name and those of the templates the
    previous run recorded in ``stats.json`` (``run.products``), whatever their frame
    numbers, and then every directory they leave empty; no other file is touched.
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
        self.fresh = True  # False when resuming a run that left files in out

    def __enter__(self) -> RunDirectory:
        out = self.out
        if out.exists() and not out.is_dir():
            raise BadOption(f"--out {out}: exists and is not a directory")
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise BadOption(f"--out {out}: cannot create ({error.strerror})") from None
        if self.scene is not None:
            _check_not_a_stage_layer(self.layer_path, self.scene)
        self._lock()
        try:
            self._claim()
            self.keep_reserve(RESERVE_MIN_BYTES)
            frames = out / FRAMES_DIR
            if frames.is_symlink() or (frames.exists() and not frames.is_dir()):
                raise PhrtError(f"{frames}: not a directory of this run (a link or a file)")
        except BaseException:
            self._unlock()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.release_reserve()
        self._unlock()

    def keep_reserve(self, nbytes: int) -> None:
        """Hold at least ``max(nbytes, RESERVE_MIN_BYTES)`` of disk in ``OUT/.phrt.reserve``
        (allocated, never written to) so that when the disk fills, releasing it leaves
        room to write the finished frames' records. Without room for it, nothing is held."""
        nbytes = max(int(nbytes), RESERVE_MIN_BYTES)
        try:
            fd = os.open(self.out / RESERVE_FILE, os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW, 0o600)
        except OSError:
            return
        try:
            if os.fstat(fd).st_size < nbytes:
                os.posix_fallocate(fd, 0, nbytes)
        except OSError:
            pass  # no room for the reserve (the disk is full already) or no fallocate here
        finally:
            os.close(fd)

    def release_reserve(self) -> None:
        with suppress(FileNotFoundError):
            (self.out / RESERVE_FILE).unlink()

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
        """Delete phrt's own files in ``out`` (never following a symlink: a link is
        removed itself), and the job's selection layer."""
        templates = set(self.images) | set(_recorded_templates(self.out / STATS_FILE))
        for template in sorted(templates):
            _clear_template(self.out, template)
        for name in (STATS_FILE, SELECTION_LAYER_FILE, CHECKPOINT_FILE, RESERVE_FILE):
            with suppress(FileNotFoundError):
                (self.out / name).unlink()
        with suppress(FileNotFoundError):
            if self.layer_path.is_symlink() or self.layer_path.is_file():
                self.layer_path.unlink()
        frames = self.out / FRAMES_DIR
        if frames.is_symlink():
            frames.unlink()
        elif frames.is_dir():
            for entry in frames.iterdir():
                if _FRAME_IMAGE.match(entry.name) or entry.name.startswith("."):
                    if entry.is_dir() and not entry.is_symlink():
                        continue
                    entry.unlink()
            with suppress(OSError):
                frames.rmdir()  # only when nothing else is left in it


def _recorded_templates(stats: Path) -> list[str]:
    """The image file name templates a previous run recorded in its stats.json (``run``
    ``products``: their keys and ``preview``s); none without a readable record."""
    try:
        if stats.is_symlink():
            return []
        run = json.loads(stats.read_text(encoding="utf-8")).get("run", {})
        products = run.get("products") or {}
        names = [*products, *(p.get("preview") for p in products.values())]
    except (OSError, UnicodeDecodeError, ValueError, AttributeError, TypeError):
        return []
    return [n for n in names if isinstance(n, str) and n]


def _clear_template(out: Path, template: str) -> None:
    """Delete the files in ``out`` that ``template`` names (a link is removed itself,
    never followed; a directory is never entered through a link), and the directories
    on its way that this leaves empty."""
    parts = Path(template).parts
    if not parts or Path(template).is_absolute() or ".." in parts:
        return  # never one of ours: products are relative names inside out
    folder = out.joinpath(*parts[:-1])
    here = out
    for part in parts[:-1]:
        here = here / part
        if here.is_symlink() or not here.is_dir():
            return
    pattern = template_pattern(parts[-1])
    for entry in folder.iterdir():
        # a killed writer's temp file: .<name without extension>.<random>.tmp<extension>
        name = _TEMP_FILE.sub(r"\1\2", entry.name)
        if pattern.match(name) and (entry.is_symlink() or not entry.is_dir()):
            entry.unlink()
    while folder != out:
        with suppress(OSError):
            folder.rmdir()  # only when nothing else is left in it
        folder = folder.parent


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
