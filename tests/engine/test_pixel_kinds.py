"""How each pixel was made (``FrameOutput.pixel_kind``, ``model/pixel_kinds.py``): the
codes the renderer writes agree with what it counted and traced.

The mirror gallery (``scenes.mirror_gallery_stage``: five mirror panels on a camera path)
at 160 x 120, every reflector traced (``heuristic all``) with one bounce, so each traced
pixel casts exactly one reflection ray and the tracer's reflection-ray counter counts the
traced pixels independently of the codes.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scenes import mirror_gallery_stage  # noqa: E402

from phrt_usd.engine.renderer import FrameRenderer  # noqa: E402
from phrt_usd.engine.trace.sparse_pixels import pattern_spacing, rotation_phase  # noqa: E402
from phrt_usd.model import pixel_kinds as pk  # noqa: E402
from phrt_usd.model.render_options import RenderOptions  # noqa: E402
from phrt_usd.model.trace_density import sparse_floor  # noqa: E402
from phrt_usd.usd.stage import open_stage  # noqa: E402

W, H = 160, 120
FRAMES = [10.0, 20.0]


@pytest.fixture(scope="module")
def gallery(tmp_path_factory):
    return mirror_gallery_stage(tmp_path_factory.mktemp("kinds") / "gallery.usda", 40, W, H)


def _frames(stage: Path, mode: str, density: str = "full"):
    """(FrameOutput, reflection rays cast) of FRAMES."""
    scene = open_stage(stage)
    options = RenderOptions(  # no time budget: no calibration rounds cast rays
        mode=mode, heuristic="all", width=W, height=H, bounce_limit=1, trace_density=density,
        budget_ms=None,
    )
    renderer = FrameRenderer(scene, options)
    out = []
    try:
        renderer.plan(FRAMES)
        for t in FRAMES:
            if renderer.tracer is not None:
                renderer.tracer.reset_counters()
            output = renderer.render(t)
            rays = renderer.tracer.rays_cast["reflection"] if renderer.tracer else 0
            out.append((output, rays))
    finally:
        renderer.close()
    return out


def _counts(output) -> dict[str, int]:
    return pk.kind_counts(output.pixel_kind)


@pytest.mark.slow
@pytest.mark.parametrize("density", ["full", "quarter", "sixteenth"])
def test_kinds_count_what_the_renderer_traced_and_filled(gallery, density):
    """Traced pixels are the reflection rays cast (one each at one bounce); traced,
    reused and filled together are the frame's traced mask; every pixel of a traced
    reflector is traced, reused, filled or (a skipped pixel without a traced neighbour)
    raster; background is exactly the uncovered pixels. At full density nothing is
    filled; at a reduced one the traced pixels of a reflector over its density's sparse_floor lie
    on its pattern, shifted by the frame's rotation (``rotation_phase`` of its index in
    the plan: no probe has refused history before the second frame)."""
    for k, (output, rays) in enumerate(_frames(gallery, "hybrid", density)):
        counts = _counts(output)
        kinds = output.pixel_kind
        gb = output.gbuffer
        assert kinds.dtype == np.uint8 and kinds.shape == (H, W)
        assert counts["traced"] == rays > 0
        made = counts["traced"] + counts["reused"] + counts["filled"]
        assert made == int(output.traced_mask.sum())
        assert np.array_equal(kinds == pk.BACKGROUND, ~gb.covered)
        assert counts["screen-space"] == 0  # --screen-space is off by default
        selected = np.isin(gb.element_id, [
            i for i, e in enumerate(open_stage(gallery).scene.elements)
            if e.path in output.stats.selected
        ])  # fmt: skip
        made = np.isin(kinds, (pk.TRACED, pk.REUSED, pk.FILLED))
        assert not (made & ~selected).any()
        if density == "full":
            assert counts["filled"] == 0 and np.array_equal(made, selected)
            continue
        # Most of a sparse reflector is not traced (filled, or reused from frame 10).
        assert counts["filled"] + counts["reused"] > counts["traced"]
        step = pattern_spacing(density)
        phase_row, phase_col = rotation_phase(k)
        rows, cols = np.nonzero(kinds == pk.TRACED)
        ids = gb.element_id[rows, cols]
        large = np.bincount(gb.element_id[gb.covered])[ids] >= sparse_floor(density)
        assert np.all(((rows[large] - phase_row) % step == 0)
                      & ((cols[large] - phase_col) % step == 0))  # fmt: skip


@pytest.mark.slow
def test_raster_mode_has_only_raster_and_background(gallery):
    for output, _ in _frames(gallery, "raster"):
        assert set(np.unique(output.pixel_kind).tolist()) == {pk.BACKGROUND, pk.RASTER}
        assert np.array_equal(output.pixel_kind == pk.RASTER, output.gbuffer.covered)
