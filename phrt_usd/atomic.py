"""The one way phrt writes a file: atomically, checked, never through a planted link.

``atomic_path`` writes to an exclusively created hidden temp file beside the target (same
extension, so OpenImageIO and USD pick the right format), checks it, fsyncs it and renames
it over the target. A reader never sees a half-written file, a crash or a full disk leaves
the old file whole, and a symlink at the target is replaced, never followed. Every phase
that writes (authoring, run files, images, sweeps) goes through it.
"""

from __future__ import annotations

import contextlib
import os
import re
import stat
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from phrt_usd.errors import PhrtError


class WriteFailed(PhrtError):
    """An output could not be written (OS error, full disk, writer failure). The previous
    file under that name, if any, is untouched and no temp file is left behind."""


#: Permission bits a new output gets before the umask (what ``open(..., "w")`` uses).
NEW_FILE_MODE = 0o666
#: The temp file a write goes through: ``.<stem>.<random>.tmp<ext>``, the random part
#: ``tempfile.mkstemp``'s (8 of lower-case letters, digits and ``_``).
_TEMP_NAME = re.compile(r"^\.(?P<stem>.+)\.[a-z0-9_]{8}\.tmp(?P<ext>\.[^.]+)?$")


def published_name(name: str) -> str | None:
    """The file name a temp file named ``name`` (``atomic_path``'s, left behind by a
    killed writer) was to be published under, or None if ``name`` is not such a name:
    ``.0012.k3j_x9ab.tmp.exr`` -> ``0012.exr``."""
    match = _TEMP_NAME.match(name)
    return None if match is None else match["stem"] + (match["ext"] or "")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(final: Path, check: Callable[[Path], None] | None = None) -> Iterator[Path]:
    """Yield a fresh temp path next to ``final``; once the body has written it, publish it
    under ``final``. The one way phrt writes any output file.

    * The temp file ``.<stem>.<random>.tmp<ext>`` is created exclusively in ``final``'s
      directory (``O_CREAT | O_EXCL | O_NOFOLLOW``: a planted file or symlink at that name
      is never opened, let alone followed) with ``final``'s extension, so writers that pick
      a format by extension (OpenImageIO, USD) work; the body writes it by name.
    * On success the temp must still be a regular file (not replaced by a symlink) and
      non-empty; ``check(tmp)`` (optional) may read it back and raise; it is fsynced,
      given ``final``'s current mode (a new file gets ``NEW_FILE_MODE`` less the umask),
      renamed over ``final`` (a rename replaces a symlink at ``final`` itself, never its
      target) and the directory is fsynced.
    * If anything fails, the temp file is removed, ``final`` keeps its previous content,
      and an OS error is raised as ``WriteFailed`` naming ``final`` and the error.
    """
    final = Path(final)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        stem, ext = _split_extension(final.name)
        fd, name = tempfile.mkstemp(prefix=f".{stem}.", suffix=f".tmp{ext}", dir=final.parent)
        os.close(fd)
    except OSError as error:
        raise WriteFailed(f"{final}: cannot write ({_os_reason(error)})") from None
    tmp = Path(name)
    try:
        yield tmp
        _publish(tmp, final, check)
    except OSError as error:
        raise WriteFailed(f"{final}: cannot write ({_os_reason(error)})") from None
    except PhrtError as error:  # a writer's own report: name the final file, not the temp
        message = str(error).replace(str(tmp), str(final))
        if _disk_full(final.parent) and "no space left" not in message.lower():
            message += " (no space left on device)"
        raise WriteFailed(message) from None
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def _publish(tmp: Path, final: Path, check: Callable[[Path], None] | None) -> None:
    """Verify, fsync and rename ``tmp`` over ``final`` (see ``atomic_path``)."""
    info = tmp.lstat()
    if not stat.S_ISREG(info.st_mode):
        raise WriteFailed(f"{final}: the temp file was replaced by something else")
    if info.st_size == 0:  # image writers may report success on a full disk
        raise WriteFailed(f"{final}: the writer produced an empty file")
    if check is not None:
        check(tmp)
    try:
        mode = stat.S_IMODE(final.stat().st_mode)
    except FileNotFoundError:
        mode = NEW_FILE_MODE & ~_umask()
    fd = os.open(tmp, os.O_RDONLY | os.O_NOFOLLOW)
    try:
        os.fchmod(fd, mode)
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, final)
    _fsync_directory(final.parent)


def _disk_full(path: Path) -> bool:
    try:
        info = os.statvfs(path)
    except OSError:
        return False
    return info.f_bavail * info.f_frsize < 64 * 1024  # less than a small file's room


def _fsync_directory(path: Path) -> None:
    """Make a rename in ``path`` durable (a no-op where directories cannot be opened)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # some file systems do not fsync directories; the rename itself happened
    finally:
        os.close(fd)


def _os_reason(error: OSError) -> str:
    """``No space left on device`` etc.; the strerror of an OSError without its repr."""
    return error.strerror or str(error)


def _split_extension(name: str) -> tuple[str, str]:
    """``"0012.500.exr"`` → ``("0012.500", ".exr")`` (only the last suffix is the format)."""
    dot = name.rfind(".")
    if dot <= 0:
        return name, ""
    return name[:dot], name[dot:]


def write_bytes_atomic(path: Path, data: bytes, check: Callable[[Path], None] | None = None):
    """Write ``data`` to ``path`` atomically (see ``atomic_path``)."""
    with atomic_path(path, check) as tmp:
        fd = os.open(tmp, os.O_WRONLY | os.O_TRUNC | os.O_NOFOLLOW)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view) :]
        finally:
            os.close(fd)


def write_text_atomic(path: Path, text: str, check: Callable[[Path], None] | None = None):
    """Write ``text`` (UTF-8) to ``path`` atomically (see ``atomic_path``)."""
    write_bytes_atomic(path, text.encode("utf-8"), check)
