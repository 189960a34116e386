"""Which frames a render covers: the ``--frames`` grammar to a list of time codes."""

from __future__ import annotations

import numpy as np

from phrt_usd.errors import BadOption

#: Most frames one render may list (``--frames``): a million frames of stats already
#: make a stats.json of ~1 GB.
MAX_FRAMES = 1_000_000


def parse_frames(spec: str | None, default: tuple[float, float]) -> list[float]:
    """``"A:B[:STEP]"`` → time codes A, A+STEP, … up to and including B (stage time codes).

    ``None`` gives the default range with step 1; ``"A"`` alone is one frame.
    """
    if spec is None:
        start, end, step = default[0], default[1], 1.0
    else:
        try:
            parts = [float(p) for p in spec.split(":")]
        except ValueError:
            raise BadOption(f"--frames {spec!r}: expected A:B[:STEP] with numbers") from None
        if len(parts) == 1:
            parts = [parts[0], parts[0]]
        if len(parts) not in (2, 3):
            raise BadOption(f"--frames {spec!r}: expected A:B[:STEP]")
        start, end = parts[0], parts[1]
        step = parts[2] if len(parts) == 3 else 1.0
    if not all(np.isfinite([start, end, step])) or step <= 0 or end < start:
        raise BadOption(f"--frames {spec!r}: need finite A <= B and STEP > 0")
    count = int(np.floor((end - start) / step + 1e-9)) + 1
    if count > MAX_FRAMES:
        raise BadOption(f"--frames {spec!r}: {count} frames, more than {MAX_FRAMES}")
    return [float(start + i * step) for i in range(count)]
