"""The one way to open a USD stage file (``open_usd``): what is refused before USD reads
it (a missing path, a directory, a file that is no regular file, a file without a USD
extension), how the stage is composed with a pipeline's controls (session layers,
variant selections, population mask: ``stage_controls``), and what the user is told
when USD cannot read it: USD's own reason, the parser's ``file:line:column: what``
(``errors.usd_error_reason``; a text layer whose bytes are not UTF-8 located at its
first bad byte). ``phrt_usd.usd.stage`` reads the opened stage.
"""

from __future__ import annotations

import os

from pxr import Sdf, Tf, Usd

from phrt_usd.errors import NOT_UTF8_REASON, PhrtError, usd_error_reason
from phrt_usd.usd.stage_controls import StageControls

#: File extensions of the stage files ``open_usd`` accepts (USD picks the file format
#: from the extension; ``.usd`` may hold text or crate).
USD_EXTENSIONS = (".usda", ".usdc", ".usd", ".usdz")


def open_usd(path: str | os.PathLike, controls: StageControls | None = None) -> Usd.Stage:
    """Open a USD stage file with every payload loaded, composed with ``controls``
    (session layers, variant selections, population mask; see ``stage_controls``).

    Raises ``PhrtError`` (one line naming the path and what is wrong) for a missing path,
    a directory or another file that is not a regular one (a device or pipe is never
    read), a file without one of ``USD_EXTENSIONS``, or a file USD cannot read (garbage
    bytes, invalid syntax, unreadable): then with USD's own reason, the parser's
    ``file:line:column: what`` when it gives one (``usd_error_reason``). A file without
    an extension is refused, not sniffed: USD chooses the file format from the
    extension, and the same file must open the same way in every USD tool — rename it
    to ``.usd`` (text or crate).
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise PhrtError(f"{path}: no such file")
    if os.path.isdir(path):
        raise PhrtError(f"{path}: is a directory, not a USD file")
    if not os.path.isfile(path):
        raise PhrtError(f"{path}: not a regular file (a device, pipe or socket)")
    ext = os.path.splitext(path)[1]
    expected = "/".join(USD_EXTENSIONS)
    if not ext or ext == ".":
        raise PhrtError(f"{path}: no USD file extension ({expected})")
    if not Sdf.FileFormat.FindByExtension(ext[1:]):
        raise PhrtError(f"{path}: not a USD file (extension {ext!r}, expected {expected})")
    controls = controls or StageControls()
    try:
        session = controls.session_layer()
        mask = controls.population_mask()
        root = None if session is None and mask is None else Sdf.Layer.FindOrOpen(path)
        if root is None:  # no controls, or a root USD cannot read: Open says why
            stage = Usd.Stage.Open(path, Usd.Stage.LoadAll)
        else:
            session = session or Sdf.Layer.CreateAnonymous("session.usda")
            if mask is None:
                stage = Usd.Stage.Open(root, session, Usd.Stage.LoadAll)
            else:
                stage = Usd.Stage.OpenMasked(root, session, mask, Usd.Stage.LoadAll)
    except Tf.ErrorException as exc:
        reason = usd_error_reason(exc)
        if reason == NOT_UTF8_REASON:
            reason = _first_non_utf8(path) or reason
        raise PhrtError(f"{path}: cannot open as USD ({reason})") from None
    if stage is None:
        raise PhrtError(f"{path}: cannot open as USD")
    controls.check(stage)
    return stage


#: Largest stage file searched for the bytes that are not UTF-8 (``_first_non_utf8``).
_MAX_SEARCHED_BYTES = 64 << 20


def _first_non_utf8(path: str) -> str | None:
    """``"<path>:<line>:<column>: bytes that are not UTF-8 text"`` at the first such
    bytes of a text stage file (of at most ``_MAX_SEARCHED_BYTES``), else None."""
    if os.path.getsize(path) > _MAX_SEARCHED_BYTES:
        return None
    with open(path, "rb") as f:
        data = f.read()
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as bad:
        line = data.count(b"\n", 0, bad.start) + 1
        column = bad.start - data.rfind(b"\n", 0, bad.start)
        return f"{path}:{line}:{column}: bytes that are not UTF-8 text"
    return None
