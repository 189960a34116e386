"""End-to-end frames: reflection physics, mode equivalence, no NaN/Inf on any stage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from image_thresholds import HYBRID_VS_RT_FLIP
from repo_paths import STAGES
from scenes import mirror_floor_stage, mirror_gallery_stage, mirrored_sphere_pixels

from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.errors import PhrtError
from phrt_usd.pytest_plugin import assert_images_close
from phrt_usd.run.images import write_preview_png
from phrt_usd.usd.stage import open_stage

#: Fraction of the analytically mirrored sphere's floor pixels that must show it red.
MIRROR_AGREEMENT = 0.97


def _render(stage, mode: str, width: int, height: int, time: float = 1.0):
    renderer = FrameRenderer(
        stage, RenderOptions(mode=mode, heuristic="all", width=width, height=height, budget_ms=None)
    )
    try:
        return renderer.render(time)
    finally:
        renderer.close()


def _red(image: np.ndarray) -> np.ndarray:
    return (image[..., 0] > 2 * image[..., 1]) & (image[..., 0] > 2 * image[..., 2])


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["rt", "hybrid"])
def test_sphere_reflection_lands_where_geometry_says(tmp_path, mode):
    stage = open_stage(mirror_floor_stage(tmp_path / "mirror.usda"))
    w, h = 160, 120
    out = _render(stage, mode, w, h)
    floor_id = next(i for i, e in enumerate(stage.scene.elements) if e.path == "/World/Floor")
    floor = out.gbuffer.element_id == floor_id
    expected = mirrored_sphere_pixels(stage.camera(1.0), w, h) & floor
    red = _red(out.beauty)
    try:
        assert expected.sum() > 100  # the reflection is in view at all
        assert (red & expected).sum() >= MIRROR_AGREEMENT * expected.sum()
        # No red on the floor away from the mirrored sphere (1-pixel tolerance at its rim).
        rim = np.zeros_like(expected)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                rim |= np.roll(np.roll(expected, dy, 0), dx, 1)
        assert not (red & floor & ~rim).any()
        assert out.traced_mask[floor].all()
    except AssertionError:
        write_preview_png(tmp_path / f"failed_{mode}.png", out.beauty)
        raise


@pytest.mark.slow
def test_raster_mode_shows_no_reflected_geometry(tmp_path):
    stage = open_stage(mirror_floor_stage(tmp_path / "mirror.usda"))
    out = _render(stage, "raster", 160, 120)
    floor_id = next(i for i, e in enumerate(stage.scene.elements) if e.path == "/World/Floor")
    floor = out.gbuffer.element_id == floor_id
    assert floor.sum() > 1000
    assert not (_red(out.beauty) & floor).any()
    assert "trace" not in out.stats.passes and out.stats.rays == 0
    assert not out.traced_mask.any()


@pytest.mark.slow
@pytest.mark.parametrize("name,times", [("farm", [200.0, 420.0]), ("sewer", [100.0, 400.0])])
def test_hybrid_all_matches_rt(name, times):
    stage = open_stage(STAGES / f"{name}.usda")
    for t in times:
        hybrid = _render(stage, "hybrid", 320, 240, t)
        rt = _render(stage, "rt", 320, 240, t)
        # On failure: hybrid, rt and FLIP map in tests/phrt-failures/, named in the message.
        assert_images_close(
            hybrid.beauty, rt.beauty, max_mean_flip=HYBRID_VS_RT_FLIP, min_psnr=None, name=f"{t:g}"
        )


def _all_stage_files() -> list[Path]:
    return sorted(STAGES.glob("*.usda")) + sorted((STAGES / "extreme").glob("*.usda"))


@pytest.mark.slow
@pytest.mark.parametrize("path", _all_stage_files(), ids=lambda p: p.stem)
def test_every_stage_renders_finite_or_fails_clearly(path):
    try:
        stage = open_stage(path)
        t0, t1 = stage.frame_range
        outputs = [_render(stage, mode, 80, 60, t0) for mode in ("raster", "hybrid", "rt")]
        outputs.append(_render(stage, "hybrid", 80, 60, 0.5 * (t0 + t1)))
    except PhrtError as exc:
        message = str(exc)
        assert "\n" not in message and "/" in message  # one line naming a prim path
        return
    for out in outputs:
        for channel in (out.beauty, out.alpha, out.gbuffer.depth[out.gbuffer.covered]):
            assert np.all(np.isfinite(channel))


@pytest.mark.slow
def test_screen_boxes_bound_each_reflectors_pixels(tmp_path):
    stage = open_stage(mirror_gallery_stage(tmp_path / "gallery.usda"))
    renderer = FrameRenderer(
        stage, RenderOptions(mode="hybrid", heuristic="all", width=96, height=64, budget_ms=None)
    )
    try:
        prep = renderer.prepare(1.0)
    finally:
        renderer.close()
    ids = prep.gbuffer.element_id
    seen = 0
    for e, element in enumerate(stage.scene.elements):
        rows, cols = np.nonzero(ids == e)
        box = prep.screen_boxes[e]
        if element.is_reflector and len(rows):
            seen += 1
            assert box.tolist() == [cols.min(), rows.min(), cols.max(), rows.max()]
        else:
            assert np.isnan(box).all()
    assert seen >= 2


@pytest.mark.slow
def test_planned_frames_give_each_view_the_upcoming_cameras():
    stage = open_stage(STAGES / "sewer.usda")  # its camera path moves every frame
    renderer = FrameRenderer(
        stage, RenderOptions(mode="hybrid", heuristic="heu1", width=64, height=48, budget_ms=None)
    )
    try:
        assert renderer.prepare(10.0).upcoming_cameras == ()  # no plan: no lookahead
        plan = [10.0, 12.0, 14.0, 16.0]
        renderer.plan(plan)
        ahead = renderer.prepare(12.0).upcoming_cameras
        current = renderer.prepare(14.0).camera
        last = renderer.prepare(16.0).upcoming_cameras
    finally:
        renderer.close()
    assert len(ahead) == 2 and last == ()
    assert current is ahead[0]  # the same object: policies cache per-camera figures by it
    for cam, t in zip(ahead, plan[2:], strict=True):
        np.testing.assert_array_equal(cam.world_from_camera, stage.camera(t).world_from_camera)
