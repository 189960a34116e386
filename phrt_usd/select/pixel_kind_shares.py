"""How a policy learns the way a reflector's pixels are made, for the time model's prices
of them (``select.cost_model``: a filled or reused pixel, and a pixel whose first ray
was marched in screen space, cost their figure in rays beyond the rays counted).

From each ``TraceRecord`` (the tracer counts its pixels of each kind): per reflector, the
share of its skipped pixels (those a reduced density started no ray at) that took their
reprojected history rather than a fill, an exponential average (newest weight
SHARE_ALPHA) kept across frames like its rays per pixel. ``BudgetedPolicy.level_rays``
prices a reflector's skipped pixels at that mix of reused and filled (no history yet:
all filled), and its pixels that start rays at the march's cost when the recent rounds
marched theirs (screen space on: every first ray is marched, resolved or not).
"""

from __future__ import annotations

from phrt_usd.model.frame import TraceRecord
from phrt_usd.model.trace_density import TRACE_DENSITIES, traced_fraction

#: Weight of the newest record in a reflector's shares: as its rays per pixel
#: (``policies.RAYS_PER_PIXEL_ALPHA``), a reflector's last frames decide.
SHARE_ALPHA = 0.5


def made_without_rays(record: TraceRecord, level: int | None) -> tuple[float, float, float]:
    """(filled, reused, marched) pixels of ``record``: its counts; for a record without
    them (made elsewhere than the tracer: a replay, a test), at density level ``level``
    (index into TRACE_DENSITIES; None: the view's own, not counted), the pixels the
    density skips, filled."""
    if record.filled is not None:
        return float(record.filled), float(record.reused or 0), float(record.marched or 0)
    if level is None or record.pixels <= 0:
        return 0.0, 0.0, 0.0
    skipped = record.pixels * (1.0 - traced_fraction(record.pixels, TRACE_DENSITIES[level]))
    return skipped, 0.0, 0.0


def average_into(table: dict[int, float], key: int, value: float,
                 alpha: float = SHARE_ALPHA) -> None:  # fmt: skip
    """``table[key]`` moved towards ``value`` by ``alpha`` (set to it when absent): the
    per-reflector exponential average of the policies' learned figures."""
    old = table.get(key)
    table[key] = value if old is None else alpha * value + (1.0 - alpha) * old


def learn_reused_share(table: dict[int, float], source: int, filled: float,
                       reused: float) -> None:  # fmt: skip
    """A record's reused share of its skipped pixels into ``table`` (none skipped: no
    news)."""
    if filled + reused > 0.0:
        average_into(table, source, reused / (filled + reused))


def skipped_cost(pixels: float, share: float, reused_share: float, fill_rays: float,
                 reuse_rays: float) -> float:  # fmt: skip
    """Rays-equivalent of the ``pixels * (1 - share)`` pixels a density skips, the
    ``reused_share`` of them reused at ``reuse_rays`` each, the rest filled at
    ``fill_rays``."""
    per_pixel = reused_share * reuse_rays + (1.0 - reused_share) * fill_rays
    return pixels * (1.0 - share) * per_pixel
