"""Which frames a render covers: the ``--frames`` grammar to a list of time codes.

Accepted, in stage time codes, both ends included:

* USD's FrameSpec, as ``usdrecord`` takes it (``UsdUtils.TimeCodeRange``): ``A``,
  ``A:B``, ``A:BxSTRIDE`` (``101:109x2`` → 101, 103, ..., 109; a negative stride counts
  down), and comma lists of those (``1:5,10,20:30x5``);
* ``A:B:STEP`` (phrt's own older form, same as ``A:BxSTEP``).

Frames are rendered once each, in increasing time order (a policy's memory, transitions
and the selection layer all follow time), whatever order the list gives.

File names write a time code with ``frame_text``: rounded to 1/1000 of a time code
(``FRAME_DECIMALS``), an integral one as an integer (zero-padded to the digits asked:
``0012``, ``-003``), another with its 3 decimals (``0012.500``). Two frames that round to
the same 1/1000 would write the same files, so a render refuses them (one line naming
both frames, exit 2) before its first frame (``products.ImagePlan.check_files``); frames
1/1000 of a time code or more apart always get distinct names.
"""

from __future__ import annotations

import math

import numpy as np
from pxr import Tf, UsdUtils

from phrt_usd.errors import BadOption, PhrtError, usd_error_reason

#: Most frames one render may list (``--frames``): a million frames of stats already
#: make a stats.json of ~1 GB.
MAX_FRAMES = 1_000_000
#: Time codes closer than this are the same frame (a stride of 0.1 summed ten times).
SAME_FRAME = 1e-9
#: Decimals of a time code in file names: frames are told apart to 1/1000 of a time code.
FRAME_DECIMALS = 3


def parse_frames(spec: str | None, default: tuple[float, float]) -> list[float]:
    """The time codes ``spec`` names (see the module docstring), increasing, each once.
    ``None`` gives the ``default`` (start, end) range with stride 1. BadOption (one line)
    for a malformed spec, a stride of 0, non-finite ends or more than MAX_FRAMES."""
    if spec is None:
        start, end = default
        return _range(start, end, 1.0, f"{start:g}:{end:g}")
    times: list[float] = []
    for part in (p.strip() for p in spec.split(",")):
        if not part:
            raise BadOption(f"--frames {spec!r}: an empty item in the list")
        pieces = part.split(":")
        if len(pieces) == 3:  # A:B:STEP
            try:
                start, end, step = (float(p) for p in pieces)
            except ValueError:
                raise BadOption(f"--frames {spec!r}: {part!r} is not A:B:STEP") from None
            times += _range(start, end, step, spec)
        else:
            times += _frame_spec(part, spec)
        if len(times) > MAX_FRAMES:
            raise BadOption(f"--frames {spec!r}: more than {MAX_FRAMES} frames")
    return _unique_sorted(times)


def _frame_spec(part: str, spec: str) -> list[float]:
    try:
        codes = UsdUtils.TimeCodeRange.CreateFromFrameSpec(part)
    except Tf.ErrorException as error:
        raise BadOption(f"--frames {spec!r}: {usd_error_reason(error)}") from None
    if not codes.IsValid():
        raise BadOption(f"--frames {spec!r}: {part!r} is not a FrameSpec (A, A:B, A:BxSTRIDE)")
    start, end = codes.startTimeCode.GetValue(), codes.endTimeCode.GetValue()
    if not np.isfinite([start, end]).all():
        raise BadOption(f"--frames {spec!r}: need finite frame numbers")
    if abs(end - start) / abs(codes.stride) + 1 > MAX_FRAMES:
        raise BadOption(f"--frames {spec!r}: more than {MAX_FRAMES} frames")
    return [float(code.GetValue()) for code in codes]


def _range(start: float, end: float, step: float, spec: str) -> list[float]:
    """start, start + step, ... up to and including end (end >= start, step > 0)."""
    if not all(np.isfinite([start, end, step])) or step <= 0 or end < start:
        raise BadOption(f"--frames {spec!r}: need finite A <= B and STEP > 0")
    count = int(np.floor((end - start) / step + 1e-9)) + 1
    if count > MAX_FRAMES:
        raise BadOption(f"--frames {spec!r}: {count} frames, more than {MAX_FRAMES}")
    return [float(start + i * step) for i in range(count)]


def _unique_sorted(times: list[float]) -> list[float]:
    out: list[float] = []
    for t in sorted(times):
        if not out or t - out[-1] > SAME_FRAME:
            out.append(t)
    return out


def frame_text(time: float, width: int = 0) -> str:
    """Time code ``time`` as file names write it (module docstring): rounded to
    ``FRAME_DECIMALS`` decimals, zero-padded to ``width`` digits before the point (0: as
    many as it takes), without decimals when the rounded value is integral. PhrtError if
    ``time`` is not finite."""
    if not math.isfinite(time):
        raise PhrtError(f"frame time code {time} is not finite")
    text = f"{time:.{FRAME_DECIMALS}f}"
    if text.endswith("." + "0" * FRAME_DECIMALS):
        return f"{int(round(time)):0{width}d}" if width else str(int(round(time)))
    return f"{time:0{width + 1 + FRAME_DECIMALS}.{FRAME_DECIMALS}f}" if width else text
